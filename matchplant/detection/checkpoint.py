"""Detector checkpoints: one self-contained file per save (model settings, class names, weights and whatever the
training adds), read back with a clear error for anything else; a detector rebuilt from one; weights copied by
name and shape for transfer learning."""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path
from typing import Any

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import atomic_path
from matchplant.detection.architectures import ARCHITECTURES
from matchplant.detection.model import ModelConfig, build_detector, model_config_from_dict

CHECKPOINT_FORMAT = "matchplant-detector"
CHECKPOINT_VERSION = 1


def save_checkpoint(
    path: str | Path, model, model_cfg: ModelConfig, class_names: list[str], category_ids: list[int], **extra
) -> Path:
    """Write a self-contained checkpoint atomically (``extra``: epoch, optimizer state, metrics, ...).

    Parameters
    ----------
    path : str or Path
        The ``.pt`` file to write.
    model : torch.nn.Module
        The detector (a DistributedDataParallel wrapper is unwrapped).
    model_cfg : ModelConfig
        The settings it was built from (stored without ``checkpoint``).
    class_names, category_ids : list
        The dataset's category names and COCO ids, in label order (label i + 1 is ``class_names[i]``).
    **extra
        Further entries stored as they are.

    Returns
    -------
    Path
        ``path``.
    """
    import torch  # lazy: PyTorch is heavy; configs load without it

    model = getattr(model, "module", model)  # DistributedDataParallel
    data = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "model_config": to_dict(dataclasses.replace(model_cfg, checkpoint=None)),
        "class_names": list(class_names),
        "category_ids": [int(c) for c in category_ids],
        "model_state": model.state_dict(),
        **extra,
    }
    with atomic_path(path) as tmp:
        torch.save(data, tmp)
    return Path(path)


CHECKPOINT_FIX = "give a checkpoint written by module 6 (its output_dir/checkpoints/best.pt, last.pt or epoch_NNN.pt)"


def read_checkpoint(path: str | Path) -> dict:
    """Load a MatchPlant checkpoint's contents (on the CPU), with a clear error for anything else.

    Anything else is a missing, empty or truncated file, another program's model (YOLO, a bare state_dict, a
    pickled model), damaged contents. Checkpoints from outside MatchPlant (the paper's layout, bare torchvision
    weights): :func:`matchplant.detection.foreign.read_any_checkpoint`.

    Parameters
    ----------
    path : str or Path
        A ``.pt`` file written by module 6.

    Returns
    -------
    dict
        The checkpoint: ``model_config``, ``class_names``, ``category_ids``, ``model_state`` and what training
        added (epoch, optimizer state, history, metrics, ...).
    """
    import torch  # lazy: PyTorch is heavy; configs load without it

    path = Path(path)
    data = load_checkpoint_file(path)
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise InputError(
            f"not a MatchPlant detector checkpoint: it holds {_describe_foreign(data, torch)}",
            path=path,
            fix=f"{CHECKPOINT_FIX}; to train from other weights, use model.pretrained",
        )
    return check_checkpoint(data, path)


def load_checkpoint_file(path: str | Path) -> Any:
    """What a ``.pt`` file holds (on the CPU), with a clear error for a missing, empty, text, truncated or
    unreadable file and for a whole pickled model; nothing is checked of the contents."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    path = Path(path)
    fix = CHECKPOINT_FIX
    if not path.is_file():
        raise InputError("checkpoint not found", path=path, fix="point 'checkpoint' at a .pt file written by module 6")
    size = path.stat().st_size
    if size == 0:
        raise InputError("the checkpoint file is empty (0 bytes)", path=path, fix=f"copy it again, or {fix}")
    with open(path, "rb") as fh:
        head = fh.read(256)
    text = head.decode("ascii", "replace").strip()
    if text and head.isascii() and all(c.isprintable() or c in "\r\n\t" for c in text):
        raise InputError(
            f"this is a text file, not a checkpoint (it starts with {text.splitlines()[0][:40]!r})", path=path, fix=fix
        )
    try:
        data = torch.load(path, map_location="cpu", weights_only=False)
    except ModuleNotFoundError as exc:
        raise InputError(
            f"not a MatchPlant checkpoint: another program wrote it (reading it needs the Python module '{exc.name}')",
            path=path,
            fix=fix,
        ) from exc
    except Exception as exc:  # noqa: BLE001 - any unpickling problem means the same to the user
        if head.startswith(b"PK") and not zipfile.is_zipfile(path):
            raise InputError(
                f"the checkpoint is truncated ({size} bytes; the end of the archive is missing)",
                path=path,
                fix="the file was cut off (disk full, an interrupted copy or run): copy it "
                "again, or use another checkpoint of the run (last.pt, epoch_NNN.pt)",
            ) from exc
        raise InputError(
            f"cannot read this checkpoint: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}", path=path, fix=fix
        ) from exc
    if isinstance(data, torch.nn.Module):
        raise InputError(
            f"not a MatchPlant checkpoint: a whole pickled model ({type(data).__name__}, from "
            "torch.save(model)), without MatchPlant's settings and class names",
            path=path,
            fix=f"{fix}; or save its weights with torch.save(model.state_dict(), path) and set class_names",
        )
    return data


def check_checkpoint(data: dict, path: Path) -> dict:
    """A MatchPlant checkpoint's version and contents checked (a clear error naming the file)."""
    fix = CHECKPOINT_FIX
    if not isinstance(data.get("version"), int):
        raise InputError("the checkpoint has no version number (damaged or edited)", path=path, fix=fix)
    if data["version"] > CHECKPOINT_VERSION:
        raise InputError(
            f"checkpoint version {data['version']} is newer than this MatchPlant reads",
            path=path,
            fix="update MatchPlant",
        )
    _check_contents(data, path)
    return data


