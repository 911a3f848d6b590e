"""Tests of rtsplat.synth: ground-truth scenes rendered with Mitsuba 3 (scalar_rgb, CPU)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")
cv2 = pytest.importorskip("cv2")

from rtsplat.camera import camera_from_fov  # noqa: E402
from rtsplat.cli import main as cli_main  # noqa: E402
from rtsplat.errors import ConfigError  # noqa: E402
from rtsplat.io.colmap import quaternion_to_rotation, rotation_to_quaternion  # noqa: E402
from rtsplat.io.images import read_image  # noqa: E402
from rtsplat.synth import cli as synth_cli  # noqa: E402
from rtsplat.synth.dataset import SynthConfig, render_dataset  # noqa: E402
from rtsplat.synth.render import load_scene, render_view, set_variant  # noqa: E402

TINY = dict(views=8, width=64, height=48, spp=4, layer_spp=4)
SCENE_NAMES = ("dome", "cabin", "film", "opaque")


def _cli(tmp: Path, scene: str, **kw) -> tuple[int, Path]:
    out = tmp / scene
    parser = argparse.ArgumentParser()
    synth_cli.add_arguments(parser)
    argv = ["--scene", scene, "--out", str(out), "--no-progress"]
    for key, value in kw.items():
        flag = "--" + key.replace("_", "-")
        argv += [flag] if value is True else [flag, str(value)]
    return synth_cli.run(parser.parse_args(argv)), out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """A tiny render of every scene through the CLI entry point."""
    root = tmp_path_factory.mktemp("synth_tiny")
    outs = {}
    for scene in SCENE_NAMES:
        rc, out = _cli(root, scene, any_views=True, seed=3, **TINY)
        assert rc == 0
        outs[scene] = out
    return outs


def _read(path: Path, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    assert img is not None, path
    return img


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quaternion_to_rotation(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        q2 = rotation_to_quaternion(R)
        assert np.allclose(q2, q if q[0] >= 0 else -q, atol=1e-9)
    # COLMAP convention: rotation about +x by 90 degrees is (cos 45, sin 45, 0, 0)
    Rx = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert np.allclose(rotation_to_quaternion(Rx), [np.sqrt(0.5), np.sqrt(0.5), 0, 0])


def test_bad_arguments_are_rejected(tmp_path, capsys):
    # bad input exits with status 1, the convention of every stage (rtsplat.cli.main prints the error)
    def main(scene, *extra):
        return cli_main(["synth", "--scene", scene, "--out", str(tmp_path / scene), "--no-progress", *extra])

    assert main("teapot") == 1 and "unknown scene" in capsys.readouterr().err
    assert main("dome", "--views", "8") == 1 and "views must be in 40-200" in capsys.readouterr().err
    assert main("dome", "--views", "40", "--spp", "0") == 1 and "spp" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="views"):
        SynthConfig(views=201).validate()
    SynthConfig(views=8, allow_any_views=True).validate()
    assert list(tmp_path.iterdir()) == []


def test_failure_leaves_no_partial_output(tmp_path, monkeypatch):
    import rtsplat.synth.dataset as dataset

    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("boom")
        return render_view(*args, **kwargs)

    monkeypatch.setattr(dataset, "render_view", failing)
    config = SynthConfig(scene="opaque", views=3, width=32, height=24, spp=1, layer_spp=1, allow_any_views=True)
    with pytest.raises(RuntimeError, match="boom"):
        render_dataset(config, tmp_path / "out", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_layers_every_renders_layers_for_every_kth_view_only(tmp_path):
    config = SynthConfig(scene="dome", views=5, width=32, height=24, spp=1, layer_spp=1, layers_every=2,
                         allow_any_views=True)
    render_dataset(config, tmp_path / "out", progress=False)
    expected = ["0000", "0002", "0004"]
    assert sorted(p.stem for p in (tmp_path / "out" / "layers" / "linear").iterdir()) == expected
    meta = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert meta["layer_views"] == [s + ".png" for s in expected]


def test_scene_json_records_what_the_glass_reflects_as_the_files_give_it(tiny):
    """synth follows the reflection of every glass pixel of the views with layers while it renders them;
    the bench recomputes it from the files written (masks, float16 layers): the same pixels, and the same
    share of the reflection's luminance up to float16 rounding."""
    from rtsplat.bench.reflection_reach import dataset_reach

    for scene in ("dome", "cabin"):
        recorded = json.loads((tiny[scene] / "scene.json").read_text())["reflection_reach"]
        again = dataset_reach(tiny[scene])
        assert recorded["glass_pixels"] == again.glass_pixels > 0
        assert recorded["near_pixels"] == again.near_pixels
        assert recorded["near_share"] == pytest.approx(again.near_share)
        assert recorded["near_weight"] == pytest.approx(again.near_weight, abs=2e-3)
    # the cabin's panes, seen from above, mirror the floor nearby; the dome's upper half mirrors the sky
    cabin, dome = (json.loads((tiny[s] / "scene.json").read_text())["reflection_reach"] for s in ("cabin", "dome"))
    assert cabin["near_share"] > dome["near_share"]


