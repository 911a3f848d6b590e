"""``rtsplat view``: the viewer's camera renders what ``rtsplat render`` renders, and a real headless
Chromium draws the frames it sends (layer switch included)."""

from __future__ import annotations

import collections
import math
import shutil
import socket
import time

import numpy as np
import pytest
import torch

from rtsplat.bench.toy_scene import train_quietly, write_scene
from rtsplat.camera import look_at
from rtsplat.io.images import read_image
from rtsplat.render import Edits, load_run, render_images, render_run
from rtsplat.viewer import (
    LAYER_LABELS,
    ViewerPose,
    ViewerServer,
    ViewerSettings,
    _matrix_to_quaternion,
    _quaternion_to_matrix,
    adaptive_long_side,
    camera_from_viewer,
    frame_size,
    frame_time_model,
    open_viewer,
    to_uint8,
    viewer_pose_from_camera,
)

INSTALL_CHROMIUM = "apt-get install -y chromium (as root; `make test` does it on Debian)"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    scene = write_scene(root / "scene", views=8, width=48, height=36)
    train_quietly(scene, root / "run",
                  {"iterations": 30, "volume_until": 5, "specular_from": 10, "densify_from": 1000,
                   "reset_every": 0, "checkpoint_every": 0, "log_every": 10},
                  {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32})
    return root, scene


def test_quaternions_round_trip_every_kind_of_rotation():
    g = np.random.default_rng(0)
    rotations = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    for _ in range(50):
        q, _ = np.linalg.qr(g.normal(size=(3, 3)))
        rotations.append(q * np.sign(np.linalg.det(q)))
    for R in rotations:
        wxyz = _matrix_to_quaternion(R)
        assert wxyz[0] >= 0 and math.isclose(np.linalg.norm(wxyz), 1.0, rel_tol=1e-12)
        np.testing.assert_allclose(_quaternion_to_matrix(wxyz), R, atol=1e-12)


def test_viewer_pose_is_the_camera_centre_and_looks_along_its_z_axis():
    w2c = look_at((1.0, -3.0, 0.5), (0.0, 0.0, 0.0), dtype=torch.float64)
    pose = ViewerPose(_matrix_to_quaternion(w2c[:3, :3].T.numpy()), (1.0, -3.0, 0.5), math.radians(40))
    camera = camera_from_viewer(pose, 160, 90, dtype=torch.float64)
    torch.testing.assert_close(camera.world_to_camera, w2c)
    assert camera.K[0, 2] == 80 and camera.K[1, 2] == 45 and camera.K[0, 0] == camera.K[1, 1]
    assert math.isclose(2 * math.atan(45 / float(camera.K[1, 1])), math.radians(40), rel_tol=1e-12)
    back = viewer_pose_from_camera(camera)
    np.testing.assert_allclose(back.position, pose.position, atol=1e-12)
    np.testing.assert_allclose(back.wxyz, pose.wxyz, atol=1e-12)
    assert frame_size(1000, 500, 320) == (320, 160) and frame_size(200, 100, 320) == (200, 100)


def test_moving_frames_are_sized_to_take_the_target_time():
    """The preview's long side from recent render times, with a fake clock (a frame costs ``fixed`` seconds
    plus ``per_pixel`` per pixel; no timing): after a few moving frames, the frames take the target (within
    1%: frame sizes are whole pixels, and the sizes are chosen from the average of the last frames); never
    above the largest."""
    canvas, target = (1280, 720), 0.25
    for fixed, per_pixel in ((0.0, 1e-5), (0.1, 4e-6), (0.2, 1e-6), (0.05, 4e-7)):
        def fake_seconds(width, height):
            return fixed + per_pixel * width * height  # noqa: B023 - used inside this iteration only

        recent = collections.deque(maxlen=ViewerSettings.preview_history)
        for _ in range(10):  # the viewer's moving frames: each sized from the times of the ones before
            side = adaptive_long_side(recent, *canvas, target_seconds=target, largest=10_000)
            width, height = frame_size(*canvas, side)
            recent.append((width, height, fake_seconds(width, height)))
        assert target * 0.99 <= fake_seconds(width, height) <= target * 1.01, (fixed, per_pixel)
        spread = [(w, h, fake_seconds(w, h)) for w, h in ((320, 180), (200, 112), (100, 56))]
        torch.testing.assert_close(frame_time_model(spread), (fixed, per_pixel), rtol=1e-6, atol=1e-9)
    # slower renders give smaller frames; the largest caps fast ones; nothing timed yet: the largest
    sides = [adaptive_long_side([(320, 180, c * 320 * 180)], *canvas, target_seconds=target, largest=320)
             for c in (1e-4, 1e-5, 1e-6, 1e-8)]
    assert sides[0] < sides[1] < sides[2] == sides[3] == 320
    assert adaptive_long_side([], *canvas, target_seconds=target, largest=320) == 320
    assert adaptive_long_side([], 200, 100, target_seconds=target, largest=320) == 200  # never above the canvas
    # a frame of any size takes longer than the target: the smallest
    slow = [(320, 180, 0.5 + 1e-6 * 320 * 180), (160, 90, 0.5 + 1e-6 * 160 * 90)]
    assert adaptive_long_side(slow, *canvas, target_seconds=target, largest=320) == 32


def test_render_images_of_some_layers_equal_those_of_a_render_of_all(trained):
    """Asking :func:`render_images` for a few layers (the viewer asks for the one it shows) computes less,
    and each layer is the same as when all are rendered."""
    root, scene = trained
    run = load_run(root / "run", scene.root, split="test", device="cpu")
    edits = Edits(tint=(1.0, 0.5, 0.25))
    with torch.inference_mode():
        every = render_images(run, run.cameras[0], edits)
        for layers in (("normal",), ("depth", "normal"), ("transmission",), ("color", "depth")):
            some = render_images(run, run.cameras[0], edits, layers=layers)
            assert tuple(some) == layers
            for layer in layers:
                assert torch.equal(some[layer], every[layer]), layer
    with pytest.raises(ValueError, match="unknown layers"):
        render_images(run, run.cameras[0], edits, layers=("albedo",))


