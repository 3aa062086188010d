"""Module 2: run OpenDroneMap (local Docker or a NodeODM server) and check its outputs.

    python 2_odm_runner/odm_runner.py --config 2_odm_runner/config.yaml --set project_dir=/data/field1

Uses the config.yaml beside this script when no --config is given; see README.md.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
