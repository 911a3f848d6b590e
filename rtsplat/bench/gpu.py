"""GPU rasterizer benchmark: ``python -m rtsplat.bench.gpu`` (needs a CUDA device).

Reports, for the ``triton`` backend at ~1 megapixel (default 1024x1024):

* training step: forward + backward (a random mix of every output, the weights drawn once outside
  the timed region) in ms, for 100k and 500k surfels;
* rendering: forward only (``torch.no_grad``) in ms and frames per second, for 500k surfels;
* where gsplat has CUDA kernels (its compiled extension, or a CUDA toolkit for its JIT build, which
  takes minutes the first time; ``--no-gsplat`` skips it): the same step with two calls of gsplat's
  ``rasterize_to_pixels_2dgs`` on the same surfels, one per weight set of RT-Splatting (surface:
  occupancy with the 12 feature channels, normals, depth distortion and median depth; volume:
  occupancy x opacity with the 3 colour channels). gsplat's projection and tile intersection run
  once outside the timed region (printed separately), while the triton times include rtsplat's
  projection, binning and depth sort: the ratio triton / gsplat is conservative for triton.

The scene is :func:`rtsplat.bench.raster.sphere_scene` (surfels tangent to a unit sphere, front and
back layers, 12 surface feature channels) seen from 3 units away with a 50 degree field of view.
Times are medians over ``--repeats`` runs after one warm-up run (which includes Triton's kernel
compilation), each bracketed by ``torch.cuda.synchronize``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from rtsplat.bench.raster import IMAGE_OUTPUTS, gpu_unavailable_reason, sphere_scene, surfels_to, with_grad
from rtsplat.camera import camera_from_fov
from rtsplat.raster import RasterSettings, Surfels, rasterize


def _timed(fn, repeats: int) -> float:
    """Median wall time (ms) of ``fn()`` after one warm-up call, synchronising the GPU around each call."""
    fn()
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _weights(shapes: dict, device) -> dict:
    g = torch.Generator().manual_seed(1)
    return {name: torch.rand(shape, generator=g).to(device) for name, shape in shapes.items()}


def triton_times(surfels: Surfels, camera, repeats: int) -> dict:
    with torch.no_grad():
        out = rasterize(surfels, camera, backend="triton")
    weights = _weights({name: getattr(out, name).shape for name in IMAGE_OUTPUTS}, surfels.device)

    def step():
        leaf = with_grad(surfels)
        out = rasterize(leaf, camera, backend="triton")
        sum((getattr(out, name) * w).sum() for name, w in weights.items()).backward()

    def render():
        with torch.no_grad():
            rasterize(surfels, camera, backend="triton")

    return {"step": _timed(step, repeats), "render": _timed(render, repeats)}


def gsplat_kernels():
    """gsplat's CUDA wrapper module when its kernels can run here, else a string saying why not."""
    try:
        from gsplat.cuda._backend import _C
    except Exception as exc:  # its JIT build can fail in many ways (compiler, headers, arch)
        return f"gsplat's CUDA extension failed to load ({type(exc).__name__}: {exc})"
    if _C is None:
        return "gsplat has no compiled CUDA extension and no CUDA toolkit to build one"
    from gsplat.cuda import _wrapper

    return _wrapper


