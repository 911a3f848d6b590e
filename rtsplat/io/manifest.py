"""The input manifest of a scene: what the workflow compares to tell whether a dataset changed.

A directory's modification time does not change when a file inside it is rewritten in place, so a
rule that takes ``<data>/<scene>`` folders as inputs cannot see an edited image. The manifest lists
every file under the scene folder (hidden names skipped) with its size and modification time in
nanoseconds. :func:`refresh_manifest` rewrites ``<results>/<scene>/inputs.json`` only when that list
differs from the one on disk, so the file's own modification time is the time the inputs last
changed: the rules that read the scene take it as an input and rerun exactly then. The comparison is
for equality, so a file replaced by an older copy (``cp -p``, ``rsync -t``, ``git checkout``) counts
as a change too. Contents are not read: a manifest costs one ``stat`` per file.

Content fingerprints (:func:`content_fingerprint`) are what stage outputs record of their inputs, so
that the next stage can refuse inputs that do not belong together: names, sizes and the first and last
64 KiB of every file, never paths, so a moved or copied folder keeps its fingerprint.
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


# -- content fingerprints: what a stage output was made from ------------------------------------------

FINGERPRINT_SAMPLE = 64 * 1024  # bytes read from each end of a file


def _file_digest(path: Path, size: int) -> bytes:
    """The file's first and last :data:`FINGERPRINT_SAMPLE` bytes (all of it when it is that small)."""
    with open(path, "rb") as fh:
        if size <= 2 * FINGERPRINT_SAMPLE:
            return fh.read()
        head = fh.read(FINGERPRINT_SAMPLE)
        fh.seek(size - FINGERPRINT_SAMPLE)
        return head + fh.read(FINGERPRINT_SAMPLE)


def file_fingerprint(path: str | Path) -> str:
    """SHA-256 of a file's size and its first and last 64 KiB (16 hex digits); at most 128 KiB read."""
    import hashlib

    path = Path(path)
    size = path.stat().st_size
    return hashlib.sha256(f"{size}\0".encode() + _file_digest(path, size)).hexdigest()[:16]


def content_fingerprint(files: list[Path], root: str | Path) -> str:
    """A fingerprint of the contents of ``files`` (paths under ``root``), independent of where they are.

    SHA-256 over each file's path relative to ``root`` and its :func:`file_fingerprint` (its size and
    its first and last 64 KiB), in name order; 16 hex digits. It tells inputs apart without reading them
    whole: at most 128 KiB and one ``stat`` per file (about 125 MiB for 1000 photos), and two folders that
    differ in a name, a size or the bytes at either end of a file differ here. An edit inside a large
    file that keeps its size and both ends is not seen.
    """
    import hashlib

    root = Path(root)
    digest = hashlib.sha256()
    for path in sorted(files, key=lambda p: Path(p).relative_to(root).as_posix()):
        digest.update(f"{Path(path).relative_to(root).as_posix()}\0{file_fingerprint(path)}\n".encode())
    return digest.hexdigest()[:16]


def folder_fingerprint(folder: str | Path, skip: tuple[str, ...] = ()) -> str:
    """:func:`content_fingerprint` of every file under ``folder`` (hidden names and the top-level names in
    ``skip`` left out)."""
    root = Path(folder)
    files = []
    for current, dirnames, filenames in os.walk(root, followlinks=True):
        top = Path(current) == root
        dirnames[:] = [d for d in dirnames if not d.startswith(".") and not (top and d in skip)]
        files += [Path(current, n) for n in filenames if not n.startswith(".") and not (top and n in skip)]
    return content_fingerprint(files, root)


def photo_fingerprints(image_dir: str | Path) -> dict[str, str]:
    """:func:`file_fingerprint` of each of a scene's photos (the readable image files directly in
    ``image_dir``) by name: what ``rtsplat sfm`` and ``rtsplat masks`` record, and ``rtsplat prepare``
    compares, to tell whether their outputs belong to the same photos."""
    from rtsplat.io.images import list_images

    return {p.name: file_fingerprint(p) for p in list_images(image_dir)}


def photos_fingerprint(photos: dict[str, str]) -> str:
    """One fingerprint of :func:`photo_fingerprints` (16 hex digits)."""
    import hashlib

    return hashlib.sha256("".join(f"{n}\0{d}\n" for n, d in sorted(photos.items())).encode()).hexdigest()[:16]


def check_made_from_photos(output: str | Path, summary: dict, stage: str, image_dir: str | Path,
                           photos: dict[str, str], option: str) -> None:
    """Refuse the output folder of ``stage`` (its ``summary``) when the photos it records
    (``summary["photos"]``, :func:`photo_fingerprints`) are not ``photos``, those now in ``image_dir``:
    the output of another scene (no photo in common), or of this one before photos changed (naming
    them). ``option``: the flag that passed the folder. An output that records no photos passes."""
    from rtsplat.errors import PipelineError

    recorded = summary.get("photos")
    if not isinstance(recorded, dict) or recorded == photos:
        return
    rerun = f"re-run 'rtsplat {stage} --scene-dir {Path(image_dir).parent}'"
    common = [n for n in photos if recorded.get(n) == photos[n]]
    if not common:
        raise PipelineError(
            f"{option} {output} belongs to other photos: 'rtsplat {stage}' made it from the {len(recorded)} photos "
            f"of {summary.get('scene_dir') or 'another scene'} (fingerprint {photos_fingerprint(recorded)}), "
            f"none of which is among the {len(photos)} in {image_dir} (fingerprint {photos_fingerprint(photos)})",
            path=output,
            fix=f"pass {option} the output of 'rtsplat {stage}' for this scene, or {rerun}",
        )
    changed = [f"{n} (changed)" for n in sorted(photos) if n in recorded and recorded[n] != photos[n]]
    changed += [f"{n} (added)" for n in sorted(photos) if n not in recorded]
    changed += [f"{n} (removed)" for n in sorted(recorded) if n not in photos]
    shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
    raise PipelineError(
        f"{option} {output} was made before {len(changed)} of the photos in {image_dir} changed: {shown}",
        path=output,
        fix=f"{rerun} (or restore the photos it was made from)",
    )
