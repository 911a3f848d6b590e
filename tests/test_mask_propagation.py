"""Masks propagated from a few marked views (rtsplat.masks.propagation, masks.source propagate) on a small
ray-cast scene whose true masks are known (tests/masks_scene.py)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from rtsplat.config import MaskPropagationConfig, MasksConfig
from rtsplat.errors import PipelineError
from rtsplat.io.colmap import ColmapImage, ColmapPoints, ColmapView, write_sparse_model
from rtsplat.io.images import read_mask, write_mask, write_png
from rtsplat.masks import make_masks
from rtsplat.masks.propagation import (
    carry_marks,
    check_marked,
    opaque_depth,
    project_hull,
    project_points,
    propagate_masks,
    snap_to_edges,
    suggest_views,
    visual_hull,
)
from rtsplat.report import masks_paragraph

sys.path.insert(0, str(Path(__file__).resolve().parent))
from masks_scene import look_at, render, ring_model  # noqa: E402

VIEWS = 16
FAST = MaskPropagationConfig(grid=64)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(int((a | b).sum()), 1)


@pytest.fixture(scope="module")
def scene():
    model = ring_model(VIEWS)
    return model, {v.name: render(v) for v in model.views}


def _propagate(model, rendered, marked, refine):
    cfg = MaskPropagationConfig(grid=64, refine=refine)
    names = [v.name for v in model.views]
    return list(propagate_masks(model, {n: rendered[n][1] for n in marked}, names, lambda n: rendered[n][0], cfg))


@pytest.mark.parametrize("refine", ["none", "auto", "watershed"])
def test_masks_from_five_marked_views_match_the_true_masks(scene, refine):
    model, rendered = scene
    marked = suggest_views(model, 5)
    results = _propagate(model, rendered, marked, refine)
    assert [r.name for r in results] == [v.name for v in model.views]
    scores = [iou(r.mask, rendered[r.name][1]) for r in results if r.source == "propagated"]
    assert len(scores) == VIEWS - 5
    assert all(r.source == "given" for r in results if r.name in marked)
    assert np.mean(scores) >= 0.85
    assert min(scores) >= 0.7


def _pane_on_texture(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 120x160 photo: a tinted pane over a blotchy background (noise blurred over about 4 pixels), and the
    pane's mask."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    image = ndimage.gaussian_filter(rng.random((120, 160, 3)), (4, 4, 0))
    image = 0.2 + 0.6 * (image - image.min()) / (image.max() - image.min())
    truth = np.zeros((120, 160), bool)
    truth[30:90, 40:125] = True
    image[truth] = 0.5 * image[truth] + 0.4 * np.array([0.2, 0.6, 0.9])
    return image, truth


def test_watershed_moves_a_loose_outline_to_the_panes_edge():
    import cv2

    image, truth = _pane_on_texture()
    loose = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # two pixels too wide all round
    snapped = snap_to_edges(image, loose, MaskPropagationConfig())
    assert snapped is not None
    assert iou(snapped, truth) > 0.97 > iou(loose, truth)
    assert not (snapped & ~(cv2.dilate(loose.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)).any()


def test_watershed_keeps_the_projection_where_it_cannot_snap():
    image, truth = _pane_on_texture()
    line = np.zeros_like(truth)
    line[60:62, 20:140] = True  # thinner than the band: no inside seed
    assert snap_to_edges(image, line, MaskPropagationConfig()) is None
    assert snap_to_edges(image, np.ones_like(truth), MaskPropagationConfig()) is None  # no outside seed


def test_the_hull_silhouette_holds_the_object(scene):
    # a visual hull contains the object: its projection covers (nearly) every true mask pixel
    model, rendered = scene
    marked = [(model.view(n), rendered[n][1]) for n in suggest_views(model, 4)]
    hull = visual_hull(model, marked, FAST)
    for view in model.views:
        silhouette, truth = project_hull(hull, view), rendered[view.name][1]
        assert (silhouette & truth).sum() >= 0.97 * truth.sum()
        assert silhouette.sum() <= 2.0 * truth.sum()



def test_the_splatted_voxels_do_not_grow_the_outline(scene):
    # every view marked, voxels about 1.8 pixels across (discs of radius 1): the silhouette follows the
    # true outline instead of standing a disc's radius beyond it, and still holds the object
    model, rendered = scene
    hull = visual_hull(model, [(v, rendered[v.name][1]) for v in model.views], MaskPropagationConfig(grid=32))
    scores = []
    for view in model.views:
        silhouette, truth = project_hull(hull, view), rendered[view.name][1]
        assert (silhouette & truth).sum() >= 0.98 * truth.sum()
        scores.append(iou(silhouette, truth))
    assert np.mean(scores) >= 0.9 and min(scores) >= 0.88


def _hull_and_wall(scene):
    """The marked views' hull, view 1, and a wall of points (camera coordinates) halfway between that camera and
    the object, over the upper half of its picture; the masks' upper and lower rows (a band left out between)."""
    model, rendered = scene
    marked = [(model.view(n), rendered[n][1]) for n in suggest_views(model, 5)]
    hull = visual_hull(model, marked, FAST)
    view = model.views[1]
    x, y = np.meshgrid(np.linspace(-1.0, 1.0, 60), np.linspace(-1.0, 0.0, 30))
    wall = np.stack([x.ravel(), y.ravel(), np.full(x.size, 1.5)], 1)
    rows = np.arange(view.height)
    return hull, view, wall, rows < view.height / 2 - 3, rows > view.height / 2 + 3