def test_marker_projects_where_camera_says():
    """A small glowing glass bead at a known 3D point lands on Camera.project's pixel in the
    Mitsuba render, in the mask and in the layers (checks the sensor axis conversion)."""
    set_variant()
    point = np.array([0.31, -0.22, 0.27])
    cam = camera_from_fov((2.5, -1.5, 1.2), (0.0, 0.0, 0.0), width=64, height=48, fov_x_deg=50, dtype=torch.float64)
    bead = {
        "type": "sphere",
        "center": point.tolist(),
        "radius": 0.02,
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
        "bsdf": {"type": "thindielectric"},
    }
    scene = load_scene({"bead": bead}, [cam], spp=64)
    view = render_view(scene, 0, cam, spp=64, seed=1)
    uv, z = cam.project(torch.tensor(point[None]))
    u, v = uv[0].tolist()
    assert z[0] > 0 and 5 < u < 59 and 5 < v < 43
    jj, ii = np.mgrid[0:48, 0:64]
    for image in (view.full, view.reflection + view.transmission):
        lum = image.mean(-1)
        assert lum.sum() > 0
        cu, cv = (lum * (ii + 0.5)).sum() / lum.sum(), (lum * (jj + 0.5)).sum() / lum.sum()
        assert abs(cu - u) < 0.15 and abs(cv - v) < 0.15, (cu, cv, u, v)
    assert view.mask[int(v), int(u)] and view.mask.sum() <= 4


@pytest.mark.parametrize("scene", SCENE_NAMES)
def test_tiny_render_is_well_formed(tiny, scene):
    out = tiny[scene]
    n, w, h = TINY["views"], TINY["width"], TINY["height"]
    meta = json.loads((out / "scene.json").read_text())
    assert meta["scene"] == scene and meta["seed"] == 3 and meta["mitsuba_version"] == mi.__version__
    stems = [f"{i:04d}" for i in range(n)]
    assert sorted(p.name for p in (out / "images").iterdir()) == [s + ".png" for s in stems]
    assert sorted(p.name for p in (out / "transparent_masks").iterdir()) == [s + ".png" for s in stems]
    mask_pixels = 0
    for stem in stems:
        image = _read(out / "images" / f"{stem}.png")
        assert image.shape == (h, w, 3) and image.dtype == np.uint8 and image.std() > 5
        mask = _read(out / "transparent_masks" / f"{stem}.png")
        assert mask.shape == (h, w) and mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        mask_pixels += int((mask == 255).sum())
        for layer in ("reflection", "transmission"):
            assert _read(out / "layers" / layer / f"{stem}.png").shape == (h, w, 3)
        with np.load(out / "layers" / "linear" / f"{stem}.npz") as z:
            assert set(z.files) == {"full", "reflection", "transmission", "scatter"}
            assert all(z[k].shape == (h, w, 3) for k in z.files)
            # the layers are split wherever a pixel's footprint may touch glass: the mask (centre
            # rays) grown by one pixel; everywhere else the image is all transmission
            glass = mask == 255
            near = glass.copy()
            near[1:] |= glass[:-1]
            near[:-1] |= glass[1:]
            near[:, 1:] |= near[:, :-1].copy()
            near[:, :-1] |= near[:, 1:].copy()
            off = ~near
            assert np.all(z["reflection"][off] == 0) and np.all(z["transmission"][off] == z["full"][off])
    if scene == "opaque":
        assert mask_pixels == 0
    else:
        assert mask_pixels > 0.05 * n * w * h


