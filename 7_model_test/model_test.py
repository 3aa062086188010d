"""Module 7: COCO evaluation of a trained detector, and plant detection on whole new images.

Usage:
    python 7_model_test/model_test.py                              # uses test_config.yaml beside this script
    python 7_model_test/model_test.py --set checkpoint=runs/train/checkpoints/best.pt
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__, "test_config.yaml"))