def gsplat_times(gs, surfels: Surfels, camera, settings: RasterSettings, repeats: int) -> dict:
    """Two ``rasterize_to_pixels_2dgs`` calls (surface set, volume set), forward + backward."""
    device = surfels.device
    W, H, ts = camera.width, camera.height, settings.tile_size
    viewmat = torch.eye(4, device=device)
    viewmat[:3, :3] = camera.rotation
    viewmat[:3, 3] = camera.translation
    scales3 = torch.cat([surfels.scales, torch.zeros_like(surfels.scales[:, :1])], 1)

    def project():
        radii, means2d, depths, ray_transforms, normals = gs.fully_fused_projection_2dgs(
            surfels.means, surfels.quats, scales3, viewmat[None], camera.K[None], W, H,
            near_plane=settings.near, far_plane=settings.far,
        )
        tiles_x, tiles_y = (W + ts - 1) // ts, (H + ts - 1) // ts
        _, isect_ids, flatten_ids = gs.isect_tiles(means2d, radii, depths, ts, tiles_x, tiles_y)
        offsets = gs.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
        return means2d, depths, ray_transforms, normals, offsets, flatten_ids

    with torch.no_grad():
        means2d, depths, ray_transforms, normals, offsets, flatten_ids = project()
    project_ms = _timed(lambda: torch.no_grad()(project)(), repeats)
    n_pairs = int(flatten_ids.shape[0])
    surface_in = torch.cat([surfels.features, depths[0, :, None]], 1)[None]
    volume_in = torch.cat([surfels.colors, depths[0, :, None]], 1)[None]
    weights = _weights(
        {"surface": (1, H, W, surface_in.shape[-1]), "volume": (1, H, W, volume_in.shape[-1]), "one": (1, H, W, 1),
         "normal": (1, H, W, 3)},
        device,
    )

    def step():
        leaves = [t.detach().clone().requires_grad_(True) for t in (means2d, ray_transforms, normals)]
        occupancy = surfels.occupancy.detach().clone().requires_grad_(True)[None]
        opacity = surfels.opacity.detach().clone().requires_grad_(True)[None]
        feats = surface_in.detach().clone().requires_grad_(True)
        colors = volume_in.detach().clone().requires_grad_(True)
        densify = torch.zeros_like(means2d, requires_grad=True)
        loss = 0.0
        for values, opacities, key, distloss in ((feats, occupancy, "surface", True),
                                                 (colors, occupancy * opacity, "volume", False)):
            image, alpha, normal, distort, median = gs.rasterize_to_pixels_2dgs(
                leaves[0], leaves[1], values, opacities, leaves[2], densify, W, H, ts, offsets, flatten_ids,
                distloss=distloss,
            )
            loss = loss + (image * weights[key]).sum() + (alpha * weights["one"]).sum()
            if key == "surface":
                loss = loss + (normal * weights["normal"]).sum() + distort.sum() + median.sum()
        loss.backward()

    return {"project": project_ms, "step": _timed(step, repeats), "pairs": n_pairs}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--resolution", default="1024x1024", help="WxH (default 1024x1024, ~1 MP)")
    parser.add_argument("--sizes", default="100000,500000", help="surfel counts for the training step")
    parser.add_argument("--render-size", type=int, default=500_000, help="surfel count for the render FPS")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per measurement (median)")
    parser.add_argument("--no-gsplat", action="store_true", help="skip the gsplat comparison")
    args = parser.parse_args(argv)
    reason = gpu_unavailable_reason()
    if reason is not None:
        print(f"rtsplat.bench.gpu needs a CUDA device and triton ({reason}); run it on a GPU machine. "
              "For the CPU backends use python -m rtsplat.bench.raster.", file=sys.stderr)
        return 2
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    device = torch.device("cuda")
    settings = RasterSettings()
    camera = camera_from_fov((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=width, height=height, fov_x_deg=50.0)
    camera = camera.to(device)
    gs = None if args.no_gsplat else gsplat_kernels()
    print(f"{torch.cuda.get_device_name(device)}, torch {torch.__version__}, {width}x{height}; "
          f"median of {args.repeats} runs (ms)")
    if isinstance(gs, str):
        print(f"gsplat: skipped ({gs})")
        gs = None
    sizes = [int(s) for s in args.sizes.split(",")]
    for n in sorted(set(sizes) | {args.render_size}):
        surfels = surfels_to(sphere_scene(n), device)
        ours = triton_times(surfels, camera, args.repeats)
        line = f"{n:>7} surfels: triton fwd+bwd {ours['step']:8.2f} ms"
        if n == args.render_size:
            line += f" | render {ours['render']:7.2f} ms = {1e3 / ours['render']:6.1f} FPS"
        if gs is not None:
            theirs = gsplat_times(gs, surfels, camera, settings, args.repeats)
            line += (f" | gsplat 2x rasterize_to_pixels_2dgs fwd+bwd {theirs['step']:8.2f} ms "
                     f"(+ projection/intersection {theirs['project']:.2f} ms, {theirs['pairs']} pairs)"
                     f" | ratio triton / gsplat {ours['step'] / theirs['step']:.2f}")
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.gpu", main))
