"""Configuration, command line, errors, logging, atomic output, COCO I/O and the ODM project reader."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

import matchplant
from matchplant.cli import run_module
from matchplant.core.formats import coco
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.formats.odm import ODMProject
from matchplant.core.runtime.config import load_config, param, section, to_yaml, validate
from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.runtime.io import atomic_open, read_json, write_json
from matchplant.steps import StepSpec


@dataclass
class Optim:
    """Optimiser settings."""
    lr: float = param(0.01, "learning rate", min=0.0, max=1.0)
    schedule: str = param("step", "learning-rate schedule", choices=["step", "cosine"])


@dataclass
class DemoConfig:
    """A demo module."""
    images: Path | None = param(None, "folder of images", path="dir", required=True)
    output_dir: Path = param("out", "output folder", path="out")
    tile_size: int = param(1024, "tile side in pixels", min=64)
    overlap: float = param(0.1, "tile overlap fraction", min=0, max=0.9)
    names: list[str] = param(["plant"], "category names")
    mode: Literal["fast", "exact"] = param("fast", "how to compute")
    verbose: bool = param(False, "say more")
    optim: Optim = section(Optim)


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    return p


def test_load_defaults_yaml_and_overrides(tmp_path):
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\ntile_size: 512\noptim:\n  lr: 0.005\n")
    cfg = load_config(DemoConfig, p, ["overlap=0.2", "optim.schedule=cosine", "names=[a, b]"])
    assert cfg.images == tmp_path / "imgs"  # relative to the YAML file, not the cwd
    assert cfg.tile_size == 512 and cfg.overlap == 0.2 and cfg.names == ["a", "b"]
    assert cfg.optim.lr == 0.005 and cfg.optim.schedule == "cosine"
    assert cfg.output_dir == tmp_path / "out"


@pytest.mark.parametrize("text, overrides, words", [
    ("images: imgs\ntile_sise: 512\n", [], ["tile_sise", "did you mean 'tile_size'"]),
    ("images: imgs\noptim:\n  lrate: 0.1\n", [], ["optim.lrate", "optim.lr"]),
    ("images: imgs\n", ["tilesize=3"], ["tilesize", "tile_size"]),
    ("images: imgs\ntile_size: big\n", [], ["tile_size", "whole number", "big"]),
    ("images: imgs\nverbose: 3\n", [], ["verbose", "true or false"]),
    ("images: imgs\ntile_size: 10\n", [], ["tile_size", "minimum 64"]),
    ("images: imgs\noptim:\n  lr: 2\n", [], ["optim.lr", "maximum 1"]),
    ("images: imgs\nmode: slow\n", [], ["mode", "'fast' or 'exact'"]),
    ("images: imgs\noptim:\n  schedule: cosin\n", [], ["optim.schedule", "did you mean 'cosine'"]),
    ("images: nowhere\n", [], ["images", "not found", "nowhere"]),
    ("tile_size: 512\n", [], ["images", "required"]),
    ("images: imgs\n  bad: [\n", [], ["not valid YAML", "line"]),
    ("- a\n- b\n", [], ["mapping"]),
])
def test_config_errors_name_the_key_and_the_fix(tmp_path, text, overrides, words):
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(DemoConfig, p, overrides)
    message = str(info.value)
    for w in words:
        assert w in message
    assert "fix:" in message


def test_missing_config_file_and_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(DemoConfig, tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="key=value"):
        load_config(DemoConfig, None, ["tile_size"])


def test_template_is_commented_and_loads_back(tmp_path):
    text = to_yaml(DemoConfig)
    assert "# tile side in pixels (range: 64..)" in text and "# Optimiser settings." in text
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, text.replace("images: null", "images: imgs"))
    cfg = load_config(DemoConfig, p)
    assert cfg.tile_size == 1024 and cfg.optim.schedule == "step"


def test_validate_runs_check_hook():
    @dataclass
    class C:
        a: int = param(1, "a")
        b: int = param(2, "b")

        def check(self):
            if self.a > self.b:
                raise ConfigError("'a' must not exceed 'b'", fix="lower a")

    validate(C())
    with pytest.raises(ConfigError, match="exceed"):
        validate(C(a=3))


# --------------------------------------------------------------------------------------------------
# command line


def _spec(run):
    return StepSpec(name="demo", config=DemoConfig, run=run)


def test_cli_error_is_one_message_without_traceback(tmp_path, capsys, monkeypatch):
    import matchplant.cli as cli

    monkeypatch.setattr(cli, "resolve_module", lambda name: _spec(lambda cfg: None))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\ntile_sise: 1\n")
    assert run_module("demo", ["--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: unknown config key 'tile_sise'") and "Traceback" not in err


def test_cli_runs_logs_config_and_versions(tmp_path, capsys, monkeypatch):
    import matchplant.cli as cli
    seen = {}

    def run(cfg):
        seen["cfg"] = cfg
        from matchplant.core.runtime.log import get_logger
        get_logger("demo").info("working")

    monkeypatch.setattr(cli, "resolve_module", lambda name: _spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\n")
    assert run_module("demo", [str(p), "--set", "tile_size=256", "--set", f"output_dir={tmp_path / 'o'}"]) == 0
    assert seen["cfg"].tile_size == 256
    logs = list((tmp_path / "o" / "logs").glob("demo_*.log"))
    assert len(logs) == 1
    text = logs[0].read_text()
    assert "tile_size: 256" in text and "numpy" in text and "working" in text


def test_cli_internal_error_is_short_and_debug_shows_traceback(tmp_path, capsys, monkeypatch):
    import matchplant.cli as cli

    def run(cfg):
        raise RuntimeError("boom")

    monkeypatch.setattr(cli, "resolve_module", lambda name: _spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, f"images: imgs\noutput_dir: {tmp_path / 'o'}\n")
    assert run_module("demo", [str(p)]) == 1
    assert "internal error: RuntimeError: boom" in capsys.readouterr().err
    with pytest.raises(RuntimeError):
        run_module("demo", [str(p), "--debug"])


def test_cli_write_config_and_unknown_module(tmp_path, capsys, monkeypatch):
    import matchplant.cli as cli

    assert run_module("no_such_module", []) == 2
    assert "unknown module" in capsys.readouterr().err
    monkeypatch.setattr(cli, "resolve_module", lambda name: _spec(lambda cfg: None))
    assert run_module("demo", ["--write-config", str(tmp_path / "t.yaml")]) == 0
    assert "tile_size: 1024" in (tmp_path / "t.yaml").read_text()


def test_console_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "matchplant.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "project_boxes" in out.stdout


def test_device_selection():
    from matchplant.detection.device import select_device

    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type in ("cpu", "cuda", "mps")
    with pytest.raises(ConfigError):
        select_device("tpu")


# --------------------------------------------------------------------------------------------------
# atomic output


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    p = tmp_path / "a.json"
    write_json(p, {"v": 1})
    with pytest.raises(RuntimeError):
        with atomic_open(p) as fh:
            fh.write("{partial")
            raise RuntimeError("crash")
    assert read_json(p) == {"v": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["a.json"]


def test_read_json_errors_name_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{oops")
    with pytest.raises(InputError, match="line 1"):
        read_json(p)
    with pytest.raises(InputError, match="not found"):
        read_json(tmp_path / "none.json")


# --------------------------------------------------------------------------------------------------
# COCO


def _dataset():
    ds = coco.new_dataset(["maize", "weed"])
    ds["images"] = [{"id": 1, "file_name": "t.png", "width": 100, "height": 80, "source_image": "a.JPG",
                     "x0": 900, "y0": 100}]
    ds["annotations"] = [coco.make_annotation(1, 1, [10, 10, 20, 30]), coco.make_annotation(2, 1, [50, 5, 5, 5], 2)]
    return ds


def test_coco_roundtrip_and_provenance(tmp_path):
    ds = _dataset()
    assert coco.validate_dataset(ds) == []
    p = coco.write_dataset(tmp_path / "d.json", ds)
    again = coco.read_dataset(p)
    assert again["annotations"][0]["area"] == 600
    assert coco.to_source_pixels(again["annotations"][0]["bbox"], again["images"][0]) == [910, 110, 20, 30]
    np.testing.assert_array_equal(coco.boxes_xyxy(again["annotations"]), [[10, 10, 30, 40], [50, 5, 55, 10]])


@pytest.mark.parametrize("mutate, words", [
    (lambda d: d["annotations"].append(coco.make_annotation(1, 1, [0, 0, 1, 1])), "duplicate annotation ids"),
    (lambda d: d["annotations"].append(coco.make_annotation(9, 7, [0, 0, 1, 1])), "missing image 7"),
    (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [0, 0, 1, 1], 5)), "unknown category 5"),
    (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [0, 0, 0, 4])), "size 0.0x4.0"),
    (lambda d: d["annotations"].append(coco.make_annotation(9, 1, [90, 70, 30, 30])), "outside t.png"),
])
def test_coco_validation(tmp_path, mutate, words):
    ds = _dataset()
    mutate(ds)
    problems = coco.validate_dataset(ds)
    assert any(words in p for p in problems)
    p = coco.write_dataset(tmp_path / "d.json", ds)
    with pytest.raises(InputError, match="problem"):
        coco.read_dataset(p)


def test_predictions_roundtrip_and_plain_results(tmp_path):
    ds = _dataset()
    preds = [{"image_id": 1, "category_id": 1, "bbox": [1, 2, 3, 4], "score": 0.9}]
    p = coco.write_predictions(tmp_path / "p.json", ds["images"], ds["categories"], preds)
    got = read_predictions(p)
    assert got["images"][0]["source_image"] == "a.JPG" and coco.results_list(got) == preds
    plain = tmp_path / "r.json"
    plain.write_text(json.dumps(preds))
    with pytest.raises(InputError, match="no image names"):
        read_predictions(plain)
    d = coco.write_dataset(tmp_path / "d.json", ds)
    assert read_predictions(plain, images_from=d)["images"][0]["id"] == 1


# --------------------------------------------------------------------------------------------------
# ODM project reader (a minimal project around the real Berlin reconstruction)


def test_odm_project_reports_missing_outputs_with_options(tmp_path, data_dir):
    root = tmp_path / "proj"
    (root / "opensfm").mkdir(parents=True)
    shutil.copy(data_dir / "opensfm-berlin" / "reconstruction_example.json", root / "opensfm" / "reconstruction.json")
    project = ODMProject(root)
    with pytest.raises(InputError) as info:
        project.require("reconstruction", "dsm", "dtm", "undistorted_images")
    msg = str(info.value)
    assert "odm_dem/dsm.tif" in msg and "--dsm" in msg and "--dtm" in msg and "optimize-disk-space" in msg
    assert "reconstruction.json" not in msg.split("\n")[1]
    rec = project.reconstruction()
    assert len(rec.shots) == 3
    frame = project.frame()
    assert frame.kind == "topocentric" and frame.crs.to_epsg() == 32633
    with pytest.raises(InputError, match="not found"):
        ODMProject(tmp_path / "missing")


def test_odm_project_reads_real_undistorted_size(tmp_path, data_dir):
    from PIL import Image

    root = tmp_path / "proj"
    (root / "opensfm" / "undistorted" / "images").mkdir(parents=True)
    shutil.copy(data_dir / "opensfm-berlin" / "reconstruction_example.json",
                root / "opensfm" / "undistorted" / "reconstruction.json")
    Image.new("RGB", (1632, 1224)).save(root / "opensfm" / "undistorted" / "images" / "01.jpg.tif")
    project = ODMProject(root)
    shot = project.shot("01.jpg", undistorted=True)
    assert (shot.camera.width, shot.camera.height) == (1632, 1224)
    full = project.reconstruction(undistorted=True).shots["01.jpg"]
    X = full.center + full.R[2] * 10 + full.R[0] * 2  # a point in front of the camera
    np.testing.assert_allclose((shot.project(X[None])[0] + 0.5) * 2, full.project(X[None])[0] + 0.5, atol=1e-9)
    with pytest.raises(InputError, match="02.jpg"):
        project.shot("02.jpg")
    with pytest.raises(InputError, match="not in the reconstruction"):
        project.reconstruction(undistorted=True).shot("nope.jpg")


def test_odm_project_on_synthetic_field(tiny_field):
    project = ODMProject(tiny_field.root)
    assert project.missing() == []
    frame = project.frame()
    assert frame.kind == "utm_offset"
    field = json.loads(tiny_field.field_json.read_text())
    assert frame.crs.to_epsg() == int(str(field["crs"]).split(":")[-1])


def test_errors_format():
    e = MatchPlantError("bad thing", path="x/y.tif", fix="do this")
    assert str(e) == "bad thing\n  file: x/y.tif\n  fix:  do this"


def test_quiet_keeps_info_off_the_console(tmp_path, capsys, monkeypatch):
    import matchplant.cli as cli

    def run(cfg):
        from matchplant.core.runtime.log import get_logger
        get_logger("demo").info("chatter")
        get_logger("demo").warning("important")

    monkeypatch.setattr(cli, "resolve_module", lambda name: _spec(run))
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, f"images: imgs\noutput_dir: {tmp_path / 'o'}\n")
    assert run_module("demo", [str(p), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "important" in err and "chatter" not in err
    assert "chatter" in next((tmp_path / "o" / "logs").glob("*.log")).read_text()  # the log file has it all


# -- progress in logs, device honesty, GUIs without a display (issue 17) ---------------------------

class _Records:
    """The messages one matchplant logger emits (a handler of its own: independent of propagation)."""

    def __init__(self, name: str, level: int):
        import logging

        self.logger, self.level, self.records = logging.getLogger(name), level, []
        self.handler = logging.Handler(level)
        self.handler.emit = self.records.append

    def __enter__(self):
        self.old = self.logger.level
        self.logger.setLevel(self.level)
        self.logger.addHandler(self.handler)
        return self

    def __exit__(self, *exc):
        self.logger.removeHandler(self.handler)
        self.logger.setLevel(self.old)

    def messages(self, level: int = 0) -> list[str]:
        return [r.getMessage() for r in self.records if r.levelno >= level]


def _progress_records(caplog, monkeypatch, interval: str, body):
    import logging

    from matchplant.core.runtime import progress as progress_module

    monkeypatch.delenv("MATCHPLANT_QUIET", raising=False)
    monkeypatch.delenv("MATCHPLANT_PROGRESS", raising=False)
    monkeypatch.setenv("MATCHPLANT_PROGRESS_INTERVAL", interval)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    with _Records("matchplant.progress", logging.INFO) as rec:
        body(progress_module.progress)
    return rec.messages()


def test_progress_logs_lines_when_not_on_a_terminal(caplog, monkeypatch):
    clock = {"t": 1000.0}
    monkeypatch.setattr("tqdm.std.time", lambda: clock["t"])  # tqdm's clock: one simulated second per image

    def body(progress):
        for _ in progress(range(40), desc="detecting", unit="image"):
            clock["t"] += 1.0  # one image per second: a line at about every 10 images

    lines = _progress_records(caplog, monkeypatch, "10", body)
    assert 3 <= len(lines) <= 5, lines
    assert lines[0].startswith("detecting: 1") and "/40 image" in lines[0]
    # rate 1.00 image/s and the ETA from it: after n images, 40 - n seconds left
    n = int(lines[1].split(":")[1].split("/")[0])
    assert "1.00 image/s" in lines[1] and f"ETA 0:{40 - n:02d}" in lines[1], lines[1]
    assert lines[-1].startswith("detecting: 40/40 image 100%")


def test_progress_postfix_updates_do_not_add_lines(caplog, monkeypatch):
    """Training sets the loss as a postfix on every batch: still one line per interval, not one per batch."""
    clock = {"t": 1000.0}
    monkeypatch.setattr("tqdm.std.time", lambda: clock["t"])

    def body(progress):
        bar = progress(range(60), desc="epoch 1/2", unit="batch")
        for k in bar:
            clock["t"] += 2.0  # a batch every 2 s
            bar.set_postfix(loss=1.0 / (k + 1))

    lines = _progress_records(caplog, monkeypatch, "10", body)
    assert 10 <= len(lines) <= 14, lines  # 120 s at one line per 10 s (and the last)


def test_progress_is_silent_for_short_loops_and_when_quiet(caplog, monkeypatch):
    def body(progress):
        assert list(progress([1, 2, 3], desc="quick")) == [1, 2, 3]
        bar = progress(None, desc="tiles", total=5)
        bar.update(5)
        bar.close()

    assert _progress_records(caplog, monkeypatch, "10", body) == []
    monkeypatch.setenv("MATCHPLANT_QUIET", "1")
    assert list(__import__("matchplant.core.runtime.progress", fromlist=["x"]).progress([1, 2])) == [1, 2]


def test_progress_line_format():
    from matchplant.core.runtime.progress import progress_line

    assert progress_line("tiles", 30, 120, 60.0, "tile") == "tiles: 30/120 tile 25% (1:00 elapsed, 2.0 s/tile, ETA 3:00)"
    assert progress_line("x", 5, None, 2.0) == "x: 5 it (0:02 elapsed, 2.50 it/s)"


def test_device_is_chosen_out_loud():
    import logging

    import torch

    from matchplant.detection.device import cuda_unusable_reason, explain_device, select_device

    dev, why = explain_device("auto")
    if torch.cuda.is_available():
        assert dev.type == "cuda" and "CUDA GPU found" in why
    else:
        assert dev.type in ("cpu", "mps") and cuda_unusable_reason(torch) in why
    assert explain_device("cpu") == (torch.device("cpu"), "asked for (device: cpu)")
    with _Records("matchplant.device", logging.INFO) as rec:
        select_device("cpu")
    assert rec.messages() == ["device: cpu (asked for (device: cpu))"]
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA cannot be used"):
            explain_device("cuda")


def test_cuda_reasons_name_the_cause():
    from types import SimpleNamespace

    from matchplant.detection.device import cuda_unusable_reason

    cpu_build = SimpleNamespace(version=SimpleNamespace(cuda=None))
    assert "CPU-only" in cuda_unusable_reason(cpu_build)

    def old_driver():
        import warnings

        warnings.warn("CUDA initialization: The NVIDIA driver on your system is too old (found version 11040)")
        return False

    cuda_build = SimpleNamespace(version=SimpleNamespace(cuda="13.0"), cuda=SimpleNamespace(is_available=old_driver))
    assert "driver on your system is too old" in cuda_unusable_reason(cuda_build)


def test_slow_cpu_work_is_announced():
    import logging

    import torch

    from matchplant.detection.architectures import get_architecture
    from matchplant.detection.device import warn_if_slow

    with _Records("matchplant.device", logging.INFO) as rec:
        arch = "fasterrcnn_resnet50_fpn"
        est = warn_if_slow(torch.device("cpu"), arch, 1000, 5472, 3648)
        assert est == pytest.approx(get_architecture(arch).cpu_seconds_per_megapixel * 1000 * 5472 * 3648 / 1e6)
        assert warn_if_slow(torch.device("cpu"), arch, 2, 400, 300) < 600
        assert warn_if_slow(torch.device("cuda"), arch, 1000, 5472, 3648) is None
    warned = rec.messages(logging.WARNING)
    assert len(warned) == 1 and f"{est / 3600:.1f} h" in warned[0] and "1000 image(s) of 5472 x 3648" in warned[0]


def test_gui_without_display_exits_2_with_the_headless_command(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("a display is always there on macOS and Windows")
    assert run_module("min_img_finder", ["--gui"]) == 2
    err = capsys.readouterr().err
    assert "needs a window" in err and "matchplant min_img_finder" in err and "without --gui" in err


def test_default_outputs_are_git_ignored():
    """Every step's default output_dir (config class and folder config) is under the git-ignored runs/."""
    from matchplant.steps import STEPS, resolve_step

    root = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    for name, (folder, _) in STEPS.items():
        spec = resolve_step(name)
        default = getattr(spec.config(), spec.output_key, None) if spec.output_key else None
        paths = [default] if default is not None else []
        if folder:
            for yml in (root / folder).glob("*config.yaml"):
                cfg = load_config(spec.config, yml, check_paths=False, strict=False)
                value = getattr(cfg, spec.output_key, None)
                if value is not None:
                    paths.append(value)
        for p in paths:
            p = Path(p) if Path(p).is_absolute() else root / p
            r = subprocess.run(["git", "check-ignore", "-q", "--no-index", str(p / "x")], cwd=root)
            assert r.returncode == 0, f"{name}: default output {p} is not git-ignored"


def test_numba_cache_is_renewed_when_any_kernel_file_changes(tmp_path):
    """Numba checks only a kernel's own file before reusing its cache; ours inline kernels of other files, so
    the cache folder is named by a hash of every kernel file (a git pull updating one starts a fresh cache)."""
    pkg = Path(matchplant.__file__).resolve().parent
    assert os.environ["NUMBA_CACHE_DIR"].endswith(f"numba-{matchplant.kernel_digest(pkg)}")
    root = tmp_path / "pkg"
    (root / "core").mkdir(parents=True)
    kernel, other = root / "core" / "kernels.py", root / "other.py"
    kernel.write_text("import numba\n\n@numba.njit\ndef f(x):\n    return x + 1\n")
    other.write_text("X = 1\n")
    before = matchplant.kernel_digest(root)
    other.write_text("X = 2\n")  # not a kernel file: the cache stays
    assert matchplant.kernel_digest(root) == before
    kernel.write_text(kernel.read_text().replace("x + 1", "x + 2"))
    assert matchplant.kernel_digest(root) != before
