"""Training data from a prepared scene: cameras, images and masks as tensors."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.scene import PreparedScene


@dataclass
class ViewSet:
    names: list[str]
    cameras: list[Camera]
    images: list[Tensor]  # [H,W,3] in [0,1]
    masks: list[Tensor | None]  # [H,W,1] float, 1 = see-through; None without transparency

    def __len__(self) -> int:
        return len(self.names)

    @property
    def transparent_fraction(self) -> float:
        masks = [m for m in self.masks if m is not None]
        if not masks:
            return 0.0
        return float(sum(m.sum() for m in masks) / sum(m.numel() for m in masks))


def load_views(scene: PreparedScene, split: str, device: str | torch.device = "cpu", downsample: int = 1) -> ViewSet:
    """The views of ``split``; ``downsample`` > 1 box-filters images and masks by that factor and scales
    the cameras to match (the trainer's resolution knob: train smaller, evaluate at the prepared size)."""
    from rtsplat.io.images import area_downsample

    records = scene.train_cameras if split == "train" else scene.test_cameras
    names, cameras, images, masks = [], [], [], []
    for rec in records:
        names.append(rec.name)
        cameras.append(rec.to_camera(device=device).scaled(downsample))
        image = area_downsample(scene.load_image(rec.name), downsample)
        images.append(torch.from_numpy(np.ascontiguousarray(image)).to(device))
        mask = scene.load_mask(rec.name)
        if mask is not None:
            mask = area_downsample(mask.astype(np.float32), downsample) >= 0.5
        masks.append(None if mask is None else torch.from_numpy(mask.astype(np.float32))[..., None].to(device))
    return ViewSet(names, cameras, images, masks)


def scene_extent(cameras: list[Camera]) -> float:
    """3DGS's normalisation radius: 1.1 x the largest distance of a camera from their mean."""
    centers = torch.stack([c.center.float() for c in cameras])
    radius = (centers - centers.mean(0)).norm(dim=-1).max()
    return float(max(radius.item(), 1e-3) * 1.1)
