"""Module 8: put the detected plants on the map through the camera poses and the DSM.

Usage: python 8_plant_projection/plant_projection.py --config 8_plant_projection/config.yaml
See README.md in this folder; the algorithm is matchplant.plant_projection.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
