"""OpenSfM ``reconstruction.json``: cameras, shots (poses) and points.

A shot's ``rotation`` is the angle-axis vector of the world->camera rotation ``R`` and its
``translation`` is ``t`` with ``X_cam = R X_world + t``; the camera centre is ``C = -R^T t``
(not ``translation``, and never ``gps_position``, which ODM leaves unconverted).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matchplant.core.geometry.camera import Camera, camera_from_opensfm
from matchplant.core.geometry.shot import Shot
from matchplant.core.runtime.errors import InputError, MatchPlantError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import did_you_mean, read_json


@dataclass
class Reconstruction:
    """An OpenSfM reconstruction: cameras, shots, points and the geographic reference."""

    cameras: dict[str, Camera]
    shots: dict[str, Shot]
    point_ids: list[str] = field(default_factory=list)
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    reference_lla: dict | None = None
    path: Path | None = None

    def shot(self, shot_id: str) -> Shot:
        """The shot of an image; an error naming the file when ODM did not place it."""
        try:
            return self.shots[shot_id]
        except KeyError:
            raise InputError(
                f"image '{shot_id}' is not in the reconstruction ({len(self.shots)} images are)",
                path=self.path,
                fix="ODM could not place this image; use another image, or check the image name",
            ) from None

    def to_opensfm(self) -> list:
        """The reconstruction as OpenSfM's JSON structure (a list of one reconstruction)."""
        rec = {
            "cameras": {cid: cam.to_opensfm() for cid, cam in self.cameras.items()},
            "shots": {sid: shot.to_opensfm() for sid, shot in self.shots.items()},
            "points": {
                pid: {"coordinates": [float(c) for c in xyz], "color": [128.0, 128.0, 128.0]}
                for pid, xyz in zip(self.point_ids, self.points)
            },
        }
        if self.reference_lla is not None:
            rec["reference_lla"] = dict(self.reference_lla)
        return [rec]


log = get_logger("odm")

RESTORE = "restore the file from ODM's output, or re-run ODM (module 2) on this project"


