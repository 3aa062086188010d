"""The package itself (matchplant/__init__.py): the numba cache folder follows the kernel files."""

from __future__ import annotations

import os
from pathlib import Path

import matchplant


def test_numba_cache_is_renewed_when_any_kernel_file_changes(tmp_path):
    """Numba checks only a kernel's own file before reusing its cache; ours inline kernels of other files, so
    the cache folder is named by a hash of every kernel file (a git pull updating one starts a fresh cache)."""
    pkg = Path(matchplant.__file__).resolve().parent
    assert os.environ["NUMBA_CACHE_DIR"].endswith(f"numba-{matchplant.kernel_digest(pkg)}")
    root = tmp_path / "pkg"
    (root / "core").mkdir(parents=True)
    kernel, other = root / "core" / "kernels.py", root / "other.py"
    kernel.write_text("import numba\n\n@numba.njit\ndef f(x):\n    return x + 1\n")
    other.write_text("X = 1\n")
    before = matchplant.kernel_digest(root)
    other.write_text("X = 2\n")  # not a kernel file: the cache stays
    assert matchplant.kernel_digest(root) == before
    kernel.write_text(kernel.read_text().replace("x + 1", "x + 2"))
    assert matchplant.kernel_digest(root) != before
