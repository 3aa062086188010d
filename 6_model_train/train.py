"""Module 6: train a Faster R-CNN plant detector on COCO tiles (module 5's train and validation splits).

Usage:
    python 6_model_train/train.py                                  # uses train_config.yaml beside this script
    python 6_model_train/train.py --config 6_model_train/transfer_config.yaml
    python 6_model_train/train.py --resume                         # continue a crashed run
    torchrun --nproc_per_node 2 6_model_train/train.py             # several GPUs
"""

from pathlib import Path

from matchplant.cli import run_module

if __name__ == "__main__":
    import sys

    raise SystemExit(run_module("train", sys.argv[1:], default_config=Path(__file__).resolve().parent / "train_config.yaml"))
