"""The benchmark harness's logic: alternation order, the per-pair ratio statistics, pinning, environment; every
benchmark file is valid Python and every registered comparison exists."""

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench.harness import (
    THREAD_VARS,
    across_runs,
    alternate,
    cpu_model,
    machine_info,
    overhead,
    pin_one_core,
    ratio_text,
    single_thread_env,
    summarise,
    versions,
)
from bench.runner import REGISTRY, combine

ROOT = Path(__file__).resolve().parents[1]


def test_alternate_runs_warmup_then_ours_peer_pairs_with_resets():
    calls = []

    def clock(fn, reset):
        reset()
        fn()
        return 1.0

    ours, peer = (lambda: calls.append("A")), (lambda: calls.append("B"))
    a, b = alternate(ours, peer, pairs=3, warmup=1, reset=lambda side: calls.append(side[0]), clock=clock)
    # warm-up pair, then three timed pairs, each call preceded by its own side's reset
    assert calls == ["o", "A", "p", "B"] * 4
    assert a == b == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError):
        alternate(ours, peer, pairs=0)


def test_alternate_times_real_work_and_honours_self_timed_sections():
    a, b = alternate(lambda: sum(range(20000)), lambda: 1e-9, pairs=3, warmup=0)
    assert all(t > 0 for t in a)
    assert b == [1e-9] * 3  # a callable returning its own measured seconds (no more than the wall time)


def test_summarise_ratios_pair_by_pair():
    ours = [1.0, 2.0, 4.0]
    peer = [3.0, 4.0, 4.0]  # ratios 3, 2, 1: a slow spell hits both sides of a pair
    s = summarise(ours, peer)
    assert s["ours_median_s"] == 2.0 and s["peer_median_s"] == 4.0
    assert s["ratios"] == [3.0, 2.0, 1.0]
    assert (s["ratio_median"], s["ratio_min"], s["ratio_max"]) == (2.0, 1.0, 3.0)
    # the median of the per-pair ratios, not the ratio of the medians (which would be 2.0 here too)
    s2 = summarise([1.0, 1.0, 10.0, 10.0], [2.0, 2.0, 10.0, 10.0])
    assert s2["ratio_median"] == 1.5
    o = overhead(summarise([1.05, 1.10, 1.02], [1.0, 1.0, 1.0]))
    assert o["overhead_median"] == pytest.approx(0.05)
    assert o["overhead_min"] == pytest.approx(0.02) and o["overhead_max"] == pytest.approx(0.10)
    with pytest.raises(ValueError):
        summarise([1.0], [1.0, 2.0])
    with pytest.raises(ValueError):
        summarise([0.0], [1.0])


def test_a_rows_spread_is_over_runs_not_the_pairs_of_one_run():
    """Three runs whose pairs each agree closely but whose medians differ (as module 9's did: 4.78, 5.18,
    5.83): the row states the median of the medians and their range, not one run's narrow pair range."""
    runs = [summarise([1.0] * 3, [p] * 3) for p in (4.78, 5.18, 5.83)]
    s = across_runs(runs)
    assert s["ratio_median"] == pytest.approx(5.18)
    assert (s["ratio_min"], s["ratio_max"]) == (pytest.approx(4.78), pytest.approx(5.83))
    assert s["runs"] == 3 and s["pairs"] == 9 and s["run_medians"] == pytest.approx([4.78, 5.18, 5.83])
    assert "over 3 runs" in ratio_text(s) and "4.78-5.83" in ratio_text(s)
    assert "one run" in ratio_text(runs[0])  # a single run says so
    row = combine([{"name": "x", "summary": r, "check": {"same": True}} for r in runs])
    assert row["summary"]["runs"] == 3 and row["checks"] == [{"same": True}] * 3
    assert row["overhead"]["overhead_median"] == pytest.approx(1 / 5.18 - 1)
    with pytest.raises(ValueError):
        across_runs([])


