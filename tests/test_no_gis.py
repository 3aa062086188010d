"""Training and detection run where no GIS library is installed (a GPU node with PyTorch only): with rasterio,
pyogrio, pyproj, geopandas and shapely blocked, module 6 trains on COCO tiles, module 7 evaluates and detects with
the checkpoint, and the GPU benchmark's modules import (issue 38)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GIS = ("rasterio", "pyogrio", "pyproj", "geopandas", "shapely")

# Run in a fresh interpreter: a finder first on sys.meta_path refuses the GIS packages (and their submodules), so an
# import of one anywhere below fails as it would on a machine without them.
SCRIPT = """
import json, sys
BLOCKED = set(sys.argv[2].split(","))

class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is blocked: no GIS library on this machine")

sys.meta_path.insert(0, Refuse())
out = sys.argv[1]

import matchplant.model_train, matchplant.model_test  # noqa: E401
import bench.bench_model_train, bench.bench_model_train_real  # noqa: E401  the GPU run's modules
from matchplant.core.runtime.config import load_config
from matchplant.detection.synth import make_tiles
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.run import run as test_run
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

train_json = make_tiles(out + "/tiles", n_images=6, size=64, plants=(1, 3), radius=(5, 9), negatives=1, seed=0,
                        name="train.json")
val_json = make_tiles(out + "/val", n_images=3, size=64, plants=(1, 3), radius=(5, 9), negatives=1, seed=1,
                      name="val.json")
fast = ["model.architecture=fasterrcnn_mobilenet_v3_large_fpn", "model.pretrained=none", "model.min_size=64",
        "model.max_size=64", "model.anchor_sizes=[[8,16,32],[8,16,32],[8,16,32]]",
        "model.roi.batch_size_per_image=32", "model.rpn.pre_nms_top_n_train=100",
        "model.rpn.post_nms_top_n_train=100", "model.rpn.pre_nms_top_n_test=100", "model.rpn.post_nms_top_n_test=100",
        "batch_size=3", "num_workers=0", "warmup_iters=1", "epochs=1", "device=cpu", "threads=1"]
summary = train(load_config(ModelTrainConfig, None,
                            [f"train_json={train_json}", f"val_json={val_json}", f"output_dir={out}/train", *fast]))
cfg = load_config(ModelTestConfig, None, [
    f"checkpoint={out}/train/checkpoints/last.pt", f"evaluate.dataset_json={val_json}",
    f"detect.images={out}/val/images", "detect.tile_size=64", "detect.overlap=16", "detect.score_threshold=0.0",
    f"output_dir={out}/test", "device=cpu", "threads=1"])
test_run(cfg)
loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
print(json.dumps({"status": summary["status"], "gis_loaded": loaded}))
"""


@pytest.mark.slow
def test_training_and_detection_run_without_the_gis_libraries(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    res = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path), ",".join(GIS)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads(res.stdout.strip().splitlines()[-1])
    assert result["status"] == "finished" and result["gis_loaded"] == []
    preds = json.loads((tmp_path / "test" / "predictions.json").read_text())
    assert len(preds["images"]) == 3  # every validation tile detected on
    assert (tmp_path / "test" / "metrics.json").is_file()


def test_the_blocking_finder_does_block(tmp_path):
    """The check above is only as good as its finder: with it, importing shapely fails (shapely is installed)."""
    script = SCRIPT.split("out = sys.argv[1]")[0] + "import shapely\n"
    res = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path), ",".join(GIS)], cwd=ROOT, capture_output=True, text=True
    )
    assert res.returncode != 0 and "shapely is blocked" in res.stderr
