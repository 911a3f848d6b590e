"""Marks on flat glass seen from one side, carried through the glass's plane (rtsplat.masks.plane): the robust
plane fit on points with outliers, and a ray-cast walk past a pane in a facade whose true masks are known."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from rtsplat.config import MaskPropagationConfig
from rtsplat.io.colmap import ColmapModel, ColmapView
from rtsplat.masks.plane import (
    MAX_IN_FRONT,
    MIN_AGREEMENT,
    GlassPlane,
    cast_marks,
    glass_plane,
    in_front_share,
    mark_agreement,
    outline_points,
    ransac_planes,
    seen_through,
)
from rtsplat.masks.propagation import carry_marks, propagate_masks

sys.path.insert(0, str(Path(__file__).resolve().parent))
from masks_scene import look_at  # noqa: E402

PANE = (-1.0, 1.0, 0.5, 1.5)  # the pane in the plane y = 0: x0, x1, z0, z1
WIDTH, HEIGHT = 120, 90


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(int((a | b).sum()), 1)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def test_ransac_finds_the_plane_among_a_floor_and_scattered_points():
    rng = np.random.default_rng(3)
    normal = np.array([0.2, -0.9, 0.1])
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    on = 0.4 * normal + rng.uniform(-1, 1, (60, 1)) * u + rng.uniform(-1, 1, (60, 1)) * v
    on += rng.normal(0, 0.003, on.shape)  # SfM noise
    floor = np.column_stack([rng.uniform(-2, 2, 90), rng.uniform(-2, 2, 90), np.full(90, -1.0)])  # a bigger plane
    scattered = rng.uniform(-2, 2, (120, 3))  # points seen through the glass or in its reflection
    points = np.concatenate([on, floor, scattered])
    planes = ransac_planes(points, 0.02, np.random.default_rng(0))
    assert 2 <= len(planes) <= 6
    assert _angle(planes[0][0], np.array([0.0, 0.0, 1.0])) < 1.0  # the floor has the most points
    found = [p for p in planes if _angle(p[0], normal) < 1.0]
    assert len(found) == 1
    fitted, offset, inliers = found[0]
    assert abs(abs(offset) - 0.4) < 0.01
    assert inliers[:60].mean() > 0.95
    assert inliers[150:].mean() < 0.1


def _view(name: str, eye, target) -> ColmapView:
    fx = 0.9 * WIDTH
    K = np.array([[fx, 0, WIDTH / 2], [0, fx, HEIGHT / 2], [0, 0, 1.0]])
    return ColmapView(name, WIDTH, HEIGHT, "PINHOLE", np.array([fx, fx, WIDTH / 2, HEIGHT / 2]), K,
                      look_at(np.asarray(eye, float), np.asarray(target, float)))


def _true_mask(view: ColmapView) -> np.ndarray:
    """Where the view's rays meet the pane (nothing stands in front of it)."""
    plane = GlassPlane(np.array([0.0, -1.0, 0.0]), 0.0, 0.0, 0.0, 0, 0, 0.0)
    from rtsplat.masks.plane import plane_points

    points, depth = plane_points(plane, view)
    x, z = points[..., 0], points[..., 2]
    return np.isfinite(depth) & (x >= PANE[0]) & (x <= PANE[1]) & (z >= PANE[2]) & (z <= PANE[3])


@pytest.fixture(scope="module")
def walk():
    """A walk past the pane (cameras at y = -2.5 walking along x, looking straight ahead, a little bob in height)
    and SfM-like points: a facade around the pane (its plane), a pavement, an awning and a planter in front, a
    room's wall behind the glass, and points scattered in depth where reflections were triangulated."""
    rng = np.random.default_rng(1)
    views = []
    for i, x in enumerate(np.linspace(-1.2, 1.2, 13)):
        z = 1.0 + 0.05 * np.sin(i)
        views.append(_view(f"frame_{i:05d}.png", (x, -2.5, z), (x, 0.0, 1.0)))
    facade = np.column_stack([rng.uniform(-3, 3, 900), np.zeros(900), rng.uniform(0, 2.2, 900)])
    x, z = facade[:, 0], facade[:, 2]
    facade = facade[~((x > PANE[0]) & (x < PANE[1]) & (z > PANE[2]) & (z < PANE[3]))]
    floor = np.column_stack([rng.uniform(-3, 3, 1500), rng.uniform(-2.4, 0, 1500), np.zeros(1500)])  # the pavement
    room = np.column_stack([rng.uniform(-1, 1, 400), np.full(400, 2.0), rng.uniform(0.5, 1.5, 400)])
    reflections = np.column_stack([rng.uniform(-1, 1, 300), rng.uniform(0.3, 4.0, 300), rng.uniform(0.5, 1.5, 300)])
    # an awning sloping out above the pane and a planter below it: in front of the facade, on the marks' outlines
    out = rng.uniform(0, 1, 500)
    awning = np.column_stack([rng.uniform(-3, 3, 500), -0.5 * out, 1.52 + 0.1 * out])
    planter = np.column_stack([rng.uniform(-1.5, 1.5, 300), np.full(300, -0.3), rng.uniform(0.0, 0.5, 300)])
    points = np.concatenate([facade + rng.normal(0, 0.004, facade.shape), floor, room, reflections, awning, planter])
    return ColmapModel(views, points)


