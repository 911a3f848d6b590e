"""The viewer's speed on CPU: ``python -m rtsplat.bench.viewer``.

Builds a demo-like model (the toy scene's wall and pane seen from ``--views`` views at 200x150, about
``--surfels`` surfels started from its points, the demo's environment map (demo/config.yaml), trained
``--iterations`` iterations through the specular stage, so every branch of the render runs) unless
``--run`` (and ``--data``) name a trained run, then prints:

* time to first frame: from reading ``model.pt`` (:func:`rtsplat.viewer.open_viewer`, which renders one
  small warm-up frame) to the first ``--width`` x ``--height`` frame rendered and JPEG-encoded as the viewer
  sends it;
* frames per second while moving: ``--frames`` frames along an orbit around the first view's look-at
  point, each a new camera, rendered and encoded the same way (the server's work per frame; the browser's
  drawing and the network are not timed), at ``--width`` x ``--height``;
* the same orbit as the viewer renders it while the camera moves on a ``--canvas`` page: each frame's
  size chosen by :func:`rtsplat.viewer.adaptive_long_side` from the render times of the frames before it
  (the viewer's defaults: ``preview_seconds``, at most ``preview_size`` pixels on the long side), with its
  frames per second and the long sides it chose.

Timed on the threads torch has (``--threads``); numbers on a machine shared with other jobs are noisy.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch


def _demo_like_run(root: Path, *, views: int, surfels: int, iterations: int) -> tuple[Path, Path]:
    from rtsplat.bench.iteration import demo_environment_map
    from rtsplat.bench.toy_scene import train_quietly, write_scene

    n_side = max(4, round(math.sqrt(surfels / 3)))  # three starting surfels per point of the wall
    scene = write_scene(root / "scene", views=views, width=200, height=150, n_side=n_side)
    train_quietly(scene, root / "run",
                  {"iterations": iterations, "volume_until": 1, "specular_from": 2, "densify_from": 10_000,
                   "reset_every": 0, "checkpoint_every": 0, "log_every": 10_000, "eval_every": 0},
                  demo_environment_map())
    return root / "run", scene.root


def _encode(image: np.ndarray, quality: int) -> bytes:
    import cv2

    ok, data = cv2.imencode(".jpg", image[..., ::-1], [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    assert ok
    return data.tobytes()


def orbit_poses(viewer, frames: int) -> list:
    """``frames`` viewer poses swinging +-0.5 rad about the vertical around the point 2 units ahead of the
    first view of ``viewer`` (a :class:`rtsplat.viewer.SceneViewer`), looking at it."""
    from rtsplat.viewer import ViewerPose, _matrix_to_quaternion, viewer_pose_from_camera

    camera = next(iter(viewer.views().values()))
    first = viewer_pose_from_camera(camera)
    centre = np.asarray(first.position)
    target = centre + 2.0 * camera.world_to_camera[2, :3].double().cpu().numpy()  # 2 units ahead
    poses = []
    for i in range(frames):
        angle = 0.5 * math.sin(2 * math.pi * i / frames)  # swing +-0.5 rad about the vertical
        c, s = math.cos(angle), math.sin(angle)
        offset = centre - target
        eye = target + np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1], offset[2]])
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, (0.0, 0.0, 1.0))
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        poses.append(ViewerPose(_matrix_to_quaternion(np.stack([right, down, forward], 1)), tuple(eye), first.fov_y))
    return poses


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, help="a trained run (default: build the demo-like model)")
    parser.add_argument("--data", type=Path, help="its prepared scene (default: the one it recorded)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--canvas", default="1280x720", help="page size WxH of the adaptive run (default 1280x720)")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--surfels", type=int, default=30_000)
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    from rtsplat.viewer import ViewerSettings, moving_frame_size, open_viewer, viewer_pose_from_camera

    try:
        canvas = tuple(int(v) for v in args.canvas.lower().split("x"))
        if len(canvas) != 2 or min(canvas) < 1:
            raise ValueError
    except ValueError:
        parser.error(f"--canvas must be WxH, e.g. 1280x720, got {args.canvas!r}")

    with tempfile.TemporaryDirectory(prefix="rtsplat-bench-viewer-") as tmp:
        run_dir, data_dir = args.run, args.data
        if run_dir is None:
            print(f"building the demo-like model ({args.surfels} surfels wanted) ...", flush=True)
            run_dir, data_dir = _demo_like_run(Path(tmp), views=args.views, surfels=args.surfels,
                                               iterations=args.iterations)
        quality = ViewerSettings().jpeg_quality
        start = time.perf_counter()
        viewer = open_viewer(run_dir, data_dir, device=args.device)
        first = viewer_pose_from_camera(next(iter(viewer.views().values())))
        _encode(viewer.render(first, args.width, args.height), quality)
        first_frame = time.perf_counter() - start

        poses = orbit_poses(viewer, args.frames)
        start = time.perf_counter()
        for pose in poses:
            _encode(viewer.render(pose, args.width, args.height), quality)
        seconds = time.perf_counter() - start

        settings = viewer.settings
        recent = deque(maxlen=max(1, settings.preview_history))
        sides = []
        start = time.perf_counter()
        for pose in poses:
            width, height = moving_frame_size(recent, *canvas, settings)
            _encode(viewer.render(pose, width, height), quality)
            recent.append((width, height, viewer.last_frame["seconds"]))
            sides.append(max(width, height))
        adaptive_seconds = time.perf_counter() - start
        print(f"surfels: {len(viewer.run.model.surfels)}, device: {viewer.run.device}, torch threads: "
              f"{torch.get_num_threads()}, frame {args.width}x{args.height}, JPEG quality {quality}")
        print(f"time to first frame: {first_frame:.2f} s (model read, warm-up frame, first frame)")
        print(f"while moving: {args.frames / seconds:.2f} frames per second ({1000 * seconds / args.frames:.0f} ms "
              f"per frame over {args.frames} cameras)")
        print(f"while moving, adaptive on a {canvas[0]}x{canvas[1]} page (target {settings.preview_seconds} s, at most "
              f"{settings.preview_size} px): {args.frames / adaptive_seconds:.2f} frames per second, long side "
              f"{min(sides)}-{max(sides)} px (mean {sum(sides) / len(sides):.0f})")
    return 0


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.viewer", main))
