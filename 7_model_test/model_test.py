"""Module 7: COCO evaluation of a trained detector, and plant detection on whole new images.

Usage:
    python 7_model_test/model_test.py                              # uses test_config.yaml beside this script
    python 7_model_test/model_test.py --set checkpoint=runs/train/checkpoints/best.pt
"""

from pathlib import Path

from matchplant.cli import run_module

if __name__ == "__main__":
    import sys

    raise SystemExit(run_module("model_test", sys.argv[1:], default_config=Path(__file__).resolve().parent / "test_config.yaml"))
