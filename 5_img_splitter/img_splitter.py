"""Module 5 - cut annotated images into tiles, recompute the boxes, split train/val/test by photo.

    python 5_img_splitter/img_splitter.py --set images=PHOTOS --set annotations=LABELS/annotations.json \
        --set output_dir=TILES
    python 5_img_splitter/img_splitter.py --gui      # settings, tile-grid preview, summary, Run

See README.md.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