def test_viewer_renders_a_view_as_rtsplat_render_does(trained, tmp_path):
    """The viewer's camera of a test view, rendered at the view's size, gives the PNGs of ``rtsplat render``
    (both 8-bit: one level of rounding apart) for the image and a layer, with an edit applied live."""
    root, scene = trained
    viewer = open_viewer(root / "run", scene.root)
    assert not viewer.run.appearance  # no per-view appearance: the viewer shows the scene's own colours
    for edits in (Edits(), Edits(roughness=0.5, reflections=False, tint=(1.0, 0.5, 0.25))):
        out = tmp_path / f"render_{len(list(tmp_path.iterdir()))}"
        info = render_run(root / "run", scene.root, out, edits=edits, progress=False, warmup=0)
        viewer.set_edits(edits)
        views = viewer.views()
        for name in info["views"]:
            camera = views[f"test/{name}"]
            pose = viewer_pose_from_camera(camera)
            for layer in ("color", "transmission"):
                ours = viewer.render(pose, camera.width, camera.height, layer=layer).astype(np.float32) / 255
                theirs = read_image(out / layer / f"{name}.png")
                assert np.abs(ours - theirs).max() <= 1.01 / 255, (name, layer, edits)
    # the edits are applied to the trained model each time, not on top of the previous edit
    viewer.set_edits(Edits())
    camera = viewer.views()[f"test/{info['views'][0]}"]
    plain = viewer.render(viewer_pose_from_camera(camera), camera.width, camera.height).astype(np.float32) / 255
    np.testing.assert_allclose(plain, read_image(tmp_path / "render_0" / "color" / f"{info['views'][0]}.png"),
                               atol=1.01 / 255)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail(f"the viewer test needs Chromium and none is installed: {INSTALL_CHROMIUM}")
    return path


def _wait(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {seconds} s waiting for {what}")
        time.sleep(0.1)


def _canvas_pixels(page) -> np.ndarray:
    """The page's 3D canvas as the browser drew it (a screenshot of that element), float [H, W, 3]."""
    import io

    from PIL import Image

    png = page.locator("canvas").first.screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float32) / 255


def _settled_canvas(page, server, seconds: float = 20.0) -> np.ndarray:
    """The canvas once the page shows the full-size frame of its current state (two equal screenshots)."""
    _wait(lambda: server._clients, seconds, "the page to connect")
    state = next(iter(server._clients.values()))
    _wait(lambda: state.shown == (state.version, True), seconds, "the full-size frame")
    previous = _canvas_pixels(page)
    deadline = time.monotonic() + seconds
    while True:
        time.sleep(0.3)
        current = _canvas_pixels(page)
        if np.array_equal(current, previous) or time.monotonic() > deadline:
            return current
        previous = current


@pytest.mark.slow
def test_a_headless_browser_draws_the_frames_and_switches_layers(trained, tmp_path):
    """Chromium opens the viewer; the canvas it draws is our render of the first test view at the
    canvas's size (JPEG quality 90, drawn at 1:1), and choosing another layer in the page draws that layer."""
    try:
        from playwright.sync_api import sync_playwright
    except ModuleNotFoundError:
        pytest.fail("the viewer test needs playwright (pip install -e '.[viewer]'); " + INSTALL_CHROMIUM)
    chromium = _chromium()
    root, scene = trained
    viewer = open_viewer(root / "run", scene.root, settings=ViewerSettings(settle_seconds=0.2))
    server = ViewerServer(viewer, port=_free_port())
    reference_run = load_run(root / "run", scene.root, split="test")
    first_view = viewer_pose_from_camera(reference_run.cameras[0])
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=chromium, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 800, "height": 500}, device_scale_factor=1)
            page.goto(f"http://127.0.0.1:{server.port}")
            drawn = _settled_canvas(page, server)
            height, width = drawn.shape[:2]
            assert (viewer.last_frame["width"], viewer.last_frame["height"]) == (width, height)

            def reference(layer: str) -> np.ndarray:
                camera = camera_from_viewer(first_view, width, height)
                with torch.inference_mode():
                    image = render_images(reference_run, camera, Edits())[layer]
                return to_uint8(image).astype(np.float32) / 255

            # the page's overlays (a notice in the top-left corner, the axes in the bottom-left) are left out
            rows = slice(int(0.35 * height), int(0.85 * height))
            expected = reference("color")
            error = np.abs(drawn - expected)[rows]
            assert error.mean() < 0.01 and np.quantile(error, 0.99) < 0.06, (error.mean(), np.quantile(error, 0.99))
            assert np.abs(drawn - expected[::-1])[rows].mean() > 3 * error.mean()  # the comparison can tell

            page.get_by_role("combobox", name="layer").click()  # the page's own dropdown, as a user picks
            page.get_by_role("option", name=LAYER_LABELS["normal"], exact=True).click()
            _wait(lambda: viewer.layer == "normal", 10, "the layer chosen in the page")
            normals = _settled_canvas(page, server)
            error = np.abs(normals - reference("normal"))[rows]
            assert error.mean() < 0.01 and np.quantile(error, 0.99) < 0.06, (error.mean(), np.quantile(error, 0.99))
            assert np.abs(normals - drawn)[rows].mean() > 0.05
            page.screenshot(path=str(tmp_path / "viewer.png"))
            browser.close()
    finally:
        server.stop()
