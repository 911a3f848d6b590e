"""Test-view evaluation during and after training: the test views' pose and appearance corrections fitted
to their images with the model fixed, their PSNR, and the best PSNR the train log saw.

:class:`rtsplat.train.trainer.Trainer` holds the corrections and renders the views; these functions take
the render as a callable (camera -> colour [H,W,3]).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rtsplat.camera import Camera
from rtsplat.io.train_log import read_log
from rtsplat.model.appearance import apply_appearance, fit_appearance, remove_appearance
from rtsplat.quality import psnr
from rtsplat.train.cameras import fit_corrections
from rtsplat.train.data import ViewSet

Render = Callable[[Camera], Tensor]


def fit_test_poses(render: Render, views: ViewSet, corrections: Tensor, appearance: Tensor | None, extent: float,
                   steps: int, lr: float) -> Tensor:
    """The test views' pose corrections fitted to their images in ``steps`` Adam steps from ``corrections``,
    comparing the render with the photo brought back to the model's colours by the view's ``appearance``
    correction (None: appearance is not learnt)."""
    images = views.images
    if appearance is not None:
        images = [remove_appearance(image, correction) for image, correction in zip(images, appearance, strict=True)]
    return fit_corrections(render, views.cameras, images, corrections, extent, steps, lr)


@torch.no_grad()
def fit_test_appearance(render: Render, cameras: list[Camera], images: list[Tensor], prior: float,
                        out: Tensor) -> None:
    """Each test view's appearance correction, in closed form on the render at ``cameras``, into ``out``."""
    for index, (camera, image) in enumerate(zip(cameras, images, strict=True)):
        out[index] = fit_appearance(render(camera), image, prior)


@torch.no_grad()
def views_psnr(render: Render, cameras: list[Camera], views: ViewSet, appearance: Tensor | None) -> dict[str, float]:
    """Mean PSNR of ``views`` rendered at ``cameras``, over the entire image (``test_psnr``) and over the
    transparent region of the views that have one (``test_psnr_transparent``); ``appearance``: the views'
    corrections applied to the renders (None: none)."""
    full, region = [], []
    for index, (camera, image, mask) in enumerate(zip(cameras, views.images, views.masks, strict=True)):
        color = render(camera)
        if appearance is not None:
            color = apply_appearance(color, appearance[index])
        color = color.clamp(0, 1)
        full.append(psnr(color, image))
        if mask is not None:  # NaN marks a view without transparent pixels
            has_region = mask.sum() > 0
            region.append(torch.where(has_region, psnr(color, image, mask), torch.full_like(full[-1], math.nan)))
    # one transfer from the device for all views
    full_values = torch.stack(full).tolist()
    region_values = [v for v in (torch.stack(region).tolist() if region else []) if not math.isnan(v)]
    out = {"test_psnr": float(np.mean(full_values))}
    if region_values:
        out["test_psnr_transparent"] = float(np.mean(region_values))
    return out


def best_test_psnr(log_path: Path, iteration: int, final: dict[str, float]) -> dict:
    """The best entire-image test PSNR among the log's evaluations (iteration 0 is the initialisation)
    and the final one, with the iteration it was seen at and the final's distance to it."""
    seen = [(final["test_psnr"], iteration)] if "test_psnr" in final else []
    if log_path.exists():
        seen += [(record["test_psnr"], record["iteration"]) for record, _ in read_log(log_path, lambda _: None)
                 if "test_psnr" in record]
    if not seen:
        return {}
    best, at = max(seen, key=lambda pair: (pair[0], -pair[1]))
    out = {"best_test_psnr": best, "best_test_psnr_iteration": at}
    if "test_psnr" in final:
        out["final_minus_best_test_psnr"] = final["test_psnr"] - best
    return out
