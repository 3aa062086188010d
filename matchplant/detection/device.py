"""Which torch device to use: CUDA, then Apple MPS, then CPU, unless the user says otherwise."""

from __future__ import annotations

from matchplant.core.errors import ConfigError

DEVICE_CHOICES = ("auto", "cuda", "mps", "cpu")


def select_device(preference: str = "auto"):
    """Return a ``torch.device``. ``preference`` is auto, cpu, mps, cuda or cuda:N."""
    import torch  # lazy: PyTorch is heavy; configs load without it

    pref = (preference or "auto").lower()
    if pref == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        mps = getattr(torch.backends, "mps", None)
        if mps is not None and mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    if pref == "cpu":
        return torch.device("cpu")
    if pref.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(f"device '{preference}' was asked for but no CUDA GPU is available",
                              fix="set device: auto (or cpu)")
        dev = torch.device(pref)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"device '{preference}' does not exist: {torch.cuda.device_count()} GPU(s) found",
                              fix="use cuda:0 .. cuda:N-1, or device: auto")
        return dev
    if pref == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise ConfigError("device 'mps' was asked for but Apple Metal is not available",
                              fix="set device: auto (or cpu)")
        return torch.device("mps")
    raise ConfigError(f"unknown device '{preference}'", fix="use auto, cuda, cuda:N, mps or cpu")
