"""The demo's pipeline.yaml as a breeder reads and copies it (issue 40): plain YAML without anchors, paths
relative to the file, a comment above every step; and it reads back as the very spec it was written from."""

from __future__ import annotations

from pathlib import Path

import yaml

from matchplant.demo_pipeline import STEP_NOTES, pipeline_spec
from matchplant.pipeline import read_pipeline
from matchplant.pipeline.write import write_pipeline


def test_the_demo_pipeline_is_plain_commented_and_relative(tmp_path):
    field = tmp_path / "field"
    spec = pipeline_spec(field, "EPSG:32614", epochs=2, minutes=0, pretrained="none", tile=128)
    path = write_pipeline(tmp_path / "pipeline.yaml", spec, STEP_NOTES, "a header\nsecond line")
    text = path.read_text()
    assert "&id" not in text and "*id" not in text  # the anchor sizes, one list used three times, written out
    assert str(tmp_path) not in text  # every path relative to the file's folder
    assert yaml.safe_load(text) == yaml.safe_load(yaml.safe_dump(spec))  # the same content
    lines = text.splitlines()
    assert lines[:2] == ["# a header", "# second line"]
    for step in spec["steps"]:  # each step under its own comment
        at = lines.index(f"  - name: {step['name']}")
        assert lines[at - 1].lstrip().startswith("# "), lines[at - 2 : at + 1]
    top, steps = read_pipeline(path)
    assert [s.name for s in steps] == [s["name"] for s in spec["steps"]]
    assert Path(top["output_dir"]) == tmp_path.resolve()