def test_sfm_points_in_front_of_the_object_hide_it(scene):
    # a wall of points halfway between the camera and the object, over the upper half of the picture
    hull, view, wall, upper, lower = _hull_and_wall(scene)
    R, centre = view.world_to_camera[:3, :3], view.center
    free, hidden = project_hull(hull, view), project_hull(hull, view, occluders=wall @ R + centre)  # camera -> world
    assert free[upper].sum() > 50 and not hidden[upper].any()
    assert free[lower].sum() > 50 and (hidden == free)[lower].all()


def test_scattered_points_in_front_of_the_object_hide_nothing_while_a_surface_still_does(scene):
    # what SfM triangulates through glass: points scattered in depth between the camera and the object over the
    # lower half of the picture, beside the wall of points over the upper half; and the marked views' hull
    # carved with both as occluders
    hull, view, wall, upper, lower = _hull_and_wall(scene)
    R, centre = view.world_to_camera[:3, :3], view.center
    free = project_hull(hull, view)
    # one point over every sixth pixel of the object's lower half, at a random depth in front of it
    rng = np.random.default_rng(0)
    ys, xs = np.nonzero(free & lower[:, None])
    pick = rng.choice(len(ys), len(ys) // 6, replace=False)
    depth = rng.uniform(0.8, 2.6, len(pick))
    rays = np.stack([xs[pick] + 0.5, ys[pick] + 0.5, np.ones(len(pick))], 1) @ np.linalg.inv(view.K).T
    scattered = rays * depth[:, None]
    occluders = np.concatenate([wall, scattered]) @ R + centre  # camera -> world
    uv, z, _ = project_points(view, scattered @ R + centre)
    assert len(pick) >= 20 and np.allclose(uv, np.stack([xs[pick], ys[pick]], 1) + 0.5)  # over the object
    hidden = project_hull(hull, view, occluders=occluders)
    assert free[upper].sum() > 50 and not hidden[upper].any()
    assert free[lower].sum() > 50 and (hidden & free)[lower].sum() >= 0.97 * free[lower].sum()
    # the occluders' depth map, which also keeps marked views from carving what it hides: the wall's, not the points'
    depth = opaque_depth(view, occluders)
    assert np.isfinite(depth[upper]).mean() > 0.8 and not np.isfinite(depth[ys[pick], xs[pick]]).any()


def test_suggested_views_are_spread_around_the_capture(scene):
    model, _ = scene
    picks = suggest_views(model, 4)
    assert len(set(picks)) == 4
    centres = np.stack([model.view(n).center for n in picks])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2)[np.triu_indices(4, 1)]
    ring_step = np.linalg.norm(model.views[0].center - model.views[1].center)
    assert gaps.min() > 2.5 * ring_step  # no two neighbours on the ring of 16


