"""Module 7 (model_test) under a distributed environment that is not a job (issue 27): ``WORLD_SIZE`` left in the
shell without a rendezvous, a ``WORLD_SIZE`` that is not a number, and ``MASTER_ADDR``/``MASTER_PORT`` set for two
processes with only one started (rank 0 waits for the other, rank 1 for the first). Each ends in one clear message
within the short wait set here (``MATCHPLANT_JOIN_TIMEOUT``), never a hang or a crash; module 6 joins through the
same ``matchplant.detection.distributed.join``."""

from __future__ import annotations

import socket

from cases_model_test import detect_args, photos
from harness import Case, Work

WAIT = "2"  # seconds: the bounded wait of these cases


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def detect(w: Work) -> list[str]:
    return detect_args(w, photos(w))


def job(rank: int) -> dict:
    return {
        "WORLD_SIZE": "2",
        "RANK": str(rank),
        "LOCAL_RANK": str(rank),
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(free_port()),
        "MATCHPLANT_JOIN_TIMEOUT": WAIT,
    }


LEFT_IN_SHELL = {"WORLD_SIZE": "2", "RANK": None, "MASTER_ADDR": None, "MASTER_PORT": None}

CASES = [
    Case(
        "m7-dist-world-size-without-rendezvous",
        "model_test",
        detect,
        env=LEFT_IN_SHELL,
        mentions=("WORLD_SIZE=2", "RANK, MASTER_ADDR, MASTER_PORT", "unset WORLD_SIZE", "torchrun"),
    ),
    Case(
        "m7-dist-world-size-not-a-number",
        "model_test",
        detect,
        env={"WORLD_SIZE": "two"},
        mentions=("WORLD_SIZE='two'", "unset WORLD_SIZE"),
    ),
    Case(
        "m7-dist-rank-0-alone",
        "model_test",
        detect,
        env=job(0),
        mentions=("could not join", "within 2 s", "MASTER_ADDR", "MATCHPLANT_JOIN_TIMEOUT"),
    ),
    Case(
        "m7-dist-rank-1-without-rank-0",
        "model_test",
        detect,
        env=job(1),
        mentions=("no process of the distributed job listens", "after 2 s", "RANK=1", "MATCHPLANT_JOIN_TIMEOUT"),
    ),
    Case(
        "m7-dist-timeout-not-a-number",
        "model_test",
        detect,
        env={**job(0), "MATCHPLANT_JOIN_TIMEOUT": "soon"},
        mentions=("MATCHPLANT_JOIN_TIMEOUT='soon'",),
    ),
]
