"""Synthetic field: an ODM-shaped project of an early-season maize field with exact ground truth.

    from matchplant.simfield import generate_field
    paths = generate_field(preset="tiny", seed=0, out="field")   # a FieldPaths (see layout.py)

Command line: ``matchplant simfield --preset tiny|small|large --seed N --out DIR`` (plus
``--set altitude=12 --set tilt_deg=20 ...``). The same preset, seed and settings give the same files.
"""

from __future__ import annotations

from pathlib import Path

from matchplant.simfield.config import PRESETS, Settings, SimFieldConfig, config_from, resolve
from matchplant.simfield.generate import generate
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.split import split_field

__all__ = ["generate_field", "run", "SimFieldConfig", "Settings", "PRESETS", "FieldPaths", "resolve"]


def generate_field(preset: str = "tiny", seed: int = 0, out: str | Path = "simfield_out", **overrides) -> FieldPaths:
    """Write a synthetic field to ``out`` and return its :class:`FieldPaths`.

    Parameters
    ----------
    preset : str
        ``tiny`` (seconds, unit tests), ``small``, ``large``, ``realistic`` or ``split`` (see ``PRESETS``).
    seed : int
        Random seed: the same preset, seed and overrides give the same files.
    out : str or Path
        Folder the field is written to (created if missing).
    **overrides
        :class:`SimFieldConfig` keys: altitude, tilt_deg, slope_pct, image_width, overlap, field_width,
        field_length, weeds, shadows, attitude_noise_deg, vigour (per-plant NDVI), second_date (a later
        date with grown plants under ``date2/``), noise (``exact`` or ``realistic``).

    Returns
    -------
    FieldPaths
        The path of every file written (images, ODM outputs, truth).
    """
    return run(config_from(preset, seed, out, **overrides))


def run(cfg: SimFieldConfig) -> FieldPaths:
    """Generate the synthetic field a config describes (and split it into submodels for the ``split`` preset).

    Parameters
    ----------
    cfg : SimFieldConfig
        The preset, seed, output folder and overrides (``matchplant simfield`` builds it from the command line).

    Returns
    -------
    FieldPaths
        The paths of every file written, under ``cfg.output_dir``.
    """
    paths = generate(cfg)
    return split_field(paths, seed=cfg.seed) if cfg.preset == "split" else paths
