"""``rtsplat view``: look at a trained run in the browser, with its layers and the scene edits live.

A `viser <https://viser.studio>`_ server (the library gsplat's viewer is built on) serves the page; the
browser sends its camera, and this process renders the model from it with :func:`rtsplat.render.render_images`
(the renders of ``rtsplat render``) and sends the frame back as a JPEG that the page draws behind its
controls. While the camera moves, frames are rendered small, with the long side chosen from the render
times of the last moving frames so that one takes at most ``--preview-seconds``
(:func:`adaptive_long_side`; at most ``--preview-size`` pixels), and the page stretches them over its
canvas; once the camera has rested ``--settle`` seconds, one frame at the page's size (at most
``--max-size`` on the long side). Only the layer shown is computed (:func:`rtsplat.render.render_images`).
Controls: the layer shown (the image and its reflection / transmission / scatter layers, normals, inverse
depth), the scene edits of ``rtsplat render --edit`` applied live to the model, a jump to any
training or test view (the run's corrected pose; the viewer then shows the scene's own colours, without
that photo's appearance correction), and the last frame's render time.

The model renders on ``--device`` (auto: the GPU when torch sees one), wherever it was trained: the
checkpoint is moved there when read. ``--data`` defaults to the prepared scene the run recorded. On a
remote machine, forward the port (``ssh -L 8080:localhost:8080 host``) and open http://localhost:8080.
The page listens on ``--port`` and nowhere else: a port out of range or one another program holds is an
error naming it (:func:`check_port`), before the run is loaded, so a forwarded port never reaches another
program.

Camera convention: viser gives the camera-to-world rotation (quaternion ``wxyz``) and centre of an
OpenCV-axes camera (x right, y down, z forward, as :mod:`rtsplat.camera`) and its vertical field of
view; :func:`camera_from_viewer` and :func:`viewer_pose_from_camera` convert between that and
:class:`rtsplat.camera.Camera` (square pixels, centred principal point).
"""

from __future__ import annotations

import argparse
import collections
import errno
import math
import socket
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from rtsplat.camera import Camera, intrinsics
from rtsplat.errors import PipelineError
from rtsplat.render import LAYER_DIRS, Edits, LoadedRun, apply_parameter_edits, load_run, render_images

LAYER_LABELS = {"color": "image", "reflection": "reflection", "transmission": "transmission",
                "scatter": "scatter", "normal": "normal", "depth": "depth (inverse)"}


@dataclass(frozen=True)
class ViewerPose:
    """A camera as viser describes it: camera-to-world rotation ``wxyz``, centre ``position`` (world)
    and vertical field of view ``fov_y`` in radians."""

    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov_y: float


