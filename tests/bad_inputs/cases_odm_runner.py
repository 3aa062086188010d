"""Module 2 (odm_runner, ``check_only``: no Docker here): an existing ODM project whose outputs are broken in
one way each (truncated or malformed reconstruction, no shots, unknown camera model, a DSM without data or
CRS, a garbled coords.txt), and projects that must pass the check (non-ASCII paths, BOM/CRLF coords.txt).

Shared helpers for breaking an ODM project (also used by the module 3 and 8 cases) live here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import rasterio
from harness import Case, Work

RECON = "opensfm/reconstruction.json"
UND_RECON = "opensfm/undistorted/reconstruction.json"
DSM = "odm_dem/dsm.tif"
COORDS = "odm_georeferencing/coords.txt"


def project(w: Work, name: str = "project") -> Path:
    """A private copy of the tiny field's ODM project (photos included: it is small)."""
    return w.copy("field", name)


def edit_json(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def truncate(path: Path, share: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * share)])


def rewrite_raster(path: Path, *, data=None, crs: object = "same", nodata: object = "same") -> None:
    """Write the raster again with its values, CRS or nodata replaced."""
    with rasterio.open(path) as src:
        profile = src.profile
        arr = src.read()
    if data is not None:
        arr = np.broadcast_to(np.asarray(data, dtype=arr.dtype), arr.shape).copy()
    if crs != "same":
        profile["crs"] = crs
    if nodata != "same":
        profile["nodata"] = nodata
    path.unlink()
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(arr)


def first_camera(data: list) -> dict:
    return next(iter(data[0]["cameras"].values()))


def first_shot(data: list) -> dict:
    return next(iter(data[0]["shots"].values()))


# -- module 2 ------------------------------------------------------------------------------------------------


def args(w: Work, proj: Path, *extra: str) -> list[str]:
    a = ["--set", f"project_dir={proj}", "--set", "check_only=true", "--set", f"output_dir={w.out}"]
    for e in extra:
        a += ["--set", e]
    return a


def broken(change):
    """A case preparer: copy the project, apply ``change(project)``, check it."""

    def prepare(w: Work) -> list[str]:
        proj = project(w)
        change(proj)
        return args(w, proj)

    return prepare


def manifest_ok(w: Work) -> None:
    manifest = json.loads((w.out / "odm_manifest.json").read_text())
    assert manifest["ok"] and not manifest["problems"], manifest["problems"]
    assert manifest["details"]["undistorted_shots"] == 9


def unicode_project(w: Work) -> list[str]:
    return args(w, project(w, "campo ñandú 2024 (vuelo 1)"))


def coords_bom_crlf(w: Work) -> list[str]:
    proj = project(w)
    p = proj / COORDS
    p.write_bytes(b"\xef\xbb\xbf" + p.read_text().replace("\n", "\r\n").encode())
    return args(w, proj)


def coords_utf16(w: Work) -> list[str]:
    proj = project(w)
    p = proj / COORDS
    p.write_bytes(p.read_text().replace("\n", "\r\n").encode("utf-16"))
    return args(w, proj)


CASES = [
    Case(
        "m2-truncated-reconstruction",
        "odm_runner",
        broken(lambda p: truncate(p / RECON)),
        mentions=("reconstruction.json", "truncated"),
    ),
    Case(
        "m2-truncated-undistorted-reconstruction",
        "odm_runner",
        broken(lambda p: truncate(p / UND_RECON, 0.8)),
        mentions=("undistorted/reconstruction.json", "truncated"),
    ),
    Case(
        "m2-empty-reconstruction",
        "odm_runner",
        broken(lambda p: (p / RECON).write_bytes(b"")),
        mentions=("reconstruction.json", "empty"),
    ),
    Case(
        "m2-reconstruction-not-opensfm",
        "odm_runner",
        broken(lambda p: (p / RECON).write_text('{"type": "FeatureCollection", "features": []}')),
        mentions=("reconstruction.json", "cameras"),
    ),
    Case(
        "m2-shot-rotation-garbled",
        "odm_runner",
        broken(lambda p: edit_json(p / RECON, lambda d: first_shot(d).update(rotation=[0.1, "x"]))),
        mentions=("reconstruction.json", "rotation"),
    ),
    Case(
        "m2-shot-names-unknown-camera",
        "odm_runner",
        broken(lambda p: edit_json(p / UND_RECON, lambda d: first_shot(d).update(camera="v2 other camera"))),
        mentions=("reconstruction.json", "v2 other camera"),
    ),
    Case(
        "m2-no-shots",
        "odm_runner",
        broken(lambda p: edit_json(p / RECON, lambda d: d[0].update(shots={}))),
        mentions=("reconstruction.json", "no images"),
    ),
    Case(
        "m2-unknown-camera-model",
        "odm_runner",
        broken(lambda p: edit_json(p / UND_RECON, lambda d: first_camera(d).update(projection_type="spherical"))),
        mentions=("undistorted/reconstruction.json", "spherical", "not support"),
    ),
    Case(
        "m2-dsm-all-nodata",
        "odm_runner",
        broken(lambda p: rewrite_raster(p / DSM, data=-9999, nodata=-9999)),
        mentions=("dsm.tif", "no valid data"),
    ),
    Case(
        "m2-dsm-without-crs",
        "odm_runner",
        broken(lambda p: rewrite_raster(p / DSM, crs=None)),
        mentions=("dsm.tif", "CRS"),
    ),
    Case("m2-truncated-dsm", "odm_runner", broken(lambda p: truncate(p / DSM, 0.3)), mentions=("dsm.tif",)),
    Case(
        "m2-coords-garbled",
        "odm_runner",
        broken(lambda p: (p / COORDS).write_text("WGS84 UTM 14N\n702309;4524878;x\n")),
        mentions=("coords.txt", "line 2"),
    ),
    Case(
        "m2-coords-unknown-crs",
        "odm_runner",
        broken(lambda p: (p / COORDS).write_text("WGS84 UTM 99Q\n702309 4524878\n")),
        mentions=("coords.txt", "UTM 99Q"),
    ),
    Case("m2-coords-missing", "odm_runner", broken(lambda p: (p / COORDS).unlink()), mentions=("coords.txt",)),
    Case(
        "m2-undistorted-image-missing",
        "odm_runner",
        broken(lambda p: (p / "opensfm/undistorted/images/SIM_0005.JPG.tif").unlink()),
        mentions=("SIM_0005.JPG.tif",),
    ),
    Case(
        "m2-truncated-topocentric-reconstruction",
        "odm_runner",
        broken(lambda p: truncate(p / "opensfm/reconstruction.topocentric.json", 0.9)),
        mentions=("reconstruction.topocentric.json",),
    ),
    Case(
        "m2-truncated-orthophoto",
        "odm_runner",
        broken(lambda p: truncate(p / "odm_orthophoto/odm_orthophoto.tif")),
        mentions=("odm_orthophoto.tif",),
    ),
    Case(
        "m2-images-folder-given-as-project",
        "odm_runner",
        lambda w: args(w, w.copy("field/images")),
        mentions=("reconstruction.json", "dsm.tif"),
    ),
    Case("m2-unicode-space-project", "odm_runner", unicode_project, expect="ok", check=manifest_ok),
    Case("m2-coords-bom-crlf", "odm_runner", coords_bom_crlf, expect="ok", check=manifest_ok),
    Case("m2-coords-utf16", "odm_runner", coords_utf16, expect="ok", check=manifest_ok),
]