def _describe_foreign(data: Any, torch) -> str:
    if not isinstance(data, dict):
        return f"a {type(data).__name__}"
    if data and all(torch.is_tensor(v) for v in data.values()):
        return f"bare weights (a state_dict of {len(data)} tensors, without MatchPlant's settings and class names)"
    if "model" in data and ("train_args" in data or "ema" in data):
        return "a YOLO (Ultralytics) model"
    return f"a dictionary with the keys {', '.join(map(str, list(data)[:8]))}"


def _check_contents(data: dict, path: Path) -> None:
    """The keys a checkpoint needs, of the right kinds, and model settings this version can build."""
    fix = "the file is damaged or was edited; use the checkpoint as module 6 wrote it"
    names, ids = data.get("class_names"), data.get("category_ids")
    for key, ok in (
        ("model_config", isinstance(data.get("model_config"), dict)),
        ("model_state", isinstance(data.get("model_state"), dict)),
        ("class_names", isinstance(names, list) and bool(names) and all(isinstance(n, str) for n in names)),
        ("category_ids", isinstance(ids, list) and isinstance(names, list) and len(ids) == len(names)),
    ):
        if not ok:
            raise InputError(f"the checkpoint's '{key}' is missing or not valid", path=path, fix=fix)
    arch = data["model_config"].get("architecture")
    if not isinstance(arch, str) or arch not in ARCHITECTURES:
        raise InputError(
            f"the checkpoint is a '{arch}' model, which MatchPlant cannot build (it builds {', '.join(ARCHITECTURES)})",
            path=path,
            fix="use a checkpoint trained by module 6, or update MatchPlant if a newer one wrote it",
        )
    try:
        model_config_from_dict(data["model_config"])
    except ConfigError as exc:
        raise InputError(
            f"the checkpoint's model settings cannot be used here: {exc.problem}",
            path=path,
            fix="it comes from another MatchPlant version or was edited: update MatchPlant, or use a "
            "checkpoint written by this version's module 6",
        ) from exc


def load_detector(
    path_or_data: str | Path | dict,
    device: Any = "cpu",
    *,
    overrides: dict | None = None,
    source: str | Path | None = None,
):
    """Rebuild a detector from a checkpoint, in eval mode on ``device``; returns ``(model, checkpoint_dict)``.

    The score threshold is ``model.roi_heads.score_thresh`` (set it before predicting, or use
    :func:`~matchplant.detection.model.set_score_threshold`).

    Parameters
    ----------
    path_or_data : str, Path or dict
        A checkpoint file written by module 6, or its contents as :func:`read_checkpoint` returns them.
    device : str or torch.device
        Where to put the model.
    overrides : dict, optional
        Model settings to replace, e.g. ``{"roi": {"detections_per_img": 500}}``.
    source : str or Path, optional
        The file a given dict came from (for the messages).

    Returns
    -------
    tuple
        ``(model, checkpoint)``: the detector with the checkpoint's weights, and the checkpoint dict.
    """
    data = path_or_data if isinstance(path_or_data, dict) else read_checkpoint(path_or_data)
    source = source if source is not None or isinstance(path_or_data, dict) else path_or_data
    mcfg = dict(data["model_config"])
    for key, value in (overrides or {}).items():
        mcfg[key] = {**mcfg[key], **value} if isinstance(value, dict) else value
    cfg = model_config_from_dict(mcfg)
    model = build_detector(cfg, len(data["class_names"]) + 1, load_weights=False)
    own = model.state_dict()
    state = data["model_state"]
    wrong = sorted(k for k in own if k in state and tuple(own[k].shape) != tuple(getattr(state[k], "shape", ())))
    counter = "num_batches_tracked"  # frozen and plain batch norms load each other's (torchvision drops it)
    missing = sorted(k for k in own if k not in state and not k.endswith(counter))
    extra = sorted(k for k in state if k not in own and not str(k).endswith(counter))
    if wrong or missing or extra:
        parts = [
            f"{len(v)} {what} (e.g. {v[0]})"
            for v, what in ((missing, "missing"), (extra, "unexpected"), (wrong, "of another shape"))
            if v
        ]
        raise InputError(
            f"the checkpoint's weights do not fit its model ({cfg.architecture}, "
            f"{len(data['class_names'])} class(es)): {'; '.join(parts)} tensors",
            path=source,
            fix="the file was edited or mixes two models; use the checkpoint as module 6 wrote it",
        )
    model.load_state_dict(state)
    model.to(device).eval()
    return model, data


def load_matching_weights(model, state: dict) -> tuple[list[str], list[str]]:
    """Copy the tensors of ``state`` whose name and shape match ``model`` (transfer learning).

    Returns (loaded, skipped) names; a different class count skips only the box predictor.
    """
    own = model.state_dict()
    loaded = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    skipped = sorted(k for k in own if k not in loaded and not k.endswith("num_batches_tracked"))
    model.load_state_dict(loaded, strict=False)
    return sorted(loaded), skipped
