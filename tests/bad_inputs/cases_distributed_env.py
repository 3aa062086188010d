"""Modules 6 and 7 under torchrun variables that contradict each other (issue 39): a RANK outside the job, a RANK
without a job, a LOCAL_RANK outside LOCAL_WORLD_SIZE, a LOCAL_WORLD_SIZE larger than the job, a WORLD_SIZE of 0, a
port that is no number or no port, and a job of two where only this process comes (module 6; module 7's is in
cases_model_test_distributed.py). Each ends in one message naming the variables, exit 2, before any wait (the
last within the short wait set here), never a hang."""

from __future__ import annotations

from cases_model_test import detect_args, photos
from cases_model_test_distributed import WAIT, free_port
from cases_model_train import args, splits
from harness import Case, Work

VARS = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")


def env(**values: str) -> dict:
    """Exactly these torchrun variables (the others unset)."""
    return {v: values.get(v) for v in VARS} | {k: v for k, v in values.items() if k not in VARS}


def job(**values: str) -> dict:
    base = {"WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "29511"}
    return env(**(base | values))


def train(w: Work) -> list[str]:
    tr, _, val, _ = splits(w)
    return args(w, tr, val)


def detect(w: Work) -> list[str]:
    return detect_args(w, photos(w))


INCONSISTENT = [
    ("rank-outside-job", job(RANK="2", LOCAL_RANK="1"), ("RANK=2 is outside 0..1", "WORLD_SIZE=2")),
    ("rank-without-job", env(RANK="1"), ("RANK=1", "WORLD_SIZE 1 or unset")),
    ("local-rank-outside", job(RANK="1", LOCAL_RANK="2", LOCAL_WORLD_SIZE="2"), ("LOCAL_RANK=2", "LOCAL_WORLD_SIZE")),
    ("local-world-too-large", job(LOCAL_WORLD_SIZE="4"), ("LOCAL_WORLD_SIZE=4", "WORLD_SIZE=2")),
    ("world-size-zero", env(WORLD_SIZE="0"), ("WORLD_SIZE=0",)),
    ("port-not-a-number", job(MASTER_PORT="http"), ("MASTER_PORT='http'",)),
    ("port-out-of-range", job(MASTER_PORT="70000"), ("MASTER_PORT=70000", "1..65535")),
    ("missing-master-addr", job(MASTER_ADDR=None), ("WORLD_SIZE=2", "MASTER_ADDR")),
]

CASES = [
    Case(f"{module}-dist-{name}", step, prepare, env=values, mentions=(*mentions, "unset WORLD_SIZE"))
    for module, step, prepare in (("m6", "model_train", train), ("m7", "model_test", detect))
    for name, values, mentions in INCONSISTENT
] + [
    Case(
        "m6-dist-rank-0-alone",
        "model_train",
        train,
        env=job(MASTER_PORT=str(free_port()), MATCHPLANT_JOIN_TIMEOUT=WAIT),
        mentions=("could not join", "within 2 s", "WORLD_SIZE=2", "MATCHPLANT_JOIN_TIMEOUT"),
    ),
    Case(
        "m6-dist-rank-1-without-rank-0",
        "model_train",
        train,
        env=job(RANK="1", LOCAL_RANK="1", MASTER_PORT=str(free_port()), MATCHPLANT_JOIN_TIMEOUT=WAIT),
        mentions=("no process of the distributed job listens", "after 2 s", "RANK=1"),
    ),
]
