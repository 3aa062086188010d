"""Module 3: choose the fewest undistorted images that cover the field, and the part each one owns.

    python 3_min_img_finder/min_img_finder.py --set project_dir=/data/field1 --set output_dir=/data/field1/min_images
    python 3_min_img_finder/min_img_finder.py --gui

Uses the config.yaml beside this script when no --config is given; see README.md.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
