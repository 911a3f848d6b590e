"""The error type every pipeline stage raises for bad input.

A :class:`PipelineError` always names what is wrong (the file or config key) and how to fix it, so
the CLI can print it as-is and exit with status 1 instead of showing a traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
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


BAD_INPUT_EXIT = 1
INTERRUPTED_EXIT = 130


def run_command(prog: str, work: Callable[[], int | None]) -> int:
    """The exit status of a command's ``work``: its return value (None: 0); a :class:`PipelineError` is
    printed once as ``<prog>: error: <message>`` on stderr (status 1) and ctrl-C as one line (status 130),
    never as a traceback. ``rtsplat <stage>`` and every ``python -m rtsplat.*`` command run through it."""
    try:
        return int(work() or 0)
    except PipelineError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return BAD_INPUT_EXIT
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; its outputs were left as they were", file=sys.stderr)
        return INTERRUPTED_EXIT
