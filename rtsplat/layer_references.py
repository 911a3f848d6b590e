"""References for the layer metrics of a synthetic scene, made from its ground truth itself: what a
reflection-layer PSNR inside the transparent mask means. Per view, in the metric's way (PSNR inside the
mask, then the mean over the views):

* ``zero``: no reflection at all;
* ``truth's mean``: the true reflection's mean colour (over every view's mask) painted on the whole mask:
  the best a reflection without any structure scores;
* ``truth blurred s px``: the true reflection blurred by a Gaussian of ``s`` pixels inside the mask: what a
  reflection with every detail right down to that scale scores;
* ``layers' sum``: the true reflection plus transmission against the scene's image: how well the renderer's
  two layers (their own samples) agree with the image they split, a ceiling of any layer metric.

And for the image itself (:func:`image_references`, :func:`run_image`): the true transmission plus the
reflection's mean colour against the image (a model with every detail behind the glass right and a reflection
without structure), and how much of a run's error inside the mask lies along the true reflection's detail
(its deviation from its mean): the part of the error a better reflection could remove.

Used by ``rtsplat report`` beside the runs' layer scores and by ``python -m rtsplat.bench.layer_ceiling``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rtsplat.errors import PipelineError
from rtsplat.scene import GT_LAYERS_DIR

BLUR_SIGMAS = (1.0, 2.0, 4.0)
LAYERS_SUM = "layers' sum against the image"


@dataclass
class View:
    name: str
    mask: np.ndarray  # [H,W] bool
    reflection: np.ndarray  # [H,W,3] the true reflection
    transmission: np.ndarray  # [H,W,3] the true transmission
    image: np.ndarray  # [H,W,3] the scene's image


def read_views(data: Path, names=None) -> list[View]:
    """The views of a prepared scene (those in ``names`` when given) that have ground-truth layers and a
    non-empty transparent mask."""
    from rtsplat.io.images import read_image, read_mask

    folder = data / GT_LAYERS_DIR / "reflection"
    if not folder.is_dir():
        raise PipelineError("no ground-truth layers", path=folder,
                            fix="pass a scene prepared from a `rtsplat synth` dataset rendered with layers")
    views = []
    for path in sorted(folder.glob("*.png")):
        if names is not None and path.stem not in names:
            continue
        mask_path = data / "masks" / path.name
        if not mask_path.is_file():
            continue
        mask = read_mask(mask_path)
        if not mask.any():
            continue
        views.append(View(path.stem, mask, read_image(path)[..., :3],
                          read_image(data / GT_LAYERS_DIR / "transmission" / path.name)[..., :3],
                          read_image(data / "images" / path.name)[..., :3]))
    if not views:
        raise PipelineError("no view has both a ground-truth reflection and a transparent mask", path=folder,
                            fix="prepare the scene with its masks (rtsplat masks, then rtsplat prepare)")
    return views


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """The metric's PSNR inside ``mask`` (:func:`rtsplat.quality.psnr`)."""
    from rtsplat.quality import psnr

    weight = torch.from_numpy(mask.astype(np.float32))[..., None]
    return float(psnr(torch.from_numpy(np.ascontiguousarray(a, np.float32)),
                      torch.from_numpy(np.ascontiguousarray(b, np.float32)), weight))