def test_too_few_marked_views_suggests_views_to_mark(scene):
    model, rendered = scene
    with pytest.raises(PipelineError, match="at least 3") as err:
        check_marked(model, {n: rendered[n][1] for n in ("view_000.png", "view_008.png")})
    suggested = err.value.fix.split("add masks for ")[1].split(" (")[0].split(", ")
    assert len(suggested) == 3 and all(s in rendered for s in suggested)
    assert not {"view_000.png", "view_008.png"} & set(suggested)


def test_marked_views_without_a_pose_are_named(scene):
    model, rendered = scene
    marked = {n: rendered[n][1] for n in ("view_000.png", "view_005.png", "view_010.png")}
    marked["IMG_lost.png"] = rendered["view_003.png"][1]
    with pytest.raises(PipelineError, match=r"SfM did not register them\): IMG_lost.png"):
        check_marked(model, marked)


def test_marks_from_one_side_are_refused(scene):
    model, rendered = scene
    near = ring_model(400).views[0:6:2]  # three cameras 1.8 degrees apart at one height
    one_side = type(model)(near, model.xyz)
    marked = {v.name: render(v)[1] for v in near}
    # a curved object with nothing flat on its outline: neither a hull nor a plane bounds it
    with pytest.raises(PipelineError, match="from one side.*SfM points on the marks' outlines") as err:
        carry_marks(one_side, marked, FAST)
    assert "draw each mark on the glass's own edges" in str(err.value)
    assert "from other sides too" in str(err.value)
    with pytest.raises(PipelineError, match="from one side.*depth is not bounded") as err:
        carry_marks(one_side, marked, MaskPropagationConfig(method="hull"))
    assert "masks.propagate.method: plane" in str(err.value)


def test_disagreeing_marks_name_the_views(scene):
    model, rendered = scene
    marked = {n: rendered[n][1].copy() for n in ("view_000.png", "view_005.png", "view_010.png")}
    wrong = np.zeros_like(marked["view_005.png"])
    wrong[:10, :10] = True  # the corner of the picture: no point there is inside the other two masks
    marked["view_005.png"] = wrong
    with pytest.raises(PipelineError, match="share no 3D region") as err:
        list(propagate_masks(model, marked, ["view_001.png"], lambda n: rendered[n][0], FAST))
    assert "view_005.png" in str(err.value)


# ----------------------------------------------------------------------------------------------
# the stage


def _write_scene(root: Path, model, rendered, marked, mask_size=None) -> tuple[Path, Path]:
    scene = root / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "transparent_masks").mkdir()
    for name, (image, mask) in rendered.items():
        write_png(scene / "images" / name, image)
        if name in marked:
            if mask_size is not None:
                mask = np.zeros(mask_size[::-1], bool)
                mask[2:8, 2:8] = True
            write_mask(scene / "transparent_masks" / name, mask)
    images = [ColmapImage(v.name, v.K, v.world_to_camera, v.width, v.height) for v in model.views]
    write_sparse_model(root / "sfm" / "sparse" / "0", images,
                       ColmapPoints(model.xyz, np.full((len(model.xyz), 3), 128, np.uint8), [[] for _ in model.xyz]))
    return scene, root / "sfm"


