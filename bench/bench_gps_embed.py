"""Benchmark module 0 (gps_embed): match N images to a GNSS log and write their GPS EXIF.

    python bench/bench_gps_embed.py            # 1,000 images of 2000x1500 px
    python bench/bench_gps_embed.py --quick    # 200 images

Prints images per second for the whole run (read EXIF, estimate the clock offset, match, write the
copies, report) and the time of the clock-offset estimate alone.
"""

from __future__ import annotations

import argparse
import calendar
import datetime as dt
import io
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MATCHPLANT_QUIET", "1")


def make_flight(root: Path, n: int, width: int) -> tuple[Path, Path]:
    import piexif
    from PIL import Image

    from matchplant.core.exif import splice_exif

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
        exif = {"0th": {piexif.ImageIFD.Make: b"Bench"},
                "Exif": {piexif.ExifIFD.DateTimeOriginal: stamp,
                         piexif.ExifIFD.SubSecTimeOriginal: f"{int((t - whole) * 1000):03d}".encode()}}
        (images / f"IMG_{i:05d}.JPG").write_bytes(splice_exif(data, piexif.dump(exif)))
    log = root / "events.txt"
    e = 700000 + (np.arange(n) // 50) * 10.0
    nn = 4500000 + (np.arange(n) % 50) * 5.0
    with open(log, "w") as fh:
        fh.write("Timestamp\tX\tY\tZ\n")
        for i in range(n):
            fh.write(f"{cam[i] + 3600.4 + 18:.3f}\t{e[i]:.4f}\t{nn[i]:.4f}\t{380.0:.3f}\n")
    return images, log


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="200 images instead of 1,000")
    ap.add_argument("--n", type=int, default=None, help="number of images")
    ap.add_argument("--width", type=int, default=2000, help="image width in pixels")
    args = ap.parse_args(argv)
    n = args.n or (200 if args.quick else 1000)

    from matchplant.gps_embeder.embed import GpsEmbedConfig, embed_gps
    from matchplant.gps_embeder.gnss_log import read_gnss_log
    from matchplant.gps_embeder.matching import estimate_clock_offset, read_images

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t = time.perf_counter()
        images, log = make_flight(root, n, args.width)
        size_mb = sum(p.stat().st_size for p in images.iterdir()) / 1e6
        print(f"set-up: {n} images ({size_mb / n:.2f} MB each) in {time.perf_counter() - t:.1f} s")
        cfg = GpsEmbedConfig(images=images, gnss_log=log, output_dir=root / "out", log_crs="EPSG:32614")
        t = time.perf_counter()
        rows = embed_gps(cfg)
        dt_all = time.perf_counter() - t
        assert all(r["status"] == "matched" for r in rows), "benchmark flight must match completely"
        g = read_gnss_log(log, crs="EPSG:32614")
        cam = np.array([r.time for r in read_images(images)])
        t = time.perf_counter()
        off, support = estimate_clock_offset(cam, g.times, 0.5)
        dt_off = time.perf_counter() - t
    print(f"gps_embed: {n} images in {dt_all:.2f} s = {n / dt_all:.0f} images/s "
          f"({size_mb / dt_all:.0f} MB/s written)")
    print(f"clock offset estimate alone: {dt_off * 1000:.0f} ms for {n}x{n} pairs (offset {off:.3f} s, "
          f"support {support})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
