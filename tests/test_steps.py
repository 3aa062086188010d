"""The step registry (matchplant.steps): every step's default output is git-ignored."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from matchplant.core.runtime.config import load_config
from matchplant.steps import STEPS, resolve_step


def test_default_outputs_are_git_ignored():
    """Every step's default output_dir (config class and folder config) is under the git-ignored runs/."""

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
