"""The older name of spatial_stat_extractor.py in this folder, kept so that existing commands and scripts keep working."""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
