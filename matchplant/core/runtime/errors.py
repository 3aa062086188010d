"""One exception family: every error a user can fix is a MatchPlantError.

The command line prints ``str(error)`` and exits non-zero without a traceback, so each message must say
what is wrong, where (file or config key) and how to fix it.
"""

from __future__ import annotations

from pathlib import Path


class MatchPlantError(Exception):
    """An error the user can act on: a problem, where it is, and what to do about it."""

    def __init__(self, problem: str, *, path: str | Path | None = None, fix: str | None = None):
        self.problem = problem
        self.path = Path(path) if path is not None else None
        self.fix = fix
        super().__init__(self._format())

    def _format(self) -> str:
        lines = [self.problem]
        if self.path is not None:
            lines.append(f"  file: {self.path}")
        if self.fix:
            lines.append(f"  fix:  {self.fix}")
        return "\n".join(lines)


class ConfigError(MatchPlantError):
    """A configuration value or key is wrong."""


class InputError(MatchPlantError):
    """An input file is missing, unreadable or inconsistent."""


class GeometryError(MatchPlantError):
    """A camera, pose or coordinate frame cannot be used as given."""


class DependencyError(MatchPlantError):
    """An optional dependency, service or resource (Docker, weights, network) is not available."""


class OutputError(MatchPlantError):
    """An output cannot be written where asked (a read-only folder, a file in the way, an input's place)."""
