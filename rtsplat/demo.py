"""Rasterizer demo: render a small procedural surfel scene and write its buffers as PNGs.

``rtsplat demo --out demo_out`` (or ``make demo``) writes the volume color, the surface normal,
the surface alpha/volume alpha and the expected depth of a scene made of an opaque textured
"floor", a ring of coloured surfels and a glass-like pane: surfels with full occupancy but
low opacity, which appear in the surface G-buffers (normal, alpha) but let the volume color
through. The folder is written atomically and replaced only when this command wrote it
(:func:`rtsplat.io.outputs.output_dir`).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from rtsplat.camera import camera_from_fov
from rtsplat.errors import run_command
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.raster import RasterOutput, Surfels, rasterize


def demo_scene(n_floor: int = 3000, n_ring: int = 600, n_pane: int = 400, seed: int = 0) -> Surfels:
    """Floor (opaque), a ring of blobs (opaque), and a vertical pane (occupancy 1, opacity 0.05)."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g)

    floor_xy = rand(n_floor, 2) * 4 - 2
    floor = torch.cat([floor_xy, torch.zeros(n_floor, 1)], 1)
    checker = ((floor_xy[:, 0].floor() + floor_xy[:, 1].floor()) % 2)[:, None]
    floor_col = 0.25 + 0.5 * checker * torch.tensor([0.9, 0.8, 0.6]) + 0.1 * rand(n_floor, 3)
    angle = rand(n_ring) * 2 * math.pi
    ring = torch.stack([0.9 * angle.cos(), 0.9 * angle.sin(), 0.3 + 0.1 * rand(n_ring)], 1)
    ring_col = torch.stack([0.5 + 0.5 * angle.cos(), 0.5 + 0.5 * angle.sin(), 0.6 * torch.ones(n_ring)], 1)
    pane_uv = rand(n_pane, 2)
    pane = torch.stack([pane_uv[:, 0] * 1.6 - 0.8, torch.full((n_pane,), -1.2), pane_uv[:, 1] * 0.9], 1)
    pane_col = torch.tensor([0.7, 0.9, 1.0]).expand(n_pane, 3)

    means = torch.cat([floor, ring, pane])
    n = means.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0  # floor and ring: normal +z
    s = math.sqrt(0.5)
    quats[n_floor + n_ring :] = torch.tensor([s, s, 0.0, 0.0])  # pane: normal along y
    scales = torch.cat(
        [torch.full((n_floor, 2), 0.06), torch.full((n_ring, 2), 0.05), torch.full((n_pane, 2), 0.07)]
    )
    occupancy = torch.cat([torch.full((n_floor + n_ring,), 0.9), torch.ones(n_pane)])
    opacity = torch.cat([torch.full((n_floor + n_ring,), 1.0), torch.full((n_pane,), 0.05)])
    colors = torch.cat([floor_col, ring_col, pane_col]).clamp(0, 1)
    is_glass = torch.cat([torch.zeros(n_floor + n_ring, 1), torch.ones(n_pane, 1)])
    return Surfels(means, quats, scales, occupancy, opacity, is_glass, colors)


def write_buffers(out: RasterOutput, out_dir: Path) -> list[Path]:
    """The buffers of ``out`` as PNGs in the existing folder ``out_dir``; returns their names."""
    from rtsplat.io.images import write_png

    depth = out.depth[..., 0]
    valid = out.alpha[..., 0] > 0.5
    d = depth[valid]
    depth_vis = ((depth - d.min()) / (d.max() - d.min() + 1e-9)).clamp(0, 1) if d.numel() else depth * 0
    images = {
        "volume_color.png": out.color,
        "surface_normal.png": out.normal * 0.5 + 0.5 * out.alpha,
        "surface_alpha.png": out.alpha.expand(-1, -1, 3),
        "volume_alpha.png": out.volume_alpha.expand(-1, -1, 3),
        "glass_gbuffer.png": out.features[..., :1].expand(-1, -1, 3),
        "depth.png": torch.where(valid, 1 - depth_vis, torch.zeros_like(depth))[..., None].expand(-1, -1, 3),
    }
    paths = []
    for name, image in images.items():
        write_png(out_dir / name, image.detach().cpu().numpy())
        paths.append(Path(name))
    return paths


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("demo_out"), help="output directory (created; replaced "
                        "only when this command wrote it)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--backend", default="auto", help="rasterizer backend: auto, reference, ...")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    check_output_dir(args.out, "demo")
    surfels = demo_scene(seed=args.seed)
    camera = camera_from_fov((0.0, -3.2, 1.4), (0.0, 0.0, 0.3), width=args.width, height=args.height)
    start = time.perf_counter()
    with torch.no_grad():
        out = rasterize(surfels, camera, backend=args.backend)
    elapsed = time.perf_counter() - start
    with output_dir(args.out, "demo") as tmp:
        names = write_buffers(out, tmp)
    print(f"rendered {len(surfels)} surfels at {args.width}x{args.height} in {elapsed:.2f} s")
    for name in names:
        print(f"  wrote {args.out / name}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.demo", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    return run_command("rtsplat.demo", lambda: run(args))


if __name__ == "__main__":
    raise SystemExit(main())
