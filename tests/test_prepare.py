"""rtsplat prepare: downsampling with exact intrinsics, masks, ROI, split, formats, bad input."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from fixtures_pipeline import WINDOW, make_corner_scene  # noqa: E402

from rtsplat.cli import main as cli_main  # noqa: E402
from rtsplat.config import PrepareConfig, RoiConfig  # noqa: E402
from rtsplat.errors import PipelineError  # noqa: E402
from rtsplat.io.images import area_downsample, read_image, read_mask, write_png  # noqa: E402
from rtsplat.masks import make_masks  # noqa: E402
from rtsplat.prepare import checked_mask_roi, mask_hull, mask_rays_in_roi, prepare_scene  # noqa: E402
from rtsplat.scene import PreparedScene, Roi  # noqa: E402
from rtsplat.sfm import run_sfm  # noqa: E402

W, H = 160, 120


def _stages(scene: Path, work: Path, masks: bool = True):
    run_sfm(scene, work / "sfm", progress=False)
    if masks:
        make_masks(scene, work / "masks", progress=False)
    return work / "sfm", (work / "masks" if masks else None)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = tmp_path_factory.mktemp("prep")
    views = make_corner_scene(root / "scene", n_views=10, width=W, height=H, with_model=True, with_masks=True)
    sfm, masks = _stages(root / "scene", root)
    return root, views, sfm, masks


def test_prepare_downsamples_with_exact_intrinsics(base, tmp_path):
    root, views, sfm, masks = base
    s = prepare_scene(root / "scene", sfm, tmp_path / "prepared", PrepareConfig(downsample=2), masks, progress=False)
    assert (s.width, s.height, s.downsample) == (W // 2, H // 2, 2)
    scene = PreparedScene.load(tmp_path / "prepared")
    assert scene.has_transparency and len(scene.cameras) == 10
    gt = {Path(v.name).stem: v for v in views}
    for cam in scene.cameras:
        v = gt[cam.name]
        assert np.allclose(cam.K_array[:2], v.K[:2] / 2) and np.allclose(cam.w2c_array, v.world_to_camera)
        img = scene.load_image(cam.name)
        ref = area_downsample(read_image(root / "scene" / "images" / v.name), 2)
        assert img.shape == (H // 2, W // 2, 3) and np.abs(img - ref).max() <= 0.5 / 255 + 1e-6
    # the mask's window lands where the scaled camera projects the window corners
    cam = scene.cameras[3]
    mask = scene.load_mask(cam.name)
    corners = np.array(
        [[0, WINDOW[0], WINDOW[2]], [0, WINDOW[1], WINDOW[2]], [0, WINDOW[0], WINDOW[3]], [0, WINDOW[1], WINDOW[3]]],
        float,
    )
    c = corners @ cam.w2c_array[:3, :3].T + cam.w2c_array[:3, 3]
    uv = c @ cam.K_array.T
    uv = uv[:, :2] / uv[:, 2:]
    ys, xs = np.nonzero(mask)
    assert abs((xs + 0.5).min() - uv[:, 0].min()) < 1.5 and abs((xs + 0.5).max() - uv[:, 0].max()) < 1.5
    assert abs((ys + 0.5).min() - uv[:, 1].min()) < 1.5 and abs((ys + 0.5).max() - uv[:, 1].max()) < 1.5
    # torch camera of the shared convention
    torch_cam = cam.to_camera()
    assert torch_cam.width == W // 2 and float(torch_cam.K[0, 0]) == pytest.approx(cam.K[0][0])


def test_split_roi_and_points(base, tmp_path):
    root, views, sfm, masks = base
    prepare_scene(root / "scene", sfm, tmp_path / "p", PrepareConfig(downsample=1), masks, progress=False)
    scene = PreparedScene.load(tmp_path / "p")
    assert [c.name for c in scene.test_cameras] == ["view_000", "view_008"]  # every 8th, name order
    assert len(scene.train_cameras) == 8
    # with masks: the sphere around their visual hull holds the window's corners
    assert scene.roi.source == "masks"
    corners = np.array([[0, y, z] for y in WINDOW[:2] for z in WINDOW[2:]], float)
    assert (np.linalg.norm(corners - scene.roi.center, axis=1) < scene.roi.radius).all()
    # without the masks' hull: estimated from the SfM points around where the cameras look
    prepare_scene(root / "scene", sfm, tmp_path / "p1", PrepareConfig(roi_from_masks=False), masks, progress=False)
    estimated = PreparedScene.load(tmp_path / "p1").roi
    assert estimated.source == "estimated"
    assert np.allclose(estimated.center, [0.6, 0.6, 0.6], atol=1e-6)  # where the fixture cameras look
    assert 1.0 < estimated.radius < 2.5  # covers the corner's points
    xyz, rgb = scene.load_points()
    assert xyz.shape == (500, 3) and rgb.dtype == np.uint8
    # ROI from the config
    roi = RoiConfig(center=[1.0, 2.0, 3.0], radius=0.5)
    prepare_scene(root / "scene", sfm, tmp_path / "p2", PrepareConfig(roi=roi, test_every=3), masks, progress=False)
    scene2 = PreparedScene.load(tmp_path / "p2")
    assert scene2.roi.source == "config" and scene2.roi.center == [1.0, 2.0, 3.0] and scene2.roi.radius == 0.5
    assert [c.name for c in scene2.test_cameras] == ["view_000", "view_003", "view_006", "view_009"]


def test_prescaled_images_are_used(tmp_path):
    import cv2

    make_corner_scene(tmp_path / "s", n_views=4, width=W, height=H, with_model=True)
    (tmp_path / "s" / "images_4").mkdir()
    for p in sorted((tmp_path / "s" / "images").iterdir()):
        img = cv2.imread(str(p))
        cv2.imwrite(
            str(tmp_path / "s" / "images_4" / p.name), cv2.resize(img, (W // 4, H // 4), interpolation=cv2.INTER_AREA)
        )
    sfm, _ = _stages(tmp_path / "s", tmp_path, masks=False)
    s = prepare_scene(tmp_path / "s", sfm, tmp_path / "p", PrepareConfig(downsample=4), progress=False)
    assert s.used_prescaled and (s.width, s.height) == (W // 4, H // 4) and not s.has_transparency
    scene = PreparedScene.load(tmp_path / "p")
    assert scene.cameras[0].K[0][0] == pytest.approx(0.9 * W / 4)
    assert not (tmp_path / "p" / "masks").exists()


@pytest.mark.parametrize("fmt", ["png16", "exr", "rgba"])
def test_16bit_exr_and_alpha_inputs(tmp_path, fmt):
    import OpenImageIO as oiio

    views = make_corner_scene(tmp_path / "s", n_views=3, width=W, height=H, with_model=True)
    images = tmp_path / "s" / "images"
    ref = {}
    for v in views:
        p = images / v.name
        img = read_image(p)
        ref[Path(v.name).stem] = img
        if fmt == "png16":
            write_png(p, img, bits=16)
        elif fmt == "rgba":  # semi-transparent alpha must not darken the colours (no premultiplication)
            rgba = np.concatenate([img, np.full(img.shape[:2] + (1,), 0.5, np.float32)], axis=2)
            out = oiio.ImageOutput.create(str(p))
            spec = oiio.ImageSpec(W, H, 4, "uint8")
            spec.attribute("oiio:UnassociatedAlpha", 1)
            out.open(str(p), spec)
            out.write_image((rgba * 255).round().astype(np.uint8))
            out.close()
        else:
            lin = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4).astype(np.float32)
            p.unlink()
            exr = p.with_suffix(".exr")
            out = oiio.ImageOutput.create(str(exr))
            out.open(str(exr), oiio.ImageSpec(W, H, 3, "float"))
            out.write_image(lin)
            out.close()
    if fmt == "exr":  # rename the images in the model too
        from rtsplat.io.colmap import write_model

        write_model(
            tmp_path / "s" / "sparse" / "0", [(Path(v.name).stem + ".exr", v.K, v.world_to_camera, W, H) for v in views]
        )
    sfm, _ = _stages(tmp_path / "s", tmp_path, masks=False)
    cfg = PrepareConfig(downsample=2, bit_depth=16)
    prepare_scene(tmp_path / "s", sfm, tmp_path / "p", cfg, progress=False)
    scene = PreparedScene.load(tmp_path / "p")
    for cam in scene.cameras:
        got = scene.load_image(cam.name)
        want = area_downsample(ref[cam.name], 2)
        assert np.abs(got - want).max() < 1.5 / 255, (fmt, np.abs(got - want).max())


def test_prepare_cli_and_failures_keep_earlier_output(base, tmp_path, capsys):
    root, _, sfm, masks = base
    scene = tmp_path / "scene"
    shutil.copytree(root / "scene", scene)
    out = tmp_path / "prepared"
    args = ["prepare", "--scene-dir", str(scene), "--sfm", str(sfm), "--masks", str(masks), "--out", str(out)]
    assert cli_main(args + ["--downsample", "2"]) == 0
    assert "8 train + 2 test views at 80x60 (downsample 2)" in capsys.readouterr().out
    # a flag is an override of its config key, validated like one: status 1 and the key, no traceback
    assert cli_main(args + ["--downsample", "0"]) == 1
    assert "prepare.downsample" in capsys.readouterr().err
    before = (out / "scene.json").read_text()
    # an image truncated after SfM: clear error naming it, earlier prepared scene intact
    img = Path(json.loads((sfm / "summary.json").read_text())["image_dir"]) / "view_004.png"
    original = img.read_bytes()
    try:
        img.write_bytes(original[: len(original) // 3])
        assert cli_main(args) == 1
        err = capsys.readouterr().err
        assert "view_004.png: cannot read image" in err and "Fix:" in err
    finally:
        img.write_bytes(original)
    assert (out / "scene.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prepared", "scene"]  # no temporary leftovers
    # no SfM result yet
    assert (
        cli_main(["prepare", "--scene-dir", str(scene), "--sfm", str(tmp_path / "nope"), "--out", str(tmp_path / "x")])
        == 1
    )
    assert "run 'rtsplat sfm'" in capsys.readouterr().err


@pytest.mark.parametrize("resolution", [1000, W, 79])
def test_resolution_picks_the_smallest_factor_that_meets_it(base, tmp_path, resolution):
    root, _, sfm, masks = base
    cfg = PrepareConfig(downsample=4, resolution=resolution)  # resolution decides, downsample is not used
    s = prepare_scene(root / "scene", sfm, tmp_path / "p", cfg, masks, progress=False)
    scene = PreparedScene.load(tmp_path / "p")
    f = scene.downsample
    assert s.downsample == f and scene.resolution == s.resolution == resolution
    assert max(s.width, s.height) <= resolution  # meets the target ...
    assert f == 1 or max(W // (f - 1), H // (f - 1)) > resolution  # ... with the smallest factor
    assert (s.width, s.height) == (W // f, H // f)
    cam = scene.cameras[0]
    assert scene.load_image(cam.name).shape == (cam.height, cam.width, 3) == (H // f, W // f, 3)
    assert scene.load_mask(cam.name).shape == (H // f, W // f)
    if f == 1:
        assert "not smaller than the images (160x120): factor 1" in s.downsample_reason
    else:
        assert f"factor {f} for prepare.resolution {resolution}" in s.downsample_reason


def test_downsample_factor_refuses_what_leaves_no_pixel():
    from rtsplat.prepare import downsample_factor

    here = Path("images")
    assert downsample_factor({(W, H)}, PrepareConfig(downsample=H), here)[0] == H  # 1 pixel high: allowed
    with pytest.raises(PipelineError, match=r"prepare.downsample 121 is larger than the images \(160x120\)") as err:
        downsample_factor({(W, H)}, PrepareConfig(downsample=H + 1), here)
    assert "at most 120" in str(err.value)
    # a panorama: the factor a small target needs would leave nothing of the short side
    with pytest.raises(PipelineError, match=r"prepare.resolution 5 is too small for the images \(400x40\)") as err:
        downsample_factor({(400, 40)}, PrepareConfig(resolution=5), here)
    least = int(str(err.value).split("at least ")[1].split()[0])
    f, _ = downsample_factor({(400, 40)}, PrepareConfig(resolution=least), here)  # the fix works
    assert f <= 40 and 400 // f <= least


def test_resolution_and_downsample_on_the_command_line(base, tmp_path, capsys):
    root, _, sfm, masks = base
    args = ["prepare", "--scene-dir", str(root / "scene"), "--sfm", str(sfm), "--masks", str(masks)]
    assert cli_main(args + ["--out", str(tmp_path / "a"), "--resolution", "100"]) == 0
    out = capsys.readouterr().out
    assert "factor 2 for prepare.resolution 100" in out and "at 80x60 (downsample 2)" in out
    assert json.loads((tmp_path / "a" / "scene.json").read_text())["resolution"] == 100
    # a factor on the command line wins over a configured resolution
    argv = args + ["--out", str(tmp_path / "b"), "--config-json", '{"resolution": 100}', "--downsample", "4"]
    assert cli_main(argv) == 0
    scene = json.loads((tmp_path / "b" / "scene.json").read_text())
    assert (scene["downsample"], scene["resolution"]) == (4, None)
    assert "prepare.downsample 4" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:  # both flags: a usage error
        cli_main(args + ["--out", str(tmp_path / "c"), "--resolution", "100", "--downsample", "2"])
    assert exc.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    # a factor larger than the images: exit 1 naming their size, nothing written
    assert cli_main(args + ["--out", str(tmp_path / "d"), "--downsample", "500"]) == 1
    err = capsys.readouterr().err
    assert "prepare.downsample 500 is larger than the images (160x120)" in err and "Fix:" in err
    assert not (tmp_path / "d").exists()
    with pytest.raises(SystemExit) as exc:
        cli_main(["prepare", "--help"])
    assert "--resolution PIXELS" in capsys.readouterr().out


def test_mask_of_wrong_size_is_rejected(base, tmp_path):
    root, _, sfm, masks = base
    bad = tmp_path / "masks"
    shutil.copytree(masks, bad)
    from rtsplat.io.images import write_mask

    write_mask(bad / "view_005.png", np.ones((10, 12), bool))
    with pytest.raises(PipelineError, match=r"view_005.png: mask is 12x10, image is 160x120"):
        prepare_scene(root / "scene", sfm, tmp_path / "p", masks_dir=bad, progress=False)
    assert not (tmp_path / "p").exists()


def test_model_image_mismatch_is_rejected(base, tmp_path):
    root, views, sfm, masks = base
    scene = tmp_path / "scene"
    shutil.copytree(root / "scene", scene)
    (scene / "images" / views[2].name).unlink()
    sfm2 = tmp_path / "sfm"
    shutil.copytree(sfm, sfm2)
    summary = json.loads((sfm2 / "summary.json").read_text())
    summary["image_dir"] = str(scene / "images")
    (sfm2 / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(PipelineError, match="view_002.png"):
        prepare_scene(scene, sfm2, tmp_path / "p", progress=False)
    assert read_mask(masks / "view_002.png").any()  # inputs untouched


def test_masks_are_undistorted_with_the_images(tmp_path):
    make_corner_scene(tmp_path / "s", n_views=9, width=W, height=H, with_masks=True)  # no model: real SfM
    sfm, masks = _stages(tmp_path / "s", tmp_path)
    summary = json.loads((sfm / "summary.json").read_text())
    assert summary["undistorted"]  # SIMPLE_RADIAL -> PINHOLE
    s = prepare_scene(tmp_path / "s", sfm, tmp_path / "p", PrepareConfig(downsample=1), masks, progress=False)
    scene = PreparedScene.load(tmp_path / "p")  # checks that every mask has its image's size
    import cv2

    for cam in scene.cameras:
        got = scene.load_mask(cam.name)
        orig = read_mask(tmp_path / "s" / "transparent_masks" / f"{cam.name}.png")
        # the undistortion is tiny here: the warped mask overlaps the original one almost fully
        ref = cv2.resize(orig.astype(np.uint8), (cam.width, cam.height), interpolation=cv2.INTER_NEAREST) > 0
        assert (got & ref).sum() / (got | ref).sum() > 0.85
    assert s.has_transparency and 0.03 < s.mask_coverage < 0.2


def test_empty_masks_mean_no_transparency(tmp_path):
    from rtsplat.io.images import write_mask

    make_corner_scene(tmp_path / "s", n_views=3, width=80, height=60, with_model=True, with_masks=True)
    for p in (tmp_path / "s" / "transparent_masks").iterdir():
        write_mask(p, np.zeros((60, 80), bool))
    sfm, masks = _stages(tmp_path / "s", tmp_path)
    s = prepare_scene(tmp_path / "s", sfm, tmp_path / "p", masks_dir=masks, progress=False)
    assert not s.has_transparency
    scene = PreparedScene.load(tmp_path / "p")
    assert not scene.has_transparency and not (tmp_path / "p" / "masks").exists()


def _ball_views(center, radius, n_views=24, size=(64, 48), stray_views=()):
    """Cameras on two rings around the origin and the masks of a ball (pixels whose ray hits it);
    ``stray_views`` also mark a wrong blob in the top-left corner."""
    from rtsplat.camera import look_at

    w, h = size
    K = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    views = []
    for i in range(n_views):
        angle = 2 * np.pi * i / n_views
        eye = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.0 + (i % 2)])
        w2c = look_at(eye, (0.0, 0.0, 0.3), dtype=torch_float64()).numpy()
        xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
        rays = rays @ w2c[:3, :3]  # camera to world directions
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        to_center = np.asarray(center) - eye
        along = rays @ to_center
        miss = np.linalg.norm(to_center) ** 2 - along**2
        mask = (along > 0) & (miss <= radius**2)
        if i in stray_views:
            mask[:10, :10] = True
        views.append((K, w2c, mask))
    return views


def torch_float64():
    import torch

    return torch.float64


def test_roi_from_masks_wraps_the_visual_hull():
    from rtsplat.prepare import roi_from_masks
    from rtsplat.scene import Roi

    center, radius = np.array([0.3, -0.2, 0.5]), 0.4
    bound = Roi([0.0, 0.0, 0.0], 3.0, "estimated")
    step = 2 * bound.radius / 95
    roi = roi_from_masks(_ball_views(center, radius), bound)
    assert roi is not None and roi.source == "masks"
    # the sphere contains the ball and is not much larger than it (hull: a little larger than the ball)
    assert np.linalg.norm(np.array(roi.center) - center) + radius <= roi.radius
    assert roi.radius <= 1.1 * (radius + 0.15) + step + 0.1
    # two views with a wrong blob in their masks do not move the sphere
    strayed = roi_from_masks(_ball_views(center, radius, stray_views=(3, 11)), bound)
    assert np.allclose(strayed.center, roi.center) and strayed.radius == pytest.approx(roi.radius)
    # masks that mark nothing carve nothing
    empty = [(K, w2c, np.zeros_like(m)) for K, w2c, m in _ball_views(center, radius)]
    assert roi_from_masks(empty, bound) is None


def test_hull_surface_lies_on_the_ball_and_faces_out():
    from rtsplat.prepare import hull_surface, mask_hull
    from rtsplat.scene import Roi

    center, radius = np.array([0.3, -0.2, 0.5]), 0.4
    views = _ball_views(center, radius)
    hull = mask_hull(views, Roi([0.3, -0.2, 0.5], 1.0, "masks"), grid=48)
    points, normals = hull_surface(hull, views)
    assert len(points) > 100
    offset = points - center
    distance = np.linalg.norm(offset, axis=1)
    # the carved hull of a ball seen from two rings is a little larger than the ball, nowhere smaller
    assert distance.min() > radius - 2 * hull.step and np.median(distance) < radius + 0.12
    # normals point away from the centre
    assert np.median((offset / distance[:, None] * normals).sum(1)) > 0.9


def test_propagated_masks_carve_the_hull_without_their_outline():
    """Masks that hold the ball's silhouette with a pixel to spare (what a propagated mask is: the
    marked views' hull projected holds the silhouette) carve a hull that stands off the ball all round;
    carved through :func:`hull_mask` it lies where the drawn masks' hull does. Drawn masks are carved
    as they are."""
    from scipy import ndimage

    from rtsplat.prepare import hull_mask, hull_surface, mask_hull
    from rtsplat.scene import Roi

    center, radius = np.array([0.3, -0.2, 0.5]), 0.4
    drawn = _ball_views(center, radius, n_views=24, size=(128, 96))
    assert all(np.array_equal(hull_mask(m, False), m) for _, _, m in drawn)
    wide = [(K, w2c, ndimage.binary_dilation(m)) for K, w2c, m in drawn]
    bound = Roi(center.tolist(), 1.0, "masks")

    def surface_distance(views):
        hull = mask_hull(views, bound, grid=64)
        points, _ = hull_surface(hull, views)
        return np.linalg.norm(points - center, axis=1) - radius, hull.step

    true_offset, step = surface_distance(drawn)
    wide_offset, _ = surface_distance(wide)
    carved_offset, _ = surface_distance([(K, w2c, hull_mask(m, True)) for K, w2c, m in wide])
    assert np.median(wide_offset) > np.median(true_offset) + 0.5 * step  # the outline's pixel, carved in
    assert abs(np.median(carved_offset) - np.median(true_offset)) < 0.5 * step
    assert carved_offset.min() > true_offset.min() - step  # no deeper into the ball than the drawn hull


def test_prepare_carves_with_the_propagated_masks_eroded_and_writes_them_whole(base, tmp_path):
    """A masks folder whose summary records propagated masks (``mask_sources``): the region of interest is
    carved from them less their outline, so it is smaller than from the same masks drawn; the prepared
    masks are the masks as given either way."""
    import json
    import shutil

    root, views, sfm, masks = base
    prepare_scene(root / "scene", sfm, tmp_path / "drawn", PrepareConfig(downsample=1), masks, progress=False)
    propagated = tmp_path / "masks"
    shutil.copytree(masks, propagated)
    summary = json.loads((propagated / "summary.json").read_text())
    names = sorted(Path(v.name).name for v in views)
    summary["mask_sources"] = {n: "given" if i % 3 == 0 else "propagated" for i, n in enumerate(names)}
    summary["source"], summary["marked"] = "propagate", [n for i, n in enumerate(names) if i % 3 == 0]
    (propagated / "summary.json").write_text(json.dumps(summary))
    prepare_scene(root / "scene", sfm, tmp_path / "prop", PrepareConfig(downsample=1), propagated, progress=False)
    a, b = PreparedScene.load(tmp_path / "drawn"), PreparedScene.load(tmp_path / "prop")
    assert a.marked_views == [] and b.marked_views == sorted(Path(n).stem for n in summary["marked"])
    assert a.roi.source == b.roi.source == "masks"
    assert b.roi.radius < a.roi.radius
    for cam in a.cameras:
        assert np.array_equal(a.load_mask(cam.name), b.load_mask(cam.name))


@pytest.mark.parametrize("shape", ["ball", "tilted cube"])
def test_hull_surface_normals_follow_the_true_surface_not_the_grids_staircase(shape):
    """The normals of a voxelised ball and of a tilted cube's faces, from hull_surface, against the
    shapes' own normals: within a degree or two (the voxel staircase alone bends the indicator's
    gradient by 3-6 degrees)."""
    from scipy.spatial.transform import Rotation

    from rtsplat.prepare import MaskHull, hull_surface

    center, grid = np.array([0.3, -0.2, 0.5]), 48
    axis = np.linspace(-1.0, 1.0, grid)
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) + center
    rotation = Rotation.from_euler("xyz", [20, 35, 10], degrees=True).as_matrix()
    local = (points - center) @ rotation  # coordinates in the cube's frame
    inside = np.linalg.norm(local, axis=1) < 0.6 if shape == "ball" else (np.abs(local) < 0.5).all(1)
    hull = MaskHull(points=points, inside=inside.reshape(grid, grid, grid), step=float(axis[1] - axis[0]))
    surface, normals = hull_surface(hull, _ball_views(center, 0.4))
    assert len(surface) > 500
    offset = (surface - center) @ rotation
    if shape == "ball":
        truth, judged = offset / np.linalg.norm(offset, axis=1, keepdims=True), np.ones(len(offset), bool)
    else:
        face = np.argmax(np.abs(offset), 1)
        truth = np.eye(3)[face] * np.sign(offset[np.arange(len(offset)), face])[:, None]
        judged = np.sort(np.abs(offset), 1)[:, 1] < 0.3  # on a face, clear of its edges
    angle = np.degrees(np.arccos(np.clip((truth[judged] * (normals[judged] @ rotation)).sum(1), -1.0, 1.0)))
    assert judged.sum() > 300
    assert np.median(angle) < 1.5 and np.percentile(angle, 90) < 3.0


def _ring_of_views(mask_of):
    """Eight cameras on a ring around the origin, looking at it, with the mask ``mask_of(camera)`` each."""
    import torch

    from rtsplat.camera import camera_from_fov

    views = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        cam = camera_from_fov((3 * np.cos(a), 3 * np.sin(a), 1.0), (0, 0, 0), width=40, height=30,
                              dtype=torch.float64)
        views.append((cam.K.numpy(), cam.world_to_camera.numpy(), mask_of(cam)))
    return views


def _disc_mask(cam, radius=6):
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    return (u + 0.5 - cam.width / 2) ** 2 + (v + 0.5 - cam.height / 2) ** 2 <= radius**2


def test_a_region_of_interest_on_the_glass_meets_its_masked_rays_and_one_beside_it_falls_back():
    # the masks: a disc at the image centre of every view, i.e. glass around the origin the ring looks at
    views = _ring_of_views(_disc_mask)
    on_glass, beside = Roi([0.0, 0.0, 0.0], 0.7, "masks"), Roi([-2.7, 3.5, -0.3], 0.7, "masks")
    fallback = Roi([0.0, 0.0, 0.5], 4.0, "estimated")
    assert mask_rays_in_roi(on_glass, views) == 1.0
    assert mask_rays_in_roi(beside, views) < 0.5
    assert checked_mask_roi(on_glass, fallback, views) == (on_glass, "")
    roi, warning = checked_mask_roi(beside, fallback, views)
    assert roi == fallback and "lies away from the glass" in warning and "prepare.roi" in warning


def test_scene_json_records_whether_the_masks_region_of_interest_was_used(base, tmp_path, monkeypatch):
    """prepare writes why it did not use the masks' region of interest into scene.json (``roi_warning``, with
    ``roi.source`` naming the region used instead), the loader reads it back, and a scene.json written without
    the field loads with no warning."""
    root, views, sfm, masks = base
    prepare_scene(root / "scene", sfm, tmp_path / "kept", PrepareConfig(downsample=2), masks, progress=False)
    kept = json.loads((tmp_path / "kept" / "scene.json").read_text())
    assert kept["roi"]["source"] == "masks" and kept["roi_warning"] == ""
    assert PreparedScene.load(tmp_path / "kept").roi_warning == ""
    assert (tmp_path / "kept" / "transparent_surface.npz").is_file()
    # asked for a share of the masked rays above 100%, the check falls back to the estimated region
    monkeypatch.setattr("rtsplat.prepare.MIN_MASK_RAYS_IN_ROI", 1.01)
    s = prepare_scene(root / "scene", sfm, tmp_path / "fell", PrepareConfig(downsample=2), masks, progress=False)
    assert "lies away from the glass" in s.roi_warning and "set prepare.roi" in s.roi_warning
    data = json.loads((tmp_path / "fell" / "scene.json").read_text())
    assert data["roi"]["source"] == "estimated" and data["roi_warning"] == s.roi_warning
    scene = PreparedScene.load(tmp_path / "fell")
    assert scene.roi_warning == s.roi_warning and scene.roi.source == "estimated"
    assert not (tmp_path / "fell" / "transparent_surface.npz").exists()  # nothing seeded from that hull
    # a scene.json written before the field: no warning
    del data["roi_warning"]
    (tmp_path / "fell" / "scene.json").write_text(json.dumps(data))
    assert PreparedScene.load(tmp_path / "fell").roi_warning == ""
    data["roi_warning"] = 3
    (tmp_path / "fell" / "scene.json").write_text(json.dumps(data))
    with pytest.raises(PipelineError, match="roi_warning must be a string"):
        PreparedScene.load(tmp_path / "fell")


def test_the_masks_hull_of_a_disc_seen_from_a_ring_gives_a_region_of_interest_that_meets_the_masks():
    views = _ring_of_views(_disc_mask)
    hull = mask_hull(views, Roi([0.0, 0.0, 0.0], 2.0, "estimated"), grid=32)
    assert hull is not None and hull.inside.any()
    from rtsplat.prepare import roi_around

    roi, warning = checked_mask_roi(roi_around(hull), Roi([0.0, 0.0, 0.0], 4.0, "estimated"), views)
    assert warning == "" and roi.source == "masks" and np.linalg.norm(roi.center) < 0.3
