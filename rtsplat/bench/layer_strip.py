"""A picture of one test view and its decomposition, for the README (``docs/images/demo_strip.png``).

    python -m rtsplat.bench.layer_strip --data PREPARED --renders RENDERS --out PNG [--view NAME]

``PREPARED``: a prepared scene (``rtsplat prepare``), ``RENDERS``: ``rtsplat render`` of a run trained on it.
Top row: the held-out photo | the run's render | its reflection layer | its transmission layer. Bottom row:
the view's transparent mask | the render's per-pixel error (the report's colour map, :func:`rtsplat.report.
error_map`) | the ground-truth reflection and transmission layers where the scene has them (synthetic
scenes, ``gt_layers/``), else black. Each panel carries its label; colours are kept at 5 bits per channel to
keep the file small. ``--view`` defaults to the first test view with ground-truth layers.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from rtsplat.bench.mask_propagation import label_panel
from rtsplat.errors import PipelineError, run_command
from rtsplat.io.images import read_image, write_png
from rtsplat.io.outputs import check_png_output
from rtsplat.report import error_map
from rtsplat.scene import GT_LAYERS_DIR

GAP = 4  # white pixels between panels


def _panel(image: np.ndarray | None, label: str, shape: tuple[int, int]) -> np.ndarray:
    panel = np.zeros((*shape, 3), np.uint8) if image is None else (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    panel = np.ascontiguousarray(panel)
    label_panel(panel, label)
    return panel


def _optional(path: Path) -> np.ndarray | None:
    return read_image(path) if path.is_file() else None


def default_view(data: Path, renders: Path) -> str:
    """The first rendered view (``rtsplat render`` renders the test views) with ground-truth layers, else the
    first rendered view."""
    info = json.loads((renders / "render.json").read_text()) if (renders / "render.json").is_file() else {}
    names = sorted(p.stem for p in (renders / "color").glob("*.png"))
    if not names:
        raise PipelineError("no rendered views (color/*.png)", path=renders, fix="pass the folder rtsplat render wrote")
    tested = [n for n in names if n in info.get("views", names)] or names
    with_layers = [n for n in tested if (data / GT_LAYERS_DIR / "reflection" / f"{n}.png").is_file()]
    return (with_layers or tested)[0]


def layer_strip(data: Path, renders: Path, view: str) -> np.ndarray:
    """The two rows as one uint8 RGB image (see the module's description)."""
    photo = read_image(data / "images" / f"{view}.png")
    shape = photo.shape[:2]
    render = read_image(renders / "color" / f"{view}.png")
    mask = _optional(data / "masks" / f"{view}.png")
    top = [_panel(photo, "photo (held out)", shape), _panel(render, "render", shape),
           _panel(_optional(renders / "reflection" / f"{view}.png"), "reflection", shape),
           _panel(_optional(renders / "transmission" / f"{view}.png"), "transmission", shape)]
    bottom = [_panel(mask, "see-through mask", shape), _panel(error_map(render, photo), "|render - photo|", shape),
              _panel(_optional(data / GT_LAYERS_DIR / "reflection" / f"{view}.png"), "true reflection", shape),
              _panel(_optional(data / GT_LAYERS_DIR / "transmission" / f"{view}.png"), "true transmission", shape)]

    def row(panels):
        gap = np.full((shape[0], GAP, 3), 255, np.uint8)
        return np.concatenate([x for p in panels for x in (p, gap)][:-1], axis=1)

    top_row, bottom_row = row(top), row(bottom)
    gap = np.full((GAP, top_row.shape[1], 3), 255, np.uint8)
    return np.concatenate([top_row, gap, bottom_row], axis=0) & 0xF8


PROGRAM = "python -m rtsplat.bench.layer_strip"  # also the PNG's Software text: --out replaces only its own


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="prepared scene (rtsplat prepare)")
    parser.add_argument("--renders", type=Path, required=True, help="rtsplat render of a run on that scene")
    parser.add_argument("--view", help="the view to show (default: the first test view with true layers)")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args(argv)
    return run_command(PROGRAM, lambda: write_strip(args.data, args.renders, args.view, args.out))


def write_strip(data: Path, renders: Path, view: str | None, out: Path) -> None:
    """The strip of ``view`` (None: :func:`default_view`) written to the PNG ``out``."""
    check_png_output(out, PROGRAM, inputs=[data, renders])
    view = view or default_view(data, renders)
    strip = layer_strip(data, renders, view)
    write_png(out, strip, software=PROGRAM)
    print(f"{out}: view {view}, {strip.shape[1]}x{strip.shape[0]}, {out.stat().st_size // 1024} KB")


if __name__ == "__main__":
    raise SystemExit(main())
