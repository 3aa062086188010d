"""Capturing what one matchplant logger emits, for tests of log lines."""

from __future__ import annotations

import logging


class Records:
    """The messages one matchplant logger emits (a handler of its own: independent of propagation)."""

    def __init__(self, name: str, level: int):
        self.logger, self.level, self.records = logging.getLogger(name), level, []
        self.handler = logging.Handler(level)
        self.handler.emit = self.records.append

    def __enter__(self):
        self.old = self.logger.level
        self.logger.setLevel(self.level)
        self.logger.addHandler(self.handler)
        return self

    def __exit__(self, *exc):
        self.logger.removeHandler(self.handler)
        self.logger.setLevel(self.old)

    def messages(self, level: int = 0) -> list[str]:
        return [r.getMessage() for r in self.records if r.levelno >= level]
