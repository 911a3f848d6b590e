"""Rasterizer backends side by side: ``python -m rtsplat.bench.raster``.

For every image size and surfel count it renders one synthetic scene with each backend and
prints, per backend, the forward time (inference, ``torch.no_grad``), the forward+backward time
(a training step: forward with autograd, backward of a random mix of every output) and the peak
resident memory above the process baseline during forward+backward; then the ratios of the last
backend to the first (default: cpu / reference). All backends run in the same process on the same
scene, so the ratios are comparable even on a loaded machine; absolute times are not.

With a CUDA device (and triton installed) the ``triton`` backend is added as the last column; it
runs on the GPU (times include ``torch.cuda.synchronize``; its peak column is the GPU memory
allocated above the baseline, not resident memory). Without one it is skipped with a note.

The scene: ``N`` surfels tangent to a unit sphere (front and back layers overlap, like a trained
object), sizes matched to the surfel spacing, 12 surface feature channels (the G-buffer width of
RT-Splatting), seen from 3 units away with a 50 degree field of view.

The reference backend keeps dense [tiles, pixels, surfels] tensors for autograd; a run whose
estimated memory exceeds ``--max-reference-gb`` is printed as ``skipped (memory)``. A cell whose
estimated time (the backend's seconds per dense pixel x surfel pair in the cells it already ran,
times this cell's pairs) exceeds ``--max-cell-seconds`` is printed as ``skipped (time)`` instead
of running for minutes.
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import math
import os
import statistics
import threading
import time

import torch

from rtsplat.camera import camera_from_fov
from rtsplat.raster import RasterSettings, Surfels, available_backends, rasterize
from rtsplat.raster.binning import bin_tiles
from rtsplat.raster.projection import project_surfels

IMAGE_OUTPUTS = (
    "features",
    "normal",
    "depth",
    "depth_median",
    "alpha",
    "distortion",
    "color",
    "volume_alpha",
    "volume_depth",
)
# peak bytes per dense (pixel, surfel) pair of the reference's forward+backward (float32),
# measured with this script (5k and 20k surfels at 160x120 gave ~ 330-420 B); rounded up
REFERENCE_BYTES_PER_PAIR = 450


def sphere_scene(n: int, seed: int = 0, n_features: int = 12, dtype=torch.float32) -> Surfels:
    g = torch.Generator().manual_seed(seed)
    normal = torch.randn(n, 3, generator=g, dtype=torch.float64)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # quaternion rotating +z onto the normal: (1 + n_z, -n_y, n_x, 0), normalised by the rasterizer
    quats = torch.stack([1.0 + normal[:, 2], -normal[:, 1], normal[:, 0], torch.zeros(n, dtype=torch.float64)], 1)
    quats[quats.norm(dim=-1) < 1e-6] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    spacing = math.sqrt(4 * math.pi / max(n, 1))
    scales = spacing * (0.5 + torch.rand(n, 2, generator=g, dtype=torch.float64))

    def uniform(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

    fields = dict(
        means=normal,
        quats=quats,
        scales=scales,
        occupancy=uniform(0.3, 0.95, n),
        opacity=uniform(0.2, 0.9, n),
        features=uniform(0.0, 1.0, n, n_features),
        colors=uniform(0.0, 1.0, n, 3),
    )
    return Surfels(**{k: v.to(dtype) for k, v in fields.items()})


def _release_freed_memory() -> None:
    """Give memory freed by earlier runs back to the OS (glibc keeps it), so RSS measures this run."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


class PeakRSS:
    """Peak resident set size above the value at entry, sampled from /proc every 2 ms."""

    def __enter__(self):
        _release_freed_memory()
        self.baseline = self.peak = self._rss()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.wait(0.002):
            self.peak = max(self.peak, self._rss())

    @staticmethod
    def _rss() -> int:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:  # not Linux: no memory column
            return 0

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())
        return False

    @property
    def megabytes(self) -> float:
        return (self.peak - self.baseline) / 2**20