def test_marks_from_one_side_are_cast_through_the_panes_plane(walk):
    marked_names = ["frame_00000.png", "frame_00006.png", "frame_00012.png"]
    marked = {n: _true_mask(walk.view(n)) for n in marked_names}
    carrier = carry_marks(walk, marked, MaskPropagationConfig(occlusion=False))
    assert carrier.method == "plane"
    assert "from one side" in carrier.reason and "glass's plane" in carrier.reason
    plane = carrier.plane
    assert _angle(plane.normal, np.array([0.0, 1.0, 0.0])) < 1.0
    assert abs(plane.offset) < 0.02
    assert plane.normal[1] < 0  # facing the cameras at y < 0
    assert plane.relative_residual < 0.01
    assert plane.agreement > 0.95 and not plane.refined
    for view in walk.views:
        if view.name not in marked:
            assert iou(carrier.silhouette(view), _true_mask(view)) > 0.97, view.name
    results = propagate_masks(walk, marked, [v.name for v in walk.views], lambda n: np.zeros((HEIGHT, WIDTH, 3)),
                              MaskPropagationConfig(refine="none", occlusion=False), carrier=carrier)
    assert {r.source for r in results} == {"given", "propagated"}


def test_without_points_on_the_glass_outline_the_marks_place_the_plane(walk):
    """No SfM point on the facade (a pane in a plain, featureless wall): the planes the other points propose are
    not the glass's, and the best is moved to where the marks agree."""
    without_facade = walk.xyz[np.abs(walk.xyz[:, 1]) > 0.02]
    names = ("frame_00000.png", "frame_00006.png", "frame_00012.png")
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in names]
    plane = glass_plane(without_facade, marked, 0.03, 1.0)
    assert plane.refined and plane.record()["refined"]
    assert _angle(plane.normal, np.array([0.0, 1.0, 0.0])) < 2.0
    assert abs(plane.offset) < 0.05
    assert plane.agreement > 0.95
    view = walk.view("frame_00003.png")
    assert iou(cast_marks(plane, marked, view), _true_mask(view)) > 0.95


def test_the_marks_agree_best_through_the_true_plane(walk):
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in ("frame_00001.png", "frame_00007.png")]
    true = GlassPlane(np.array([0.0, -1.0, 0.0]), 0.0, 0.0, 0.0, 0, 0, 0.0)
    floor = GlassPlane(np.array([0.0, 0.0, 1.0]), 0.0, 0.0, 0.0, 0, 0, 0.0)
    behind = GlassPlane(np.array([0.0, -1.0, 0.0]), 2.0, 0.0, 0.0, 0, 0, 0.0)  # the room's back wall at y = 2
    assert mark_agreement(true, marked, 1.0) > 0.97
    assert mark_agreement(floor, marked, 1.0) < 0.5
    assert mark_agreement(behind, marked, 1.0) < mark_agreement(true, marked, 1.0) - 0.05


def test_outline_points_are_mostly_in_front_of_the_glass(walk):
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in ("frame_00002.png", "frame_00010.png")]
    points = outline_points(walk.xyz, marked, 0.05)
    assert (np.abs(points[:, 1]) < 0.02).sum() >= 20  # the facade around the pane
    assert np.mean(points[:, 1] > 0.1) < 0.1  # little of the room and the reflections behind the glass


def test_a_plane_in_front_of_what_is_seen_through_the_glass_is_not_the_glass(walk):
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in ("frame_00000.png", "frame_00012.png")]
    seen = seen_through(walk.xyz, marked)
    assert all(len(points) > 50 and (points[:, 1] > 0.2).all() for _, points in seen)  # the room and reflections
    assert in_front_share(np.array([0.0, -1.0, 0.0]), 0.0, seen, 0.03) == 0.0  # the pane
    assert in_front_share(np.array([0.0, -1.0, 0.0]), 2.0, seen, 0.03) > 0.1  # the room's wall at y = 2
    tilted = np.array([0.0, -1.0, 3.0]) / np.sqrt(10)  # through the pane's bottom edge, leaning back into the room
    assert in_front_share(tilted, -1.5 / np.sqrt(10), seen, 0.03) > MAX_IN_FRONT


