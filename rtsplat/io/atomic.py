"""Atomic outputs: a failed or killed stage never leaves something that looks finished.

Stages write into a hidden temporary sibling of their output and rename it into place only when
everything succeeded. An existing output is replaced only at that moment, so a failure keeps the
previous result intact.

This is also the one place that turns the operating system's refusals to write (a read-only file
system, a full disk or quota, no permission, a file where a folder is needed or a folder where a file
is) into a :class:`~rtsplat.errors.PipelineError` that names the path, the cause and the fix:
:func:`atomic_dir` and :func:`atomic_file` do it for what is written through them, and
:func:`write_errors` for the few writes that are not atomic (the training log, the run folder).
An ``OSError`` that a library wrapped in an exception of its own (``torch.save`` reports a full disk
as ``RuntimeError: ... unexpected pos``) is found through the exception's cause and context; a
library error without one counts as a full disk when the disk has less than
:data:`NEARLY_FULL_BYTES` free.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from rtsplat.errors import PipelineError

NEARLY_FULL_BYTES = 1 << 20
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
_ALWAYS_WRITES = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)  # failures only a write can have
_WRITE_ERRNOS = (*_ALWAYS_WRITES, errno.EACCES, errno.EPERM, errno.EEXIST, errno.ENOTDIR, errno.EISDIR)


def _existing_ancestor(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (a file or a folder)."""
    for candidate in (path, *path.parents):
        try:
            os.stat(candidate)
        except OSError:
            continue
        return candidate
    return Path("/")


def _free_bytes(path: Path) -> int | None:
    """Free bytes for this user on the disk that holds ``path`` (or its nearest existing folder)."""
    where = _existing_ancestor(path)
    try:
        return shutil.disk_usage(where if where.is_dir() else where.parent).free
    except OSError:
        return None


def _size(n: int) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} bytes"  # pragma: no cover


def _os_error_in(exc: BaseException) -> OSError | None:
    """``exc`` itself when it is an ``OSError`` with an errno, else the first one in its causes and contexts."""
    seen: set[int] = set()
    stack: list[BaseException | None] = [exc]
    while stack:
        current = stack.pop(0)
        if current is None or id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, OSError) and current.errno is not None:
            return current
        stack += [current.__cause__, current.__context__]
    return None


def _within(path: Path, roots: list[Path]) -> bool:
    """Whether ``path`` is, lies inside or lies above (is a folder on the way to) one of ``roots``, or is
    one of their hidden temporary siblings (``.<name>.tmp-...``, ``.<name>.old-...``)."""
    path = Path(os.path.abspath(path))
    return any(path == root or root in path.parents or path in root.parents
               or (path.parent == root.parent and path.name.startswith(f".{root.name}.")) for root in roots)


def write_failure(exc: BaseException, outputs: Iterable[str | Path], rename: dict[Path, Path] | None = None,
                  atomic: bool = False) -> PipelineError | None:
    """The :class:`PipelineError` for ``exc`` when it is the operating system refusing to write one of
    ``outputs`` (see the module docstring), else None.

    An ``OSError`` that names a file counts when that file is, lies inside or lies on the way to one of
    ``outputs`` (reading an input elsewhere is not a write failure); one without a file name counts when
    only a write can fail that way (no space, quota, read-only). ``rename`` maps temporary paths to the
    output paths they stand for, so the message names what the user asked for. ``atomic``: the write
    went through a temporary file or folder, so the message can say that nothing was left half-written.
    """
    if isinstance(exc, PipelineError):
        return None
    roots = [Path(os.path.abspath(p)) for p in outputs]
    rename = {Path(os.path.abspath(k)): Path(v) for k, v in (rename or {}).items()}
    os_error = _os_error_in(exc)
    if os_error is None:
        if not isinstance(exc, RuntimeError) or not roots:  # what C++ writers (torch, pycolmap) raise
            return None
        free = _free_bytes(roots[0])  # a library that lost the OSError: is the disk full?
        if free is None or free >= NEARLY_FULL_BYTES:
            return None
        code, named = errno.ENOSPC, None
    else:
        code = os_error.errno
        named = [Path(n) for n in (os_error.filename, os_error.filename2) if n is not None]
        named = [n for n in named if _within(n, roots)]
        if code not in _WRITE_ERRNOS and not named:
            return None
        if not named and code not in _ALWAYS_WRITES:
            return None

    def shown(path: Path) -> Path:
        absolute = Path(os.path.abspath(path))
        for tmp, final in rename.items():
            if absolute == tmp or tmp in absolute.parents:
                return final / absolute.relative_to(tmp)
        for root in roots:  # a hidden temporary sibling stands for its output
            if absolute.parent == root.parent and absolute.name.startswith(f".{root.name}."):
                return root
        return path

    target = shown(named[-1] if named else roots[0])
    where = ("an earlier output there is kept as it was and nothing was left half-written" if atomic
             else "what was written before stays")
    if code in (errno.ENOTDIR, errno.EEXIST):
        blocker = next((p for p in (named[0], *named[0].parents) if p.exists() and not p.is_dir()), named[0]) \
            if named else target
        return WriteFailed(f"a file where a folder is needed to write {shown(roots[0])} ({where})", path=shown(blocker),
                             fix="remove or rename that file, or choose another output path")
    if code == errno.EISDIR:
        blocker = next((p for p in named if p.is_dir()), target)
        return WriteFailed(f"a folder where a file is to be written ({where})", path=shown(blocker),
                             fix="remove or rename that folder, or pass the path of a file (for example "
                             "<name>.json) instead")
    if code == errno.EROFS:
        return WriteFailed(f"cannot write: the file system is read-only ({where})", path=target,
                             fix="write the output to a writable disk (another output path), or remount that "
                             "file system read-write")
    if code in (errno.EACCES, errno.EPERM):
        return WriteFailed(f"cannot write: permission denied ({where})", path=target,
                             fix=f"make {_existing_ancestor(target.parent)} writable for this user (chmod, chown) "
                             "or choose another output path")
    if code in _NO_SPACE:
        free = _free_bytes(target)
        cause = "no space left on device" if code == errno.ENOSPC else "disk quota exceeded (no space left for you)"
        left = f", {_size(free)} free there now" if free is not None else ""
        return WriteFailed(f"cannot write: {cause}{left} ({where})", path=target,
                             fix="free some space on that disk (or raise the quota), or write the output to "
                             "another disk, then run the stage again")
    return WriteFailed(f"cannot write: {os_error.strerror or os_error} ({where})", path=target,
                         fix="check that disk and the output path, or choose another output path")


