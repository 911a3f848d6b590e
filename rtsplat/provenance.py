"""What produced a result: the code (its git commit, whether the tree had uncommitted changes and a hash of
them), the machine (host name, CPU model, cores), the device and the package versions.

``rtsplat train`` records it in the run's ``summary.json`` (``provenance``: the part of the training that
finished it, with ``earlier_parts`` when a resumed run was started by other code or on another machine);
``rtsplat render`` and ``rtsplat metrics`` copy the run's record into theirs (``training_provenance``) beside
their own; the report groups the runs by it (:func:`group_runs`) and says on its first screen when they mix
commits, trees with uncommitted changes or machines (:func:`mixture_sentences`).

Uncommitted changes are the differences of the tracked files to the commit (``git diff HEAD``) outside the
documentation (:data:`NOT_CODE`: the docs/ folder and Markdown files, which no stage reads), so a run trained
while only pages were edited is the commit's run; untracked files are not counted.
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
from pathlib import Path

PACKAGES = ("rtsplat", "torch", "numpy", "numba", "scipy", "pycolmap", "mitsuba", "scikit-image", "triton")
SHORT = 12  # the commit's characters a label shows
NOT_RECORDED = "not recorded"
ROOT = Path(__file__).resolve().parent.parent  # the checkout that holds this package, when it is one
# pathspecs of what uncommitted changes leave out: pages that no stage reads (``*.md`` at any depth)
NOT_CODE = (":(exclude)docs", ":(exclude)*.md")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux; ``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _git(*args: str, root: Path) -> subprocess.CompletedProcess | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return done if done.returncode == 0 else None


def source_tree(root: Path = ROOT) -> dict:
    """``commit`` (the full hash of HEAD), ``dirty`` (tracked files other than :data:`NOT_CODE` differ from it)
    and ``diff_sha256`` (the first 16 hex digits of the SHA-256 of that ``git diff HEAD``; None on a clean tree);
    all None when ``root`` is not the top of a git checkout (an installed package)."""
    unknown = {"commit": None, "dirty": None, "diff_sha256": None}
    top = _git("rev-parse", "--show-toplevel", root=root)
    if top is None or Path(top.stdout.decode().strip()).resolve() != root.resolve():
        return unknown
    head, diff = _git("rev-parse", "HEAD", root=root), _git("diff", "HEAD", "--binary", "--", ".", *NOT_CODE, root=root)
    if head is None or diff is None:
        return unknown
    digest = hashlib.sha256(diff.stdout).hexdigest()[:16] if diff.stdout else None
    return {"commit": head.stdout.decode().strip(), "dirty": bool(diff.stdout), "diff_sha256": digest}


def machine() -> dict:
    return {"hostname": platform.node(), "processor": cpu_model(), "cpus": os.cpu_count(),
            "platform": platform.platform(), "python": platform.python_version()}


def versions() -> dict[str, str]:
    """The installed versions of :data:`PACKAGES` (those installed), and Python's."""
    from importlib import metadata

    found = {}
    for package in PACKAGES:
        try:
            found[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            continue
    return {**found, "python": platform.python_version()}


def collect(device: str | None = None) -> dict:
    """The provenance of the work this process does, on ``device`` (None: not tied to one)."""
    return {**source_tree(), "machine": machine(), "device": device, "versions": versions()}


def commit_label(record: dict | None) -> str:
    """``abc123def456``, ``abc123def456+changes (diff 0123abcd...)`` for a tree with uncommitted changes, or
    :data:`NOT_RECORDED`."""
    if not record or not record.get("commit"):
        return NOT_RECORDED
    label = record["commit"][:SHORT]
    return f"{label}+changes (diff {record.get('diff_sha256') or '?'})" if record.get("dirty") else label


def machine_label(record: dict | None) -> str:
    m = (record or {}).get("machine") or {}
    if not m:
        return NOT_RECORDED
    return f"{m.get('hostname') or '?'}: {m.get('processor') or '?'}, {m.get('cpus', '?')} cores"


def versions_label(record: dict | None) -> str:
    return ", ".join(f"{k} {v}" for k, v in ((record or {}).get("versions") or {}).items()) or NOT_RECORDED


def same_source(a: dict, b: dict) -> bool:
    """Whether two records name the same code on the same machine and device."""
    keys = ("commit", "dirty", "diff_sha256", "device")
    return all(a.get(k) == b.get(k) for k in keys) and machine_label(a) == machine_label(b)


def run_record(parts: list[dict]) -> dict | None:
    """What a run's summary records of the parts that trained it (each a :func:`collect`, in order, one more
    each time a resume ran other code or on another machine): the last, with the others as ``earlier_parts``."""
    if not parts:
        return None
    return {**parts[-1], "earlier_parts": parts[:-1]} if len(parts) > 1 else dict(parts[-1])


def parts_of(record: dict | None) -> list[dict]:
    """The parts a run's record names (:func:`run_record`), earliest first; [] when none was recorded."""
    if not record:
        return []
    return [*record.get("earlier_parts", []), {k: v for k, v in record.items() if k != "earlier_parts"}]


def group_runs(records: dict[str, dict | None]) -> list[dict]:
    """Runs ("scene/method" -> their record) grouped by what trained them: each group's ``commit``,
    ``machine``, ``device``, ``packages`` labels and its ``runs``, the group of most runs first. A run resumed
    by other code shows each part's label, joined by " then "."""
    groups: dict[tuple, dict] = {}
    for run, record in records.items():
        parts = parts_of(record) or [None]
        labels = {"commit": " then ".join(commit_label(p) for p in parts),
                  "machine": " then ".join(dict.fromkeys(machine_label(p) for p in parts)),
                  "device": " then ".join(dict.fromkeys(str((p or {}).get("device") or NOT_RECORDED) for p in parts)),
                  "packages": versions_label(parts[-1])}
        groups.setdefault(tuple(labels.values()), {**labels, "runs": []})["runs"].append(run)
    return sorted(groups.values(), key=lambda g: -len(g["runs"]))


def mixture_sentences(records: dict[str, dict | None]) -> list[str]:
    """What a reader of results over these runs must know first: the sentences that say when they were trained
    by more than one commit, from trees with uncommitted changes, on more than one machine, or without a
    record; [] when one clean commit on one machine trained them all."""
    parts = {run: parts_of(record) for run, record in records.items()}
    commits = {commit_label(p) for ps in parts.values() for p in ps if p.get("commit")}
    dirty = sorted(run for run, ps in parts.items() if any(p.get("dirty") for p in ps))
    machines = {machine_label(p) for ps in parts.values() for p in ps if p.get("machine")}
    missing = sorted(run for run, ps in parts.items() if not ps or not all(p.get("commit") for p in ps))
    sentences = []
    if len(commits) > 1:
        sentences.append(f"These runs were trained by {len(commits)} different versions of the code "
                         f"({', '.join(sorted(commits))}): differences between them may come from the code.")
    if dirty:
        sentences.append(f"{len(dirty)} of {len(parts)} runs were trained from a tree with uncommitted changes, "
                         "which no commit reproduces: " + ", ".join(dirty) + ".")
    if len(machines) > 1:
        sentences.append(f"The runs were trained on {len(machines)} machines ({'; '.join(sorted(machines))}): "
                         "their times are not comparable.")
    if missing:
        sentences.append(f"{len(missing)} of {len(parts)} runs do not record the code that trained them: "
                         + ", ".join(missing) + ".")
    return sentences


def training_record(run_dir: str | Path) -> dict | None:
    """The provenance a finished run's ``summary.json`` records (None: no summary, or one without it)."""
    import json

    try:
        summary = json.loads((Path(run_dir) / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    return summary.get("provenance") if isinstance(summary, dict) else None
