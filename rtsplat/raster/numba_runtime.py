"""The numba runtime shared by the CPU kernels (the ``cpu`` rasterizer, its projection and binning,
the model's kernels): where compiled kernels are cached, how kernel modules are imported (without numba:
one warning and ``None``, so callers fall back to torch), whether a kernel module takes some tensors,
the thread count and parallel chunking of a kernel call, and the tensor -> float64 array conversion the
kernels read. Importing this module does not import numba.
"""

from __future__ import annotations

import importlib
import os
import threading
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

__all__ = ["CHUNK", "SURFEL_CHUNK", "TILE_CHUNK", "cache_dir", "kernels_take", "load_numba_module", "numba_threads",
           "to_float64_array"]

_lock = threading.Lock()
_modules: dict[str, object] = {}
_unavailable: str | None = None


def cache_dir() -> Path:
    """Where the compiled kernels are cached (user cache directory, not the repository)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rtsplat" / "numba"


def load_numba_module(name: str):
    """Import the numba kernel module ``name`` (compile cache and threading layer configured first);
    None when numba is missing, after one warning."""
    global _unavailable
    with _lock:
        if name in _modules:
            return _modules[name]
        if _unavailable is not None:
            return None
        path = cache_dir()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            pass
        os.environ.setdefault("NUMBA_CACHE_DIR", str(path))
        try:
            import numba

            # numba reads NUMBA_CACHE_DIR when it is first imported; it may have been imported
            # before us, so set the live config too (read when the kernels are decorated)
            numba.config.CACHE_DIR = str(path)
            # numba's OpenMP threading layer and torch's own OpenMP runtime both spin-wait for work,
            # and in one process on few cores they can starve each other; the workqueue layer
            # sleeps when idle. NUMBA_THREADING_LAYER still wins when a user sets it.
            if "NUMBA_THREADING_LAYER" not in os.environ:
                numba.config.THREADING_LAYER = "workqueue"
            module = importlib.import_module(name)
        except ImportError as exc:  # pragma: no cover - exercised only without numba
            _unavailable = str(exc)
            warnings.warn(
                f"rtsplat: numba is not available ({exc}); the CPU kernels (the 'cpu' rasterizer, the SH "
                "colours) fall back to the slow torch code. Install numba (see README).",
                RuntimeWarning,
                stacklevel=3,
            )
            return None
        _modules[name] = module
        return module


def kernels_take(name: str, *tensors: Tensor) -> bool:
    """Whether the numba kernel module ``name`` takes ``tensors``: all on the CPU, of one float type, float32 or
    float64, and numba installed (:func:`load_numba_module`). Callers fall back to their torch version otherwise."""
    dtypes = {t.dtype for t in tensors}
    if len(dtypes) != 1 or dtypes.pop() not in (torch.float32, torch.float64):
        return False
    if any(t.device.type != "cpu" for t in tensors):
        return False
    return load_numba_module(name) is not None


# iterations per chunk of a parallel loop (numba's ``set_parallel_chunksize``). The chunks are dealt out
# on demand by the tbb threading layer, but split into one contiguous run per thread by the
# workqueue layer, which :func:`load_numba_module` picks: a kernel with uneven work spreads it itself
# (the compositing kernels visit their tiles in :func:`rtsplat.raster.cpu_kernels.spread_order`).
CHUNK = 4  # tiles per chunk of the tile entry lists (``tile_entries_kernel``), the default
TILE_CHUNK = 1  # tiles per chunk of the compositing kernels, forward and backward (uneven work, ~1 ms a tile)
SURFEL_CHUNK = 256  # surfels per chunk of the per-surfel kernels (even, cheap work: ~1 us per chunk saved)


class numba_threads:
    """Run numba kernels with torch's thread count and chunks of ``chunk`` parallel iterations."""

    def __init__(self, chunk: int = CHUNK):
        self.chunk = chunk

    def __enter__(self):
        import numba

        self._threads = numba.get_num_threads()
        numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
        self._chunk = numba.set_parallel_chunksize(self.chunk)
        return numba.get_num_threads()

    def __exit__(self, *exc):
        import numba

        numba.set_parallel_chunksize(self._chunk)
        numba.set_num_threads(self._threads)
        return False




def to_float64_array(x: Tensor) -> np.ndarray:
    """``x`` as a contiguous float64 numpy array on the host (a copy unless it already is one)."""
    return np.ascontiguousarray(x.detach().to(device="cpu", dtype=torch.float64).numpy())
