"""Step 8's DSM checked before any ray is cast (the predictions are checked where they are read,
:func:`matchplant.core.formats.predictions.read_predictions`)."""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate_gis import check_raster


def check_dsm(path: Path, key: str | None) -> None:
    """The DSM opens, is georeferenced and holds heights; ``key`` names the config key when the user set it."""
    try:
        check_raster(path, bands=1, what="DSM" + (f" ('{key}')" if key else ""))
    except InputError as exc:
        fix = exc.fix if key is None else f"{exc.fix}; or leave '{key}' empty to use the project's odm_dem/dsm.tif"
        raise InputError(exc.problem, path=exc.path, fix=fix) from exc
