# Run OpenDroneMap for MatchPlant (module 2) on Windows: a thin wrapper around odm_runner.py.
#
#   .\run_odm.ps1                                              # uses config.yaml beside this script
#   .\run_odm.ps1 --set 'project_dir=C:\Users\me\My Field'     # quote paths with spaces
#
# Every argument is passed to odm_runner.py (see --help). Set $env:PYTHON to choose the interpreter
# (default: python, e.g. the one of your MatchPlant virtual environment). Docker Desktop must be running
# for backend: docker.
$ErrorActionPreference = 'Stop'
$python = if ($env:PYTHON) { $env:PYTHON } else { 'python' }
$script = Join-Path $PSScriptRoot 'odm_runner.py'
& $python $script @args
exit $LASTEXITCODE
