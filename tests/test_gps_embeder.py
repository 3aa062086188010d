"""Module 0 (gps_embed): GNSS log readers, clock offset, one-to-one matching, lossless EXIF GPS writing."""

from __future__ import annotations

import calendar
import csv
import datetime as dt
import io
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import piexif
import pytest
from PIL import Image
from pyproj import Transformer

from matchplant.core.formats.exif import (
    exif_gps,
    exif_time,
    jpeg_scan_data,
    jpeg_segments,
    load_exif,
    splice_exif,
    write_gps_copy,
)
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.runtime.io import BatchedWrites
from matchplant.gps_embeder import GpsEmbederConfig
from matchplant.gps_embeder import run as embed_gps
from matchplant.gps_embeder.gnss_log import read_gnss_log
from matchplant.gps_embeder.matching import assign_events, estimate_clock_offset

ROOT = Path(__file__).resolve().parents[1]
T0 = calendar.timegm((2024, 6, 3, 15, 0, 0))  # camera clock of the first image (UTC)
XMP = (
    b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
    b'<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" drone-dji:FlightYawDegree="+12.3"/>'
    b"</rdf:RDF></x:xmpmeta>"
)


def make_jpeg(path: Path, t: float | None, seed: int = 0, xmp: bool = True, size=(48, 32)) -> None:
    """A small JPEG with a JFIF APP0, EXIF (capture time with sub-seconds) and an XMP APP1 segment."""
    rng = np.random.default_rng(seed)
    im = Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    exif = {"0th": {piexif.ImageIFD.Make: b"TestCam"}, "Exif": {}}
    if t is not None:
        whole = int(np.floor(t))
        stamp = dt.datetime.fromtimestamp(whole, dt.timezone.utc)
        exif["Exif"][piexif.ExifIFD.DateTimeOriginal] = stamp.strftime("%Y:%m:%d %H:%M:%S").encode()
        exif["Exif"][piexif.ExifIFD.SubSecTimeOriginal] = f"{int(round((t - whole) * 1000)):03d}".encode()
    buf = io.BytesIO()
    im.save(buf, "jpeg", quality=90, exif=piexif.dump(exif))
    data = buf.getvalue()
    if xmp:  # an XMP APP1 after the EXIF APP1, as cameras write it
        segs, _ = jpeg_segments(data)
        end_exif = [e for m, s, e in segs if m == 0xE1][0]
        payload = b"http://ns.adobe.com/xap/1.0/\x00" + XMP
        data = data[:end_exif] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[end_exif:]
    path.write_bytes(data)


def make_flight(
    tmp: Path, n: int = 12, offset: float = 3600.4, crs: str = "EPSG:32614", drop_events=(), no_time=(), gps_base=True
):
    """Images every 2.0 s (+ jitter) and an events.txt whose clock is the camera's + ``offset``."""
    rng = np.random.default_rng(1)
    img_dir = tmp / "images"
    img_dir.mkdir()
    cam_t = T0 + np.arange(n) * 2.0 + rng.uniform(-0.05, 0.05, n)
    e = 500000 + np.arange(n) * 5.0 + 0.123
    nn = 4600000 + rng.uniform(-1, 1, n)
    z = 300 + rng.uniform(-1, 1, n)
    for i in range(n):
        make_jpeg(img_dir / f"IMG_{i:04d}.JPG", None if i in no_time else cam_t[i], seed=i)
    utc = cam_t + offset + rng.uniform(-0.01, 0.01, n)
    stamp = utc + (18.0 if gps_base else 0.0)
    to_log = Transformer.from_crs("EPSG:32614", crs, always_xy=True)
    x, y = to_log.transform(e, nn)
    lines = ["Timestamp\tX\tY\tZ"] + [
        f"{stamp[i]:.3f}\t{x[i]:.10f}\t{y[i]:.10f}\t{z[i]:.3f}" for i in range(n) if i not in drop_events
    ]
    log = tmp / "events.txt"
    log.write_text("\n".join(lines) + "\n")
    lon, lat = Transformer.from_crs("EPSG:32614", "EPSG:4326", always_xy=True).transform(e, nn)
    return img_dir, log, np.stack([lat, lon, z], axis=-1)


def run(img_dir, log, out, **kw) -> list[dict]:
    cfg = GpsEmbederConfig(images=img_dir, gnss_log=log, output_dir=out, **{"log_crs": "EPSG:32614", **kw})
    return embed_gps(cfg)


