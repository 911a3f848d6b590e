"""The reflection-layer references of rtsplat.layer_references on a small prepared folder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rtsplat import layer_references as layer_ceiling
from rtsplat.bench.layer_ceiling import main as bench_main
from rtsplat.errors import PipelineError
from rtsplat.io.images import write_mask, write_png


def write_prepared(root: Path, views: int = 3, seed: int = 0) -> list[np.ndarray]:
    """A prepared-like folder: a smooth reflection with fine stripes on it, its transmission, the image as
    their sum, a mask over the middle; returns the reflections written."""
    rng = np.random.default_rng(seed)
    H, W = 40, 60
    yy, xx = np.mgrid[0:H, 0:W]
    reflections = []
    for k in range(views):
        smooth = 0.2 + 0.1 * np.sin(xx / 9.0 + k)[..., None] * np.ones(3)
        stripes = 0.08 * ((xx // 2) % 2)[..., None] * np.ones(3)
        reflection = np.clip(smooth + stripes, 0, 1)
        transmission = np.clip(rng.uniform(0.1, 0.6, (H, W, 3)), 0, 1)
        mask = (xx > 10) & (xx < 50) & (yy > 5) & (yy < 35)
        name = f"{k:04d}.png"
        write_png(root / "gt_layers" / "reflection" / name, reflection)
        write_png(root / "gt_layers" / "transmission" / name, transmission)
        write_png(root / "images" / name, np.clip(reflection + transmission, 0, 1))
        write_mask(root / "masks" / name, mask)
        reflections.append(reflection)
    return reflections


def test_references_order_as_detail_is_kept(tmp_path):
    write_prepared(tmp_path)
    result = layer_ceiling.ceilings(layer_ceiling.read_views(tmp_path))
    blurred = [result[f"truth blurred {s:g} px"] for s in layer_ceiling.BLUR_SIGMAS]
    assert result["zero"] < result["truth's mean"] < blurred[-1]
    assert blurred == sorted(blurred, reverse=True)  # less blur, more of the truth kept
    assert result["layers' sum against the image"] > 40  # written as their sum (8-bit rounding only)


def test_a_run_equal_to_the_truth_scores_above_every_reference(tmp_path):
    reflections = write_prepared(tmp_path / "data")
    for k, reflection in enumerate(reflections):
        write_png(tmp_path / "renders" / "reflection" / f"{k:04d}.png", reflection)
    views = layer_ceiling.read_views(tmp_path / "data")
    ours = layer_ceiling.run_reflection(views, tmp_path / "renders")
    assert ours["psnr"] > max(layer_ceiling.ceilings(views).values())
    assert ours["correlation"] > 0.99
    assert abs(ours["mean"] - ours["truth mean"]) < 1e-6
    (tmp_path / "renders" / "reflection" / "0001.png").unlink()
    with pytest.raises(PipelineError, match="0001"):
        layer_ceiling.run_reflection(views, tmp_path / "renders")


def test_the_bench_prints_every_reference_and_the_run(tmp_path, capsys):
    reflections = write_prepared(tmp_path / "data")
    for k, reflection in enumerate(reflections):
        write_png(tmp_path / "renders" / "reflection" / f"{k:04d}.png", reflection)
        write_png(tmp_path / "renders" / "color" / f"{k:04d}.png", reflection)
    assert bench_main(["--data", str(tmp_path / "data"), "--renders", str(tmp_path / "renders")]) == 0
    printed = capsys.readouterr().out
    for reference in ("zero", "truth's mean", "truth blurred 1 px", "layers' sum", "luminance correlation +1.00",
                      "transmission alone", "transmission + reflection's mean", "reflection's detail: slope"):
        assert reference in printed


def test_an_image_without_the_reflection_detail_has_all_its_error_along_that_detail(tmp_path):
    """A render that is the true transmission plus the reflection's mean colour errs by exactly the
    reflection's detail (slope and share near 1); the image with noise that ignores the reflection scores
    above it, and almost none of its error is laid on the detail."""
    write_prepared(tmp_path / "data")
    views = layer_ceiling.read_views(tmp_path / "data")
    mean_colour = np.mean(np.concatenate([v.reflection[v.mask] for v in views]), axis=0)
    rng = np.random.default_rng(1)
    for v in views:
        write_png(tmp_path / "flat" / "color" / f"{v.name}.png", np.clip(v.transmission + mean_colour, 0, 1))
        noisy = np.clip(v.image + rng.normal(0, 0.05, v.image.shape), 0, 1)
        write_png(tmp_path / "noisy" / "color" / f"{v.name}.png", noisy)
    references = layer_ceiling.image_references(views)
    flat = layer_ceiling.run_image(views, tmp_path / "flat")
    assert references["transmission alone"] < references["transmission + reflection's mean"]
    assert abs(flat["psnr"] - references["transmission + reflection's mean"]) < 0.2  # the same image, 8-bit
    assert flat["slope"] > 0.9 and flat["share"] > 0.9
    noisy = layer_ceiling.run_image(views, tmp_path / "noisy")
    assert noisy["psnr"] > flat["psnr"] and noisy["share"] < 0.1
    (tmp_path / "flat" / "color" / "0002.png").unlink()
    with pytest.raises(PipelineError, match="0002"):
        layer_ceiling.run_image(views, tmp_path / "flat")


def test_the_share_of_an_error_along_a_detail():
    detail = np.array([[0.1, -0.2, 0.3], [-0.1, 0.2, 0.0]])
    assert layer_ceiling.reflection_share_of_error(0.5 * detail, detail) == pytest.approx((0.5, 1.0))
    across = np.array([[0.2, 0.1, 0.0], [0.0, 0.0, 0.5]])  # orthogonal to the detail: explains nothing
    assert float((across * detail).sum()) == pytest.approx(0.0)
    assert layer_ceiling.reflection_share_of_error(across, detail) == pytest.approx((0.0, 0.0))
    assert layer_ceiling.reflection_share_of_error(detail, np.zeros_like(detail)) == (0.0, 0.0)


def test_only_the_named_views_are_read(tmp_path):
    write_prepared(tmp_path, views=3)
    assert [v.name for v in layer_ceiling.read_views(tmp_path, names={"0000", "0002"})] == ["0000", "0002"]


def test_a_scene_without_layers_is_refused(tmp_path):
    with pytest.raises(PipelineError, match="ground-truth layers"):
        layer_ceiling.read_views(tmp_path)


def test_the_report_adds_the_references_of_its_test_views(tmp_path):
    from rtsplat.report import layer_reference_rows, scene_layer_references

    write_prepared(tmp_path, views=3)
    rows, text = layer_reference_rows(scene_layer_references(tmp_path, {"0001", "0002"}))
    expected = layer_ceiling.ceilings(layer_ceiling.read_views(tmp_path, names={"0001", "0002"}), sigmas=(2.0,))
    assert [row[1] for row in rows] == [f"{expected[k]:.2f}" for k in ("truth's mean", "truth blurred 2 px")]
    assert f"{expected[layer_ceiling.LAYERS_SUM]:.2f} dB against the image" in text
    assert layer_reference_rows(scene_layer_references(tmp_path / "nothing", None)) == ([], "")
