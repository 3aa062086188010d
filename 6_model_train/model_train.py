"""Module 6: train a Faster R-CNN plant detector on COCO tiles (module 5's train and validation splits).

Usage:
    python 6_model_train/model_train.py                                  # uses train_config.yaml beside this script
    python 6_model_train/model_train.py --config 6_model_train/transfer_config.yaml
    python 6_model_train/model_train.py --resume                         # continue a crashed run
    torchrun --nproc_per_node 2 6_model_train/model_train.py             # several GPUs
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__, "train_config.yaml"))
