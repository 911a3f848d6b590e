"""``rtsplat metrics``: PSNR, SSIM and LPIPS-VGG on the entire image and on the transparent region.

Definitions (METHOD.md section 7), images in [0,1]:

* PSNR: ``-10 log10(MSE)``; the region's MSE averages the pixels whose mask is 1 (all channels).
* SSIM: the 3DGS definition (11x11 Gaussian window, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2, zero
  padding); the entire-image value is the mean of the SSIM map, the region's value the mean of the
  map over mask pixels. Inside the image (5 px from the border) the map equals scikit-image's
  ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1)``, which a test checks; at the border 3DGS pads with zeros.
* LPIPS-VGG: real weights only (``metrics.lpips_weights`` / ``--lpips-weights`` or the torch hub cache, see
  :mod:`rtsplat.quality.lpips`); the region's value is the mean of the spatial LPIPS map over mask
  pixels. Without weights the value is the string ``"n/a (weights not found)"``.

Views are the renders of ``rtsplat render`` (``<renders>/color/<name>.png``) against the prepared
scene's images and masks; a grey render of a colour photo is refused (:func:`check_colour`). The JSON
records the split the renders are of (``split``: ``test``, or ``train`` / ``all``, which include training
views: said when printed, labelled in the report), per-view values, means, the run's config hash, the
provenance of the training that ``render.json`` carries (``training_provenance``) and its own
(``provenance``: the code, machine and packages that computed the metrics; :mod:`rtsplat.provenance`).
Synthetic scenes also get the decomposition scored (:func:`layer_metrics`) against the ground-truth layers
that ``rtsplat prepare`` carries into ``<data>/gt_layers`` (or ``--gt-layers DIR`` with
``DIR/{reflection,transmission}/<name>.png`` at the prepared resolution).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rtsplat.config import add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.outputs import check_output_file, json_with_keys
from rtsplat.model.composite import transmission_with_scatter
from rtsplat.provenance import collect as collect_provenance
from rtsplat.provenance import training_record
from rtsplat.quality import psnr, ssim_map
from rtsplat.scene import GT_LAYERS_DIR

NOT_AVAILABLE = "n/a (weights not found)"


def image_metrics(render: Tensor, target: Tensor, mask: Tensor | None, lpips_model=None) -> dict:
    """Metrics of one [H,W,3] render against its target; ``mask`` [H,W] bool or None."""
    out = {"psnr": float(psnr(render, target)), "ssim": float(ssim_map(render, target).mean())}
    lp = None
    if lpips_model is not None:
        with torch.no_grad():
            lp = lpips_model.distance_map(render, target)
        out["lpips"] = float(lp.mean())
    else:
        out["lpips"] = NOT_AVAILABLE
    if mask is not None and bool(mask.any()):
        weight = mask[..., None].to(render.dtype)
        smap = ssim_map(render, target)
        out["psnr_transparent"] = float(psnr(render, target, weight))
        out["ssim_transparent"] = float((smap * weight).sum() / (weight.sum() * smap.shape[-1]))
        out["lpips_transparent"] = float(lp[mask].mean()) if lp is not None else NOT_AVAILABLE
    return out


def ground_truth_layers_for(name: str, gt_dir: Path) -> dict[str, np.ndarray] | None:
    """Ground-truth reflection/transmission of a view from ``gt_dir`` (``rtsplat prepare`` writes
    ``<prepared>/gt_layers`` for synthetic scenes; only prepare knows whether SfM undistorted the
    images, so the layers are never rebuilt here), or None when the view has none."""
    from rtsplat.io.images import read_image

    paths = {layer: gt_dir / layer / f"{name}.png" for layer in ("reflection", "transmission")}
    if not all(p.is_file() for p in paths.values()):
        return None
    return {layer: read_image(p) for layer, p in paths.items()}


def layer_metrics(renders: Path, name: str, truth: dict[str, np.ndarray], mask: Tensor | None) -> dict:
    """PSNR of our reflection and transmission layers against the ground truth, on the transparent
    region when the view has one (elsewhere both layers are trivial), else the entire image. Our
    transmission is compared with scatter included (colour - reflection), as the ground truth defines it
    (:func:`rtsplat.prepare.ground_truth_layers`)."""
    from rtsplat.io.images import read_image

    ours = {layer: torch.from_numpy(read_image(renders / layer / f"{name}.png")) for layer in ("color", "reflection")}
    ours["transmission"] = transmission_with_scatter(ours["color"], ours["reflection"]).clamp(0, 1)
    weight = mask[..., None].to(ours["color"].dtype) if mask is not None and bool(mask.any()) else None
    out = {}
    for layer in ("reflection", "transmission"):
        reference = torch.from_numpy(np.ascontiguousarray(truth[layer], dtype=np.float32))
        if reference.shape != ours[layer].shape:
            raise PipelineError(f"ground-truth {layer} layer is {tuple(reference.shape)}, the render "
                                f"{tuple(ours[layer].shape)}", path=renders / layer / f"{name}.png",
                                fix="render from the prepared scene the ground-truth layers belong to")
        out[f"psnr_{layer}_layer"] = float(psnr(ours[layer], reference, weight))
    return out


def _mean(values: list) -> float | str | None:
    numbers = [v for v in values if isinstance(v, float)]
    if not values:
        return None
    if len(numbers) < len(values):
        return NOT_AVAILABLE
    return float(np.mean(numbers))


def config_hash(run_dir: Path) -> str | None:
    path = run_dir / "config.json"
    if not path.is_file():
        return None
    return hashlib.sha256(json.dumps(json.loads(path.read_text()), sort_keys=True).encode()).hexdigest()[:16]


def check_colour(render: Path, target: Tensor) -> None:
    """Refuse a grey render (one channel, or grey and alpha) of a colour photo: scored as colour, its grey would
    be compared with the photo's colours, a number that means neither. ``rtsplat render`` writes colour."""
    from rtsplat.io.images import read_header

    channels = read_header(render).channels
    if channels in (1, 2) and not bool((target == target[..., :1]).all()):
        raise PipelineError(f"the render is grey ({channels} channel{'s' if channels > 1 else ''}) but the photo it is "
                            "scored against is in colour; a grey render cannot be scored as colour", path=render,
                            fix="score the colour renders that `rtsplat render` wrote (render the run again into a "
                            "new --out), not a grey copy of them")


