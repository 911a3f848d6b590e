"""Test-view evaluation during and after training: the test views' pose and appearance corrections fitted
to their images with the model fixed (:class:`TestViews`), their PSNR, and the best PSNR the train log saw.

The render is a callable (camera -> colour [H,W,3]) that :class:`rtsplat.train.trainer.Trainer` passes in;
nothing here holds the model.
"""

from __future__ import annotations

import math
import time
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


class TestViews:
    """The test views and their corrections [views, 6]: the pose (rotation vector, translation; fitted only
    where the training poses are refined) and the appearance (log gain, offset per channel; fitted only where
    the training views learn one), both zero until :meth:`fit` runs, and the seconds the fits took."""

    def __init__(self, views: ViewSet, device: torch.device, *, poses: bool, appearance: bool):
        self.views = views
        self.fits_poses, self.fits_appearance = poses, appearance
        self.poses = torch.zeros(len(views), 6, device=device)
        self.appearance = torch.zeros(len(views), 6, device=device)
        self.seconds = 0.0

    def fit(self, render: Render, steps: int, extent: float, pose_lr: float, appearance_prior: float) -> None:
        """Fit the poses to the photos in ``steps`` steps from the current ones (the photo brought back to the
        model's colours by the view's current appearance correction), then the appearance corrections in
        closed form on the render at the fitted pose."""
        if len(self.views) == 0:
            return
        start = time.perf_counter()
        if self.fits_poses and steps > 0:
            self.poses = fit_test_poses(render, self.views, self.poses,
                                        self.appearance if self.fits_appearance else None, extent, steps, pose_lr)
        if self.fits_appearance:
            fit_test_appearance(render, self.cameras(), self.views.images, appearance_prior, self.appearance)
        self.seconds += time.perf_counter() - start

    def cameras(self) -> list[Camera]:
        """The views' cameras with their pose corrections."""
        return [camera.corrected(correction)
                for camera, correction in zip(self.views.cameras, self.poses, strict=True)]

    def psnr(self, render: Render) -> dict[str, float]:
        """:func:`views_psnr` of the views at their corrected cameras, their appearance corrections applied."""
        return views_psnr(render, self.cameras(), self.views, self.appearance if self.fits_appearance else None)

    def restore(self, poses: dict[str, list[float]], appearance: dict[str, list[float]]) -> None:
        """Copy in the saved corrections (by view name) of the views that have one."""
        for rows, saved in ((self.poses, poses), (self.appearance, appearance)):
            for index, name in enumerate(self.views.names):
                if name in saved:
                    rows[index] = torch.as_tensor(saved[name], device=rows.device)


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


def rows_by_name(names: list[str], rows: Tensor) -> dict[str, list[float]]:
    """Per-view rows [views, ...] by view name (how a checkpoint keeps the views' corrections)."""
    return dict(zip(names, rows.tolist(), strict=True))


@torch.no_grad()
def views_psnr(render: Render, cameras: list[Camera], views: ViewSet, appearance: Tensor | None) -> dict[str, float]:
    """Mean PSNR of ``views`` rendered at ``cameras``, over the entire image (``test_psnr``) and over the
    transparent region of the views that have one (``test_psnr_transparent``); ``appearance``: the views'
    corrections applied to the renders (None: none). No views: an empty dict."""
    if len(views) == 0:
        return {}
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
