"""Benchmark module 0 (gps_embed): match N images to a GNSS log and write their GPS EXIF.

    python -m bench.bench_gps_embeder            # 1,000 images of 2000x1500 px
    python -m bench.bench_gps_embeder --quick    # 200 images

Prints images per second for the whole run (read EXIF, estimate the clock offset, match, write the
copies, report) and the time of the clock-offset estimate alone.

``python -m bench --only gps-embed`` times it against ``exiftool -geotag`` on the same 300 images
(:func:`comparison`; exiftool from the system: ``apt-get install libimage-exiftool-perl``);
``--only gps-embed-process`` as whole processes on 1.1 MB JPEGs (:func:`process_comparison`).
"""

from __future__ import annotations

import argparse
import calendar
import datetime as dt
import io
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import piexif
import yaml
from PIL import Image
from pyproj import Transformer

from bench.process import matchplant_command, run_process
from matchplant.core.formats.exif import exif_gps, load_exif, splice_exif
from matchplant.gps_embeder import GpsEmbederConfig
from matchplant.gps_embeder import run as embed_gps
from matchplant.gps_embeder.gnss_log import read_gnss_log
from matchplant.gps_embeder.matching import estimate_clock_offset, read_images

os.environ.setdefault("MATCHPLANT_QUIET", "1")