def test_single_thread_env_and_pinning():
    env = single_thread_env({"PATH": "/bin", "OMP_NUM_THREADS": "8"})
    assert env["PATH"] == "/bin"
    assert all(env[v] == "1" for v in THREAD_VARS)
    if not hasattr(os, "sched_setaffinity"):
        assert pin_one_core() is None
        return
    code = (
        "from bench.harness import pin_one_core; import os; c = pin_one_core(); "
        "print(c, sorted(os.sched_getaffinity(0)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True).stdout
    core, allowed = out.split(" ", 1)
    assert allowed.strip() == f"[{core}]"


def test_machine_and_versions():
    info = machine_info()
    assert info["cores"] == os.cpu_count() and info["cpu"] == cpu_model() and info["python"]
    v = versions(["numpy", "surely-not-an-installed-package"])
    assert v["numpy"] and v["surely-not-an-installed-package"] is None


def test_cli_refuses_too_few_pairs_and_unknown_names():
    run = [sys.executable, "-m", "bench", "--no-save"]
    r = subprocess.run(run + ["--pairs", "2"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "at least 3" in r.stderr
    r = subprocess.run(run + ["--only", "nonsense"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "invalid choice" in r.stderr


@pytest.mark.slow
def test_cuda_request_without_a_gpu_says_so():
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    r = subprocess.run(
        [sys.executable, "-m", "bench", "--device", "cuda", "--no-save"], capture_output=True, text=True, cwd=ROOT
    )
    assert r.returncode == 2 and "no CUDA GPU" in r.stderr and "Traceback" not in r.stderr


def test_every_benchmark_parses_and_each_registered_one_has_its_comparison():
    """The benchmarks run only by hand or in ``python -m bench``: a broken one would otherwise go unseen. A
    registered module has comparison() (ours against a peer) or run_row() (a whole run and its result)."""
    files = sorted((ROOT / "bench").glob("*.py"))
    trees = {f"bench.{f.stem}": ast.parse(f.read_text(), str(f)) for f in files}
    for name, (module, _) in REGISTRY.items():
        defined = {node.name for node in trees[module].body if isinstance(node, ast.FunctionDef)}
        assert {"comparison", "run_row"} & defined, f"{name}: {module} has neither comparison() nor run_row()"


def test_gpu_rows_print_every_acceptance_figure_even_when_a_row_fails():
    """``python -m bench --device cuda`` ends with each of issue 38's figures, PASS or FAIL: a row that failed or was
    skipped still lists its figures, as not measured (a GPU session must see what it did not get)."""
    from bench.gpu_figures import TARGETS, acceptance_line
    from bench.runner import GPU_NAMES, acceptance

    assert set(TARGETS) <= set(GPU_NAMES) <= set(REGISTRY)
    rows = [
        {"name": "train", "summary": {"ratio_median": 0.97}},
        {"name": "detect", "summary": {"ratio_median": 0.9}},  # no target: informational
        {"name": "train-ceiling", "error": "the benchmark process exited with status 1"},
        {"name": "detect-photos", "row": "...", "acceptance": []},
        {"name": "train-real", "skipped": "no deepforest-*.whl"},
    ]
    lines = [acceptance_line(a) for r in rows for a in acceptance(r, "cuda")]
    assert lines[0].startswith("PASS  train 800 px") and "0.97" in lines[0]
    assert sum(line.startswith("FAIL") and "not measured" in line for line in lines) == 4
    assert all(acceptance(r, "cpu") == [] for r in rows)  # the CPU rows have no GPU targets


def test_every_documented_bench_command_can_run_as_written():
    """``python bench/x.py`` puts bench/ (not the project) first on the path, so a script that imports ``bench.``
    fails there with ModuleNotFoundError (four documented commands did): such a script is documented as
    ``python -m bench.x``. The commands are not run by the suite (minutes each), so this is checked from the text."""
    docs = [ROOT / "README.md", *ROOT.glob("[0-9]_*/README.md"), *ROOT.glob("docs/**/*.md"), *ROOT.glob("bench/*.py")]
    named = {m for doc in docs for m in re.findall(r"python bench/(\w+)\.py", doc.read_text())}
    assert named  # the pattern still finds the commands
    broken = sorted(
        name
        for name in named
        if re.search(r"^(from bench[. ]|import bench)", (ROOT / "bench" / f"{name}.py").read_text(), re.M)
    )
    assert broken == [], f"document these as `python -m bench.<name>`: {broken}"
