"""Writing a pipeline file a breeder can read and copy: plain YAML (no anchors such as ``&id001``/``*id001``, which
PyYAML writes for a value used twice), each step under a comment that says what it does and which keys one
typically changes. ``python -m matchplant.demo`` writes its ``pipeline.yaml`` with it."""

from __future__ import annotations

import textwrap
from pathlib import Path

import yaml

from matchplant.core.runtime.io import write_text


class _PlainDumper(yaml.SafeDumper):
    """Every value written out in full where it is used: no anchors and aliases."""

    def ignore_aliases(self, data) -> bool:
        return True

    def represent_list(self, data):  # a list of numbers or words on one line ([0.55, 0.15, 0.3]); sections as blocks
        flat = all(not isinstance(v, (list, dict)) for v in data)
        return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


_PlainDumper.add_representer(list, _PlainDumper.represent_list)


def _comment(text: str, indent: str = "") -> str:
    """``text`` as comment lines of at most 110 columns (its own line breaks kept)."""
    lines = [w for line in text.strip().splitlines() for w in textwrap.wrap(line, 106 - len(indent)) or [""]]
    return "".join(f"{indent}# {line}".rstrip() + "\n" for line in lines)


def pipeline_text(spec: dict, notes: dict[str, str], header: str) -> str:
    """The YAML of ``spec`` (top-level keys, then ``steps``), ``header`` on top and ``notes[step name]`` above
    each step."""
    top = {k: v for k, v in spec.items() if k != "steps"}
    text = _comment(header) + "\n" + yaml.dump(top, Dumper=_PlainDumper, sort_keys=False) + "steps:\n"
    for step in spec["steps"]:
        body = yaml.dump([step], Dumper=_PlainDumper, sort_keys=False, width=110)
        note = notes.get(step["name"], "")
        text += "\n" + (_comment(note, "  ") if note else "") + "".join(f"  {ln}\n" for ln in body.splitlines())
    return text


def write_pipeline(path: Path, spec: dict, notes: dict[str, str], header: str) -> Path:
    """Write ``spec`` as a commented pipeline file at ``path`` (whole or not at all)."""
    write_text(path, pipeline_text(spec, notes, header))
    return path