def make_flight(root: Path, n: int, width: int) -> tuple[Path, Path]:
    """Write ``n`` JPEGs with camera times and a matching GNSS log under ``root``; their folder and the log."""
    rng = np.random.default_rng(0)
    h = width * 3 // 4
    # one textured photo, re-stamped for every image (encoding 1,000 JPEGs would dominate the set-up)
    base = rng.integers(60, 200, (h // 8, width // 8, 3), dtype=np.uint8)
    img = Image.fromarray(base).resize((width, h), Image.BILINEAR)
    buf = io.BytesIO()
    img.save(buf, "jpeg", quality=90, exif=piexif.dump({"0th": {piexif.ImageIFD.Make: b"Bench"}}))
    data = buf.getvalue()
    images = root / "images"
    images.mkdir()
    t0 = calendar.timegm((2024, 6, 5, 15, 0, 0))
    cam = t0 + np.arange(n) * 2.0 + rng.uniform(-0.02, 0.02, n)
    for i, t in enumerate(cam):
        whole = int(t)
        stamp = dt.datetime.fromtimestamp(whole, dt.timezone.utc).strftime("%Y:%m:%d %H:%M:%S").encode()
        exif = {
            "0th": {piexif.ImageIFD.Make: b"Bench"},
            "Exif": {
                piexif.ExifIFD.DateTimeOriginal: stamp,
                piexif.ExifIFD.SubSecTimeOriginal: f"{int((t - whole) * 1000):03d}".encode(),
            },
        }
        (images / f"IMG_{i:05d}.JPG").write_bytes(splice_exif(data, piexif.dump(exif)))
    log = root / "events.txt"
    e = 700000 + (np.arange(n) // 50) * 10.0
    nn = 4500000 + (np.arange(n) % 50) * 5.0
    with open(log, "w") as fh:
        fh.write("Timestamp\tX\tY\tZ\n")
        for i in range(n):
            fh.write(f"{cam[i] + 3600.4 + 18:.3f}\t{e[i]:.4f}\t{nn[i]:.4f}\t{380.0:.3f}\n")
    return images, log


def write_gpx(path: Path, log: Path, offset_s: float) -> Path:
    """The events as a GPX track in WGS84, times moved onto the camera clock (exiftool cannot estimate
    the offset; it gets it for free here), for ``exiftool -geotag``."""
    rows = np.loadtxt(log, skiprows=1)
    lon, lat = Transformer.from_crs("EPSG:32614", "EPSG:4326", always_xy=True).transform(rows[:, 1], rows[:, 2])
    pts = []
    for t, x, y, z in zip(rows[:, 0] - offset_s, lon, lat, rows[:, 3]):
        stamp = dt.datetime.fromtimestamp(t, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        pts.append(f'<trkpt lat="{y:.9f}" lon="{x:.9f}"><ele>{z:.3f}</ele><time>{stamp}</time></trkpt>')
    path.write_text(
        '<?xml version="1.0"?>\n<gpx version="1.1" creator="bench"><trk><trkseg>\n'
        + "\n".join(pts)
        + "\n</trkseg></trk></gpx>\n"
    )
    return path


def exiftool_command(exiftool: str, gpx: Path, images: Path, out: Path) -> list[str]:
    """exiftool writing the GPS of the track into copies of the images in ``out``."""
    return [
        exiftool,
        "-q",
        "-m",
        "-geotag",
        str(gpx),
        "-geotime<${SubSecDateTimeOriginal}+00:00",
        "-o",
        f"{out}/",
        str(images),
    ]


def comparison(name: str, work: Path, quick: bool, device: str, width: int = 2000):
    """For ``python -m bench``: module 0 on 300 JPEGs of 2000 x 1500 (quick: 60) against
    ``exiftool -geotag`` writing copies of the same images into another folder (in-process: module 0's
    ``run``; ``gps-embed-process``: :func:`process_comparison`)."""
    from bench.harness import Comparison

    if name == "gps-embed-process":
        return process_comparison(work, quick)
    n = 60 if quick else 300
    images, log = make_flight(work, n, width)
    gpx = write_gpx(work / "track.gpx", log, 3600.4 + 18)
    ours_out, peer_out = work / "ours", work / "exiftool"
    cfg = GpsEmbederConfig(images=images, gnss_log=log, output_dir=ours_out, log_crs="EPSG:32614")

    def reset(side: str):
        shutil.rmtree(ours_out if side == "ours" else peer_out, ignore_errors=True)

    def ours():
        rows = embed_gps(cfg)
        if not all(r["status"] == "matched" for r in rows):
            raise RuntimeError("benchmark flight must match completely")

    exiftool = shutil.which("exiftool")
    version = subprocess.run([exiftool, "-ver"], capture_output=True, text=True).stdout.strip() if exiftool else None

    def peer():
        peer_out.mkdir()
        return run_process(exiftool_command(exiftool, gpx, images, peer_out))

    def check() -> dict:
        """Both wrote every image with a position; largest distance between them (m, rough)."""
        worst = 0.0
        for p in sorted(images.iterdir()):
            a = exif_gps(load_exif(ours_out / "images" / p.name))
            b = exif_gps(load_exif(peer_out / p.name))
            worst = max(worst, abs(a[0] - b[0]) * 111e3, abs(a[1] - b[1]) * 80e3)
        return {"images_written_by_both": n, "largest_position_difference_m": worst}

    size = sum(p.stat().st_size for p in images.iterdir()) / n / 1e6
    return Comparison(
        name,
        f"{n} JPEGs of {width} x {width * 3 // 4} ({size:.2f} MB each): GPS into EXIF copies",
        "matchplant gps_embed",
        "exiftool -geotag",
        ours,
        peer if exiftool else None,
        reset=reset,
        check=check if exiftool else None,
        items=n,
        unit="images",
        skip=None if exiftool else "exiftool is not installed (apt-get install libimage-exiftool-perl)",
        notes={"exiftool": version},
    )


def process_comparison(work: Path, quick: bool):
    """``gps-embed-process``: module 0's command (``python -m matchplant.cli gps_embeder --config``) against
    ``exiftool -geotag``, both writing GPS into copies of 300 JPEGs of 2600 x 1950 (1.1 MB each; quick: 60),
    whole processes: imports, reading and writing the files as a user meets them."""
    from bench.harness import Comparison

    cmp = comparison("gps-embed", work, quick, "cpu", width=2600)
    cfg = work / "module0.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "images": str(work / "images"),
                "gnss_log": str(work / "events.txt"),
                "output_dir": str(work / "ours"),
                "log_crs": "EPSG:32614",
            }
        )
    )
    return Comparison(
        "gps-embed-process",
        cmp.what + ", whole processes",
        "matchplant gps_embeder (command)",
        cmp.peer_label,
        lambda: run_process(matchplant_command("gps_embeder", cfg)),
        cmp.peer,
        reset=cmp.reset,
        check=cmp.check,
        items=cmp.items,
        unit=cmp.unit,
        skip=cmp.skip,
        notes=cmp.notes,
    )


def main(argv=None) -> int:
    """Parse the options, time module 0 on a generated flight and print the images per second."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="200 images instead of 1,000")
    ap.add_argument("--n", type=int, default=None, help="number of images")
    ap.add_argument("--width", type=int, default=2000, help="image width in pixels")
    args = ap.parse_args(argv)
    n = args.n or (200 if args.quick else 1000)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t = time.perf_counter()
        images, log = make_flight(root, n, args.width)
        size_mb = sum(p.stat().st_size for p in images.iterdir()) / 1e6
        print(f"set-up: {n} images ({size_mb / n:.2f} MB each) in {time.perf_counter() - t:.1f} s")
        cfg = GpsEmbederConfig(images=images, gnss_log=log, output_dir=root / "out", log_crs="EPSG:32614")
        t = time.perf_counter()
        rows = embed_gps(cfg)
        dt_all = time.perf_counter() - t
        assert all(r["status"] == "matched" for r in rows), "benchmark flight must match completely"
        g = read_gnss_log(log, crs="EPSG:32614")
        cam = np.array([r.time for r in read_images(images)])
        t = time.perf_counter()
        off, support = estimate_clock_offset(cam, g.times, 0.5)
        dt_off = time.perf_counter() - t
    print(f"gps_embed: {n} images in {dt_all:.2f} s = {n / dt_all:.0f} images/s ({size_mb / dt_all:.0f} MB/s written)")
    print(
        f"clock offset estimate alone: {dt_off * 1000:.0f} ms for {n}x{n} pairs (offset {off:.3f} s, support {support})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