def test_stage_propagates_and_records_each_masks_source(scene, tmp_path):
    model, rendered = scene
    rendered = dict(rendered)
    marked = suggest_views(model, 5)
    away = ColmapView("view_away.png", 96, 72, "PINHOLE", model.views[0].params, model.views[0].K,
                      look_at(np.array([3.0, 0.0, 0.0]), np.array([6.0, 0.0, 0.0])))
    rendered[away.name] = render(away)
    lost_image, lost_mask = render(model.views[3])
    rendered["view_lost.png"] = (lost_image[::-1].copy(), lost_mask[::-1].copy())  # a photo SfM did not register
    model = type(model)(model.views + [away], model.xyz)
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, marked)
    cfg = MasksConfig(propagate=FAST)  # source auto: some photos have a mask
    summary = make_masks(scene_dir, tmp_path / "masks", cfg, progress=False, sfm_dir=sfm)
    assert summary.source == "propagate" and summary.has_masks
    assert sorted(summary.marked) == sorted(marked)
    assert summary.mask_sources["view_away.png"] == "empty"
    assert summary.mask_sources["view_lost.png"] == "unregistered"
    assert sum(s == "propagated" for s in summary.mask_sources.values()) == VIEWS - 5
    written = json.loads((tmp_path / "masks" / "summary.json").read_text())
    assert written["mask_sources"] == summary.mask_sources
    assert not read_mask(tmp_path / "masks" / "view_away.png").any()
    assert not read_mask(tmp_path / "masks" / "view_lost.png").any()
    scores = [iou(read_mask(tmp_path / "masks" / n), rendered[n][1])
              for n, s in summary.mask_sources.items() if s == "propagated"]
    assert np.mean(scores) >= 0.85
    # the report says where the masks came from
    text = masks_paragraph(written)
    assert f"propagated from 5 marked views (5 mask files: {', '.join(sorted(marked))})" in text
    assert f"to {VIEWS - 5} of the {VIEWS + 2} photos through the marked views' visual hull" in text
    assert written["propagation_method"] == "hull" and written["glass_plane"] == {}
    assert "1 left empty" in text and "1 without an SfM pose" in text


def test_stage_refuses_marked_masks_of_another_size(scene, tmp_path):
    model, rendered = scene
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, suggest_views(model, 3), mask_size=(48, 36))
    with pytest.raises(PipelineError, match="mask is 48x36 but image") as err:
        make_masks(scene_dir, tmp_path / "masks", MasksConfig(source="propagate", propagate=FAST), progress=False,
                   sfm_dir=sfm)
    assert "transparent_masks" in str(err.value)


def test_stage_without_the_sfm_result_says_what_to_pass(scene, tmp_path):
    model, rendered = scene
    scene_dir, _ = _write_scene(tmp_path, model, rendered, suggest_views(model, 3))
    with pytest.raises(PipelineError, match="3 of 16 photos have a mask in transparent_masks/: propagating"):
        make_masks(scene_dir, tmp_path / "masks", MasksConfig(propagate=FAST), progress=False)


# ----------------------------------------------------------------------------------------------
# marks drawn in the config (masks.marks)


