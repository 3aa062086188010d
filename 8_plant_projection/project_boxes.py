"""The older name of plant_projection.py in this folder, kept so that existing commands and scripts keep working."""

from matchplant.cli import folder_main

if __name__ == "__main__":
    raise SystemExit(folder_main(__file__))
