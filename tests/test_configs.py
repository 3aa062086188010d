"""Each numbered folder's config files are what the config classes write (docs/DESIGN.md §1).

A key added, renamed or re-documented in the code without regenerating the folder's file fails here,
with the command that regenerates it (it keeps the file's values and rewrites the comments).
"""

from __future__ import annotations

import difflib
from pathlib import Path

import pytest

from matchplant.cli import config_header, run_module
from matchplant.core.runtime.config import load_config, to_yaml
from matchplant.steps import STEPS, resolve_step

ROOT = Path(__file__).resolve().parents[1]
FOLDER_CONFIGS = sorted(p for folder, _ in STEPS.values() if folder for p in (ROOT / folder).glob("*.yaml"))


def test_every_numbered_folder_has_a_config():
    folders = {p.parent.name for p in FOLDER_CONFIGS}
    assert folders == {folder for folder, _ in STEPS.values() if folder}


@pytest.mark.parametrize("path", FOLDER_CONFIGS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_folder_config_matches_the_code(path):
    spec = resolve_step(path.parent.name.split("_", 1)[1])
    cfg = load_config(spec.config, path, strict=False)
    expected = to_yaml(cfg, header=config_header(spec), base=path.parent)
    text = path.read_text(encoding="utf-8")
    diff = "\n".join(
        difflib.unified_diff(text.splitlines(), expected.splitlines(), "on disk", "from the code", lineterm="", n=0)
    )
    assert text == expected, (
        f"{path.relative_to(ROOT)} has drifted from the code; regenerate it with\n"
        f"  matchplant {spec.name} --config {path.relative_to(ROOT)} "
        f"--write-config {path.relative_to(ROOT)}\n{diff}"
    )


def test_write_config_keeps_values_and_paths_relative(tmp_path, capsys):
    """Rewriting a config keeps its values (paths stay relative to the file) and its loaded meaning."""
    (tmp_path / "photos").mkdir()
    src = tmp_path / "my.yaml"
    src.write_text("images: photos\noutput_dir: ../elsewhere/labels\ncategories: [maize, weed]\n")
    out = tmp_path / "sub" / "again.yaml"
    assert run_module("bbox_drawer", ["--config", str(src), "--write-config", str(out)]) == 0
    text = out.read_text()
    assert "images: ../photos\n" in text and "output_dir: ../../elsewhere/labels\n" in text
    spec = resolve_step("bbox_drawer")
    again, first = load_config(spec.config, out, strict=False), load_config(spec.config, src, strict=False)
    assert again.images.resolve() == first.images.resolve() == (tmp_path / "photos").resolve()
    assert again.output_dir.resolve() == first.output_dir.resolve()
    assert again.categories == first.categories == ["maize", "weed"]
    # without a config: the defaults
    assert run_module("bbox_drawer", ["--write-config", str(tmp_path / "defaults.yaml")]) == 0
    assert load_config(spec.config, tmp_path / "defaults.yaml", strict=False).categories == ["plant"]


@pytest.mark.parametrize(
    "step, old, new",
    [
        ("plant_projection", "write_shapefile", "vector_formats: [gpkg, shp]"),
        ("spatial_stat_extractor", "write_polygons", "vector_formats: [gpkg, shp]"),
    ],
)
def test_a_renamed_key_names_its_successor(tmp_path, step, old, new):
    from matchplant.core.runtime.errors import ConfigError

    cls = resolve_step(step).config
    path = tmp_path / "old.yaml"
    path.write_text(f"{old}: true\n")
    for where in ({"path": path}, {"overrides": [f"{old}=true"]}):
        with pytest.raises(ConfigError, match=f"'{old}'.*replaced by 'vector_formats'") as err:
            load_config(cls, strict=False, **where)
        assert new in err.value.fix