def reference_pairs(surfels: Surfels, camera, settings: RasterSettings) -> int:
    """Dense (pixel, surfel) pairs the reference backend evaluates."""
    with torch.no_grad():
        proj = project_surfels(surfels, camera, settings)
        bins = bin_tiles(
            proj.bbox_min, proj.bbox_max, proj.depths, proj.valid, camera.width, camera.height, settings.tile_size
        )
        kmax_by_tile = bins.tile_count
    return int(kmax_by_tile.sum()) * settings.tile_size**2


def _loss(out) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    total = 0.0
    for name in IMAGE_OUTPUTS:
        value = getattr(out, name)
        weights = torch.rand(value.shape, generator=g, dtype=value.dtype).to(value.device)
        total = total + (value * weights).sum()
    return total


GPU_BACKENDS = ("triton",)


def backend_device(backend: str) -> torch.device:
    """Where a backend's inputs live in this benchmark: CUDA for the GPU backends, else CPU."""
    return torch.device("cuda" if backend in GPU_BACKENDS else "cpu")


def gpu_unavailable_reason() -> str | None:
    """Why the GPU backends cannot run here (None when they can)."""
    if not torch.cuda.is_available():
        return "no CUDA device"
    from rtsplat.raster.gpu import triton_available

    if not triton_available():
        return "triton is not installed"
    return None


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class PeakCUDA:
    """Peak CUDA memory allocated above the value at entry."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def __enter__(self):
        torch.cuda.synchronize(self.device)
        self.baseline = torch.cuda.memory_allocated(self.device)
        torch.cuda.reset_peak_memory_stats(self.device)
        return self

    def __exit__(self, *exc):
        torch.cuda.synchronize(self.device)
        self.peak = torch.cuda.max_memory_allocated(self.device)
        return False

    @property
    def megabytes(self) -> float:
        return (self.peak - self.baseline) / 2**20


def surfels_to(surfels: Surfels, device: torch.device) -> Surfels:
    return Surfels(**{f.name: getattr(surfels, f.name).detach().to(device) for f in dataclasses.fields(Surfels)})


def with_grad(surfels: Surfels) -> Surfels:
    return Surfels(
        *[
            t.detach().clone().requires_grad_(True)
            for t in (
                surfels.means,
                surfels.quats,
                surfels.scales,
                surfels.occupancy,
                surfels.opacity,
                surfels.features,
                surfels.colors,
            )
        ]
    )


def time_backend(backend: str, surfels: Surfels, camera, repeats: int, budget_s: float) -> dict:
    """Median forward and forward+backward times (s) and peak memory (MB) of one backend, on its device."""
    device = backend_device(backend)
    camera = camera.to(device)
    surfels = surfels_to(surfels, device)
    fwd, step, peak = [], [], 0.0
    spent = 0.0
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        with torch.no_grad():
            rasterize(surfels, camera, backend=backend)
        _sync(device)
        fwd.append(time.perf_counter() - t0)
        leaf = with_grad(surfels)
        with PeakCUDA(device) if device.type == "cuda" else PeakRSS() as mem:
            t0 = time.perf_counter()
            out = rasterize(leaf, camera, backend=backend)
            _loss(out).backward()
            _sync(device)
            step.append(time.perf_counter() - t0)
            del out, leaf
        peak = max(peak, mem.megabytes)
        spent += fwd[-1] + step[-1]
        if spent > budget_s:
            break
    return {"fwd": statistics.median(fwd), "step": statistics.median(step), "peak": peak, "runs": len(fwd)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--backends",
        default=None,
        help="comma-separated backends; ratios are last / first (default: reference,cpu, and triton on a "
        "CUDA machine)",
    )
    parser.add_argument("--sizes", default="5000,20000,100000", help="surfel counts (default: 5000,20000,100000)")
    parser.add_argument("--resolutions", default="160x120,640x480", help="WxH list (default: 160x120,640x480)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per cell (median; fewer when slow)")
    parser.add_argument("--budget", type=float, default=20.0, help="stop repeating a cell after this many seconds")
    parser.add_argument(
        "--max-reference-gb",
        type=float,
        default=12.0,
        help="skip reference runs whose estimated memory exceeds this (default 12)",
    )
    parser.add_argument(
        "--max-cell-seconds",
        type=float,
        default=150.0,
        help="skip a backend's cell when its estimated time for one forward plus one "
        "forward+backward, extrapolated from its earlier cells, exceeds this (default 150)",
    )
    args = parser.parse_args(argv)
    gpu_missing = gpu_unavailable_reason()
    requested = args.backends or ("reference,cpu" if gpu_missing else "reference,cpu,triton")
    backends = [b.strip() for b in requested.split(",") if b.strip()]
    for b in backends:
        if b not in available_backends():
            parser.error(f"unknown backend {b!r}; available: {available_backends()}")
    if gpu_missing:
        skipped = [b for b in backends if b in GPU_BACKENDS] or list(GPU_BACKENDS)
        print(f"note: {', '.join(skipped)} skipped ({gpu_missing}); run on a CUDA machine for its column")
        backends = [b for b in backends if b not in GPU_BACKENDS]
        if not backends:
            return
    sizes = [int(s) for s in args.sizes.split(",")]
    resolutions = [tuple(int(v) for v in r.lower().split("x")) for r in args.resolutions.split(",")]
    settings = RasterSettings()

    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads; times in ms (median of up to "
        f"{args.repeats}), peak = resident memory above baseline during forward+backward (MB)"
    )
    # warm up every backend once (the cpu backend compiles or loads its kernels here)
    warm_camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=32, height=24, fov_x_deg=50.0)
    for b in backends:
        t0 = time.perf_counter()
        device = backend_device(b)
        leaf = with_grad(surfels_to(sphere_scene(200), device))
        _loss(rasterize(leaf, warm_camera.to(device), backend=b)).backward()
        _sync(device)
        print(f"warm-up {b}: {time.perf_counter() - t0:.1f} s (includes kernel compilation/cache load)")

    cols = " | ".join(f"{b + ' fwd':>14} {'fwd+bwd':>9} {'peak MB':>8}" for b in backends)
    ratio_head = f" | {'ratio fwd':>9} {'fwd+bwd':>8}" if len(backends) > 1 else ""
    header = f"{'image':>8} {'surfels':>7} | {cols}{ratio_head}"
    print(header)
    print("-" * len(header))
    seconds_per_pair: dict[str, float] = {}  # per backend: slowest (fwd + fwd+bwd) / pairs seen so far
    for width, height in resolutions:
        camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=width, height=height, fov_x_deg=50.0)
        for n in sizes:
            scene = sphere_scene(n)
            pairs = reference_pairs(scene, camera, settings)
            cells, results = [], {}
            for b in backends:
                if b == "reference":
                    est_gb = pairs * REFERENCE_BYTES_PER_PAIR / 1e9
                    if est_gb > args.max_reference_gb:
                        cells.append(f"{f'skipped (memory, ~{est_gb:.0f} GB)':>33}")
                        continue
                est_s = seconds_per_pair.get(b, 0.0) * pairs
                if est_s > args.max_cell_seconds:
                    cells.append(f"{f'skipped (time, ~{est_s:.3g} s/run)':>33}")
                    continue
                r = time_backend(b, scene, camera, args.repeats, args.budget)
                results[b] = r
                rate = (r["fwd"] + r["step"]) / max(pairs, 1)
                seconds_per_pair[b] = max(seconds_per_pair.get(b, 0.0), rate)
                cells.append(f"{r['fwd'] * 1e3:>14.1f} {r['step'] * 1e3:>9.1f} {r['peak']:>8.0f}")
            line = f"{f'{width}x{height}':>8} {n:>7} | " + " | ".join(cells)
            if len(backends) > 1:
                first, last = results.get(backends[0]), results.get(backends[-1])
                if first and last:
                    line += f" | {last['fwd'] / first['fwd']:>9.4f} {last['step'] / first['step']:>8.4f}"
                else:
                    line += f" | {'-':>9} {'-':>8}"
            print(line, flush=True)


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.raster", main))
