"""Joining a torchrun job (matchplant.detection.distributed, issue 39): two processes that meet join within
seconds; a job whose peers never come fails within the bounded wait, by default half a minute."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from matchplant.detection.distributed import COLLECTIVE_TIMEOUT_S, TIMEOUT_VAR, join_timeout

ROOT = Path(__file__).resolve().parents[1]
JOIN = """
import torch
from matchplant.detection.distributed import join
shard, device = join(torch.device("cpu"))
print("gathered", shard.gather([shard.rank * 10]), flush=True)
shard.leave()
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(rank: int, port: int, world: int = 2, wait: str = "20") -> subprocess.Popen:
    env = {
        **{k: v for k, v in os.environ.items() if k not in ("LOCAL_WORLD_SIZE", "TORCHELASTIC_USE_AGENT_STORE")},
        "PYTHONPATH": str(ROOT),
        "WORLD_SIZE": str(world),
        "RANK": str(rank),
        "LOCAL_RANK": str(rank),
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(port),
        TIMEOUT_VAR: wait,
    }
    return subprocess.Popen(
        [sys.executable, "-c", JOIN], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


@pytest.mark.slow  # two imports of PyTorch
def test_two_processes_join_and_gather():
    port = _port()
    procs = [_start(r, port) for r in (0, 1)]
    outs = [p.communicate(timeout=60) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert "gathered [0, 10]" in outs[0][0] and "gathered []" in outs[1][0]


@pytest.mark.slow  # one import of PyTorch; m6/m7-dist-rank-0-alone are the fast versions
def test_a_peer_that_never_comes_ends_in_the_bounded_wait():
    start = time.monotonic()
    p = _start(0, _port(), world=3, wait="3")
    _, err = p.communicate(timeout=60)
    assert p.returncode != 0 and time.monotonic() - start < 30
    assert "could not join the distributed job" in err and "WORLD_SIZE=3" in err and TIMEOUT_VAR in err


def test_the_default_wait_is_half_a_minute(monkeypatch):
    monkeypatch.delenv(TIMEOUT_VAR, raising=False)
    assert join_timeout() == 30  # torchrun starts the processes together: half a minute without them is an error
    assert COLLECTIVE_TIMEOUT_S >= 600  # while the wait inside a joined job (a collective) stays long