class WriteFailed(PipelineError):
    """The operating system refused to write an output (see :func:`write_failure`)."""

    def renamed(self, rename: dict[Path, Path]) -> WriteFailed:
        """The same error with the temporary paths in ``rename`` replaced by what they stand for."""
        def swap(text: str | None) -> str | None:
            for tmp, final in rename.items():
                text = None if text is None else text.replace(str(tmp), str(final))
            return text
        return WriteFailed(swap(self.problem), path=swap(self.path), fix=swap(self.fix))


@contextmanager
def write_errors(*outputs: str | Path | None, rename: dict[Path, Path] | None = None,
                 atomic: bool = False) -> Iterator[None]:
    """Turn a failure to write ``outputs`` inside the block into a :class:`PipelineError` (see
    :func:`write_failure`); every other exception passes unchanged."""
    roots = [p for p in outputs if p is not None]
    try:
        yield
    except WriteFailed as exc:  # from a write inside a temporary folder: name the output instead
        if not rename:
            raise
        raise exc.renamed({Path(os.path.abspath(k)): Path(v) for k, v in rename.items()}) from exc
    except Exception as exc:
        error = write_failure(exc, roots, rename, atomic)
        if error is None:
            raise
        raise error from exc


@contextmanager
def atomic_dir(final: str | Path) -> Iterator[Path]:
    """Yield a temporary directory that becomes ``final`` when the block exits without error; a failure
    to write anything inside it (or ``final`` itself) is a :class:`PipelineError` naming the path."""
    final = Path(final)
    with write_errors(final, atomic=True):
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))
    try:
        with write_errors(final, tmp, rename={tmp: final}, atomic=True):
            yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    try:
        with write_errors(final, tmp, rename={tmp: final}, atomic=True):
            old = None
            if final.exists():
                old = final.parent / f".{final.name}.old-{os.getpid()}"
                os.replace(final, old)
            try:
                os.replace(tmp, final)
            except BaseException:
                if old is not None:
                    os.replace(old, final)
                raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_file(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Yield a file opened on a temporary sibling of ``path`` (``mode`` "w" for text in UTF-8, "wb"
    for bytes) that is renamed to ``path`` when the block exits without error; on an error the
    temporary file is removed and an existing ``path`` is left as it was. A failure to write is a
    :class:`PipelineError` naming ``path``."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_file writes a new file: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    # O_EXCL on a unique name, with the permissions a plain open() gives (0o666 less the umask)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    with write_errors(path, tmp, rename={tmp: path}, atomic=True):
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        try:
            with os.fdopen(fd, mode, **({"encoding": "utf-8"} if mode == "w" else {})) as fh:
                yield fh
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield the path of a new, empty temporary sibling of ``path`` for a library that writes a file by its
    name (an encoder); it is renamed to ``path`` when the block exits without error, and removed on an
    error, leaving an existing ``path`` as it was. A failure to write is a :class:`PipelineError` naming
    ``path``."""
    path = Path(path)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:12]}{path.suffix}"
    with write_errors(path, tmp, rename={tmp: path}, atomic=True):
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        try:
            yield tmp
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename."""
    with atomic_file(path, "w") as fh:
        fh.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    with atomic_file(path, "wb") as fh:
        fh.write(data)


def write_json_atomic(path: str | Path, data: Any) -> None:
    """``data`` as indented JSON (keys in their order) and a final newline, written atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=False) + "\n")
