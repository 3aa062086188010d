"""Module 0: write the GNSS log's positions into copies of the flight's images (EXIF GPS).

Usage: python 0_gps_embeder/gps_embeder.py --config 0_gps_embeder/config.yaml
See README.md in this folder; the algorithm is matchplant.gps_embeder.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