@pytest.mark.parametrize("scene", ("dome", "cabin", "film"))
def test_layers_add_up(tiny, scene):
    """Over see-through pixels, reflection + transmission is the full image up to MC noise."""
    out = tiny[scene]
    diffs, fulls, refl, scatter = [], [], [], []
    for npz in sorted((out / "layers" / "linear").glob("*.npz")):
        mask = _read(out / "transparent_masks" / (npz.stem + ".png")) == 255
        with np.load(npz) as z:
            f, r, t, s = (
                z[k].astype(np.float64)[mask].mean(-1) for k in ("full", "reflection", "transmission", "scatter")
            )
        diffs.append(r + t - f)
        fulls.append(f)
        refl.append(r)
        scatter.append(s)
    d, f = np.concatenate(diffs), np.concatenate(fulls)
    standard_error = d.std() / np.sqrt(d.size)
    assert abs(d.mean()) < 4 * standard_error + 0.002 * f.mean(), (d.mean(), standard_error)
    assert np.concatenate(refl).mean() > 0.01 * f.mean()  # the glass visibly reflects
    scatter_mean = np.concatenate(scatter).mean()
    assert (scatter_mean > 0.02 * f.mean()) if scene == "film" else scatter_mean == 0
    check = json.loads((out / "scene.json").read_text())["layer_check"]
    assert check["pixels_channels"] == 3 * d.size


def test_cameras_and_colmap_model_agree(tiny):
    pycolmap = pytest.importorskip("pycolmap")
    out = tiny["dome"]
    cams = json.loads((out / "cameras.json").read_text())["cameras"]
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == len(cams) == TINY["views"] and rec.num_points3D() > 100
    by_name = {im.name: im for im in rec.images.values()}
    for c in cams:
        image = by_name[c["name"]]
        cam = rec.cameras[image.camera_id]
        assert (cam.width, cam.height) == (c["width"], c["height"])
        K = np.asarray(c["K"])
        assert np.allclose(cam.calibration_matrix(), K)
        w2c = np.asarray(c["world_to_camera"])
        assert np.allclose(image.cam_from_world().matrix(), w2c[:3], atol=1e-9)
    # every ground-truth 3D point reprojects onto its 2D observation
    errors = []
    for point in list(rec.points3D.values())[:300]:
        el = point.track.elements[0]
        image = rec.images[el.image_id]
        xy = image.points2D[el.point2D_idx].xy
        m = image.cam_from_world().matrix()
        p = np.asarray(rec.cameras[image.camera_id].calibration_matrix()) @ (m[:, :3] @ point.xyz + m[:, 3])
        errors.append(np.linalg.norm(p[:2] / p[2] - xy))
    assert max(errors) < 1e-2  # points come from float32 Mitsuba ray hits (max seen 0.003 px)
    # the text model says the same as the binary one
    text = pycolmap.Reconstruction()
    text.read_text(str(out / "sparse" / "0"))
    assert text.num_images() == rec.num_images() and text.num_points3D() == rec.num_points3D()


def test_pipeline_reads_a_synth_dataset(tiny, tmp_path):
    """The pipeline's own stages take a synth dataset like a user's: sfm uses sparse/0 as given,
    masks are ingested from transparent_masks/, prepare writes cameras equal to the ground truth."""
    pytest.importorskip("pycolmap")
    from rtsplat.masks import make_masks
    from rtsplat.prepare import prepare_scene
    from rtsplat.scene import PreparedScene
    from rtsplat.sfm import run_sfm

    out = tiny["dome"]
    sfm = run_sfm(out, tmp_path / "sfm", progress=False)
    assert sfm.source == "dataset" and sfm.registered == sfm.total == TINY["views"] and not sfm.undistorted
    masks = make_masks(out, tmp_path / "masks", progress=False)
    assert masks.has_masks and masks.source == "ingest" and masks.mean_coverage > 0.05
    summary = prepare_scene(out, tmp_path / "sfm", tmp_path / "prepared", masks_dir=tmp_path / "masks",
                            progress=False)
    scene = PreparedScene.load(tmp_path / "prepared")
    assert scene.has_transparency and len(scene.cameras) == TINY["views"]
    # the ground-truth layers come along for the test views, in the training images' display space
    assert summary.gt_layer_views == len(scene.test_cameras) >= 1
    for cam in scene.test_cameras:
        image = scene.load_image(cam.name)
        mask = scene.load_mask(cam.name)
        refl, trans = (read_image(tmp_path / "prepared" / "gt_layers" / layer / f"{cam.name}.png")
                       for layer in ("reflection", "transmission"))
        gap = np.abs(refl + trans - image)  # 0 except where Monte-Carlo noise (4 spp here) makes R < 0: clipped
        print("R + T - image: mean", gap.mean(), "99th percentile", np.percentile(gap, 99))
        assert gap.mean() < 0.01 and np.median(gap) < 1e-4
        assert np.abs(trans - image)[~mask].mean() < 0.01  # no reflection off the glass
        assert refl[mask].mean() > 0.01 and refl[~mask].mean() < 0.005  # the glass reflects
    # what the glass reflects comes along too, for the report
    carried = json.loads((tmp_path / "prepared" / "gt_layers" / "reflection_reach.json").read_text())
    assert carried == json.loads((out / "scene.json").read_text())["reflection_reach"]
    truth = {c["name"]: c for c in json.loads((out / "cameras.json").read_text())["cameras"]}
    for cam in scene.cameras:
        gt = truth[cam.image]
        assert np.allclose(cam.K_array, gt["K"], atol=1e-6)
        assert np.allclose(cam.w2c_array, gt["world_to_camera"], atol=1e-6)


