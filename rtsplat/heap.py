"""The C heap's settings for a command that runs torch on the CPU (glibc's ``malloc``).

A training step allocates and frees the same large buffers every iteration: the specular network's
activations and their gradients are [pixels, 256] float32 arrays, about 7.7 MB each at 100x75. With
glibc's defaults, blocks that large are either mapped afresh for every allocation (above the mmap
threshold) or handed back to the kernel when freed (the top of the heap is trimmed past the trim
threshold), so an iteration can fault their pages in again and the kernel zeroes them. How often
depends on what the process freed before (glibc's thresholds follow the largest block it has freed):
a whole rtsplat training of a glass scene at the demo's settings took 1.58 million page faults and 2.9 s
of system time (docs/performance.md, "The C heap keeps what it frees").

:func:`keep_freed_memory` raises both thresholds, so that blocks up to :data:`MMAP_THRESHOLD` come from
the heap and freed memory stays with the process up to :data:`TRIM_THRESHOLD`: the next iteration
reuses the same pages. The process's peak memory is unchanged (the buffers were allocated anyway);
only its resident size no longer falls between iterations. It is a per-process setting, applied at
the command's edge (:func:`rtsplat.cli.main`), never by library code; under another C library (or
with a different allocator preloaded in front of glibc's) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024  # the largest glibc accepts on 64-bit systems (HEAP_MAX_SIZE / 2)
TRIM_THRESHOLD = 1024 * 1024 * 1024  # freed memory the heap keeps before it returns any to the kernel


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (it has ``mallopt`` and ``gnu_get_libc_version``), else None."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version  # noqa: B018 (glibc only: the probe)
        libc.mallopt  # noqa: B018
    except (OSError, AttributeError):
        return None
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    libc.mallopt.restype = ctypes.c_int
    return libc


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (see the module's docstring); True when
    both took effect, False under another C library or when glibc refused a value."""
    libc = _glibc()
    if libc is None:
        return False
    mmap_ok = libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
    trim_ok = libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    return mmap_ok and trim_ok
