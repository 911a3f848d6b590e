"""The input manifest of a scene: what the workflow compares to tell whether a dataset changed.

A directory's modification time does not change when a file inside it is rewritten in place, so a
rule that takes ``<data>/<scene>`` folders as inputs cannot see an edited image. The manifest lists
every file under the scene folder (hidden names skipped) with its size and modification time in
nanoseconds. :func:`refresh_manifest` rewrites ``<results>/<scene>/inputs.json`` only when that list
differs from the one on disk, so the file's own modification time is the time the inputs last
changed: the rules that read the scene take it as an input and rerun exactly then. The comparison is
for equality, so a file replaced by an older copy (``cp -p``, ``rsync -t``, ``git checkout``) counts
as a change too. Contents are not read: a manifest costs one ``stat`` per file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from rtsplat.io.atomic import write_text_atomic

MANIFEST_VERSION = 2


def scene_manifest(scene_dir: str | Path) -> dict[str, Any]:
    """``{"scene": <the folder's name>, "files": {relative path: [size, mtime_ns]}}`` for every file
    under ``scene_dir`` whose path has no component starting with a dot (symbolic links followed).
    Only names relative to the data folder are stored, so a project folder moved or copied elsewhere
    with its files' modification times (``cp -a``, ``rsync -a``) has the same manifest."""
    root = Path(scene_dir).resolve()
    files: dict[str, list[int]] = {}
    for folder, dirnames, filenames in os.walk(root, followlinks=True):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for name in filenames:
            if name.startswith("."):
                continue
            path = Path(folder, name)
            st = path.stat()
            files[path.relative_to(root).as_posix()] = [st.st_size, st.st_mtime_ns]
    return {"version": MANIFEST_VERSION, "scene": root.name, "files": dict(sorted(files.items()))}


def refresh_manifest(scene_dir: str | Path, path: str | Path) -> Path:
    """Write the manifest of ``scene_dir`` to ``path`` when it differs from the one there (or there is
    none, or it is unreadable); leave ``path`` untouched, modification time included, otherwise."""
    path = Path(path)
    current = scene_manifest(scene_dir)
    try:
        if json.loads(path.read_text()) == current:
            return path
    except (OSError, ValueError):
        pass
    write_text_atomic(path, json.dumps(current, indent=0) + "\n")
    return path
