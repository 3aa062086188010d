"""Cases across the steps that show the corpus's patterns: a missing or broken input (exit 2, the file or key
named), and inputs that must work (spaces and non-ASCII letters in paths, BOM + CRLF text, junk files)."""

from __future__ import annotations

import json

from harness import Case, Work


def crs(w: Work) -> str:
    return json.loads((w.artifacts / "field" / "truth" / "field.json").read_text())["crs"]


# -- module 0 ------------------------------------------------------------------------------------------------


def gps_args(w: Work, images, log) -> list[str]:
    return [
        "--set",
        f"images={images}",
        "--set",
        f"gnss_log={log}",
        "--set",
        f"log_crs={crs(w)}",
        "--set",
        f"output_dir={w.out}",
    ]


def gps_missing_log(w: Work) -> list[str]:
    return gps_args(w, w.copy("field/images_nogps"), w.inputs / "events.txt")


def gps_bom_crlf_junk(w: Work) -> list[str]:
    images = w.copy("field/images_nogps", "photos ñandú 1")
    (images / "Thumbs.db").write_bytes(b"\x00junk")
    (images / "._SIM_0001.JPG").write_bytes(b"\x00\x05\x16\x07 resource fork")
    log = w.inputs / "événements.txt"
    text = (w.artifacts / "field" / "gnss" / "events.txt").read_text()
    log.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    return gps_args(w, images, log)


def gps_all_matched(w: Work) -> None:
    rows = (w.out / "match_report.csv").read_text().splitlines()[1:]
    assert len(rows) == 9 and all(",matched," in r for r in rows), rows
    assert len(list((w.out / "images").glob("*.JPG"))) == 9


# -- module 8 ------------------------------------------------------------------------------------------------


def projection_args(w: Work, project, predictions) -> list[str]:
    return ["--set", f"project={project}", "--set", f"predictions={predictions}", "--set", f"output_dir={w.out}"]


def projection_truncated_reconstruction(w: Work) -> list[str]:
    project = w.copy("field", "my field")
    rec = project / "opensfm" / "undistorted" / "reconstruction.json"
    rec.write_bytes(rec.read_bytes()[: len(rec.read_bytes()) // 2])
    return projection_args(w, project, w.copy("predictions.json"))


def projection_unicode_paths(w: Work) -> list[str]:
    return projection_args(w, w.copy("field", "champ d'essai ñ 2024"), w.copy("predictions.json", "détections.json"))


def plants_written(w: Work) -> None:
    assert (w.out / "plants.gpkg").is_file() and (w.out / "plants.csv").is_file()


# -- module 9 ------------------------------------------------------------------------------------------------


def stats_missing_dsm(w: Work) -> list[str]:
    return [
        "--set",
        f"polygons={w.copy('plants/plants.gpkg')}",
        "--set",
        f"rasters.dsm={w.inputs / 'dsm.tif'}",
        "--set",
        f"output_dir={w.out}",
    ]


CASES = [
    Case("m0-missing-gnss-log", "gps_embeder", gps_missing_log, mentions=("events.txt",)),
    Case("m0-bom-crlf-log-junk-files-unicode", "gps_embeder", gps_bom_crlf_junk, expect="ok", check=gps_all_matched),
    Case(
        "m8-truncated-reconstruction",
        "plant_projection",
        projection_truncated_reconstruction,
        mentions=("reconstruction.json",),
    ),
    Case("m8-unicode-and-space-paths", "plant_projection", projection_unicode_paths, expect="ok", check=plants_written),
    Case("m9-missing-dsm", "spatial_stat_extractor", stats_missing_dsm, mentions=("dsm",)),
]