def read_reconstruction(path: str | Path) -> Reconstruction:
    """Read every partial reconstruction of the file into one (ODM shares one frame between them).

    A truncated or malformed file, a camera of an unsupported model, a shot without a valid pose or naming
    an unknown camera, and a file without shots are errors naming the file and the key."""
    path = Path(path)
    data = read_json(path, what="reconstruction file")
    if isinstance(data, dict):
        # accepted on purpose: tools that write one reconstruction (OpenSfM's own API, converters) drop the list
        if "shots" in data or "cameras" in data:
            log.info("%s holds one reconstruction object, not OpenSfM's list of them: read as a list of one", path)
        data = [data]
    if not isinstance(data, list) or not data or not all(isinstance(r, dict) for r in data):
        raise InputError(
            "not an OpenSfM reconstruction (expected a list of reconstructions, each with 'cameras' and 'shots')",
            path=path,
            fix="point to opensfm/reconstruction.json of an ODM project",
        )
    if not any("shots" in r or "cameras" in r for r in data):
        hint = did_you_mean("shots", data[0])
        raise InputError(
            f"not an OpenSfM reconstruction: no 'cameras' or 'shots' (keys: "
            f"{', '.join(map(str, data[0])) or 'none'}){'; ' + hint if hint else ''}",
            path=path,
            fix=RESTORE,
        )
    cameras: dict[str, Camera] = {}
    shots: dict[str, Shot] = {}
    pids: list[str] = []
    pts: list = []
    reference = None
    for k, rec in enumerate(data):
        where = f"reconstruction {k}: " if len(data) > 1 else ""
        for cid, cd in _section(rec, "cameras", where, path).items():
            try:
                cameras[cid] = camera_from_opensfm(cid, cd if isinstance(cd, dict) else {})
            except MatchPlantError as exc:
                raise InputError(f"{where}cameras.'{cid}': {exc.problem}", path=path, fix=exc.fix) from exc
            except (TypeError, ValueError) as exc:
                raise InputError(
                    f"{where}cameras.'{cid}' has a value that is not a number ({exc})", path=path, fix=RESTORE
                ) from exc
            cam = cameras[cid]
            if cam.width <= 0 or cam.height <= 0 or not (np.isfinite(cam.focal_x) and cam.focal_x > 0):
                raise InputError(
                    f"{where}cameras.'{cid}' has an impossible size or focal length ({cam.width}x"
                    f"{cam.height}, focal {cam.focal_x:g})",
                    path=path,
                    fix=RESTORE,
                )
        reference = reference or rec.get("reference_lla")
        for sid, sd in _section(rec, "shots", where, path).items():
            shots[sid] = _shot(sid, sd, cameras, f"{where}shots.'{sid}'", path)
        for pid, pd in _section(rec, "points", where, path).items():
            xyz = pd.get("coordinates") if isinstance(pd, dict) else None
            if not _vector(xyz):
                raise InputError(
                    f"{where}points.'{pid}'.coordinates is not three numbers: {xyz!r}", path=path, fix=RESTORE
                )
            pids.append(pid)
            pts.append(xyz)
    if reference is not None and not (
        isinstance(reference, dict) and all(_finite(reference.get(key)) for key in ("latitude", "longitude"))
    ):
        raise InputError(f"reference_lla is not a latitude/longitude: {reference!r}", path=path, fix=RESTORE)
    if not shots:
        raise InputError(
            "the reconstruction holds no images (its 'shots' are empty)",
            path=path,
            fix="ODM did not reconstruct anything: check its log, the image overlap and the GPS tags, then re-run it",
        )
    points = np.asarray(pts, dtype=float).reshape(-1, 3)
    return Reconstruction(
        cameras=cameras, shots=shots, point_ids=pids, points=points, reference_lla=reference, path=path
    )


def _section(rec: dict, key: str, where: str, path: Path) -> dict:
    value = rec.get(key, {})
    if not isinstance(value, dict):
        raise InputError(
            f"{where}'{key}' holds {type(value).__name__}, expected an object {{id: ...}}", path=path, fix=RESTORE
        )
    return value


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _vector(v, n: int = 3) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == n and all(_finite(x) for x in v)


def _shot(sid: str, sd, cameras: dict[str, Camera], key: str, path: Path) -> Shot:
    if not isinstance(sd, dict):
        raise InputError(f"{key} is not an object", path=path, fix=RESTORE)
    for name in ("rotation", "translation"):
        if name not in sd:
            raise InputError(f"{key} has no '{name}'", path=path, fix=RESTORE)
        if not _vector(sd[name]):
            raise InputError(f"{key}.{name} is not three finite numbers: {sd[name]!r}", path=path, fix=RESTORE)
    cid = sd.get("camera")
    if cid not in cameras:
        hint = did_you_mean(str(cid), cameras)
        raise InputError(
            f"{key}.camera '{cid}' is not among the file's cameras"
            f"{'; ' + hint if hint else ''} ({len(cameras)} cameras)",
            path=path,
            fix=RESTORE,
        )
    gps = sd.get("gps_position")
    known = {"rotation", "translation", "camera", "capture_time", "gps_position"}
    return Shot(
        id=sid,
        camera=cameras[cid],
        rotation=np.asarray(sd["rotation"], dtype=float),
        translation=np.asarray(sd["translation"], dtype=float),
        capture_time=sd.get("capture_time"),
        gps_position=tuple(gps) if isinstance(gps, (list, tuple)) else None,
        extra={k: v for k, v in sd.items() if k not in known},
    )


def write_reconstruction(path: str | Path, recon: Reconstruction) -> Path:
    """Write a reconstruction as OpenSfM's reconstruction.json, whole or not at all."""
    return write_json(path, recon.to_opensfm(), indent=None)
