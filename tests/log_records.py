"""Capturing what one matchplant logger emits, for tests of log lines."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def log_records(name: str, level: int) -> Iterator[list[logging.LogRecord]]:
    """The records logger ``name`` emits inside the block, at ``level`` and above (a handler of its own:
    independent of propagation)."""
    logger, records = logging.getLogger(name), []
    handler = logging.Handler(level)
    handler.emit = records.append
    before = logger.level
    logger.setLevel(level)
    logger.addHandler(handler)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.setLevel(before)


def messages(records: list[logging.LogRecord], level: int = 0) -> list[str]:
    return [r.getMessage() for r in records if r.levelno >= level]
