"""Module 1: find the images that see each GCP, mark the targets (GUI or --set auto=true), write
ODM's gcp_list.txt.

Usage: python 1_gcp_finder/gcp_finder.py --config 1_gcp_finder/config.yaml [--gui]
See README.md in this folder; the algorithm is matchplant.gcp_finder, the GUI matchplant.gcp_finder_gui.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main("gcp_finder", __file__))