def check_positions(rows, out: Path, truth: np.ndarray, img_dir: Path) -> None:
    for row in rows:
        if row["status"] != "matched":
            continue
        k = int(row["image"][4:8])
        written = out / "images" / row["image"]
        lat, lon, alt = exif_gps(load_exif(written))
        assert abs(lat - truth[k, 0]) < 1e-7 and abs(lon - truth[k, 1]) < 1e-7
        assert abs(alt - truth[k, 2]) < 1e-3
        src, dst = (img_dir / row["image"]).read_bytes(), written.read_bytes()
        assert jpeg_scan_data(src) == jpeg_scan_data(dst)  # compressed pixels byte-identical
        assert b"http://ns.adobe.com/xap/1.0/\x00" + XMP in dst  # XMP segment kept
        with Image.open(io.BytesIO(src)) as a, Image.open(io.BytesIO(dst)) as b:
            assert np.array_equal(np.asarray(a), np.asarray(b))


def test_shifted_clock_positions_lossless(tmp_path):
    img_dir, log, truth = make_flight(tmp_path, offset=3600.4)
    before = {p.name: p.read_bytes() for p in img_dir.iterdir()}
    rows = run(img_dir, log, tmp_path / "out")
    assert [r["status"] for r in rows] == ["matched"] * 12
    assert [r["event"] for r in rows] == [str(i + 1) for i in range(12)]
    assert all(abs(float(r["dt_s"])) < 0.05 for r in rows)
    check_positions(rows, tmp_path / "out", truth, img_dir)
    assert {p.name: p.read_bytes() for p in img_dir.iterdir()} == before  # originals untouched
    geo = (tmp_path / "out" / "geo.txt").read_text().splitlines()
    assert geo[0] == "EPSG:4326" and len(geo) == 13
    name, lon, lat, alt = geo[1].split()
    assert name == "IMG_0000.JPG" and abs(float(lat) - truth[0, 0]) < 1e-8
    with open(tmp_path / "out" / "match_report.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 12


def test_batched_writes_rename_only_synced_whole_files(tmp_path):
    """Copies appear under their names only after their batch is synced; an error drops the pending ones."""
    out = tmp_path / "copies"
    payload = [bytes([i]) * (1000 + i) for i in range(7)]
    with pytest.raises(RuntimeError):
        with BatchedWrites(out, batch=3) as w:
            for i, data in enumerate(payload):
                w.write(f"f{i}.jpg", data)
                if i == 1:  # before the first batch is full: nothing under a final name yet
                    assert not list(out.glob("f*.jpg")) and len(list(out.glob(".f*.partial"))) == 2
                if i == 4:
                    raise RuntimeError("crash in the middle of the second batch")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["f0.jpg", "f1.jpg", "f2.jpg"]  # the synced batch, whole; no temporaries left
    assert all((out / f"f{i}.jpg").read_bytes() == payload[i] for i in range(3))
    with BatchedWrites(out, batch=3) as w:
        for i, data in enumerate(payload):
            w.write(f"f{i}.jpg", data)
    assert w.syncs == 3 and sorted(p.name for p in out.iterdir()) == [f"f{i}.jpg" for i in range(7)]
    assert all((out / f"f{i}.jpg").read_bytes() == payload[i] for i in range(7))


def test_missing_timestamp_gap_and_other_crs(tmp_path):
    # image 3 has no EXIF time; events of images 6, 7 are missing (a gap); the log is in lon/lat degrees
    # with X Y columns (EPSG:4326), not the UTM zone
    img_dir, log, truth = make_flight(tmp_path, offset=-7.3, crs="EPSG:4326", drop_events=(6, 7), no_time=(3,))
    rows = run(img_dir, log, tmp_path / "out", log_crs="EPSG:4326")
    status = {r["image"]: r for r in rows}
    assert "no capture time" in status["IMG_0003.JPG"]["reason"]
    assert "gap" in status["IMG_0006.JPG"]["reason"] and "gap" in status["IMG_0007.JPG"]["reason"]
    matched = [r for r in rows if r["status"] == "matched"]
    assert len(matched) == 9
    # events are numbered by log line; image k matches the event that was written for it
    for r in matched:
        k = int(r["image"][4:8])
        assert int(r["event"]) == k + 1 - (2 if k > 7 else 0)
    check_positions(rows, tmp_path / "out", truth, img_dir)
    assert not (tmp_path / "out" / "images" / "IMG_0006.JPG").exists()


def test_wrong_first_image_does_not_fool_offset():
    # the first camera time has no event; the log has 3 extra events at the start
    cam = T0 + np.arange(30) * 2.0
    events = np.concatenate([[T0 - 100, T0 - 50, T0 - 30], cam[1:] + 42.25])
    off, support = estimate_clock_offset(cam, events, 0.3)
    assert abs(off - 42.25) < 1e-6 and support == 29
    idx = assign_events(cam + off, events, 0.3)
    assert idx[0] == -1 and list(idx[1:]) == list(range(3, 32))


def test_assignment_is_one_to_one():
    cam = np.array([10.0, 10.2, 20.0])
    events = np.array([10.1, 20.05])
    idx = assign_events(cam, events, 0.3)
    assert sorted(i for i in idx if i >= 0) == [0, 1] and idx[2] == 1


def test_splice_keeps_jfif_and_xmp(tmp_path):
    make_jpeg(tmp_path / "a.jpg", T0 + 0.5)
    data = (tmp_path / "a.jpg").read_bytes()
    exif = load_exif(tmp_path / "a.jpg")
    exif["GPS"] = {piexif.GPSIFD.GPSLatitude: ((1, 1), (2, 1), (3, 1))}
    out = splice_exif(data, piexif.dump(exif))
    segs, sos = jpeg_segments(out)
    markers = [m for m, _, _ in segs]
    assert markers[0] == 0xE0 and markers[1] == 0xE1  # JFIF then EXIF, as before
    assert sum(out[s + 4 : s + 10] == b"Exif\x00\x00" for m, s, e in segs if m == 0xE1) == 1
    assert XMP in out and jpeg_scan_data(out) == jpeg_scan_data(data)
    # a JPEG without EXIF gets one after its JFIF segment
    buf = io.BytesIO()
    Image.new("RGB", (8, 8)).save(buf, "jpeg")
    plain = buf.getvalue()
    out2 = splice_exif(plain, piexif.dump({"GPS": {piexif.GPSIFD.GPSAltitude: (5, 1)}}))
    assert [m for m, _, _ in jpeg_segments(out2)[0]][:2] == [0xE0, 0xE1]
    assert exif_gps(piexif.load(out2)) is None  # no lat/lon given
    assert jpeg_scan_data(out2) == jpeg_scan_data(plain)


def test_exif_time_subseconds_and_offset():
    exif = {"Exif": {piexif.ExifIFD.DateTimeOriginal: b"2024:06:03 15:00:00", piexif.ExifIFD.SubSecTimeOriginal: b"45"}}
    assert exif_time(exif) == T0 + 0.45
    assert exif_time(exif, utc_offset_h=-5) == T0 + 0.45 + 5 * 3600
    exif["Exif"][0x9011] = b"+02:00"
    assert exif_time(exif, utc_offset_h=-5) == T0 + 0.45 - 7200
    assert exif_time({"Exif": {}}) is None


def test_log_formats(tmp_path):
    # CSV with lat/lon and ISO UTC times
    p = tmp_path / "log.csv"
    p.write_text("time,lat,lon,alt\n2024-06-03T15:00:01.250,40.1,-96.5,300.5\n2024-06-03T15:00:03.250,40.2,-96.6,301\n")
    g = read_gnss_log(p, time_base="utc")
    assert g.format == "csv" and g.crs.to_epsg() == 4326
    assert g.times[0] == T0 + 1.25 and np.allclose(g.wgs84()[1], [-96.6, 40.2, 301])
    # RTKLIB .pos (GPST, degrees)
    p = tmp_path / "sol.pos"
    p.write_text(
        "% program   : RTKPOST ver.2.4.3\n"
        "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)\n"
        "2024/06/03 15:00:19.000   40.123456789  -96.123456789   215.1234   1  10   0.0034\n"
    )
    g = read_gnss_log(p)
    assert g.times[0] == T0 + 1.0 and np.allclose(g.wgs84()[0], [-96.123456789, 40.123456789, 215.1234])
    # DJI MRK: seconds of GPS week and [week]
    gps_s = T0 + 18 + 2.5 - calendar.timegm((1980, 1, 6, 0, 0, 0))
    week, sow = divmod(gps_s, 604800)
    p = tmp_path / "DJI_202406031500_001_Timestamp.MRK"
    p.write_text(
        f"1\t{sow:.6f}\t[{int(week)}]\t    -8,N\t    12,E\t   -99,V\t40.26851713,Lat\t-96.73881287,Lon\t"
        "196.052,Ellh\t0.010176, 0.008962, 0.024126\t16,Q\n"
    )
    g = read_gnss_log(p)
    assert g.format == "mrk" and abs(g.times[0] - (T0 + 2.5)) < 1e-6
    assert np.allclose(g.wgs84()[0], [-96.73881287, 40.26851713, 196.052])


def test_clear_errors(tmp_path):
    img_dir, log, _ = make_flight(tmp_path, n=3)
    with pytest.raises(ConfigError, match="log_crs"):
        run(img_dir, log, tmp_path / "o1", log_crs=None)
    bad = tmp_path / "bad.txt"
    bad.write_text("Timestamp\tX\tY\tZ\n1.0\t2\tthree\t4\n")
    with pytest.raises(InputError, match="line 2"):
        read_gnss_log(bad, crs="EPSG:32614")
    bad.write_text("when\tfoo\n1\t2\n")
    with pytest.raises(InputError, match="header"):
        read_gnss_log(bad, crs="EPSG:32614")
    with pytest.raises(MatchPlantError, match="coordinate reference"):
        run(img_dir, log, tmp_path / "o2", log_crs="EPSG:999999")
    with pytest.raises(ConfigError, match="originals"):
        run(img_dir, log, img_dir.parent)
    far = tmp_path / "far.txt"
    far.write_text("Timestamp\tX\tY\tZ\n1000.0\t500000\t4600000\t3\n")
    with pytest.raises(MatchPlantError):
        run(img_dir, far, tmp_path / "o3", max_clock_offset_s=10)


def test_folder_config_and_help():
    cfg = load_config(GpsEmbederConfig, ROOT / "0_gps_embeder" / "config.yaml", check_paths=False, strict=False)
    assert cfg.tolerance_s > 0
    r = subprocess.run(
        [sys.executable, str(ROOT / "0_gps_embeder" / "gps_embeder.py"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "--config" in r.stdout


def test_synthetic_field(tiny_field, tmp_path):
    """The field's GNSS log into its GPS-stripped images: positions equal the raw images' GPS."""
    import json

    field = json.loads(tiny_field.field_json.read_text())
    out = tmp_path / "out"
    cfg = GpsEmbederConfig(
        images=tiny_field.images_nogps, gnss_log=tiny_field.gnss_log, output_dir=out, log_crs=field["crs"]
    )
    rows = embed_gps(cfg)
    assert rows and all(r["status"] == "matched" for r in rows)
    summary = json.loads((out / "match_summary.json").read_text())  # the field's true clock error
    assert abs(summary["clock_offset_s"] + field["clock_offset_s"]) < 0.01
    for r in rows:
        truth = exif_gps(load_exif(tiny_field.images / r["image"]))
        got = exif_gps(load_exif(out / "images" / r["image"]))
        assert abs(got[0] - truth[0]) < 1e-7 and abs(got[1] - truth[1]) < 1e-7
        src = (tiny_field.images_nogps / r["image"]).read_bytes()
        assert jpeg_scan_data(src) == jpeg_scan_data((out / "images" / r["image"]).read_bytes())


def test_unwritable_vendor_tag_is_dropped(tmp_path):
    # SceneType stored as a number (some cameras do): piexif cannot write it back; the copy still works
    make_jpeg(tmp_path / "a.jpg", T0 + 0.25)
    exif = load_exif(tmp_path / "a.jpg")
    exif["Exif"][piexif.ExifIFD.SceneType] = 1
    write_gps_copy(tmp_path / "a.jpg", tmp_path / "b.jpg", exif, 40.1, -96.2, 300.0)
    out = load_exif(tmp_path / "b.jpg")
    assert exif_gps(out) == pytest.approx((40.1, -96.2, 300.0)) and exif_time(out) == T0 + 0.25


def test_log_values_are_checked_with_their_line(tmp_path):
    """Values that read as numbers but cannot be a camera event are refused with the log's line."""
    p = tmp_path / "events.txt"
    head = "# receiver export\nTimestamp\tX\tY\tZ\n"
    good = [f"{1717601400 + 2 * k}.0\t{500000 + k}\t4600000\t300" for k in range(5)]
    cases = {
        "nan position": (3, "\tnan\t", "position"),
        "ms timestamp": (None, None, "timestamp_unit"),
        "absurd time": (4, "9e15", "absurd"),
        "height in mm": (None, "mm", "height"),
    }
    for name, (line, what, expect) in cases.items():
        rows = list(good)
        if name == "nan position":
            rows[0] = rows[0].replace("\t500000\t", what)
        elif name == "ms timestamp":
            rows = [f"{float(r.split()[0]) * 1000:.0f}\t" + "\t".join(r.split()[1:]) for r in rows]
        elif name == "absurd time":
            rows[1] = what + rows[1][rows[1].index("\t") :]
        else:
            rows = [r[: r.rindex("\t")] + "\t300000" for r in rows]
        p.write_text(head + "\n".join(rows) + "\n")
        with pytest.raises(InputError, match=expect) as err:
            read_gnss_log(p, crs="EPSG:32614")
        if line is not None:
            assert f"line {line}" in str(err.value), (name, err.value)
    # the same log in milliseconds reads exactly like the one in seconds once the unit is set
    p.write_text(head + "\n".join(good) + "\n")
    seconds = read_gnss_log(p, crs="EPSG:32614")
    p.write_text(head + "\n".join(f"{float(r.split()[0]) * 1000:.0f}\t" + "\t".join(r.split()[1:]) for r in good))
    ms = read_gnss_log(p, crs="EPSG:32614", timestamp_unit="ms")
    assert np.array_equal(seconds.times, ms.times) and seconds.lines == [3, 4, 5, 6, 7]


def test_duplicate_and_swapped_log_lines(tmp_path):
    p = tmp_path / "events.txt"
    rows = ["Timestamp\tX\tY\tZ", "1717601400.0\t500000\t4600000\t300", "1717601402.0\t500005\t4600000\t300"]
    p.write_text("\n".join(rows + [rows[2]]) + "\n")  # the same line twice: used once
    g = read_gnss_log(p, crs="EPSG:32614")
    assert len(g.times) == 2 and g.lines == [2, 3]
    p.write_text("\n".join(rows + ["1717601402.0\t500009\t4600000\t300"]) + "\n")  # same time, other place
    with pytest.raises(InputError, match="lines 3 and 4"):
        read_gnss_log(p, crs="EPSG:32614")
    p.write_text("Timestamp\tY\tX\tZ\n" + "\n".join(rows[1:]) + "\n")  # northing in X
    with pytest.raises(InputError, match="swapped"):
        read_gnss_log(p, crs="EPSG:32614")


def test_ambiguous_or_weak_offset_is_refused(tmp_path):
    from matchplant.gps_embeder.matching import check_support

    cam = T0 + np.arange(9) * 2.0
    one = type("G", (), {"times": np.array([T0 + 100.0]), "path": tmp_path / "e.txt"})()
    with pytest.raises(InputError, match="ambiguous"):  # one event fits any of the 9 images
        check_support(1, 100.0, cam, one, 0.5)
    weak = type("G", (), {"times": T0 + 100 + np.arange(9) * 2000.0, "path": tmp_path / "e.txt"})()
    with pytest.raises(InputError, match="ms, set 'timestamp_unit'"):  # events 1000x as far apart
        check_support(1, 100.0, cam, weak, 0.5)
    fine = type("G", (), {"times": cam + 100.0, "path": tmp_path / "e.txt"})()
    check_support(9, 100.0, cam, fine, 0.5)


def test_failed_run_leaves_no_copies(tmp_path):
    img_dir, log, _ = make_flight(tmp_path, n=6)
    data = (img_dir / "IMG_0003.JPG").read_bytes()
    (img_dir / "IMG_0003.JPG").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="IMG_0003.JPG"):
        run(img_dir, log, tmp_path / "out")
    assert not (tmp_path / "out" / "images").exists() or not any((tmp_path / "out" / "images").iterdir())
    with pytest.raises(InputError, match="no image could be matched"):
        (img_dir / "IMG_0003.JPG").write_bytes(data)
        run(img_dir, log, tmp_path / "out2", clock_offset_s=-5000.0)
    assert sorted(p.name for p in (tmp_path / "out2").rglob("*") if p.is_file()) == ["match_report.csv"]
