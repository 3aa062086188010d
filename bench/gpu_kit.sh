#!/usr/bin/env bash
# Prepare the GPU session of issue 38 on this (CPU) machine, from the project's root:
#   bash bench/gpu_kit.sh
# then on the GPU machine, with the ignored .gpu/ sent along (about 22 MB):
#   bash .gpu/run.sh python3 -m bench --device cuda
# It does what the shared kit does (../shared/gpu/prepare.sh: wheels, stand-ins, its .gpu/run.sh), also in a git
# worktree (where .git is a file, which that script cannot write its exclude into), and adds the real photos of the
# train-real row: the 8 files of DeepForest's wheel that bench/deepforest_photos.py cuts (MIT licence), in
# .gpu/deepforest/ where bench/bench_model_train_real.py looks first.
set -euo pipefail
root=$(git rev-parse --show-toplevel)
cd "$root"
kit=${GPU_KIT:-$root/../shared/gpu}
# the project's environment (`make` builds .venv) reads the benchmark's list of photos; a bare python3 lacks OpenCV
py=${PYTHON:-$([ -x "$root/.venv/bin/python" ] && echo "$root/.venv/bin/python" || echo python3)}
exclude=$(git rev-parse --git-path info/exclude)
mkdir -p "$(dirname "$exclude")"
grep -qx '/.gpu/' "$exclude" 2>/dev/null || echo '/.gpu/' >> "$exclude"
rm -rf .gpu && mkdir -p .gpu/whl
cp -r "$kit/stubs" .gpu/stubs  # unused now (training and detection import no GIS library); kept as a safety net
for p in pycocotools shapely affine piexif; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d .gpu/whl "$p" 2>&1 | grep -v '^WARNING: Location' || true
done
sed -n "/<<'RUN'$/,/^RUN$/p" "$kit/prepare.sh" | sed '1d;$d' > .gpu/run.sh  # the shared kit's run.sh, as it is
chmod +x .gpu/run.sh
wheel_dir=${DEEPFOREST_WHEEL_DIR:-$HOME/deepforest-wheel}
if ! ls "$wheel_dir"/deepforest-*.whl >/dev/null 2>&1; then
  python3 -m pip download -q deepforest==2.1.0 --no-deps -d "$wheel_dir"
fi
wheel=$(ls "$wheel_dir"/deepforest-*.whl | tail -1)
mkdir -p .gpu/deepforest
"$py" - "$wheel" .gpu/deepforest <<'PY'
import sys, zipfile
from pathlib import Path
sys.path.insert(0, ".")
from bench.deepforest_photos import SOURCES  # the files the benchmark reads
out = Path(sys.argv[2])
with zipfile.ZipFile(sys.argv[1]) as z:
    for name in [n for img, xml, _ in SOURCES for n in (img, xml)]:
        (out / name).write_bytes(z.read(f"deepforest/data/{name}"))
PY
du -sh .gpu
