#!/usr/bin/env bash
# Run OpenDroneMap for MatchPlant (module 2): a thin wrapper around odm_runner.py.
#
#   ./run_odm.sh                                   # uses config.yaml beside this script
#   ./run_odm.sh --set project_dir="/data/my field" --set backend=nodeodm
#
# Every argument is passed to odm_runner.py (see --help). Set PYTHON to choose the interpreter
# (default: python3, e.g. the one of your MatchPlant virtual environment).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
exec "${PYTHON:-python3}" "$here/odm_runner.py" "$@"
