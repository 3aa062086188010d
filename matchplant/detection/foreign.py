"""Checkpoints from outside MatchPlant: the paper's layout and bare torchvision weights (modules 6 and 7).

The MatchPlant paper's code saves ``{'epoch', 'model_state_dict', 'optimizer_state_dict', 'best_map'}``
(its published maize model, ``Pre-trained model_Faster R-CNN.pt``); other code saves a bare
``model.state_dict()``. Neither says which architecture, which classes or which input size. Here:

- the **architecture** is the one of MatchPlant's (:data:`~matchplant.detection.architectures.ARCHITECTURES`)
  whose layer names the weights have (the config's ``architecture`` is tried first), each candidate built
  on PyTorch's ``meta`` device (no memory, no download);
- the **number of classes** is read from the class-dependent tensors, found by building the architecture for
  2 and 3 classes and comparing shapes (the box predictor of Faster R-CNN, the class logits of RetinaNet
  and FCOS), so no layer name is hard-coded; the class names come from the config, and a count that does
  not fit the weights is a clear error naming the file and the shapes;
- the **input size** is torchvision's default (``min_size`` 800, ``max_size`` 1333), what the paper's code
  trains with; batch norms frozen (no ``num_batches_tracked``) mean a COCO-pretrained start.

:func:`read_any_checkpoint` returns a MatchPlant checkpoint dict (docs/DESIGN.md §2) for either kind of file,
which :func:`~matchplant.detection.model.load_detector` rebuilds (module 7) and whose ``model_state`` module
6 fine-tunes from.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

from matchplant.core.runtime.config import to_dict
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.architectures import ARCHITECTURES
from matchplant.detection.checkpoint import (
    CHECKPOINT_FIX,
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    _describe_foreign,
    check_checkpoint,
    load_checkpoint_file,
)
from matchplant.detection.model import ModelConfig, build_detector

log = get_logger("detector")

STATE_KEYS = ("model_state_dict", "state_dict", "model_state", "model")  # where other code keeps the weights
COUNTER = "num_batches_tracked"  # plain batch norms have it, frozen ones (a pretrained backbone) do not
CLASSES_FIX = "set class_names (module 7) to the names of the classes the model was trained with, in order"


def read_any_checkpoint(
    path: str | Path, *, class_names: list[str] | None = None, architecture: str | None = None, fit_classes: bool = True
) -> dict:
    """A MatchPlant checkpoint dict from a MatchPlant checkpoint, a checkpoint in the paper's layout or a bare
    torchvision state_dict of an architecture MatchPlant builds.

    ``class_names``: the classes of a foreign file (background not included); with ``fit_classes`` their number
    must fit the weights (detection, module 7), without it (fine-tuning, module 6: the box predictor is
    replaced) any number is fine and missing names are numbered. ``architecture``: tried first (None or
    ``auto``: every one)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    path = Path(path)
    data = load_checkpoint_file(path)
    if isinstance(data, dict) and data.get("format") == CHECKPOINT_FORMAT:
        return check_checkpoint(data, path)
    state, layout, extra = _foreign_state(data, torch)
    if state is None:
        raise InputError(
            f"not a detector checkpoint MatchPlant reads: it holds {_describe_foreign(data, torch)}",
            path=path,
            fix=f"{CHECKPOINT_FIX}, the paper's checkpoint ({{'epoch', 'model_state_dict', "
            f"...}}) or a torchvision detector's state_dict",
        )
    return adopt_state_dict(
        state,
        path,
        layout=layout,
        class_names=class_names,
        architecture=architecture,
        fit_classes=fit_classes,
        extra=extra,
    )


def _foreign_state(data: Any, torch) -> tuple[dict | None, str, dict]:
    """``(state_dict, layout, other entries)`` of a foreign file; a None state_dict when it holds none."""

    def is_state(d):
        return isinstance(d, dict) and bool(d) and all(torch.is_tensor(v) for v in d.values())

    if is_state(data):
        return _strip_wrapper(data), "a bare state_dict", {}
    if isinstance(data, dict):
        for key in STATE_KEYS:
            if is_state(data.get(key)):
                extra = {k: v for k, v in data.items() if isinstance(v, (int, float, str)) and k != key}
                return _strip_wrapper(data[key]), f"a dict with its weights under '{key}'", extra
    return None, "", {}


def _strip_wrapper(state: dict) -> dict:
    """Weights saved from ``nn.DataParallel`` / ``DistributedDataParallel`` carry a ``module.`` prefix."""
    if all(str(k).startswith("module.") for k in state):
        return {str(k)[len("module.") :]: v for k, v in state.items()}
    return state


