"""Masks propagated from a few marked views against a scene's full mask set.

    python -m rtsplat.bench.mask_propagation --data DATASET_SCENE --marked 3,5,8 [--refine grabcut,none]

``DATASET_SCENE`` has ``images/``, a mask for every photo in ``transparent_masks/`` and a COLMAP model
(``sparse/0``, e.g. the ground-truth cameras of ``rtsplat synth``, or ``--model``). For each count in
``--marked`` the views to mark are chosen like the stage suggests them (farthest-point sampling over the
camera centres, :func:`rtsplat.masks_propagate.suggest_views`); the other views' propagated masks are
compared with their true masks: mean and worst-view IoU (a view whose two masks are both empty counts 1),
how many views GrabCut refined, and the seconds taken (wall clock, noisy on a shared machine).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from rtsplat.config import MaskPropagationConfig
from rtsplat.io.colmap import dataset_model_dir, load_model
from rtsplat.io.images import list_images, read_image, read_mask
from rtsplat.masks import match_masks
from rtsplat.masks_propagate import propagate_masks, suggest_views


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = int((a | b).sum())
    return 1.0 if union == 0 else float((a & b).sum()) / union


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="dataset scene with images/ and transparent_masks/")
    parser.add_argument("--model", type=Path, help="COLMAP model (default: the scene's sparse/0)")
    parser.add_argument("--marked", default="3,5,8", help="numbers of marked views, comma-separated")
    parser.add_argument("--refine", default="auto,grabcut,none", help="refinements to compare, comma-separated")
    parser.add_argument("--grid", type=int, default=MaskPropagationConfig.grid)
    parser.add_argument("--no-occlusion", action="store_true", help="SfM points do not hide the object")
    args = parser.parse_args(argv)
    model = load_model(args.model or dataset_model_dir(args.data))
    images = list_images(args.data / "images")
    by_name = {p.name: p for p in images}
    masks = {p.name: read_mask(m) for p, m in match_masks(images, args.data / "transparent_masks").items() if m}
    names = [v.name for v in model.views if v.name in masks]
    print(f"{args.data}: {len(names)} registered views with a true mask, "
          f"mean coverage {100 * np.mean([masks[n].mean() for n in names]):.2f}%")
    for refine in args.refine.split(","):
        for count in (int(c) for c in args.marked.split(",")):
            marked = suggest_views(model, count)
            settings = MaskPropagationConfig(grid=args.grid, refine=refine, occlusion=not args.no_occlusion)
            start = time.perf_counter()
            scores, refined = {}, 0
            for out in propagate_masks(model, {n: masks[n] for n in marked}, names,
                                       lambda n: read_image(by_name[n]), settings):
                if out.source != "given":
                    scores[out.name] = iou(out.mask, masks[out.name])
                    refined += out.refined
            seconds = time.perf_counter() - start
            worst = min(scores, key=scores.get)
            mean = float(np.mean(list(scores.values())))
            print(f"refine={refine:8s} marked={count} ({', '.join(marked)}): mean IoU {mean:.3f}, worst "
                  f"{scores[worst]:.3f} ({worst}), {refined}/{len(scores)} refined with GrabCut, {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
