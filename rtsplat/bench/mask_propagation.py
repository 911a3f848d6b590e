"""Masks propagated from a few marked views against a scene's full mask set.

    python -m rtsplat.bench.mask_propagation --data DATASET_SCENE --marked 3,5,8 [--refine grabcut,none]
        [--mark file|polygon|box]

``DATASET_SCENE`` has ``images/``, true masks in ``transparent_masks/`` (registered views without one are
neither marked nor scored) and a COLMAP model (``sparse/0``, e.g. the ground-truth cameras of ``rtsplat synth``,
or ``--model``). For each count in ``--marked`` the views to mark are chosen like the stage suggests them
(farthest-point sampling over the camera centres, :func:`rtsplat.masks.propagation.suggest_views`); the other
views' propagated masks are compared with their true masks: mean and worst-view IoU (a view whose two masks
are both empty counts 1), how many views were refined and by what, and the seconds taken (wall clock, noisy on
a shared machine).

    python -m rtsplat.bench.mask_propagation --data DATASET_SCENE --marked 5 --mark polygon --figure PNG

The marked views are marked with their true masks (``--mark file``), or like the config's ``masks.marks`` with
polygons (``--mark polygon``: one polygon per part of their true mask, its outline with corners 1.5 pixels off
it at most, filled; parts under a pixel of area are left out) or a box (``--mark box``: their true mask's
bounding box grown by a tenth on each side, cut out with GrabCut). ``--figure`` draws instead one PNG: the
first marked view with its mark, and the two unmarked views whose cameras are nearest to it with their
propagated masks (outlined in green, IoU against the true mask in the corner); colours are kept at 5 bits per
channel to keep the file small.
"""

from __future__ import annotations

import argparse
import collections
import time
from pathlib import Path

import numpy as np

from rtsplat.config import MaskPropagationConfig
from rtsplat.errors import run_command
from rtsplat.io.colmap import dataset_model_dir, load_model
from rtsplat.io.images import list_images, read_image, read_mask, write_png
from rtsplat.io.outputs import check_png_output
from rtsplat.masks import match_masks
from rtsplat.masks.propagation import carry_marks, propagate_masks, suggest_views

PROGRAM = "python -m rtsplat.bench.mask_propagation"  # also the --figure PNG's Software text


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = int((a | b).sum())
    return 1.0 if union == 0 else float((a & b).sum()) / union


def _outlined(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    """8-bit RGB of ``image`` with ``mask`` tinted and outlined in ``colour``."""
    import cv2

    rgb = (np.clip(image[..., :3], 0, 1) * 255).round().astype(np.uint8)
    tint = rgb.copy()
    tint[mask] = (0.6 * tint[mask] + 0.4 * np.array(colour)).astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(tint, contours, -1, colour, 1)
    return tint


def label_panel(panel: np.ndarray, text: str) -> None:
    """Write ``text`` in the top-left corner of a uint8 RGB panel, white on a black outline."""
    import cv2

    for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(panel, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, width, cv2.LINE_AA)


def _suggested(model, count: int, masks: dict[str, np.ndarray]) -> list[str]:
    """The first ``count`` views with a true mask in the stage's suggestion order (every view suggested)."""
    return [n for n in suggest_views(model, len(model.views)) if n in masks][:count]


def drawn_marks(marked: list[str], masks: dict[str, np.ndarray], by_name: dict[str, Path], mark: str,
                settings: MaskPropagationConfig) -> tuple[dict[str, list[np.ndarray]], dict[str, np.ndarray]]:
    """The outlines (each [N, 2], pixels) and the marked mask of each marked view, marked with its true mask
    (``file``), a polygon around each of its parts or a box around it (see the module's description); drawn
    marks become masks like the config's (:func:`rtsplat.masks.mark_to_mask`)."""
    import cv2

    from rtsplat.config import MaskMark
    from rtsplat.masks import mark_to_mask

    outlines, drawn = {}, {}
    for name in marked:
        true = masks[name]
        h, w = true.shape
        if mark == "box":
            ys, xs = np.nonzero(true)
            gx, gy = 0.1 * (xs.max() + 1 - xs.min()), 0.1 * (ys.max() + 1 - ys.min())
            x0, y0 = max(0.0, xs.min() - gx), max(0.0, ys.min() - gy)
            x1, y1 = min(w, xs.max() + 1 + gx), min(h, ys.max() + 1 + gy)
            outlines[name] = [np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])]
            drawn[name], _ = mark_to_mask(MaskMark(box=[x0, y0, x1, y1]), by_name[name], settings)
            continue
        contours, _ = cv2.findContours(true.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if mark == "polygon":
            polygons = [cv2.approxPolyDP(c, 1.5, True)[:, 0] + 0.5 for c in contours]
            outlines[name] = [p for p in polygons if len(p) >= 3 and cv2.contourArea(p.astype(np.float32)) >= 1.0]
            drawn[name], _ = mark_to_mask(MaskMark(polygons=[p.tolist() for p in outlines[name]]), by_name[name],
                                          settings)
        else:
            outlines[name], drawn[name] = [c[:, 0] + 0.5 for c in contours], true
    return outlines, drawn


def draw_figure(model, by_name: dict[str, Path], masks: dict[str, np.ndarray], names: list[str], count: int,
                settings: MaskPropagationConfig, path: Path, mark: str = "polygon") -> None:
    """The ``--figure`` PNG (see the module's description)."""
    import cv2

    marked = _suggested(model, count, masks)
    outlines, drawn = drawn_marks(marked, masks, by_name, mark, settings)
    first = model.view(marked[0])
    others = sorted((n for n in names if n not in marked),
                    key=lambda n: float(np.linalg.norm(model.view(n).center - first.center)))[:2]
    results = {r.name: r for r in propagate_masks(model, drawn, others, lambda n: read_image(by_name[n]), settings)}
    panel = _outlined(read_image(by_name[first.name]), drawn[first.name], (255, 0, 255))
    corners = [np.round(o - 0.5).astype(np.int32).reshape(-1, 1, 2) for o in outlines[first.name]]
    cv2.polylines(panel, corners, True, (255, 220, 0), 1)
    label_panel(panel, f"{first.name}: marked ({mark})")
    panels = [panel]
    for name in others:
        panel = _outlined(read_image(by_name[name]), results[name].mask, (0, 255, 0))
        label_panel(panel, f"{name}: IoU {iou(results[name].mask, masks[name]):.2f}")
        panels.append(panel)
    gap = np.full((panels[0].shape[0], 4, 3), 255, np.uint8)
    row = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1) & 0xF8
    write_png(path, row, software=PROGRAM)
    print(f"{path}: {first.name} marked with a {mark} ({len(marked)} marked), {', '.join(others)} propagated")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="dataset scene with images/ and transparent_masks/")
    parser.add_argument("--model", type=Path, help="COLMAP model (default: the scene's sparse/0)")
    parser.add_argument("--marked", default="3,5,8", help="numbers of marked views, comma-separated")
    parser.add_argument("--refine", default="auto,grabcut,watershed,none",
                        help="refinements to compare, comma-separated")
    parser.add_argument("--method", choices=["auto", "hull", "plane"], default="auto",
                        help="how the marks reach the other views (masks.propagate.method)")
    parser.add_argument("--grid", type=int, default=MaskPropagationConfig.grid)
    parser.add_argument("--no-occlusion", action="store_true", help="SfM points do not hide the object")
    parser.add_argument("--figure", type=Path, help="write a PNG of a view marked with a box and two propagated "
                        "neighbours (the first --marked count, the first --refine) instead of measuring")
    parser.add_argument("--mark", choices=["file", "polygon", "box"], default="file",
                        help="how the views are marked: their true masks, polygons or boxes drawn around them")
    args = parser.parse_args(argv)
    return run_command(PROGRAM, lambda: measure(args))


