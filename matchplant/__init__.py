"""MatchPlant: UAV images to one row per plant (position, height, NDVI).

The numbered folders of the repository are thin entry points; the algorithms live here so that every
module, test and GUI shares one implementation.
"""

import hashlib
import os
import sys
from pathlib import Path

__version__ = "0.1.0"


def kernel_digest(root: Path) -> str:
    """A hash of the package's source files that hold compiled (numba) kernels."""
    h = hashlib.sha1()
    for path in sorted(root.rglob("*.py")):
        text = path.read_bytes()
        if b"numba" in text:
            h.update(path.relative_to(root).as_posix().encode() + b"\0" + text)
    return h.hexdigest()[:16]


def _numba_cache_dir() -> None:
    """Numba keeps a compiled kernel until its own file changes, but our kernels build on (and inline) kernels
    of other files: after an update of one of those (a git pull) the cache would run the old code. So the
    cache lives in a folder named by a hash of every kernel file, and any change to them starts a fresh one.
    A user's own NUMBA_CACHE_DIR is respected."""
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    root = Path(__file__).resolve().parent
    base = root / "__pycache__" if os.access(root, os.W_OK) else Path.home() / ".cache" / "matchplant"
    os.environ["NUMBA_CACHE_DIR"] = str(base / f"numba-{kernel_digest(root)}")
    if "numba" in sys.modules:  # imported before us: its configuration is read already
        sys.modules["numba"].config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]


_numba_cache_dir()
