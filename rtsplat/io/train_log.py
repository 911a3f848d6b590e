"""The training log, ``train_log.jsonl``: one JSON object per line, each with its ``iteration``.

A run that was killed (or hit a full disk) while writing a line leaves its last line half-written;
:func:`read_log` drops that line and says so, for ``rtsplat train`` resuming the run and for
``rtsplat report`` reading it alike. A malformed line before the last is an error that names it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from rtsplat.errors import PipelineError

LOG_NAME = "train_log.jsonl"


def read_log(path: Path, note: Callable[[str], None]) -> list[tuple[dict, str]]:
    """Every record of the log ``path`` with its line, in order; a half-written last line is dropped and
    said through ``note``."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            if not isinstance(record, dict) or not isinstance(record.get("iteration"), int):
                raise ValueError("no iteration")
        except ValueError as exc:
            if number == len(lines):
                note(f"{path}: dropped its half-written last line ({len(line)} characters; the run that wrote it "
                     "stopped while writing it)")
                break
            raise PipelineError(f"line {number} of the training log is not a log record ({exc})", path=path,
                                fix="delete that line (or the file); `rtsplat train` resuming the run writes "
                                "the lines after its checkpoint again") from exc
        records.append((record, line))
    return records
