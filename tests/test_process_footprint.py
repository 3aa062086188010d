"""What a plain command run loads and starts: no GUI or plotting stack, no statistics library it does not use,
and no child process counted as a worker."""

import subprocess
import sys

import pytest

HEAVY = ["matplotlib.pyplot", "matplotlib.widgets", "scipy.stats", "scipy.signal", "torch"]


def run_python(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout


def test_module_9s_command_loads_no_window_and_no_unused_statistics():
    out = run_python(
        "import sys\n"
        "from matchplant.cli import build_parser\n"
        "from matchplant.steps import resolve_step\n"
        "spec = resolve_step('spatial_stat_extractor')\n"
        "build_parser(spec)\n"
        f"print([m for m in {HEAVY!r} + [spec.gui.split(':')[0]] if m in sys.modules])\n"
    )
    assert out.strip() == "[]", out  # the window itself is loaded on --gui (tests/test_layers.py)


@pytest.mark.skipif(sys.platform == "win32", reason="no resource module")
def test_the_run_log_starts_no_child_process():
    # platform.platform() forks 'uname -p': module 9 reported that child as its workers' peak memory
    out = run_python(
        "import resource\n"
        "from matchplant.core.runtime.log import package_versions\n"
        "assert package_versions()['platform']\n"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
    )
    assert out.strip() == "0"