def compute_metrics(renders: str | Path, data_dir: str | Path, *, run_dir: str | Path | None = None,
                    lpips_weights: str = "", gt_layers: str | Path | None = None) -> dict:
    from rtsplat.io.images import read_image
    from rtsplat.quality.lpips import load_lpips
    from rtsplat.scene import PreparedScene

    renders = Path(renders)
    info_path = renders / "render.json"
    if not info_path.is_file():
        raise PipelineError("not a render directory (no render.json)", path=renders,
                            fix="run `rtsplat render` first and pass its --out here")
    info = json.loads(info_path.read_text())
    scene = PreparedScene.load(data_dir)
    lpips_model, lpips_note = load_lpips(lpips_weights)
    gt_dir = Path(gt_layers) if gt_layers is not None else Path(data_dir) / GT_LAYERS_DIR
    gt_dir = gt_dir if gt_dir.is_dir() else None
    per_view = {}
    for name in info["views"]:
        path = renders / "color" / f"{name}.png"
        if not path.is_file():
            raise PipelineError("render missing for a view listed in render.json", path=path,
                                fix="rerun `rtsplat render`")
        render = torch.from_numpy(read_image(path))
        target = torch.from_numpy(scene.load_image(name))
        if render.shape != target.shape:
            raise PipelineError(f"render is {tuple(render.shape)} but the image is {tuple(target.shape)}", path=path,
                                fix="render from the same prepared scene the metrics use")
        check_colour(path, target)
        mask = scene.load_mask(name)
        mask_t = None if mask is None else torch.from_numpy(mask)
        values = image_metrics(render, target, mask_t, lpips_model)
        truth = ground_truth_layers_for(name, gt_dir) if gt_dir else None
        if truth is not None:
            values.update(layer_metrics(renders, name, truth, mask_t))
        per_view[name] = values
    keys = sorted({k for v in per_view.values() for k in v})
    means = {k: _mean([v[k] for v in per_view.values() if k in v]) for k in keys}
    return {
        "split": info.get("split", "test"), "mean": means, "views": per_view, "lpips": lpips_note,
        "gt_layers": str(gt_dir) if gt_dir else None,
        "layer_views": sum("psnr_reflection_layer" in v for v in per_view.values()), "fps": info.get("fps"),
        "render_device": info.get("device"), "renders": str(renders), "data": str(data_dir),
        "run": str(run_dir) if run_dir else info.get("run"),
        "config_hash": config_hash(Path(run_dir or info.get("run", ""))),
        "training_provenance": info.get("training_provenance") or training_record(run_dir or info.get("run", "")),
        "provenance": collect_provenance(),
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--renders", type=Path, required=True, help="output directory of `rtsplat render`")
    parser.add_argument("--data", type=Path, required=True, help="the prepared scene (images and masks)")
    parser.add_argument("--out", type=Path, required=True, help="metrics JSON file (written atomically)")
    parser.add_argument("--run", type=Path, help="run directory (for the config hash; default: from render.json)")
    parser.add_argument("--lpips-weights", help="override metrics.lpips_weights (directory with "
                        "vgg16-397923af.pth and vgg.pth)")
    parser.add_argument("--gt-layers", type=Path, help="ground-truth reflection/transmission layers "
                        "(default: <data>/gt_layers when it exists)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "metrics", {"lpips_weights": args.lpips_weights})
    check_output_file(args.out, "metrics", lambda path: json_with_keys(path, ("mean", "views")),
                      inputs=[args.renders, args.data, args.run, args.gt_layers])
    result = compute_metrics(args.renders, args.data, run_dir=args.run, lpips_weights=cfg.lpips_weights,
                             gt_layers=args.gt_layers)
    write_json_atomic(args.out, result)
    m = result["mean"]
    parts = [f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in m.items()]
    split = result["split"]
    print(f"{args.out}: {split} views ({len(result['views'])}): " + ", ".join(parts))
    if split != "test":
        print(f"{args.out}: scored on the {split!r} views of the render, training views included: not a held-out "
              "score (render with --split test for one)", file=sys.stderr)
    return 0
