"""The error type every pipeline stage raises for bad input.

A :class:`PipelineError` always names what is wrong (the file or config key) and how to fix it, so
the CLI can print it as-is and exit with status 1 instead of showing a traceback.
"""

from __future__ import annotations

from pathlib import Path


class PipelineError(Exception):
    """Bad input or a failed stage, with a message a user can act on."""

    def __init__(self, problem: str, *, path: str | Path | None = None, fix: str | None = None) -> None:
        self.problem = problem
        self.path = None if path is None else str(path)
        self.fix = fix
        parts = [f"{self.path}: {problem}" if self.path else problem]
        if fix:
            parts.append(f"Fix: {fix}")
        super().__init__("\n  ".join(parts))


class ConfigError(PipelineError):
    """A config file or override that does not match the schema."""