def test_cabin_interior_is_seen_only_through_windows(tmp_path):
    """No camera ray of the cabin orbit reaches an interior object without crossing a window
    first, and the objects are visible through the windows."""
    from synth_rays import interior_hits

    from rtsplat.synth.scenes import build_scene

    set_variant()
    spec = build_scene("cabin", 3, tmp_path)
    cams = spec.orbit.cameras(12, 48, 36)
    bare, through_glass = interior_hits(load_scene(spec.elements, cams, spp=1), cams)
    assert bare == 0, "an interior object is visible without glass"
    assert through_glass > 20


def test_render_is_deterministic(tiny, tmp_path):
    rc, again = _cli(tmp_path, "dome", any_views=True, seed=3, **TINY)
    assert rc == 0
    first = tiny["dome"]
    for rel in ("images", "transparent_masks", "layers/linear", "layers/reflection", "sparse/0"):
        for path in sorted((first / rel).iterdir()):
            if path.suffix == ".npz":
                with np.load(path) as a, np.load(again / rel / path.name) as b:
                    assert all(np.array_equal(a[k], b[k]) for k in a.files), path
            else:
                assert path.read_bytes() == (again / rel / path.name).read_bytes(), path
    assert (first / "scene.json").read_text() == (again / "scene.json").read_text()


@pytest.mark.slow
def test_colmap_recovers_dome_poses(tmp_path):
    """The sfm stage on a default-size dome render registers >= 90% of the views with sub-pixel
    reprojection error, and its poses match the ground truth within 1 degree after a similarity
    fit (the focal length is estimated, not given).

    40 views (the minimum of the range) at 16 spp without layers keep this at 45 s (idle) to 2.5 min (loaded) on
    two cores.
    """
    pytest.importorskip("pycolmap")
    from rtsplat.synth.sfm_check import check_dataset

    config = SynthConfig(scene="dome", views=40, spp=16, layer_spp=0)  # default size: 200 x 150
    render_dataset(config, tmp_path / "dome", progress=False)
    stats = check_dataset(tmp_path / "dome", tmp_path / "sfm")
    print(json.dumps(stats, indent=1))
    assert stats["registered_ratio"] >= 0.9, stats
    assert stats["mean_reprojection_error_px"] < 1.0, stats
    assert stats["rotation_error_deg_max"] < 1.0, stats
    assert stats["center_error_relative"] < 0.02, stats


def test_overwrite_never_replaces_a_folder_synth_did_not_write(tmp_path):
    from rtsplat.errors import PipelineError
    from rtsplat.synth.dataset import SynthConfig, render_dataset

    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "holiday.jpg").write_bytes(b"not a dataset")
    with pytest.raises(PipelineError, match="not written by 'rtsplat synth'"):
        config = SynthConfig(scene="dome", views=2, width=16, height=16, spp=1, allow_any_views=True)
        render_dataset(config, photos, overwrite=True, progress=False)
    assert (photos / "holiday.jpg").read_bytes() == b"not a dataset"
