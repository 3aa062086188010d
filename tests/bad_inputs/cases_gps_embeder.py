"""Module 0 (gps_embeder): broken images, GNSS logs in the wrong unit or CRS, absurd values, outputs in the
wrong place, and the inputs that must work (BOM/CRLF, lat/lon CSV, a line logged twice, ms with the unit set).

The must-work checks compare the written GPS with the tiny field's truth: its ``images/`` carry the true
position of every photo (the field generator wrote them), ``images_nogps/`` are the same photos without.
"""

from __future__ import annotations

import csv
import json
import os
import stat
from pathlib import Path

import piexif
import pytest
from harness import Case, Work, read_rows, write_rows
from pyproj import Transformer

from matchplant.core.formats.exif import exif_gps, load_exif


def crs(w: Work) -> str:
    return json.loads((w.artifacts / "field" / "truth" / "field.json").read_text())["crs"]


def args(w: Work, images: Path, log: Path, *extra: str, log_crs: str | None = "field") -> list[str]:
    a = ["--set", f"images={images}", "--set", f"gnss_log={log}", "--set", f"output_dir={w.out}"]
    if log_crs:
        a += ["--set", f"log_crs={crs(w) if log_crs == 'field' else log_crs}"]
    for e in extra:
        a += ["--set", e]
    return a


def events(w: Work) -> list[list[str]]:
    """The field's events.txt as rows (header first)."""
    return read_rows(w.artifacts / "field" / "gnss" / "events.txt", "\t")


def write_events(w: Work, rows: list[list[str]], name: str = "events.txt", sep: str = "\t") -> Path:
    return write_rows(w, rows, name, sep)


def images(w: Work, name: str = "images_nogps") -> Path:
    return w.copy(f"field/{name}")


# -- checks --------------------------------------------------------------------------------------------------


