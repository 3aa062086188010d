"""Module 4 - draw and correct plant boxes on images; export COCO and YOLO.

    python 4_bbox_drawer/bbox_drawer.py --gui --set images=PHOTOS --set output_dir=LABELS
    python 4_bbox_drawer/bbox_drawer.py --config my.yaml      # no window: imports + exports only

Every edit is saved at once to <output_dir>/session.json; reopening resumes. See README.md.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