def blur_inside(image: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of ``image`` [H,W,3] that averages only pixels inside ``mask`` (normalised convolution)."""
    import cv2

    weight = mask.astype(np.float32)
    numerator = cv2.GaussianBlur(image.astype(np.float32) * weight[..., None], (0, 0), sigma)
    denominator = cv2.GaussianBlur(weight, (0, 0), sigma)[..., None]
    return numerator / np.maximum(denominator, 1e-6)


def luminance_correlation(a: np.ndarray, b: np.ndarray) -> float:
    x, y = a.mean(-1), b.mean(-1)
    if x.std() == 0 or y.std() == 0:
        return 0.0
    return float(np.corrcoef(x, y)[0, 1])


def ceilings(views: list[View], sigmas=BLUR_SIGMAS) -> dict[str, float]:
    """Mean over the views of each reference's reflection-layer PSNR (and the layers' sum's)."""
    mean_colour = _mean_reflection(views)
    rows: dict[str, list[float]] = {"zero": [], "truth's mean": []}
    rows.update({f"truth blurred {s:g} px": [] for s in sigmas})
    rows[LAYERS_SUM] = []
    for v in views:
        rows["zero"].append(masked_psnr(np.zeros_like(v.reflection), v.reflection, v.mask))
        flat = np.broadcast_to(mean_colour, v.reflection.shape)
        rows["truth's mean"].append(masked_psnr(flat, v.reflection, v.mask))
        for s in sigmas:
            rows[f"truth blurred {s:g} px"].append(masked_psnr(blur_inside(v.reflection, v.mask, s), v.reflection,
                                                               v.mask))
        rows[LAYERS_SUM].append(masked_psnr(v.reflection + v.transmission, v.image, v.mask))
    return {k: float(np.mean(x)) for k, x in rows.items()}


def _mean_reflection(views: list[View]) -> np.ndarray:
    """The true reflection's mean colour over every view's mask."""
    return np.mean(np.concatenate([v.reflection[v.mask] for v in views]), axis=0)


def image_references(views: list[View]) -> dict[str, float]:
    """Mean over the views of the image PSNR inside the mask of the true transmission alone and of the true
    transmission plus the reflection's mean colour (:func:`ceilings` scores the layers' sum)."""
    mean_colour = _mean_reflection(views)
    alone = [masked_psnr(v.transmission, v.image, v.mask) for v in views]
    flat = [masked_psnr(np.clip(v.transmission + mean_colour, 0, 1), v.image, v.mask) for v in views]
    return {"transmission alone": float(np.mean(alone)), "transmission + reflection's mean": float(np.mean(flat))}


def reflection_share_of_error(error: np.ndarray, detail: np.ndarray) -> tuple[float, float]:
    """The least-squares fit ``error ~ k detail`` over the pixels given ([N,3] each): ``k`` (1 where the
    error is exactly the detail left out, 0 where the error ignores it) and the share of the error's energy
    it explains (0 where there is no detail)."""
    e, d = error.astype(np.float64).ravel(), detail.astype(np.float64).ravel()
    dd, ee = float(d @ d), float(e @ e)
    if dd == 0.0 or ee == 0.0:
        return 0.0, 0.0
    k = float(d @ e) / dd
    return k, 1.0 - float(((e - k * d) ** 2).sum()) / ee


def _rendered(renders: Path, folder: str, what: str, name: str) -> np.ndarray:
    """The run's ``folder`` render (``color``, ``reflection``) of view ``name``, [H,W,3]; a clear error naming
    the view where ``rtsplat render`` did not write it."""
    from rtsplat.io.images import read_image

    path = renders / folder / f"{name}.png"
    if not path.is_file():
        raise PipelineError(f"the run has no {what} for view {name}", path=path,
                            fix="pass the folder `rtsplat render` wrote for this prepared scene")
    return read_image(path)[..., :3]


def run_image(views: list[View], renders: Path) -> dict[str, float]:
    """A run's final image inside the mask: its PSNR, and :func:`reflection_share_of_error` of its error
    (image minus render) against the true reflection's detail (medians over the views of the fit)."""
    mean_colour = _mean_reflection(views)
    psnrs, slopes, shares = [], [], []
    for v in views:
        ours = _rendered(renders, "color", "image", v.name)
        psnrs.append(masked_psnr(ours, v.image, v.mask))
        k, share = reflection_share_of_error((v.image - ours)[v.mask], (v.reflection - mean_colour)[v.mask])
        slopes.append(k)
        shares.append(share)
    return {"psnr": float(np.mean(psnrs)), "slope": float(np.median(slopes)), "share": float(np.median(shares))}


def run_reflection(views: list[View], renders: Path) -> dict[str, float]:
    """A run's reflection layer against the truth: PSNR, mean, luminance correlation (means over the views)."""
    psnrs, means, truth_means, correlations = [], [], [], []
    for v in views:
        ours = _rendered(renders, "reflection", "reflection layer", v.name)
        psnrs.append(masked_psnr(ours, v.reflection, v.mask))
        means.append(float(ours[v.mask].mean()))
        truth_means.append(float(v.reflection[v.mask].mean()))
        correlations.append(luminance_correlation(ours[v.mask], v.reflection[v.mask]))
    return {"psnr": float(np.mean(psnrs)), "mean": float(np.mean(means)), "truth mean": float(np.mean(truth_means)),
            "correlation": float(np.mean(correlations))}
