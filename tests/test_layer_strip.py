"""The README's picture: one test view, its render and layers, beside the true layers where they exist."""

from __future__ import annotations

import numpy as np

from rtsplat.bench.layer_strip import GAP, default_view, layer_strip
from rtsplat.bench.toy_scene import write_scene
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.images import read_image, write_png
from rtsplat.scene import GT_LAYERS_DIR


def _renders(root, names, height, width):
    rng = np.random.default_rng(0)
    for layer in ("color", "reflection", "transmission"):
        for name in names:
            write_png(root / layer / f"{name}.png", rng.random((height, width, 3)).astype(np.float32))
    write_json_atomic(root / "render.json", {"views": names, "split": "test"})


def test_strip_places_each_image_in_its_panel(tmp_path):
    h, w = 30, 40
    scene = write_scene(tmp_path / "prepared", views=8, width=w, height=h)
    tests = [c.name for c in scene.test_cameras]
    _renders(tmp_path / "renders", tests, h, w)
    view = tests[1]
    (tmp_path / "prepared" / GT_LAYERS_DIR / "reflection").mkdir(parents=True)
    write_png(tmp_path / "prepared" / GT_LAYERS_DIR / "reflection" / f"{view}.png", np.full((h, w, 3), 0.5, np.float32))
    assert default_view(tmp_path / "prepared", tmp_path / "renders") == view  # the first with true layers

    strip = layer_strip(tmp_path / "prepared", tmp_path / "renders", view)
    assert strip.shape == (2 * h + GAP, 4 * w + 3 * GAP, 3) and strip.dtype == np.uint8

    def panel(row, col):
        return strip[row * (h + GAP):row * (h + GAP) + h, col * (w + GAP):col * (w + GAP) + w]

    expected = {
        (0, 0): read_image(tmp_path / "prepared" / "images" / f"{view}.png"),
        (0, 1): read_image(tmp_path / "renders" / "color" / f"{view}.png"),
        (0, 3): read_image(tmp_path / "renders" / "transmission" / f"{view}.png"),
        (1, 2): np.full((h, w, 3), 0.5, np.float32),
    }
    for (row, col), image in expected.items():
        want = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8) & 0xF8
        below_label = slice(18, h)  # the label is written in the top rows
        assert np.array_equal(panel(row, col)[below_label], want[below_label]), (row, col)
    assert panel(1, 3)[18:].max() == 0  # no true transmission layer here: black
    assert (strip[h:h + GAP] == 0xF8).all()  # the white gap between the rows, at 5 bits