@lru_cache(maxsize=32)
def _meta_state(arch: str, num_classes: int, pretrained: str) -> dict:
    """The state_dict shapes of MatchPlant's ``arch`` for ``num_classes`` (background included), on PyTorch's
    meta device: no memory, no download (kept: a second file of the same kind is read at once; not changed)."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    with torch.device("meta"):
        model = build_detector(ModelConfig(architecture=arch, pretrained=pretrained), num_classes, load_weights=False)
    return {k: tuple(v.shape) for k, v in model.state_dict().items()}


def _names(state: dict) -> set[str]:
    return {str(k) for k in state if not str(k).endswith(COUNTER)}


def _find_architecture(state: dict, path: Path, first: str | None) -> str:
    """The architecture whose layer names the weights have; an error naming the closest one otherwise."""
    order = ([first] if first in ARCHITECTURES else []) + [a for a in ARCHITECTURES if a != first]
    have, best = _names(state), None
    for arch in order:
        own = _names(_meta_state(arch, 2, "none"))
        if own == have:
            return arch
        missing, extra = sorted(own - have), sorted(have - own)
        if best is None or len(missing) + len(extra) < len(best[1]) + len(best[2]):
            best = (arch, missing, extra)
    arch, missing, extra = best
    parts = [f"{len(v)} {what} (e.g. {v[0]})" for v, what in ((missing, "missing"), (extra, "unexpected")) if v]
    raise InputError(
        f"these weights ({len(state)} tensors) are of no architecture MatchPlant builds; the closest "
        f"is {arch}, with {' and '.join(parts)} layer names",
        path=path,
        fix=f"use weights of one of {', '.join(ARCHITECTURES)} as torchvision builds them (default "
        f"anchors), or a checkpoint written by module 6",
    )


def _class_count(state: dict, arch: str) -> tuple[int, str, tuple, int, int]:
    """``(classes with background, tensor name, its shape, the dimension that counts classes, per-class step)``
    read from the class-dependent tensor (the one whose shape changes with the class count)."""
    two, three = _meta_state(arch, 2, "none"), _meta_state(arch, 3, "none")
    key = next(k for k in two if two[k] != three[k])
    dim = next(d for d, (a, b) in enumerate(zip(two[key], three[key])) if a != b)
    step = three[key][dim] - two[key][dim]
    shape = tuple(state[key].shape)
    return (shape[dim] // step if shape[dim] % step == 0 else -1), key, shape, dim, step


def adopt_state_dict(
    state: dict,
    path: Path,
    *,
    layout: str = "a bare state_dict",
    class_names: list[str] | None,
    architecture: str | None = None,
    fit_classes: bool = True,
    extra: dict | None = None,
) -> dict:
    """A MatchPlant checkpoint dict for the torchvision weights ``state`` read from ``path`` (see
    :func:`read_any_checkpoint`); the shapes are checked against the model it rebuilds."""
    arch = _find_architecture(state, path, architecture if architecture != "auto" else None)
    n, key, shape, dim, step = _class_count(state, arch)
    in_weights = f"{key} has shape {shape}: {n - 1} class(es) + background" if n > 0 else f"{key} has shape {shape}"
    if class_names is None and fit_classes:
        raise InputError(
            f"{layout} of a {arch} without class names ({in_weights})",
            path=path,
            fix=f"{CLASSES_FIX} (a list of {max(n - 1, 1)}, e.g. class_names: [maize])",
        )
    names = list(class_names or [])
    if fit_classes and len(names) + 1 != n:
        raise InputError(
            f"class_names lists {len(names)} class(es) ({', '.join(names)}) but the weights have "
            f"{in_weights}; a model for {len(names)} would need {key} of shape "
            f"{tuple((len(names) + 1) * step if d == dim else s for d, s in enumerate(shape))}",
            path=path,
            fix=CLASSES_FIX,
        )
    if not fit_classes and not names:
        names = [f"class_{i}" for i in range(1, max(n, 2))]
    frozen = not any(str(k).startswith("backbone.body.") and str(k).endswith(COUNTER) for k in state)
    pretrained = "coco" if frozen and ARCHITECTURES[arch].frozen_backbone_norms else "none"
    classes = len(names) + 1 if fit_classes else n
    own = _meta_state(arch, classes, pretrained)
    wrong = [(k, tuple(state[k].shape), own[k]) for k in sorted(own) if k in state and tuple(state[k].shape) != own[k]]
    if wrong:
        shown = "; ".join(f"{k} {a} in the file, {b} in MatchPlant's {arch}" for k, a, b in wrong[:3])
        raise InputError(
            f"{layout} of a {arch} whose weights do not fit the model MatchPlant builds: "
            f"{len(wrong)} tensor(s) of another shape ({shown})",
            path=path,
            fix="MatchPlant builds torchvision's default anchors (3 aspect ratios); use weights "
            "trained with those, or retrain with module 6",
        )
    mcfg = ModelConfig(architecture=arch, pretrained=pretrained)
    log.info(
        "checkpoint %s: %s of a %s (%d class(es): %s; input size %d..%d px, torchvision's default; %s)",
        path.name,
        layout,
        arch,
        len(names),
        ", ".join(names),
        mcfg.min_size,
        mcfg.max_size,
        "frozen backbone batch norms: a COCO-pretrained start" if pretrained == "coco" else "plain batch norms",
    )
    return {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "model_config": to_dict(mcfg),
        "class_names": names,
        "category_ids": list(range(1, len(names) + 1)),
        "model_state": state,
        "foreign": {"layout": layout, "file": str(path), "classes_in_weights": n - 1, **(extra or {})},
    }


__all__ = ["adopt_state_dict", "read_any_checkpoint"]