def _loose_box(mask: np.ndarray, margin: int) -> list[float]:
    """The mask's bounding box (pixel edges) grown by ``margin`` pixels, inside the image."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    return [float(max(0, xs.min() - margin)), float(max(0, ys.min() - margin)),
            float(min(w, xs.max() + 1 + margin)), float(min(h, ys.max() + 1 + margin))]


def _propagated_iou(out: Path, rendered, summary) -> float:
    return float(np.mean([iou(read_mask(out / n), rendered[n][1])
                          for n, s in summary.mask_sources.items() if s == "propagated"]))


def test_box_marks_propagate_like_mask_files(scene, tmp_path):
    model, rendered = scene
    marked = suggest_views(model, 5)
    scene_dir, sfm = _write_scene(tmp_path / "files", model, rendered, marked)
    from_files = make_masks(scene_dir, tmp_path / "from_files", MasksConfig(propagate=FAST), progress=False,
                            sfm_dir=sfm)
    scene_dir, sfm = _write_scene(tmp_path / "boxes", model, rendered, [])
    boxes = {n: {"box": _loose_box(rendered[n][1], margin=5)} for n in marked}
    from_boxes = make_masks(scene_dir, tmp_path / "from_boxes", MasksConfig(marks=boxes, propagate=FAST),
                            progress=False, sfm_dir=sfm)  # source auto: marks are propagated
    assert from_boxes.source == "propagate" and sorted(from_boxes.marked) == sorted(marked)
    assert from_boxes.mark_sources == dict.fromkeys(sorted(marked), "box")
    assert set(from_files.mark_sources.values()) == {"file"}
    for name in marked:  # GrabCut cut the object out of the loose box: far closer to it than the box
        cut, truth = read_mask(tmp_path / "from_boxes" / name), rendered[name][1]
        filled = np.zeros_like(truth)
        x0, y0, x1, y1 = map(int, boxes[name]["box"])
        filled[y0:y1, x0:x1] = True
        assert iou(cut, truth) >= iou(filled, truth) + 0.2
    # both propagate to about 0.995 mean IoU here: the boxes lose at most 0.02 against the mask files
    files_iou = _propagated_iou(tmp_path / "from_files", rendered, from_files)
    assert files_iou >= 0.9
    assert _propagated_iou(tmp_path / "from_boxes", rendered, from_boxes) >= files_iou - 0.02


def test_polygon_marks_are_taken_as_drawn(scene, tmp_path):
    model, rendered = scene
    marked = suggest_views(model, 4)
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, marked[:1])  # one mask file, three polygons
    polygons = {}
    for name in marked[1:]:
        x0, y0, x1, y1 = _loose_box(rendered[name][1], margin=0)
        cx, cy, rx, ry = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
        angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)  # the ellipse that fits the box
        polygons[name] = {"polygon": np.stack([cx + rx * np.cos(angles), cy + ry * np.sin(angles)], 1).tolist()}
    summary = make_masks(scene_dir, tmp_path / "masks", MasksConfig(marks=polygons, propagate=FAST),
                         progress=False, sfm_dir=sfm)
    assert summary.mark_sources == {marked[0]: "file", **dict.fromkeys(marked[1:], "polygon")}
    for name in marked[1:]:
        assert iou(read_mask(tmp_path / "masks" / name), rendered[name][1]) >= 0.85  # the ellipse of the outline
    assert _propagated_iou(tmp_path / "masks", rendered, summary) >= 0.85


def _split_polygons(mask: np.ndarray) -> list[list[list[float]]]:
    """The outlines of the left and right parts of ``mask`` cut at its middle column: two separate panes."""
    import cv2

    xs = np.nonzero(mask.any(0))[0]
    cut = mask.copy()
    middle = (xs.min() + xs.max()) // 2
    cut[:, middle] = False
    contours, _ = cv2.findContours(cut.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    assert len(contours) == 2
    return [(c[:, 0] + 0.5).tolist() for c in contours]


def test_several_shapes_per_view_are_unioned(scene, tmp_path):
    # every marked view drawn as two panes (its mask split at the middle): the view's mask holds both
    from rtsplat.masks import check_marks, marks_to_masks

    model, rendered = scene
    marked = suggest_views(model, 5)
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, [])
    panes = {n: _split_polygons(rendered[n][1]) for n in marked}
    both = {n: {"polygons": panes[n]} for n in marked}
    both[marked[0]] = {"polygon": panes[marked[0]][0], "boxes": [_loose_box(rendered[marked[0]][1], 5)]}
    images = sorted((scene_dir / "images").iterdir())
    cfg = MasksConfig(propagate=FAST)
    one_pane, _ = marks_to_masks(check_marks({n: {"polygon": panes[n][0]} for n in marked}, images), images, cfg)
    summary = make_masks(scene_dir, tmp_path / "masks", MasksConfig(marks=both, propagate=FAST), progress=False,
                         sfm_dir=sfm)
    assert summary.mark_sources == {marked[0]: "polygon, box", **dict.fromkeys(marked[1:], "polygon, polygon")}
    for name in marked:
        drawn, truth = read_mask(tmp_path / "masks" / name), rendered[name][1]
        assert one_pane[name].sum() < 0.7 * truth.sum()
        assert iou(drawn, truth) >= 0.9  # both panes less the gap between them, or the box's cut
        assert (drawn >= one_pane[name]).all()
    assert _propagated_iou(tmp_path / "masks", rendered, summary) >= 0.85


@pytest.mark.parametrize("mark, key, message", [
    ({"view_0001.png": {"box": [10, 10, 40, 40]}}, "masks.marks.view_0001.png", "closest names: view_001.png"),
    ({"view_001.png": {"box": [10, 10, 400, 40]}}, "masks.marks.view_001.png.box", "outside the photo (96x72"),
    ({"view_001.png": {"box": [40, 10, 10, 40]}}, "masks.marks.view_001.png.box", "x1 > x0"),
    ({"view_001.png": {"polygon": [[1, 1], [20, 1]]}}, "masks.marks.view_001.png.polygon", "too short"),
    ({"view_001.png": {"polygon": [[1, 1], [20, 1], [40, 1]]}}, "masks.marks.view_001.png.polygon", "no area"),
    ({"view_001.png": {}}, "masks.marks.view_001.png", "a mark needs a box or a polygon"),
    ({"view_001.png": {"polygons": [[[1, 1], [20, 1], [9, 9]], [[1, 1], [20, 1], [40, 1]]]}},
     "masks.marks.view_001.png.polygons.1", "no area"),
    ({"view_001.png": {"polygons": [[[1, 1], [20, 1], [9, 9]], [[1, 1], [20, 1]]]}},
     "masks.marks.view_001.png.polygons.1", "too short"),
    ({"view_001.png": {"polygon": [[1, 1], [20, 1], [9, 9]], "boxes": [[1, 1, 9, 9], [1, 1, 9, 99]]}},
     "masks.marks.view_001.png.boxes.1", "outside the photo (96x72"),
    ({"view_001.png": {"boxes": [[1, 1, 9, 9], [9, 1, 1, 9]]}}, "masks.marks.view_001.png.boxes.1", "x1 > x0"),
    ({"view_000.png": {"box": [1, 1, 9, 9]}}, "masks.marks.view_000.png", "has a mask file"),
])
def test_bad_marks_name_the_key_and_write_nothing(scene, tmp_path, mark, key, message):
    model, rendered = scene
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, ["view_000.png"])
    with pytest.raises(PipelineError, match=re.escape(message)) as err:
        make_masks(scene_dir, tmp_path / "masks", MasksConfig(marks=mark, propagate=FAST), progress=False,
                   sfm_dir=sfm)
    assert key in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene", "sfm"]  # no output, no temporary leftovers


def test_marks_with_another_source_are_refused(scene, tmp_path):
    model, rendered = scene
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, [])
    cfg = MasksConfig(source="none", marks={"view_001.png": {"box": [10, 10, 40, 40]}})
    with pytest.raises(PipelineError, match="masks.source is none"):
        make_masks(scene_dir, tmp_path / "masks", cfg, progress=False, sfm_dir=sfm)


def test_bench_measures_drawn_marks_and_draws_the_figure(scene, tmp_path, capsys):
    from rtsplat.bench.mask_propagation import main as bench
    from rtsplat.io.images import read_image

    model, rendered = scene
    scene_dir, sfm = _write_scene(tmp_path, model, rendered, list(rendered))  # every view has its true mask
    model_dir = str(sfm / "sparse" / "0")
    for mark in ("file", "box"):
        assert bench(["--data", str(scene_dir), "--model", model_dir, "--marked", "5", "--grid", "64",
                      "--refine", "auto", "--mark", mark]) == 0
    file_iou, box_iou = map(float, re.findall(r"mean IoU ([\d.]+)", capsys.readouterr().out))
    assert box_iou >= file_iou - 0.02  # tinted glass: GrabCut cuts it out of the boxes (both 1.000 here)
    figure = tmp_path / "figure.png"
    assert bench(["--data", str(scene_dir), "--model", model_dir, "--marked", "5", "--refine", "none",
                  "--grid", "64", "--mark", "polygon", "--figure", str(figure)]) == 0
    image = read_image(figure)
    assert image.shape == (72, 3 * 96 + 2 * 4, 3)  # the marked view and two neighbours, 4-pixel gaps
    assert (image[:, 96:100] > 0.95).all()  # white gaps (colours at 5 bits)