def test_a_plane_the_marks_do_not_agree_on_is_refused(walk):
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in ("frame_00000.png", "frame_00006.png")]
    shifted = _true_mask(walk.view("frame_00012.png"))
    marked.append((walk.view("frame_00012.png"), np.roll(shifted, 25, axis=1)))  # a mark drawn on the wrong place
    marked.append((walk.view("frame_00003.png"), np.roll(_true_mask(walk.view("frame_00003.png")), -25, axis=1)))
    with pytest.raises(ValueError, match="agree on no plane"):
        glass_plane(walk.xyz, marked, 0.03, 1.0)


def test_cast_marks_leave_out_what_stands_in_front(walk):
    view = walk.view("frame_00005.png")
    marked = [(walk.view(n), _true_mask(walk.view(n))) for n in ("frame_00000.png", "frame_00012.png")]
    plane = GlassPlane(np.array([0.0, -1.0, 0.0]), 0.0, 0.0, 0.0, 0, 0, 0.0)
    free = cast_marks(plane, marked, view)
    rng = np.random.default_rng(0)
    post = np.column_stack([rng.uniform(-0.1, 0.1, 400) + view.center[0], rng.uniform(-1.01, -0.99, 400),
                            rng.uniform(0.5, 1.5, 400)])  # a post a metre in front of the pane
    hidden = cast_marks(plane, marked, view, occluders=post)
    assert hidden.sum() < free.sum() - 50
    assert not (hidden & ~free).any()


# ----------------------------------------------------------------------------------------------
# the family's walks past glass, rendered with Mitsuba, through the masks CLI


def _marked_scene(dataset: Path, root: Path, count: int) -> tuple[Path, Path, dict, dict]:
    """A scene folder with the dataset's photos alone, its true cameras and points as the SfM result, and
    ``count`` views spread over the capture marked with polygons traced on their true masks (as a user draws
    them: the outline's corners within 1.5 pixels): (scene, sfm, masks.marks, true masks by photo name)."""
    import shutil

    from rtsplat.bench.mask_propagation import drawn_marks
    from rtsplat.io.colmap import load_model
    from rtsplat.io.images import list_images, read_mask
    from rtsplat.masks import match_masks
    from rtsplat.masks.propagation import suggest_views

    scene, sfm = root / "scene", root / "sfm"
    shutil.copytree(dataset / "images", scene / "images")
    shutil.copytree(dataset / "sparse" / "0", sfm / "sparse" / "0")
    images = list_images(scene / "images")
    truth = {p.name: read_mask(m) for p, m in match_masks(images, dataset / "transparent_masks").items()}
    marked = suggest_views(load_model(sfm / "sparse" / "0"), count)
    outlines, _ = drawn_marks(marked, truth, {p.name: p for p in images}, "polygon", MaskPropagationConfig())
    marks = {n: {"polygons": [np.round(o, 1).tolist() for o in outlines[n]]} for n in marked}
    return scene, sfm, marks, truth


@pytest.mark.slow
@pytest.mark.parametrize("member", ["shop_window-2", "grazing-3", "car-2", "car-3"])
def test_three_polygons_on_a_walk_past_glass_mask_every_frame(member, tmp_path, capsys):
    """A walk past a shop window, a pane at grazing angles and cars: three marked frames carry their polygons
    to the other frames through the glass's plane (a car's end windows, marked at the walk's ends, through planes
    of their own), within IoU 0.9 of the rendered masks on average and 0.8 at worst; the choice and the planes'
    residuals are printed and recorded."""
    import json

    pytest.importorskip("mitsuba")
    from rtsplat.cli import main as cli_main
    from rtsplat.io.images import read_mask
    from rtsplat.report import masks_paragraph

    dataset = tmp_path / "data"
    assert cli_main(["synth", "--scene", f"family/{member}", "--out", str(dataset), "--no-progress", "--views",
                     "16", "--width", "160", "--height", "120", "--spp", "4", "--layer-spp", "0", "--any-views"]) == 0
    scene, sfm, marks, truth = _marked_scene(dataset, tmp_path, 3)
    capsys.readouterr()
    out = tmp_path / "masks"
    assert cli_main(["masks", "--scene-dir", str(scene), "--out", str(out), "--sfm", str(sfm),
                     "--config-json", json.dumps({"marks": marks})]) == 0
    printed = capsys.readouterr().out
    assert "carried through the plane: the marked views" in printed
    if not member.startswith("car"):  # flat glass: the views look from one side; a car's walk turns around it
        assert "carried through the plane: the marked views look from one side" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["propagation_method"] == "plane"
    assert summary["glass_plane"]["relative_residual"] < 0.01
    assert summary["glass_plane"]["inliers"] >= 12
    if member.startswith("car"):  # its end windows, marked at the walk's ends, each through a plane of its own
        assert "its own plane" in printed and any(pane["own_plane"] for pane in summary["glass_panes"])
    residual = f"RMS residual {100 * summary['glass_plane']['relative_residual']:.2f}% of their depth"
    assert "photos through the glass's plane (" in masks_paragraph(summary)  # what the report says
    assert residual in masks_paragraph(summary)
    scores = [iou(read_mask(out / f"{Path(n).stem}.png"), truth[n])
              for n, source in summary["mask_sources"].items() if source == "propagated"]
    assert len(scores) == 13
    print(member, f"mean IoU {np.mean(scores):.3f}, worst {min(scores):.3f}")
    assert np.mean(scores) >= 0.9
    assert min(scores) >= 0.8


