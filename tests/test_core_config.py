"""Configuration (matchplant.core.runtime.config): YAML and overrides, errors that name the key and the fix,
the commented template, the check hook."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from demo_step import DemoConfig, write

from matchplant.core.runtime.config import load_config, param, to_yaml, validate
from matchplant.core.runtime.errors import ConfigError


def test_load_defaults_yaml_and_overrides(tmp_path):
    (tmp_path / "imgs").mkdir()
    p = write(tmp_path, "images: imgs\ntile_size: 512\noptim:\n  lr: 0.005\n")
    cfg = load_config(DemoConfig, p, ["overlap=0.2", "optim.schedule=cosine", "names=[a, b]"])
    assert cfg.images == tmp_path / "imgs"  # relative to the YAML file, not the cwd
    assert cfg.tile_size == 512 and cfg.overlap == 0.2 and cfg.names == ["a", "b"]
    assert cfg.optim.lr == 0.005 and cfg.optim.schedule == "cosine"
    assert cfg.output_dir == tmp_path / "out"


@pytest.mark.parametrize(
    "text, overrides, words",
    [
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
    ],
)
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


def test_paths_of_keys_a_mode_does_not_read_are_not_checked(tmp_path):
    """Module 8's folder config names module 7's predictions; mode evaluate reads none, so a missing
    predictions file must not stop it, while mode project still refuses it by name."""
    from matchplant.plant_projection.config import PlantProjectionConfig

    (tmp_path / "ref.geojson").write_text("{}")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "plants.gpkg").write_text("")
    text = (
        f"predictions: {tmp_path / 'missing.json'}\nevaluate:\n  reference: {tmp_path / 'ref.geojson'}\n"
        f"output_dir: {tmp_path / 'out'}\n"
    )
    (tmp_path / "c.yaml").write_text(text + "mode: evaluate\n")
    cfg = load_config(PlantProjectionConfig, tmp_path / "c.yaml")
    assert cfg.mode == "evaluate"
    (tmp_path / "c.yaml").write_text(text + f"mode: project\nproject: {tmp_path}\n")
    with pytest.raises(ConfigError, match="predictions"):
        load_config(PlantProjectionConfig, tmp_path / "c.yaml")
