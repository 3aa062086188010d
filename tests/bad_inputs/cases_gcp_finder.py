"""Module 1 (gcp_finder): broken GCP surveys (columns, ids, values, CRS, GCPs nowhere near the flight), images
that cannot be used, a gcp_list.txt to continue that is missing or broken, and the inputs that must work
(BOM/CRLF/semicolons, a lon/lat survey, one GCP outside the flight, resuming a list with foreign images).

The must-work checks compare with the tiny field's truth: ``truth/gcp_pixels.csv`` holds every GCP's true
pixel in every photo that sees it.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from harness import Case, Work, read_rows, write_rows
from pyproj import Transformer

from matchplant.core.formats.gcp_list import read_gcp_list


def crs(w: Work) -> str:
    return json.loads((w.artifacts / "field" / "truth" / "field.json").read_text())["crs"]


def args(w: Work, images: Path, survey: Path, *extra: str, survey_crs: str = "field") -> list[str]:
    a = [
        "--set",
        f"images={images}",
        "--set",
        f"survey={survey}",
        "--set",
        f"output_dir={w.out}",
        "--set",
        f"survey_crs={crs(w) if survey_crs == 'field' else survey_crs}",
    ]
    for e in extra:
        a += ["--set", e]
    return a


AUTO = ("auto=true", "max_center_distance=1.0", "edge_margin_px=0")


def survey_rows(w: Work) -> list[list[str]]:
    return read_rows(w.artifacts / "field" / "gcp" / "gcp_survey.csv", ",")


def write_survey(w: Work, rows: list[list[str]], name: str = "gcp_survey.csv", sep: str = ",") -> Path:
    return write_rows(w, rows, name, sep)


def images(w: Work, name: str = "images") -> Path:
    return w.copy(f"field/{name}")


def truth(w: Work) -> dict[tuple[str, str], tuple[float, float]]:
    with open(w.artifacts / "field" / "truth" / "gcp_pixels.csv", newline="") as fh:
        return {(r["gcp_id"], r["image"]): (float(r["u"]), float(r["v"])) for r in csv.DictReader(fh)}


def candidates(w: Work) -> list[dict]:
    with open(w.out / "candidates.csv", newline="") as fh:
        return list(csv.DictReader(fh))


# -- checks --------------------------------------------------------------------------------------------------


def all_gcps_have_candidates(w: Work) -> None:
    seen = {r["gcp"] for r in candidates(w)}
    assert seen == {r[0] for r in survey_rows(w)[1:]}, seen


def auto_marks_near_truth(w: Work) -> None:
    t = truth(w)
    marks = read_gcp_list(w.out / "gcp_list.txt")[2]
    assert marks, "no marks"
    for m in marks:
        if (m.gcp, m.image) in t:
            assert math.dist((m.u, m.v), t[(m.gcp, m.image)]) < 2.0, (m, t[(m.gcp, m.image)])


# -- the survey ----------------------------------------------------------------------------------------------


def survey_missing_z(w: Work) -> list[str]:
    return args(w, images(w), write_survey(w, [r[:3] for r in survey_rows(w)]))


def survey_missing_id(w: Work) -> list[str]:
    return args(w, images(w), write_survey(w, [r[1:] for r in survey_rows(w)]))


def survey_duplicate_ids(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[3][0] = rows[2][0]
    return args(w, images(w), write_survey(w, rows))


def survey_non_numeric(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[2][2] = "n/a"
    return args(w, images(w), write_survey(w, rows))


def survey_comma_in_value(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[2][2] = "4524878,48"  # a decimal comma in a comma-separated file: one value too many
    return args(w, images(w), write_survey(w, rows))


def survey_nan(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[3][3] = "nan"
    return args(w, images(w), write_survey(w, rows))


def survey_empty(w: Work) -> list[str]:
    (w.inputs / "gcp_survey.csv").write_bytes(b"")
    return args(w, images(w), w.inputs / "gcp_survey.csv")


def survey_header_only(w: Work) -> list[str]:
    return args(w, images(w), write_survey(w, survey_rows(w)[:1]))


def survey_far_away(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[1:] = [[r[0], f"{float(r[1]) + 3000:.4f}", r[2], r[3]] for r in rows[1:]]
    return args(w, images(w), write_survey(w, rows))


def lonlat_rows(w: Work) -> list[list[str]]:
    to_ll = Transformer.from_crs(crs(w), "EPSG:4326", always_xy=True)
    out = [["name", "lat", "lon", "elevation"]]
    for r in survey_rows(w)[1:]:
        lon, lat = to_ll.transform(float(r[1]), float(r[2]))
        out.append([r[0], f"{lat:.10f}", f"{lon:.10f}", r[3]])
    return out


def survey_degrees_with_projected_crs(w: Work) -> list[str]:
    return args(w, images(w), write_survey(w, lonlat_rows(w)))


def survey_metres_with_geographic_crs(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), survey_crs="EPSG:4326")


def wrong_survey_crs_string(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), survey_crs="UTM14")


def survey_lonlat_works(w: Work) -> list[str]:
    return args(w, images(w), write_survey(w, lonlat_rows(w), "survey lonlat.csv"), survey_crs="EPSG:4326")


def survey_bom_crlf_semicolon_junk(w: Work) -> list[str]:
    imgs = w.copy("field/images", "fotos de campo ñ")
    (imgs / "Thumbs.db").write_bytes(b"\x00junk")
    (imgs / "._SIM_0003.JPG").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (imgs / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    path = w.inputs / "relevé GCP.csv"
    path.write_bytes(b"\xef\xbb\xbf" + "".join(";".join(r) + "\r\n" for r in survey_rows(w)).encode())
    return args(w, imgs, path, *AUTO)


def one_gcp_outside(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows.append(["GCP99", f"{float(rows[1][1]) + 5000:.4f}", rows[1][2], rows[1][3]])
    return args(w, images(w), write_survey(w, rows))


def only_gcp99_missing(w: Work) -> None:
    seen = {r["gcp"] for r in candidates(w)}
    assert "GCP99" not in seen and len(seen) == 4, seen


def survey_latlon_swapped(w: Work) -> list[str]:
    rows = lonlat_rows(w)
    rows[0] = ["id", "x", "y", "z"]  # x holds the latitude
    return args(w, images(w), write_survey(w, rows), survey_crs="EPSG:4326")


def survey_id_with_space(w: Work) -> list[str]:
    rows = survey_rows(w)
    rows[2][0] = "GCP 02"
    return args(w, images(w), write_survey(w, rows))


def geographic_output_crs(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), "output_crs=EPSG:4326")


def survey_utf16_whitespace(w: Work) -> list[str]:
    path = w.inputs / "survey.txt"
    path.write_bytes("".join("  ".join(r) + "\r\n" for r in survey_rows(w)).encode("utf-16"))
    return args(w, images(w), path)


# -- images --------------------------------------------------------------------------------------------------


def images_without_gps(w: Work) -> list[str]:
    return args(w, images(w, "images_nogps"), w.copy("field/gcp/gcp_survey.csv"))


def truncated_jpeg(w: Work) -> list[str]:
    imgs = images(w)
    p = imgs / "SIM_0005.JPG"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return args(w, imgs, w.copy("field/gcp/gcp_survey.csv"))


# -- resuming a gcp_list.txt ---------------------------------------------------------------------------------


def earlier_list(w: Work, lines: list[str]) -> Path:
    path = w.inputs / "gcp_list.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def resume_with_foreign_images(w: Work) -> list[str]:
    """An earlier list with marks for images of another flight: they are dropped (with a warning)."""
    t = truth(w)
    g = {r[0]: r[1:] for r in survey_rows(w)[1:]}
    (gid, image), (u, v) = next(iter(t.items()))
    lines = [
        crs(w),
        f"{' '.join(g[gid])} {u} {v} {image} {gid}",
        f"{' '.join(g['GCP02'])} 120.5 80.25 OTHER_0042.JPG GCP02",
        f"{' '.join(g['GCP03'])} 10 20 DJI_0001.JPG GCP03",
    ]
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), *AUTO, f"gcp_list={earlier_list(w, lines)}")


def foreign_dropped(w: Work) -> None:
    auto_marks_near_truth(w)
    names = {m.image for m in read_gcp_list(w.out / "gcp_list.txt")[2]}
    assert names and not names & {"OTHER_0042.JPG", "DJI_0001.JPG"}, names


def resume_in_output_folder(w: Work) -> list[str]:
    """The earlier list sits in the output folder (the default to continue), the run is not 'auto': the list
    is written back without the lines of foreign images."""
    t = truth(w)
    g = {r[0]: r[1:] for r in survey_rows(w)[1:]}
    (gid, image), (u, v) = next(iter(t.items()))
    w.out.mkdir(parents=True)
    (w.out / "gcp_list.txt").write_text(
        f"{crs(w)}\n{' '.join(g[gid])} {u} {v} {image} {gid}\n{' '.join(g['GCP02'])} 120.5 80.25 OTHER_0042.JPG GCP02\n"
    )
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"))


def kept_own_dropped_foreign(w: Work) -> None:
    (gid, image), (u, v) = next(iter(truth(w).items()))
    marks = read_gcp_list(w.out / "gcp_list.txt")[2]
    assert [(m.gcp, m.image) for m in marks] == [(gid, image)], marks
    assert abs(marks[0].u - u) < 1e-3 and abs(marks[0].v - v) < 1e-3


def missing_gcp_list(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), *AUTO, f"gcp_list={w.inputs / 'gcp_list.txt'}")


def gcp_list_without_crs(w: Work) -> list[str]:
    g = survey_rows(w)[1]
    path = earlier_list(w, [f"{' '.join(g[1:])} 10 20 SIM_0001.JPG {g[0]}"])
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), *AUTO, f"gcp_list={path}")


def gcp_list_nan_pixel(w: Work) -> list[str]:
    g = survey_rows(w)[1]
    path = earlier_list(w, [crs(w), f"{' '.join(g[1:])} nan 20 SIM_0001.JPG {g[0]}"])
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), *AUTO, f"gcp_list={path}")


def resume_mark_outside_image(w: Work) -> list[str]:
    t = truth(w)
    g = {r[0]: r[1:] for r in survey_rows(w)[1:]}
    (gid, image), (u, v) = next(iter(t.items()))
    lines = [crs(w), f"{' '.join(g[gid])} {u} {v} {image} {gid}", f"{' '.join(g['GCP02'])} 99999 20 {image} GCP02"]
    return args(w, images(w), w.copy("field/gcp/gcp_survey.csv"), *AUTO, f"gcp_list={earlier_list(w, lines)}")


def no_mark_outside(w: Work) -> None:
    auto_marks_near_truth(w)
    assert all(m.u < 10000 for m in read_gcp_list(w.out / "gcp_list.txt")[2])


# -- outputs -------------------------------------------------------------------------------------------------


def output_is_image_folder(w: Work) -> list[str]:
    imgs = images(w)
    a = args(w, imgs, w.copy("field/gcp/gcp_survey.csv"))
    return [x if not x.startswith("output_dir=") else f"output_dir={imgs}" for x in a]


CASES = [
    Case("m1-survey-missing-z", "gcp_finder", survey_missing_z, mentions=("gcp_survey.csv", "'z'")),
    Case("m1-survey-missing-id", "gcp_finder", survey_missing_id, mentions=("gcp_survey.csv", "'id'")),
    Case(
        "m1-survey-duplicate-ids",
        "gcp_finder",
        survey_duplicate_ids,
        mentions=("gcp_survey.csv", "GCP02", "lines 3 and 4"),
    ),
    Case("m1-survey-non-numeric", "gcp_finder", survey_non_numeric, mentions=("gcp_survey.csv", "line 3")),
    Case("m1-survey-comma-in-value", "gcp_finder", survey_comma_in_value, mentions=("gcp_survey.csv", "line 3")),
    Case("m1-survey-nan", "gcp_finder", survey_nan, mentions=("gcp_survey.csv", "line 4")),
    Case("m1-survey-empty", "gcp_finder", survey_empty, mentions=("gcp_survey.csv", "empty")),
    Case("m1-survey-header-only", "gcp_finder", survey_header_only, mentions=("gcp_survey.csv",)),
    Case("m1-survey-far-from-flight", "gcp_finder", survey_far_away, mentions=("gcp_survey.csv", "survey_crs")),
    Case(
        "m1-survey-degrees-projected-crs",
        "gcp_finder",
        survey_degrees_with_projected_crs,
        mentions=("gcp_survey.csv", "degrees", "survey_crs"),
    ),
    Case(
        "m1-survey-metres-geographic-crs",
        "gcp_finder",
        survey_metres_with_geographic_crs,
        mentions=("gcp_survey.csv", "line 2", "survey_crs"),
    ),
    Case("m1-wrong-survey-crs-string", "gcp_finder", wrong_survey_crs_string, mentions=("survey_crs", "UTM14")),
    Case("m1-images-without-gps", "gcp_finder", images_without_gps, mentions=("images_nogps", "GPS")),
    Case("m1-truncated-jpeg", "gcp_finder", truncated_jpeg, mentions=("SIM_0005.JPG", "truncated")),
    Case(
        "m1-resume-in-output-folder", "gcp_finder", resume_in_output_folder, expect="ok", check=kept_own_dropped_foreign
    ),
    Case("m1-missing-gcp-list", "gcp_finder", missing_gcp_list, mentions=("gcp_list",)),
    Case("m1-gcp-list-without-crs-line", "gcp_finder", gcp_list_without_crs, mentions=("gcp_list.txt", "line 1")),
    Case("m1-gcp-list-nan-pixel", "gcp_finder", gcp_list_nan_pixel, mentions=("gcp_list.txt", "line 2")),
    Case("m1-survey-latlon-swapped", "gcp_finder", survey_latlon_swapped, mentions=("gcp_survey.csv", "swapped")),
    Case("m1-survey-id-with-space", "gcp_finder", survey_id_with_space, mentions=("gcp_survey.csv", "line 3")),
    Case("m1-geographic-output-crs", "gcp_finder", geographic_output_crs, mentions=("output_crs",)),
    Case(
        "m1-survey-utf16-whitespace", "gcp_finder", survey_utf16_whitespace, expect="ok", check=all_gcps_have_candidates
    ),
    Case("m1-resume-mark-outside-image", "gcp_finder", resume_mark_outside_image, expect="ok", check=no_mark_outside),
    Case("m1-output-is-image-folder", "gcp_finder", output_is_image_folder, mentions=("output_dir",)),
    Case("m1-survey-lonlat", "gcp_finder", survey_lonlat_works, expect="ok", check=all_gcps_have_candidates),
    Case(
        "m1-survey-bom-crlf-semicolon-junk-unicode",
        "gcp_finder",
        survey_bom_crlf_semicolon_junk,
        expect="ok",
        check=auto_marks_near_truth,
    ),
    Case("m1-one-gcp-outside-flight", "gcp_finder", one_gcp_outside, expect="ok", check=only_gcp99_missing),
    Case(
        "m1-resume-list-with-foreign-images",
        "gcp_finder",
        resume_with_foreign_images,
        expect="ok",
        check=foreign_dropped,
    ),
]
