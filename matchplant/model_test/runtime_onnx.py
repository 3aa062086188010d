"""``detect.runtime: onnx``: the detector's convolutions run by ONNX Runtime on a CPU, the rest by PyTorch.

torchvision's Faster R-CNN does not export whole (its proposal sampling and per-image loops are Python), but its
convolutional part does: the backbone, the feature pyramid and the RPN head's convolutions, most of a forward
pass on a CPU. :func:`onnx_detector` exports that part (TorchScript exporter, any batch and tile size) and puts a
module in the model that runs it with ONNX Runtime; anchors, proposals, RoI pooling, the box head and the final
boxes stay PyTorch's, unchanged. ``bench/bench_detect_runtime.py`` measures both on the same tiles.
"""

from __future__ import annotations

import io
import warnings
from collections import OrderedDict

from matchplant.core.runtime.log import get_logger
from matchplant.detection.gpu import as_runtime

log = get_logger("model_test")


RUNTIMES = ("auto", "torch", "onnx")
MISSING_FIX = "pip install onnxruntime onnx (requirements.txt), or set detect.runtime: torch"


def with_runtime(model, runtime: str, device, threads: int):
    """The detector as ``detect.runtime`` asks: ``onnx`` (or ``auto`` on a CPU with ONNX Runtime installed) runs
    its convolutions in ONNX Runtime (:func:`onnx_detector`), else PyTorch runs it all. ``auto`` falls back to
    PyTorch, with the reason logged, for a GPU, a missing package or a model that is not a Faster R-CNN.
    ``device``: the run's :class:`~matchplant.detection.gpu.Runtime` (or a bare device)."""
    if runtime == "torch":
        return model
    why = (
        "it runs on the CPU only"
        if not as_runtime(device).on_cpu
        else "onnxruntime is not installed"
        if not available()
        else "only Faster R-CNN detectors are exported"
        if not hasattr(model, "rpn")
        else None
    )
    if why is not None:
        (log.warning if runtime == "onnx" else log.info)("detect.runtime: %s: PyTorch detects (%s)", runtime, why)
        return model
    return onnx_detector(model, threads)


def torch_threads() -> int:
    """The CPU threads PyTorch was given (module 7's ``threads``): ONNX Runtime gets as many."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    return torch.get_num_threads()


def available() -> bool:
    """Whether ONNX Runtime can be imported."""
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


def onnx_detector(model, threads: int = 1):
    """``model`` (a torchvision Faster R-CNN in eval mode, on the CPU) with its backbone and RPN head run by
    ONNX Runtime (``threads`` intra-op threads); the model is changed in place and returned."""
    import onnxruntime as ort  # lazy: optional

    session, keys = _exported(model, threads)
    model.backbone, model.rpn.head = _session_parts(session, keys, model.backbone.out_channels)
    log.info("detect.runtime: onnx (backbone, feature pyramid and RPN head in ONNX Runtime %s)", ort.__version__)
    return model


def _exported(model, threads: int):
    """``(ONNX Runtime session, feature names)``: the backbone, feature pyramid and RPN head exported (any batch
    and tile size) and opened with ``threads`` intra-op threads."""
    import onnxruntime as ort  # lazy: optional
    import torch  # lazy: PyTorch is heavy; configs load without it

    class ConvPart(torch.nn.Module):
        def __init__(self, backbone, head):
            super().__init__()
            self.backbone, self.head = backbone, head

        def forward(self, x):
            feats = list(self.backbone(x).values())
            logits, deltas = self.head(feats)
            return (*feats, *logits, *deltas)

    with torch.inference_mode():
        keys = list(model.backbone(torch.zeros(1, 3, 64, 64)).keys())
    n = len(keys)
    names = [f"f{i}" for i in range(n)] + [f"l{i}" for i in range(n)] + [f"d{i}" for i in range(n)]
    buf = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript exporter (needs only the onnx package) says it is legacy
        warnings.simplefilter("ignore")
        torch.onnx.export(
            ConvPart(model.backbone, model.rpn.head).eval(),
            (torch.zeros(1, 3, 64, 64),),
            buf,
            opset_version=17,
            dynamo=False,
            input_names=["x"],
            output_names=names,
            dynamic_axes={"x": {0: "b", 2: "h", 3: "w"}, **{k: {0: "b", 2: f"h{k}", 3: f"w{k}"} for k in names}},
        )
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = max(threads, 1), 1
    return ort.InferenceSession(buf.getvalue(), so, providers=["CPUExecutionProvider"]), keys


def _session_parts(session, keys: list, out_channels: int):
    """``(backbone, RPN head)`` modules in the model's places: the backbone runs the session, the head returns the
    RPN head's outputs computed with it."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    n = len(keys)

    class OrtBackbone(torch.nn.Module):
        """The backbone's place: runs the exported part, keeps the RPN head's outputs for :class:`Stashed`."""

        def __init__(self, out_channels: int):
            super().__init__()
            self.out_channels, self.stash = out_channels, None

        def forward(self, x):
            out = [torch.from_numpy(a) for a in session.run(None, {"x": x.detach().cpu().numpy()})]
            self.stash = (out[n : 2 * n], out[2 * n :])
            return OrderedDict(zip(keys, out[:n]))

    class Stashed(torch.nn.Module):
        """The RPN head's place: its outputs, computed with the backbone's."""

        def __init__(self, owner):
            super().__init__()
            self.owner = [owner]  # a list: not a submodule (no cycle in the module tree)

        def forward(self, features):
            return self.owner[0].stash

    backbone = OrtBackbone(out_channels)
    return backbone, Stashed(backbone)