def _quaternion_to_matrix(wxyz) -> np.ndarray:
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _matrix_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w >= 0) of a rotation matrix; the largest of the four terms picks the formula."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    terms = [trace, R[0, 0], R[1, 1], R[2, 2]]
    k = int(np.argmax(terms))
    if k == 0:
        s = 2 * math.sqrt(1 + trace)
        q = (0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s)
    elif k == 1:
        s = 2 * math.sqrt(1 + R[0, 0] - R[1, 1] - R[2, 2])
        q = ((R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s)
    elif k == 2:
        s = 2 * math.sqrt(1 + R[1, 1] - R[0, 0] - R[2, 2])
        q = ((R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s)
    else:
        s = 2 * math.sqrt(1 + R[2, 2] - R[0, 0] - R[1, 1])
        q = ((R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s)
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(v) for v in (q if q[0] >= 0 else -q))


def camera_from_viewer(pose: ViewerPose, width: int, height: int, *, device=None,
                       dtype=torch.float32) -> Camera:
    """The :class:`Camera` of a ``width`` x ``height`` frame of the viewer's camera ``pose``: square pixels,
    principal point at the frame's centre, focal length from the vertical field of view."""
    R = _quaternion_to_matrix(pose.wxyz)  # camera-to-world
    centre = np.asarray(pose.position, dtype=np.float64)
    w2c = np.eye(4)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ centre
    focal = 0.5 * height / math.tan(0.5 * pose.fov_y)
    K = intrinsics(focal, focal, width / 2, height / 2, dtype=dtype, device=device)
    return Camera(K, torch.as_tensor(w2c, dtype=dtype, device=device), int(width), int(height))


def viewer_pose_from_camera(camera: Camera) -> ViewerPose:
    """The viewer pose of ``camera`` (its vertical field of view from ``fy`` and the height; the viewer's
    frames have square pixels and a centred principal point, so only such a camera is reproduced exactly)."""
    w2c = camera.world_to_camera.detach().double().cpu().numpy()
    R = w2c[:3, :3].T
    centre = -R @ w2c[:3, 3]
    fy = float(camera.K[1, 1])
    return ViewerPose(_matrix_to_quaternion(R), tuple(float(v) for v in centre),
                      2 * math.atan(0.5 * camera.height / fy))


def frame_size(canvas_width: int, canvas_height: int, long_side: int) -> tuple[int, int]:
    """The frame size for a canvas: its aspect ratio, the long side at most ``long_side`` pixels."""
    scale = min(1.0, long_side / max(canvas_width, canvas_height, 1))
    return max(1, round(canvas_width * scale)), max(1, round(canvas_height * scale))


def frame_time_model(recent) -> tuple[float, float]:
    """``(fixed, per_pixel)`` seconds of a frame, ``fixed + per_pixel * pixels``, fitted by least squares
    to the ``recent`` frames (``(width, height, seconds)`` each; the per-surfel steps cost the same at any
    size, the per-pixel ones grow with it). With one size only, or a fit that says a frame costs less than
    nothing, all of the time is taken as per-pixel time."""
    pixels = [float(w * h) for w, h, _ in recent]
    seconds = [float(t) for _, _, t in recent]
    proportional = (0.0, sum(seconds) / sum(pixels))
    n = len(pixels)
    mean_p, mean_t = sum(pixels) / n, sum(seconds) / n
    var = sum((p - mean_p) ** 2 for p in pixels)
    if n < 2 or var <= (0.1 * mean_p) ** 2 * n:  # the sizes hardly differ: no slope to fit
        return proportional
    per_pixel = sum((p - mean_p) * (t - mean_t) for p, t in zip(pixels, seconds, strict=True)) / var
    fixed = mean_t - per_pixel * mean_p
    return (fixed, per_pixel) if per_pixel > 0 and fixed >= 0 else proportional


def adaptive_long_side(recent, canvas_width: int, canvas_height: int, *, target_seconds: float,
                       largest: int, smallest: int = 32) -> int:
    """The long side in pixels of the next moving frame: the largest size that renders in ``target_seconds``
    by the :func:`frame_time_model` of the ``recent`` frames (``(width, height, seconds)`` each), within
    ``smallest`` and ``largest`` (and the canvas's own long side); ``largest`` while nothing has been
    timed, ``smallest`` when even a frame of no pixels would take longer than the target."""
    largest = max(1, min(largest, max(canvas_width, canvas_height)))
    smallest = min(smallest, largest)
    recent = [(w, h, t) for w, h, t in recent if w > 0 and h > 0 and t > 0]
    if not recent:
        return largest
    fixed, per_pixel = frame_time_model(recent)
    if fixed >= target_seconds:
        return smallest
    pixels = (target_seconds - fixed) / per_pixel  # a frame with the canvas's aspect of this many pixels
    long_side, short_side = max(canvas_width, canvas_height, 1), max(min(canvas_width, canvas_height), 1)
    side = math.floor(math.sqrt(pixels * long_side / short_side))
    return max(smallest, min(side, largest))


def to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


@dataclass
class ViewerSettings:
    preview_size: int = 320  # largest long side of the frames while the camera moves
    preview_seconds: float = 0.25  # while moving, the long side is chosen so that a frame takes about this long
    preview_history: int = 4  # how many recent moving frames' render times choose it
    max_size: int = 1280  # long side of the frame at rest (the page's size when smaller)
    settle_seconds: float = 0.3  # the camera rests this long -> the full-size frame
    jpeg_quality: int = 90


def moving_frame_size(recent, canvas_width: int, canvas_height: int, settings: ViewerSettings) -> tuple[int, int]:
    """The size (width, height) of the next frame while the camera moves over a ``canvas_width`` x
    ``canvas_height`` page: the canvas's aspect at the :func:`adaptive_long_side` of the ``recent`` moving
    frames (``(width, height, seconds)`` each) for ``settings.preview_seconds``, at most ``settings.preview_size``."""
    long_side = adaptive_long_side(recent, canvas_width, canvas_height, target_seconds=settings.preview_seconds,
                                   largest=settings.preview_size)
    return frame_size(canvas_width, canvas_height, long_side)



@dataclass
class _ClientState:
    client: object
    changed_at: float = 0.0  # time.monotonic() of the last change of its camera or of the controls
    version: int = 0  # counts those changes
    shown: tuple[int, bool] | None = None  # (version, full size) of the frame on its page
    # (width, height, render seconds) of its last ViewerSettings.preview_history moving frames
    moving_times: collections.deque = field(default_factory=collections.deque)


class SceneViewer:
    """The model of a :class:`LoadedRun`, its edits and layer, and the frames it sends to each page."""

    def __init__(self, run: LoadedRun, settings: ViewerSettings | None = None):
        self.run = run
        self.settings = settings or ViewerSettings()
        self.edits = Edits()
        self.layer = "color"
        surfels = run.model.surfels
        self._unedited = {"roughness_logit": surfels.roughness_logit.detach().clone(),
                          "opacity_logit": surfels.opacity_logit.detach().clone()}
        self._model_lock = threading.Lock()  # edits and renders take turns on the model
        self.last_frame: dict = {}  # what was rendered last: seconds, size, layer, full, pose

    def set_edits(self, edits: Edits) -> None:
        """Apply ``edits`` to the model as ``rtsplat render --edit`` does, starting from the trained model."""
        with self._model_lock, torch.no_grad():
            surfels = self.run.model.surfels
            for name, value in self._unedited.items():
                getattr(surfels, name).copy_(value)
            apply_parameter_edits(self.run.model, edits)
            self.edits = edits

    def render(self, pose: ViewerPose, width: int, height: int, *, layer: str | None = None) -> np.ndarray:
        """The ``layer`` (default: the chosen one) of a ``width`` x ``height`` frame from ``pose``, uint8 [H, W, 3]."""
        layer = layer or self.layer
        camera = camera_from_viewer(pose, width, height, device=self.run.device)
        start = time.perf_counter()
        with self._model_lock, torch.inference_mode():
            image = to_uint8(render_images(self.run, camera, self.edits, layers=(layer,))[layer])
        self.last_frame = {"seconds": time.perf_counter() - start, "width": width, "height": height,
                           "layer": layer, "pose": pose}
        return image

    def views(self) -> dict[str, Camera]:
        """Every view of the scene by ``<split>/<name>`` (test views first), with the run's pose corrections."""
        pairs = sorted(zip(self.run.records, self.run.cameras, strict=True), key=lambda rc: rc[0].split != "test")
        return {f"{rec.split}/{rec.name}": camera for rec, camera in pairs}


class ViewerServer:
    """A viser server that shows a :class:`SceneViewer` to every page that connects."""

    def __init__(self, viewer: SceneViewer, *, host: str = "127.0.0.1", port: int = 8080):
        try:
            import viser
        except ModuleNotFoundError as exc:
            raise PipelineError("the viewer needs the viser package, which is not installed",
                                fix="pip install -e '.[viewer]' (or `make test`, which installs it)") from exc
        self.viewer = viewer
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(show_share_button=False)
        self.server.gui.main_panel.dock_right()  # the controls beside the frame, not over it
        self._clients: dict[int, _ClientState] = {}
        self._clients_lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._build_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._thread = threading.Thread(target=self._loop, name="rtsplat-viewer", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.server.get_port()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=30)
        self.server.stop()

    # controls -----------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        views = self.viewer.views()
        self._views = views
        self.gui_layer = gui.add_dropdown("layer", tuple(LAYER_LABELS[k] for k in LAYER_DIRS), initial_value="image")
        with gui.add_folder("scene edits"):
            self.gui_reflections = gui.add_checkbox("reflections", True)
            self.gui_roughness = gui.add_slider("roughness x", 0.0, 4.0, 0.05, 1.0)
            self.gui_transparency = gui.add_slider("opacity x", 0.0, 2.0, 0.05, 1.0)
            self.gui_tint = gui.add_vector3("tint (R, G, B)", (1.0, 1.0, 1.0), min=(0.0, 0.0, 0.0),
                                            max=(4.0, 4.0, 4.0), step=0.05)
        self.gui_view = gui.add_dropdown("go to view", tuple(views), initial_value=next(iter(views)))
        self.gui_time = gui.add_markdown("render time: -")
        labels = {v: k for k, v in LAYER_LABELS.items()}

        def layer_changed(_event) -> None:
            self.viewer.layer = labels[self.gui_layer.value]
            self._touch_all()

        def edits_changed(_event) -> None:
            self.viewer.set_edits(Edits(roughness=float(self.gui_roughness.value),
                                        transparency=float(self.gui_transparency.value),
                                        reflections=bool(self.gui_reflections.value),
                                        tint=tuple(float(v) for v in self.gui_tint.value)))
            self._touch_all()

        def view_chosen(event) -> None:
            clients = [event.client] if event.client is not None else list(self.server.get_clients().values())
            for client in clients:
                self.go_to_view(client, self.gui_view.value)

        self.gui_layer.on_update(layer_changed)
        for handle in (self.gui_reflections, self.gui_roughness, self.gui_transparency, self.gui_tint):
            handle.on_update(edits_changed)
        self.gui_view.on_update(view_chosen)

    def go_to_view(self, client, name: str) -> None:
        """Move ``client``'s camera to the view ``name`` (a key of :meth:`SceneViewer.views`)."""
        pose = viewer_pose_from_camera(self._views[name])
        R = _quaternion_to_matrix(pose.wxyz)
        with client.atomic():
            client.camera.up_direction = -R[:, 1]  # the view's own up, so its roll is kept
            client.camera.fov = pose.fov_y
            client.camera.wxyz = pose.wxyz
            client.camera.position = pose.position

    def _touch(self, state: _ClientState) -> None:
        state.version += 1
        state.changed_at = time.monotonic()
        self._wake.set()

    def _touch_all(self) -> None:
        with self._clients_lock:
            for state in self._clients.values():
                self._touch(state)

    def _connect(self, client) -> None:
        history = max(1, self.viewer.settings.preview_history)
        state = _ClientState(client, moving_times=collections.deque(maxlen=history))
        with self._clients_lock:
            self._clients[client.client_id] = state
        client.camera.on_update(lambda _camera: self._touch(state))
        self.go_to_view(client, self.gui_view.value)
        self._touch(state)

    def _disconnect(self, client) -> None:
        with self._clients_lock:
            self._clients.pop(client.client_id, None)

    # frames ---------------------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=0.05)
            self._wake.clear()
            with self._clients_lock:
                states = list(self._clients.values())
            for state in states:
                try:
                    self._serve(state)
                except Exception as exc:  # a page that went away mid-frame, or a failed render: say so, go on
                    print(f"rtsplat view: frame not sent ({exc.__class__.__name__}: {exc})")

    def _serve(self, state: _ClientState) -> None:
        version = state.version
        if state.shown == (version, True):
            return
        resting = time.monotonic() - state.changed_at >= self.viewer.settings.settle_seconds
        if not resting and state.shown is not None and state.shown[0] == version:
            return  # this camera's preview is on the page; the full frame comes when it rests
        camera = state.client.camera
        pose = ViewerPose(tuple(camera.wxyz), tuple(camera.position), float(camera.fov))
        settings = self.viewer.settings
        if resting:
            width, height = frame_size(camera.image_width, camera.image_height, settings.max_size)
        else:
            width, height = moving_frame_size(state.moving_times, camera.image_width, camera.image_height, settings)
        image = self.viewer.render(pose, width, height)
        state.client.scene.set_background_image(image, format="jpeg", jpeg_quality=settings.jpeg_quality)
        state.shown = (version, resting)
        frame = self.viewer.last_frame
        if not resting:
            state.moving_times.append((width, height, frame["seconds"]))
        self.gui_time.content = (f"render time: {1000 * frame['seconds']:.0f} ms at {width}x{height} "
                                 f"({'full' if resting else 'moving'})")


def check_port(host: str, port: int) -> None:
    """Raise :class:`PipelineError` unless ``port`` is a TCP port (1-65535) this process can listen on at
    ``host`` now (nothing else holds it)."""
    if not 1 <= port <= 65535:
        raise PipelineError(f"--port {port} is not a TCP port (1 to 65535)", fix="pass --port 8080, for example")
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a server binds: a listener blocks it
            probe.bind((host, port))
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise PipelineError(f"port {port} is in use by another program on {host}", fix="pass another --port "
                                f"(e.g. --port {port + 1 if port < 65535 else 8080}) and open or forward that one, "
                                "or stop the program that uses this one") from exc
        raise PipelineError(f"cannot listen on {host}:{port} ({exc.strerror or exc})",
                            fix="pass an address of this machine as --host (127.0.0.1 or 0.0.0.0)") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--run", type=Path, required=True, help="run directory of `rtsplat train` (has model.pt)")
    parser.add_argument("--data", type=Path, help="the prepared scene the run was trained on (default: the one "
                        "the run recorded)")
    parser.add_argument("--port", type=int, default=8080, help="port of the web page (default 8080)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this "
                        "machine only; reach it from elsewhere with ssh -L, or use 0.0.0.0)")
    parser.add_argument("--device", default="auto", help="auto (the GPU when torch sees one), cpu, cuda, cuda:N")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (auto, cpu, triton, reference)")
    parser.add_argument("--threads", type=int, help="CPU threads of the render (default: torch's, one per core); "
                        "on a machine busy with other jobs, 1 is often faster: threads that wait for a busy "
                        "core stall every step of the render")
    parser.add_argument("--preview-size", type=int, default=ViewerSettings.preview_size,
                        help="largest long side in pixels of the frames while the camera moves")
    parser.add_argument("--preview-seconds", type=float, default=ViewerSettings.preview_seconds,
                        help="while the camera moves, frames are made smaller until one renders in about this "
                        "many seconds (default %(default)s)")
    parser.add_argument("--max-size", type=int, default=ViewerSettings.max_size,
                        help="long side in pixels of the frame when the camera rests (at most the page's size)")
    parser.add_argument("--settle", type=float, default=ViewerSettings.settle_seconds,
                        help="seconds the camera rests before the full-size frame")


def open_viewer(run_dir, data_dir=None, *, device: str = "auto", backend: str = "auto",
                settings: ViewerSettings | None = None) -> SceneViewer:
    """The :class:`SceneViewer` of a run: its model on ``device`` and every view of its prepared scene."""
    settings = settings or ViewerSettings()
    for key in ("preview_size", "max_size"):
        if getattr(settings, key) < 8:
            raise PipelineError(f"--{key.replace('_', '-')} must be at least 8 pixels, got {getattr(settings, key)}")
    if not settings.preview_seconds > 0:
        raise PipelineError(f"--preview-seconds must be more than 0, got {settings.preview_seconds}")
    viewer = SceneViewer(load_run(run_dir, data_dir, split="all", backend=backend, device=device), settings)
    first = next(iter(viewer.views().values()))
    viewer.render(viewer_pose_from_camera(first), 32, 24)  # compiles or loads the kernels before a page waits
    return viewer


def run(args: argparse.Namespace) -> int:
    from rtsplat.devices import resolve_device
    from rtsplat.render import device_name

    resolve_device(args.device, key="--device")
    if args.threads is not None:
        if args.threads < 1:
            raise PipelineError(f"--threads must be at least 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    settings = replace(ViewerSettings(), preview_size=args.preview_size, max_size=args.max_size,
                       settle_seconds=args.settle, preview_seconds=args.preview_seconds)
    check_port(args.host, args.port)
    viewer = open_viewer(args.run, args.data, device=args.device, backend=args.backend, settings=settings)
    check_port(args.host, args.port)  # still free after the run loaded
    try:
        server = ViewerServer(viewer, host=args.host, port=args.port)
    except OSError as exc:
        raise PipelineError(f"cannot listen on {args.host}:{args.port} ({exc})",
                            fix="pass another --port, or stop the program that uses this one") from exc
    if server.port != args.port:  # the server moves to the next free port when its own is taken meanwhile
        server.stop()
        raise PipelineError(f"port {args.port} was taken while the viewer started (it would have listened on "
                            f"{server.port} instead)", fix="run it again, or pass another --port")
    print(f"rtsplat view: {len(viewer.run.model.surfels)} surfels on {device_name(viewer.run.device)}; open "
          f"http://{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:{server.port} "
          f"(remote machine: ssh -L {server.port}:localhost:{server.port} <host>); ctrl-C stops")
    try:
        while True:
            time.sleep(1.0)
    finally:
        server.stop()

