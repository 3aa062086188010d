"""A synthetic field's ODM project written as a Metashape export and a Pix4D project folder, each with its photos,
DSM, DTM and orthophoto where the program puts them (what a user of those programs hands MatchPlant)."""

from __future__ import annotations

import shutil
from pathlib import Path

from matchplant.core.formats.metashape_writer import write_metashape
from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.pix4d import write_pix4d


def write_exports(field_root: Path, out: Path, name: str = "field") -> dict[str, Path]:
    """``{"metashape": out/meta/cameras.xml, "pix4d": out/p4d}`` from the ODM project at ``field_root``."""
    odm = ODMProject(field_root)
    shots = odm.reconstruction().shots
    dsm, ortho = field_root / "odm_dem" / "dsm.tif", field_root / "odm_orthophoto" / "odm_orthophoto.tif"
    dtm = field_root / "odm_dem" / "dtm.tif"
    meta, p4d = out / "meta", out / "p4d"
    for folder in (meta, p4d):
        shutil.copytree(field_root / "images", folder / "images")
    write_metashape(meta / "cameras.xml", shots, odm.frame())
    shutil.copy(dsm, meta / f"{name}_dsm.tif")
    shutil.copy(ortho, meta / f"{name}_orthomosaic.tif")
    shutil.copy(dtm, meta / f"{name}_dtm.tif")
    write_pix4d(p4d / "1_initial" / "params", name, shots, odm.frame())
    for sub, src, file in (
        ("1_dsm", dsm, f"{name}_dsm.tif"),
        ("extras/dtm", dtm, f"{name}_dtm.tif"),
        ("2_mosaic", ortho, f"{name}_transparent_mosaic_group1.tif"),
    ):
        (p4d / "3_dsm_ortho" / sub).mkdir(parents=True)
        shutil.copy(src, p4d / "3_dsm_ortho" / sub / file)
    return {"metashape": meta / "cameras.xml", "pix4d": p4d}
