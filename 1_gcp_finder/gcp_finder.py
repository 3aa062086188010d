"""Module 1: find the images that see each GCP, mark the targets (GUI or --set auto=true), write
ODM's gcp_list.txt.

Usage: python 1_gcp_finder/gcp_finder.py --config 1_gcp_finder/config.yaml [--gui]
See README.md in this folder; the algorithm and the GUI are in matchplant.gcp_finder.
"""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
