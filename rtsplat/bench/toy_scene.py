"""A tiny prepared scene for trainer tests and benchmarks: a photo-textured wall seen through a glass-like pane.

Ground truth is rendered with the rasterizer's volume colour from known surfels (the wall: opaque
surfels coloured by a scikit-image photograph; the pane: full occupancy, opacity 0.15, bluish),
plus a view-dependent "reflection" (a bright band whose position moves with the camera) added on
the pane pixels, so a model that can reflect has something to learn. Masks are the pane's
projection. ``exposures`` (one ``[6]`` appearance correction per view, :mod:`rtsplat.model.appearance`)
photographs each view with its own exposure and white balance, as a phone does. Written with the
pipeline's PreparedScene contract.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from rtsplat.camera import camera_from_fov
from rtsplat.io.images import write_mask, write_png
from rtsplat.io.ply import write_points_ply
from rtsplat.raster import Surfels, rasterize
from rtsplat.scene import CameraRecord, PreparedScene, Roi


def _photo(size: int) -> np.ndarray:
    from skimage import data, transform

    img = data.astronaut().astype(np.float32) / 255.0
    return transform.resize(img, (size, size), anti_aliasing=True).astype(np.float32)


def ground_truth_surfels(n_side: int = 20, with_pane: bool = True) -> tuple[Surfels, torch.Tensor]:
    """Wall in the plane y = 1 (x, z in [-1, 1]); pane in y = -0.3 (x, z in [-0.5, 0.5])."""
    tex = _photo(n_side)
    u = (torch.arange(n_side) + 0.5) / n_side * 2 - 1
    zz, xx = torch.meshgrid(-u, u, indexing="ij")
    wall = torch.stack([xx.flatten(), torch.ones(n_side * n_side), zz.flatten()], 1)
    wall_col = torch.from_numpy(tex.reshape(-1, 3))
    s = math.sqrt(0.5)
    wall_q = torch.tensor([s, s, 0.0, 0.0]).expand(len(wall), 4)  # normal along y
    spacing = 2.0 / n_side
    means, quats, cols = [wall], [wall_q], [wall_col]
    occ, opa, glass = [torch.full((len(wall),), 0.95)], [torch.ones(len(wall))], [torch.zeros(len(wall))]
    scales = [torch.full((len(wall), 2), spacing * 0.8)]
    if with_pane:
        m = 8
        v = (torch.arange(m) + 0.5) / m - 0.5
        pz, px = torch.meshgrid(v, v, indexing="ij")
        pane = torch.stack([px.flatten(), torch.full((m * m,), -0.3), pz.flatten()], 1)
        means.append(pane)
        quats.append(torch.tensor([s, s, 0.0, 0.0]).expand(m * m, 4))
        cols.append(torch.tensor([0.6, 0.8, 1.0]).expand(m * m, 3))
        occ.append(torch.ones(m * m))
        opa.append(torch.full((m * m,), 0.15))
        glass.append(torch.ones(m * m))
        scales.append(torch.full((m * m, 2), 1.0 / m * 0.8))
    surfels = Surfels(torch.cat(means), torch.cat(quats).clone(), torch.cat(scales), torch.cat(occ),
                      torch.cat(opa), torch.cat(glass)[:, None], torch.cat(cols))
    return surfels, torch.cat(glass)


def write_scene(root: Path, *, views: int = 12, width: int = 64, height: int = 48, with_pane: bool = True,
                n_side: int = 20, test_every: int = 4, seed: int = 0, roi_source: str = "config",
                exposures: torch.Tensor | None = None) -> PreparedScene:
    from rtsplat.model.appearance import apply_appearance

    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    if with_pane:
        (root / "masks").mkdir(parents=True, exist_ok=True)
    surfels, is_glass = ground_truth_surfels(n_side=n_side, with_pane=with_pane)
    records = []
    for i in range(views):
        angle = -0.5 + i / max(views - 1, 1)
        eye = (2.6 * math.sin(angle), -2.6 * math.cos(angle), 0.25 * math.sin(3 * angle))
        cam = camera_from_fov(eye, (0.0, 0.3, 0.0), width=width, height=height, fov_x_deg=55.0)
        with torch.no_grad():
            out = rasterize(surfels, cam, backend="reference")
        image = out.color.clone()
        name = f"view_{i:03d}"
        if with_pane:
            pane = (out.features[..., :1] > 0.5).float()
            band_x = (0.5 + 0.4 * math.sin(2 * angle)) * width
            xs = torch.arange(width, dtype=torch.float32)[None, :, None] + 0.5
            band = torch.exp(-((xs - band_x) ** 2) / (2 * (0.08 * width) ** 2)).expand(height, width, 1)
            image = image + 0.5 * band * pane
            write_mask(root / "masks" / f"{name}.png", pane[..., 0].numpy() > 0.5)
        if exposures is not None:
            image = apply_appearance(image, exposures[i])
        write_png(root / "images" / f"{name}.png", image.clamp(0, 1).numpy())
        records.append(CameraRecord(
            name=name, split="test" if i % test_every == 0 else "train", width=width, height=height,
            K=cam.K.tolist(), world_to_camera=cam.world_to_camera.tolist(), image=f"{name}.png"))
    g = np.random.default_rng(seed)
    pts = surfels.means.numpy() + g.normal(0, 0.02, surfels.means.shape)
    rgb = (surfels.colors.numpy() * 255).astype(np.uint8)
    write_points_ply(root / "points.ply", pts, rgb)
    # what prepare measures at the SfM observations: each photo's own exposure (the points carry the true colours)
    gains = exposures[:, :3].tolist() if exposures is not None else [[0.0, 0.0, 0.0]] * views
    scene = PreparedScene(cameras=records, roi=Roi([0.0, -0.3, 0.0], 1.0, roi_source), has_transparency=with_pane,
                          exposure={record.name: gains[i] for i, record in enumerate(records)})
    scene.save(root)
    return PreparedScene.load(root)


def train_quietly(scene: PreparedScene, out: Path, schedule: dict, model: dict) -> dict:
    """Train ``scene`` into the run folder ``out`` with these ``schedule`` and ``model`` sections of the
    trainer's config (the rest: defaults), without a progress bar or log lines; returns the run's summary."""
    from rtsplat.train.trainer import Trainer
    from rtsplat.train_config import TrainConfig

    cfg = TrainConfig.from_dict({"schedule": schedule, "model": model})
    return Trainer(scene, cfg, Path(out), progress=False, log=lambda m: None).train()