# ----------------------------------------------------------------------------------------------
# two panes in different planes (a bay window): one plane per pane, through the masks CLI

BAY_CORNER = np.array([0.2, 0.0, 0.0])  # where it leaves the facade (the plane y = 0)
BAY_PANES = ((-1.4, -0.2), (0.4, 1.6))  # along each wall from its start: the pane's extent (z from 0.5 to 1.5)


def _bay_walls(degrees: float) -> list[GlassPlane]:
    """The facade (y = 0) and the wall turned back from it by ``degrees`` about the vertical, normals facing the
    street (y < 0)."""
    a = np.radians(degrees)
    turned = np.array([np.sin(a), -np.cos(a), 0.0])
    return [GlassPlane(np.array([0.0, -1.0, 0.0]), 0.0, 0.0, 0.0, 0, 0, 0.0),
            GlassPlane(turned, float(-turned @ BAY_CORNER), 0.0, 0.0, 0, 0, 0.0)]


def _along(points: np.ndarray, wall: int, degrees: float) -> np.ndarray:
    """The coordinate of points along a wall: x on the facade, the distance from the corner on the turned wall."""
    if wall == 0:
        return points[..., 0]
    a = np.radians(degrees)
    return (points - BAY_CORNER) @ np.array([np.cos(a), np.sin(a), 0.0])


def _bay_mask(view: ColmapView, degrees: float) -> np.ndarray:
    """Where the view's rays meet either pane (the nearer wall first)."""
    from rtsplat.masks.plane import plane_points

    hits = []
    for wall, plane in enumerate(_bay_walls(degrees)):
        points, depth = plane_points(plane, view)
        s, z = _along(points, wall, degrees), points[..., 2]
        on_wall = (s < BAY_CORNER[0]) if wall == 0 else (s > 0)
        pane = (s >= BAY_PANES[wall][0]) & (s <= BAY_PANES[wall][1]) & (z >= 0.5) & (z <= 1.5)
        hits.append((np.where(on_wall & np.isfinite(depth), depth, np.inf), pane))
    nearer = hits[0][0] <= hits[1][0]
    return np.where(nearer, hits[0][1] & np.isfinite(hits[0][0]), hits[1][1] & np.isfinite(hits[1][0]))


def _bay_model(degrees: float, walk: float) -> ColmapModel:
    """A walk past the bay (cameras at y = -2.5 from x = -``walk`` to ``walk``, looking ahead) and SfM-like points:
    both walls around their panes, the pavement, and points scattered behind the glass."""
    rng = np.random.default_rng(5)
    views = [_view(f"frame_{i:05d}.png", (x, -2.5, 1.0 + 0.05 * np.sin(i)), (x, 0.0, 1.0))
             for i, x in enumerate(np.linspace(-walk, walk, 13))]
    s, z = rng.uniform(-3.0, BAY_CORNER[0], 900), rng.uniform(0.0, 2.2, 900)
    keep = ~((s > BAY_PANES[0][0]) & (s < BAY_PANES[0][1]) & (z > 0.5) & (z < 1.5))
    facade = np.column_stack([s, np.zeros_like(s), z])[keep]
    a = np.radians(degrees)
    s, z = rng.uniform(0.0, 3.0, 900), rng.uniform(0.0, 2.2, 900)
    keep = ~((s > BAY_PANES[1][0]) & (s < BAY_PANES[1][1]) & (z > 0.5) & (z < 1.5))
    turned = (BAY_CORNER + s[:, None] * np.array([np.cos(a), np.sin(a), 0.0]) + z[:, None] * [0, 0, 1.0])[keep]
    floor = np.column_stack([rng.uniform(-3, 3, 1200), rng.uniform(-2.4, 0, 1200), np.zeros(1200)])
    behind = np.column_stack([rng.uniform(-1.5, 1.5, 400), rng.uniform(2.0, 4.0, 400), rng.uniform(0.5, 1.5, 400)])
    walls = np.concatenate([facade, turned])
    return ColmapModel(views, np.concatenate([walls + rng.normal(0, 0.004, walls.shape), floor, behind]))