def measure(args: argparse.Namespace) -> None:
    """The figure (``--figure``) or the measures of the command line ``args``."""
    if args.figure:
        check_png_output(args.figure, PROGRAM, inputs=[args.data, args.model], flag="--figure")
    model = load_model(args.model or dataset_model_dir(args.data))
    images = list_images(args.data / "images")
    by_name = {p.name: p for p in images}
    masks = {p.name: read_mask(m) for p, m in match_masks(images, args.data / "transparent_masks").items() if m}
    names = [v.name for v in model.views if v.name in masks]
    print(f"{args.data}: {len(names)} registered views with a true mask, "
          f"mean coverage {100 * np.mean([masks[n].mean() for n in names]):.2f}%")
    if args.figure:
        settings = MaskPropagationConfig(method=args.method, grid=args.grid, refine=args.refine.split(",")[0],
                                         occlusion=not args.no_occlusion)
        draw_figure(model, by_name, masks, names, int(args.marked.split(",")[0]), settings, args.figure, args.mark)
        return
    for refine in args.refine.split(","):
        for count in (int(c) for c in args.marked.split(",")):
            marked = _suggested(model, count, masks)
            settings = MaskPropagationConfig(method=args.method, grid=args.grid, refine=refine,
                                             occlusion=not args.no_occlusion)
            start = time.perf_counter()
            scores, refined = {}, collections.Counter()
            _, drawn = drawn_marks(marked, masks, by_name, args.mark, settings)
            carrier = carry_marks(model, drawn, settings)
            for out in propagate_masks(model, drawn, names, lambda n: read_image(by_name[n]), settings,
                                       carrier=carrier):
                if out.source != "given":
                    scores[out.name] = iou(out.mask, masks[out.name])
                    refined[out.refinement or "none"] += 1
            seconds = time.perf_counter() - start
            worst = min(scores, key=scores.get)
            mean = float(np.mean(list(scores.values())))
            by = ", ".join(f"{k} {n}" for k, n in sorted(refined.items()) if k != "none") or "none"
            print(f"refine={refine:8s} marked={count} ({', '.join(marked)}): {carrier.method}, mean IoU {mean:.3f}, "
                  f"worst {scores[worst]:.3f} ({worst}), {len(scores) - refined['none']}/{len(scores)} refined ({by}), "
                  f"{seconds:.1f} s")
            print(f"  {carrier.method}: {carrier.reason}")


if __name__ == "__main__":
    raise SystemExit(main())
