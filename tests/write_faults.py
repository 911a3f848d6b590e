"""Simulated write failures for the tests: a read-only folder and a full disk under one folder.

``read_only`` makes a folder read-only with ``chmod`` where that stops this user; a superuser (tests
often run as root) writes through a mode, so there the operating system's calls that create, replace
or remove anything at or under the folder are patched to fail with ``EROFS``, as on a file system
mounted read-only. ``no_space`` sends every file opened for writing at or under the folder to
``/dev/full``, whose writes fail in the kernel with ``ENOSPC``, as on a full disk (folders can still
be created). Both patch ``os`` and ``io.open``, which every Python-level writer goes through.
"""

from __future__ import annotations

import builtins
import errno
import io
import os
import stat
from collections.abc import Callable
from pathlib import Path

import pytest

_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND


def _under(path, folder: Path) -> bool:
    if isinstance(path, int):  # a file descriptor
        return False
    absolute = Path(os.path.abspath(os.fsdecode(path)))
    return absolute == folder or folder in absolute.parents


def _writes(mode: str) -> bool:
    return any(c in mode for c in "wax+")


def read_only(monkeypatch: pytest.MonkeyPatch, folder: Path) -> Callable[[], None]:
    """Make ``folder`` (and what is under it) unwritable: a real ``chmod`` where it stops this user,
    else patched calls that fail with ``EROFS``. Returns what makes it writable again."""
    folder = Path(os.path.abspath(folder))
    mode = folder.stat().st_mode
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
    probe = folder / ".probe"
    try:
        probe.mkdir()
    except PermissionError:
        return lambda: folder.chmod(mode)
    probe.rmdir()
    folder.chmod(mode)

    def refuse(path) -> None:
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))

    def guard(original: Callable, *path_args: int) -> Callable:
        def call(*args, **kwargs):
            for i in path_args:
                if i < len(args) and _under(args[i], folder):
                    refuse(args[i])
            return original(*args, **kwargs)
        return call

    real_open, real_io_open = os.open, io.open

    def os_open(path, flags, *args, **kwargs):
        if flags & _WRITE_FLAGS and _under(path, folder):
            refuse(path)
        return real_open(path, flags, *args, **kwargs)

    def io_open(file, mode="r", *args, **kwargs):
        if _writes(mode) and _under(file, folder):
            refuse(file)
        return real_io_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)
    for name in ("mkdir", "unlink", "remove", "rmdir"):
        monkeypatch.setattr(os, name, guard(getattr(os, name), 0))
    for name in ("replace", "rename"):
        monkeypatch.setattr(os, name, guard(getattr(os, name), 0, 1))
    return lambda: None


def no_space(monkeypatch: pytest.MonkeyPatch, folder: Path, only: Callable[[Path], bool] = lambda p: True) -> None:
    """Make every write of a file at or under ``folder`` (for which ``only`` holds) fail with ``ENOSPC``."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    folder = Path(os.path.abspath(folder))
    real_open, real_io_open = os.open, io.open

    def full(path) -> bool:
        return _under(path, folder) and only(Path(os.fsdecode(path)))

    def os_open(path, flags, *args, **kwargs):
        if flags & _WRITE_FLAGS and full(path):
            return real_open("/dev/full", os.O_WRONLY)
        return real_open(path, flags, *args, **kwargs)

    def io_open(file, mode="r", *args, **kwargs):
        if _writes(mode) and full(file):
            return real_io_open("/dev/full", mode.replace("x", "w").replace("a", "w"), *args, **kwargs)
        return real_io_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)
    monkeypatch.setattr(builtins, "open", io_open)