@pytest.mark.parametrize("degrees, walk", [(60.0, 0.7), (70.0, 0.65)])
def test_two_panes_in_different_planes_each_get_their_own(degrees, walk, tmp_path, capsys):
    """Marks of two panes in walls 60 or 70 degrees apart, three marked frames of a walk past them, mask files on
    disk through the masks CLI: each pane is carried through its own plane (one plane carries one pane to the
    wrong place; at 70 degrees the marks agree too little through it to take it), and the stage prints and
    records each pane's plane and residual."""
    import json

    from rtsplat.cli import main as cli_main
    from rtsplat.io.colmap import ColmapImage, ColmapPoints, write_sparse_model
    from rtsplat.io.images import read_mask, write_mask, write_png
    from rtsplat.masks.panes import mark_pieces
    from rtsplat.report import masks_paragraph

    model = _bay_model(degrees, walk)
    truth = {v.name: _bay_mask(v, degrees) for v in model.views}
    marked = ["frame_00000.png", "frame_00006.png", "frame_00012.png"]
    assert all(len(mark_pieces(truth[n])) == 2 for n in marked)  # both panes in each marked frame
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "transparent_masks").mkdir()
    for k, view in enumerate(model.views):  # photos of noise, the panes tinted blue
        image = np.random.default_rng(k).uniform(0.2, 0.8, (HEIGHT, WIDTH, 3))
        image[truth[view.name]] *= (0.6, 0.7, 1.0)
        write_png(scene / "images" / view.name, image)
        if view.name in marked:
            write_mask(scene / "transparent_masks" / view.name, truth[view.name])
    write_sparse_model(tmp_path / "sfm" / "sparse" / "0",
                       [ColmapImage(v.name, v.K, v.world_to_camera, v.width, v.height) for v in model.views],
                       ColmapPoints(model.xyz, np.full((len(model.xyz), 3), 128, np.uint8), [[] for _ in model.xyz]))
    out = tmp_path / "masks"
    config = {"propagate": {"refine": "none", "occlusion": False}}
    assert cli_main(["masks", "--scene-dir", str(scene), "--out", str(out), "--sfm", str(tmp_path / "sfm"),
                     "--config-json", json.dumps(config)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    scores = {n: iou(read_mask(out / n), truth[n]) for n, s in summary["mask_sources"].items() if s == "propagated"}
    assert len(scores) == 10 and min(scores.values()) > 0.93, scores
    printed = capsys.readouterr().out
    assert "carried through the plane: the marked views look from one side" in printed
    assert "2 panes (" in printed and printed.count("its own plane") + printed.count("the marks' plane") == 2
    panes = summary["glass_panes"]
    assert len(panes) == 2 and all(p["views"] == marked for p in panes)
    for wall in _bay_walls(degrees):  # each wall's plane is one pane's
        pane = min(panes, key=lambda p: _angle(np.array(p["normal"]), wall.normal))
        assert _angle(np.array(pane["normal"]), wall.normal) < 1.0
        assert pane["relative_residual"] < 0.01 and pane["inliers"] >= 12
    residuals = ", ".join(f"{100 * p['relative_residual']:.2f}%" for p in panes)
    assert f"the marks being 2 panes, 2 of them through a plane of its own (RMS residuals {residuals})" in \
        masks_paragraph(summary)  # what the report says
    # one plane for both panes: the pane off it lands in the wrong place
    carrier_plane = GlassPlane(np.array(summary["glass_plane"]["normal"]), summary["glass_plane"]["offset"],
                               0.0, 0.0, 0, 0, 0.0)
    single = {n: iou(cast_marks(carrier_plane, [(model.view(m), truth[m]) for m in marked], model.view(n)), truth[n])
              for n in scores}
    assert min(single.values()) < 0.85, single
    assert (summary["glass_plane"]["agreement"] < MIN_AGREEMENT) == (degrees == 70.0)  # the plane alone: refused