def matched_like_truth(n: int = 9):
    """``n`` images matched, each copy's GPS within 1e-7 degrees of the field's truth."""

    def check(w: Work) -> None:
        with open(w.out / "match_report.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        ok = [r for r in rows if r["status"] == "matched"]
        assert len(ok) == n, rows
        for r in ok:
            got = exif_gps(load_exif(w.out / "images" / r["image"]))
            true = exif_gps(load_exif(w.artifacts / "field" / "images" / r["image"]))
            assert abs(got[0] - true[0]) < 1e-7 and abs(got[1] - true[1]) < 1e-7, (r["image"], got, true)
        assert sorted(p.name for p in (w.out / "images").iterdir()) == sorted(r["image"] for r in ok)

    return check


# -- damaged images ------------------------------------------------------------------------------------------


def truncated_jpeg(w: Work) -> list[str]:
    imgs = images(w)
    p = imgs / "SIM_0004.JPG"
    p.write_bytes(p.read_bytes()[: p.stat().st_size * 2 // 3])
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def jpeg_without_eoi(w: Work) -> list[str]:
    imgs = images(w)
    p = imgs / "SIM_0007.JPG"
    p.write_bytes(p.read_bytes()[:-2])
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def empty_jpeg(w: Work) -> list[str]:
    imgs = images(w)
    (imgs / "SIM_0002.JPG").write_bytes(b"")
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def text_named_jpeg(w: Work) -> list[str]:
    imgs = images(w)
    (imgs / "notes.jpg").write_text("<html>download failed</html>")
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def no_exif_time(w: Work) -> list[str]:
    imgs = images(w)
    for p in imgs.glob("*.JPG"):
        piexif.remove(str(p))
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def one_image_without_time(w: Work) -> list[str]:
    imgs = images(w)
    piexif.remove(str(imgs / "SIM_0005.JPG"))
    return args(w, imgs, w.copy("field/gnss/events.txt"))


def one_without_time_reported(w: Work) -> None:
    matched_like_truth(8)(w)
    with open(w.out / "match_report.csv", newline="") as fh:
        row = next(r for r in csv.DictReader(fh) if r["image"] == "SIM_0005.JPG")
    assert row["status"] == "unmatched" and "capture time" in row["reason"]


# -- logs: empty, units, values ------------------------------------------------------------------------------


def empty_log(w: Work) -> list[str]:
    (w.inputs / "events.txt").write_bytes(b"")
    return args(w, images(w), w.inputs / "events.txt")


def header_only_log(w: Work) -> list[str]:
    return args(w, images(w), write_events(w, events(w)[:1]))


def timestamps_in_ms(w: Work) -> list[str]:
    rows = events(w)
    rows[1:] = [[f"{float(r[0]) * 1000:.0f}", *r[1:]] for r in rows[1:]]
    return args(w, images(w), write_events(w, rows))


def timestamps_in_ms_unit_set(w: Work) -> list[str]:
    return [*timestamps_in_ms(w), "--set", "timestamp_unit=ms"]


def timestamps_ms_since_start(w: Work) -> list[str]:
    """Milliseconds since the receiver started: small numbers that look like seconds of the GPS week."""
    rows = events(w)
    t0 = float(rows[1][0])
    rows[1:] = [[f"{(float(r[0]) - t0) * 1000 + 5000:.0f}", *r[1:]] for r in rows[1:]]
    return args(w, images(w), write_events(w, rows))


def absurd_timestamp(w: Work) -> list[str]:
    rows = events(w)
    rows[5][0] = "9.9e15"
    return args(w, images(w), write_events(w, rows))


def typo_timestamp(w: Work) -> list[str]:
    rows = events(w)
    rows[6][0] = rows[6][0].replace(".", "0.", 1)  # 315032.000 -> 3150320.000: a digit too many
    return args(w, images(w), write_events(w, rows))


def nan_position(w: Work) -> list[str]:
    rows = events(w)
    rows[3][1] = "nan"
    return args(w, images(w), write_events(w, rows))


def nan_timestamp(w: Work) -> list[str]:
    rows = events(w)
    rows[8][0] = "NaN"
    return args(w, images(w), write_events(w, rows))


def empty_cell(w: Work) -> list[str]:
    rows = events(w)
    rows[2][2] = ""
    return args(w, images(w), write_events(w, rows))


def height_in_mm(w: Work) -> list[str]:
    rows = events(w)
    rows[1:] = [[*r[:3], f"{float(r[3]) * 1000:.0f}"] for r in rows[1:]]
    return args(w, images(w), write_events(w, rows))


def duplicate_time_two_positions(w: Work) -> list[str]:
    rows = events(w)
    rows.insert(4, [rows[3][0], str(float(rows[3][1]) + 3.0), *rows[3][2:]])
    return args(w, images(w), write_events(w, rows))


def line_logged_twice(w: Work) -> list[str]:
    rows = events(w)
    rows.insert(4, list(rows[3]))
    return args(w, images(w), write_events(w, rows))


def log_of_another_flight(w: Work) -> list[str]:
    """Same number of events, same week, but a different rhythm: no clock offset fits more than one image."""
    rows = events(w)
    rows[1:] = [[f"{315018 + 7.3 * k * k:.3f}", *r[1:]] for k, r in enumerate(rows[1:])]
    return args(w, images(w), write_events(w, rows))


def fixed_offset_matches_nothing(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gnss/events.txt"), "clock_offset_s=5000", "copy_unmatched=true")


# -- logs: CRS and coordinate units --------------------------------------------------------------------------


def latlon_rows(w: Work) -> list[list[str]]:
    rows = events(w)
    to_ll = Transformer.from_crs(crs(w), "EPSG:4326", always_xy=True)
    out = [["time", "lat", "lon", "alt"]]
    for r in rows[1:]:
        lon, lat = to_ll.transform(float(r[1]), float(r[2]))
        out.append([r[0], f"{lat:.10f}", f"{lon:.10f}", r[3]])
    return out


def latlon_header_holds_metres(w: Work) -> list[str]:
    rows = events(w)
    rows[0] = ["time", "lon", "lat", "alt"]
    return args(w, images(w), write_events(w, rows, "gnss.csv", ","), log_crs=None)


def xy_header_holds_degrees(w: Work) -> list[str]:
    rows = latlon_rows(w)
    rows = [["Timestamp", "X", "Y", "Z"]] + [[r[0], r[2], r[1], r[3]] for r in rows[1:]]
    return args(w, images(w), write_events(w, rows))


def wrong_crs_string(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gnss/events.txt"), log_crs="EPSG:99999")


def wrong_utm_zone(w: Work) -> list[str]:
    """The photos carry their own GPS (as drone photos do): the log's positions in zone 15 land 500 km away."""
    return args(w, images(w, "images"), w.copy("field/gnss/events.txt"), log_crs="EPSG:32615")


def geographic_crs_for_metres(w: Work) -> list[str]:
    return args(w, images(w), w.copy("field/gnss/events.txt"), log_crs="EPSG:4326")


def latlon_csv_semicolon_bom_crlf(w: Work) -> list[str]:
    path = w.inputs / "gnss export.csv"
    text = "".join(";".join(r) + "\r\n" for r in latlon_rows(w))
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    return args(w, images(w), path)  # log_crs (projected) is set too: lat/lon columns win, with a warning


def images_with_gps_right_crs(w: Work) -> list[str]:
    return args(w, images(w, "images"), w.copy("field/gnss/events.txt"))


def log_with_comments_and_blank_lines(w: Work) -> list[str]:
    rows = events(w)
    path = w.inputs / "events.txt"
    lines = ["# exported by the receiver", "\t".join(rows[0]), ""]
    for r in rows[1:]:
        lines += ["\t".join(r), ""]
    path.write_text("\n".join(lines))
    return args(w, images(w), path)


def single_event_log(w: Work) -> list[str]:
    return args(w, images(w), write_events(w, events(w)[:2]))


def latlon_swapped_csv(w: Work) -> list[str]:
    rows = latlon_rows(w)
    rows[0] = ["time", "lon", "lat", "alt"]  # the values stay lat, lon
    return args(w, images(w), write_events(w, rows, "gnss.csv", ","), log_crs=None)


def xy_swapped(w: Work) -> list[str]:
    rows = events(w)
    rows[0] = ["Timestamp", "Y", "X", "Z"]
    return args(w, images(w), write_events(w, rows))


def utf16_log(w: Work) -> list[str]:
    path = w.inputs / "events.txt"
    path.write_bytes(
        (w.artifacts / "field" / "gnss" / "events.txt").read_text().replace("\n", "\r\n").encode("utf-16")
    )  # Windows Notepad's "Unicode"
    return args(w, images(w), path)


def semicolon_decimal_comma(w: Work) -> list[str]:
    rows = [[c.replace(".", ",") for c in r] for r in events(w)]
    return args(w, images(w), write_events(w, rows, "events.csv", ";"))


def log_ends_early(w: Work) -> list[str]:
    """The receiver stopped before the last two photos: 7 matched, the 2 others reported."""
    return args(w, images(w), write_events(w, events(w)[:8]))


def seven_matched_rest_reported(w: Work) -> None:
    matched_like_truth(7)(w)
    with open(w.out / "match_report.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["status"] != "matched"]
    assert len(rows) == 2 and all("after the GNSS log ends" in r["reason"] for r in rows), rows


def log_of_first_lines_only(w: Work) -> list[str]:
    """5 events in the rhythm of the flight lines: shifted by one line they fit as well (a regular flight)."""
    return args(w, images(w), write_events(w, events(w)[:6]))


def log_of_first_lines_window_set(w: Work) -> list[str]:
    """The same partial log works once 'max_clock_offset_s' rules out the shift by one flight line."""
    return [*log_of_first_lines_only(w), "--set", "max_clock_offset_s=5"]


# -- outputs -------------------------------------------------------------------------------------------------


def output_is_image_folder(w: Work) -> list[str]:
    imgs = images(w)
    a = args(w, imgs, w.copy("field/gnss/events.txt"))
    return [x if not x.startswith("output_dir=") else f"output_dir={imgs}" for x in a]


def output_inside_image_folder(w: Work) -> list[str]:
    imgs = images(w)
    a = args(w, imgs, w.copy("field/gnss/events.txt"))
    return [x if not x.startswith("output_dir=") else f"output_dir={imgs / 'gps'}" for x in a]


def output_folder_is_a_file(w: Work) -> list[str]:
    a = args(w, images(w), w.copy("field/gnss/events.txt"))
    blocker = w.root / "gps_out"
    blocker.write_text("not a folder")
    return [x if not x.startswith("output_dir=") else f"output_dir={blocker}" for x in a]


def readonly_output(w: Work) -> list[str]:
    a = args(w, images(w), w.copy("field/gnss/events.txt"))
    w.out.mkdir()
    os.chmod(w.out, stat.S_IRUSR | stat.S_IXUSR)
    return a


def rerun_into_previous_output(w: Work) -> list[str]:
    """A second run into the folder of a first one (here: an older, stale copy and report) must work."""
    (w.out / "images").mkdir(parents=True)
    (w.out / "images" / "SIM_0001.JPG").write_bytes(b"stale")
    (w.out / "match_report.csv").write_text("old\n")
    return args(w, images(w), w.copy("field/gnss/events.txt"))


def root_ignores_permissions() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


ROOT_SKIP = (pytest.mark.skipif(root_ignores_permissions(), reason="root writes into read-only folders"),)


CASES = [
    Case("m0-truncated-jpeg", "gps_embeder", truncated_jpeg, mentions=("SIM_0004.JPG", "truncated")),
    Case("m0-jpeg-without-eoi", "gps_embeder", jpeg_without_eoi, mentions=("SIM_0007.JPG",)),
    Case("m0-empty-jpeg", "gps_embeder", empty_jpeg, mentions=("SIM_0002.JPG",)),
    Case("m0-text-file-named-jpg", "gps_embeder", text_named_jpeg, mentions=("notes.jpg",)),
    Case("m0-no-exif-time", "gps_embeder", no_exif_time, mentions=("images_nogps", "capture time")),
    Case(
        "m0-one-image-without-time", "gps_embeder", one_image_without_time, expect="ok", check=one_without_time_reported
    ),
    Case("m0-empty-log", "gps_embeder", empty_log, mentions=("events.txt", "empty")),
    Case("m0-header-only-log", "gps_embeder", header_only_log, mentions=("events.txt", "header")),
    Case("m0-timestamps-in-ms", "gps_embeder", timestamps_in_ms, mentions=("events.txt", "timestamp_unit", "ms")),
    Case(
        "m0-timestamps-in-ms-unit-set",
        "gps_embeder",
        timestamps_in_ms_unit_set,
        expect="ok",
        check=matched_like_truth(),
    ),
    Case(
        "m0-timestamps-ms-since-start",
        "gps_embeder",
        timestamps_ms_since_start,
        mentions=("events.txt", "timestamp_unit"),
    ),
    Case("m0-absurd-timestamp", "gps_embeder", absurd_timestamp, mentions=("events.txt", "line 6")),
    Case("m0-timestamp-typo", "gps_embeder", typo_timestamp, mentions=("events.txt", "line 7")),
    Case("m0-nan-position", "gps_embeder", nan_position, mentions=("events.txt", "line 4")),
    Case("m0-nan-timestamp", "gps_embeder", nan_timestamp, mentions=("events.txt", "line 9")),
    Case("m0-empty-cell", "gps_embeder", empty_cell, mentions=("events.txt", "line 3")),
    Case("m0-height-in-mm", "gps_embeder", height_in_mm, mentions=("events.txt", "line 2", "height")),
    Case(
        "m0-same-time-two-positions",
        "gps_embeder",
        duplicate_time_two_positions,
        mentions=("events.txt", "lines 4 and 5"),
    ),
    Case("m0-line-logged-twice", "gps_embeder", line_logged_twice, expect="ok", check=matched_like_truth()),
    Case("m0-log-of-another-flight", "gps_embeder", log_of_another_flight, mentions=("events.txt", "supported by")),
    Case(
        "m0-fixed-offset-matches-nothing",
        "gps_embeder",
        fixed_offset_matches_nothing,
        mentions=("events.txt", "clock_offset_s", "match_report.csv"),
        outputs_allowed=("match_report.csv",),
    ),
    Case(
        "m0-latlon-header-holds-metres",
        "gps_embeder",
        latlon_header_holds_metres,
        mentions=("gnss.csv", "line 2", "metres"),
    ),
    Case(
        "m0-xy-header-holds-degrees",
        "gps_embeder",
        xy_header_holds_degrees,
        mentions=("events.txt", "line 2", "degrees", "log_crs"),
    ),
    Case("m0-wrong-crs-string", "gps_embeder", wrong_crs_string, mentions=("log_crs", "EPSG:99999")),
    Case("m0-wrong-utm-zone", "gps_embeder", wrong_utm_zone, mentions=("events.txt", "log_crs", "km")),
    Case(
        "m0-geographic-crs-for-metres",
        "gps_embeder",
        geographic_crs_for_metres,
        mentions=("events.txt", "log_crs", "line 2"),
    ),
    Case(
        "m0-latlon-csv-semicolon-bom-crlf",
        "gps_embeder",
        latlon_csv_semicolon_bom_crlf,
        expect="ok",
        check=matched_like_truth(),
    ),
    Case("m0-images-with-gps", "gps_embeder", images_with_gps_right_crs, expect="ok", check=matched_like_truth()),
    Case(
        "m0-log-comments-blank-lines",
        "gps_embeder",
        log_with_comments_and_blank_lines,
        expect="ok",
        check=matched_like_truth(),
    ),
    Case("m0-single-event-log", "gps_embeder", single_event_log, mentions=("events.txt", "clock_offset_s")),
    Case("m0-latlon-swapped", "gps_embeder", latlon_swapped_csv, mentions=("gnss.csv", "swapped")),
    Case("m0-xy-swapped", "gps_embeder", xy_swapped, mentions=("events.txt", "swapped")),
    Case("m0-utf16-log", "gps_embeder", utf16_log, expect="ok", check=matched_like_truth()),
    Case("m0-semicolon-decimal-comma", "gps_embeder", semicolon_decimal_comma, expect="ok", check=matched_like_truth()),
    Case("m0-log-ends-early", "gps_embeder", log_ends_early, expect="ok", check=seven_matched_rest_reported),
    Case(
        "m0-log-fits-two-offsets",
        "gps_embeder",
        log_of_first_lines_only,
        mentions=("events.txt", "ambiguous", "clock_offset_s"),
    ),
    Case(
        "m0-log-fits-two-offsets-window-set",
        "gps_embeder",
        log_of_first_lines_window_set,
        expect="ok",
        check=matched_like_truth(5),
    ),
    Case("m0-output-is-image-folder", "gps_embeder", output_is_image_folder, mentions=("output_dir",)),
    Case("m0-output-inside-image-folder", "gps_embeder", output_inside_image_folder, mentions=("output_dir",)),
    Case("m0-output-folder-is-a-file", "gps_embeder", output_folder_is_a_file, mentions=("output_dir", "gps_out")),
    Case("m0-readonly-output", "gps_embeder", readonly_output, mentions=("output_dir",), marks=ROOT_SKIP),
    Case(
        "m0-rerun-into-previous-output",
        "gps_embeder",
        rerun_into_previous_output,
        expect="ok",
        check=matched_like_truth(),
    ),
]
