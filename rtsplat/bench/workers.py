"""The parent side of the benchmarks that time several source trees in one run (``--checkout``).

A :class:`CheckoutWorker` runs a benchmark script (by file path, so every checkout is timed by the
same script) in its own process with ``PYTHONPATH`` set to one checkout, so that process imports that
checkout's ``rtsplat``. Requests are JSON lines on its stdin; the worker answers with one line
``@@<json>`` on its stdout (other output is skipped). The worker side must not import this module:
a checkout from before it has none, so each script writes its ``@@`` lines itself.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


class CheckoutWorker:
    def __init__(self, script: str | Path, checkout: Path, worker_args: list[str], label: str):
        self.checkout, self.label = checkout, label
        code = ("import runpy, sys; sys.argv = sys.argv[1:]; "
                f"runpy.run_path({str(Path(script).resolve())!r}, run_name='__main__')")
        env = {**os.environ, "PYTHONPATH": str(checkout)}
        self.proc = subprocess.Popen([sys.executable, "-c", code, "prog", *worker_args], cwd=checkout, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def receive(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith("@@"):
                return json.loads(line[2:])
        raise RuntimeError(f"worker {self.label} exited with {self.proc.wait()}")

    def ask(self, request: dict) -> dict:
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        return self.receive()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.write(json.dumps({"cmd": "quit"}) + "\n")
            self.proc.stdin.flush()
            self.proc.wait()
