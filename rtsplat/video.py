"""``rtsplat video``: a trained run rendered along a camera path into an MP4 (H.264).

The path comes from the run's training cameras (their prepared poses moved by the run's pose
corrections) and the region of interest of the prepared scene (:mod:`rtsplat.camera_path`):

* ``orbit``: a circle around the region of interest at the cameras' mean distance and elevation;
* ``spiral``: around the cameras' mean position, looking at the region of interest (forward-facing captures);
* ``interpolate``: through the training poses in capture (name) order, Catmull-Rom positions and slerped rotations.

Frames use the training cameras' intrinsics, at their size or scaled to ``--width`` (both sides rounded
down to even numbers, as H.264 in yuv420p needs). Every effect of the model is rendered, as
``rtsplat render`` does, and the scene edits (``--edit``) apply the same way; novel views have no photo,
so no per-view appearance correction is applied. ``--panels`` puts image | reflection | transmission |
normal | depth side by side (the layers of ``rtsplat render``; the depth panel's inverse depth is scaled
by the first frame's largest value, so it does not flicker).

The MP4 is written through a temporary file renamed into place at the end
(:class:`rtsplat.io.video.Mp4Writer`): a failed or interrupted video leaves no partial file and keeps a
previous one. It replaces only an MP4 that ``rtsplat video`` wrote (its metadata comment says so and
records the settings). ``--poster`` writes the first frame as a PNG (the report's poster frame), after
the video; it replaces only a PNG whose ``Software`` text says ``rtsplat video`` wrote it.
``--keep-frames DIR`` writes every frame as ``DIR/frame_00000.png``... (a folder replaced atomically, like
the other stages' outputs). Frames wider or taller than the encoder takes (:data:`MAX_SIDE`, all panels
side by side) are refused before anything is rendered; running out of memory while rendering is an error
that names the frame size.
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import nullcontext
from dataclasses import asdict
from pathlib import Path

import torch

from rtsplat.config import add_config_arguments, stage_config_from_args
from rtsplat.devices import resolve_device
from rtsplat.errors import PipelineError
from rtsplat.io.outputs import check_output_dir, check_output_file, check_png_output, output_dir
from rtsplat.render import (
    Edits,
    add_run_arguments,
    decompose,
    depth_image,
    device_name,
    inverse_depth,
    load_run,
    normal_image,
)
from rtsplat.usage import UsageClock

PANELS = ("color", "reflection", "transmission", "normal", "depth")
POSTER_SOFTWARE = "rtsplat video"  # the poster PNG's Software text: how the stage knows a poster it wrote
MAX_SIDE = 16384  # the largest frame side the H.264 encoder (libx264) opens; all panels side by side count


def check_frame_size(width: int, height: int | None, panels: int) -> None:
    """Refuse frames larger than the encoder takes, before anything is rendered: ``panels`` frames of
    ``width`` x ``height`` pixels side by side (``height`` None: not known yet). Frames too small are
    :func:`rtsplat.camera_path.path_intrinsics`'s to refuse."""
    if width * panels > MAX_SIDE or (height or 0) > MAX_SIDE:
        size = f"{width * panels}x{height}" if height else f"{width * panels} pixels wide"
        side_by_side = f" ({panels} panels side by side)" if panels > 1 else ""
        raise PipelineError(f"video frames of {size}{side_by_side} are larger than the H.264 encoder takes "
                            f"({MAX_SIDE} pixels a side)",
                            fix=f"pass a --width of at most {MAX_SIDE // panels} (video.width)")


def _is_own_video(path: Path) -> bool:
    from rtsplat.io.video import RTSPLAT_COMMENT, mp4_comment

    return (mp4_comment(path) or "").startswith(RTSPLAT_COMMENT)


def check_video_output(out: Path, inputs: list[Path]) -> None:
    """Refuse an ``--out`` that is not an .mp4 path ``rtsplat video`` may write (see the module docstring)."""
    if out.suffix.lower() != ".mp4":
        raise PipelineError(f"the video is written as MP4, but --out ends in {out.suffix or 'no extension'!r}",
                            path=out, fix=f"pass a file name ending in .mp4, e.g. {out.with_suffix('.mp4')}")
    check_output_file(out, "video", _is_own_video, inputs=inputs, example="a new <name>.mp4")


def render_video(run_dir: str | Path, data_dir: str | Path, out: str | Path, *, path: str = "orbit",
                 frames: int = 60, fps: float = 24.0, width: int | None = None, panels: bool = False,
                 edits: Edits | None = None, backend: str = "auto", device: str = "auto",
                 poster: str | Path | None = None, keep_frames: str | Path | None = None,
                 progress: bool = True) -> dict:
    """Render the run of ``run_dir`` along the camera path ``path`` into the MP4 ``out``; returns what the
    MP4's metadata records (settings, size, device) with the wall seconds per frame of rendering and of
    encoding, and the CPU seconds per frame (all threads) with their :class:`rtsplat.usage.Usage`, which
    depend less on what runs beside it."""
    from tqdm.auto import tqdm

    from rtsplat.camera import Camera
    from rtsplat.camera_path import PATHS, camera_path, path_intrinsics
    from rtsplat.io.images import write_png
    from rtsplat.io.video import RTSPLAT_COMMENT, Mp4Writer
    from rtsplat.scene import PreparedScene

    run_dir, data_dir, out = Path(run_dir), Path(data_dir), Path(out)
    if path not in PATHS:
        raise PipelineError(f"unknown camera path {path!r}", fix=f"use one of {', '.join(PATHS)}")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 2:
        raise PipelineError(f"a video needs at least 2 frames, got {frames!r}", fix="pass --frames 2 or more")
    if not fps > 0:
        raise PipelineError(f"the frame rate must be positive, got {fps!r}", fix="pass --fps 24, for example")
    inputs = [run_dir, data_dir]
    check_video_output(out, inputs)
    if poster is not None:
        poster = Path(poster)
        check_png_output(poster, POSTER_SOFTWARE, inputs=inputs, flag="--poster")
    if keep_frames is not None:
        check_output_dir(keep_frames, "video", inputs=inputs, flag="--keep-frames")
    layers = PANELS if panels else PANELS[:1]
    if width is not None:
        check_frame_size(width, None, len(layers))
    edits = edits or Edits()

    run = load_run(run_dir, data_dir, split="train", edits=edits, backend=backend, device=device)
    order = sorted(range(len(run.records)), key=lambda i: run.records[i].name)  # capture order
    records = [run.records[i] for i in order]
    w2c = torch.stack([run.cameras[i].world_to_camera.detach().cpu().double() for i in order])
    center = PreparedScene.load(data_dir, check_files=False).roi.center
    poses = camera_path(path, w2c, center, frames)
    K, frame_w, frame_h = path_intrinsics([r.K for r in records], [r.width for r in records],
                                          [r.height for r in records], width)
    check_frame_size(frame_w, frame_h, len(layers))
    info = {"path": path, "frames": frames, "fps": fps, "width": frame_w, "height": frame_h,
            "panels": list(layers), "edits": asdict(edits), "backend": backend, "device": device_name(run.device),
            "run": str(run_dir), "data": str(data_dir), "surfels": len(run.model.surfels)}
    first = None
    depth_top = None
    render_seconds = encode_seconds = 0.0
    clock = UsageClock()
    K_device = K.to(device=run.device, dtype=torch.float32)
    try:
        kept = output_dir(keep_frames, "video", inputs=inputs) if keep_frames is not None else nullcontext()
        mp4 = Mp4Writer(out, frame_w * len(layers), frame_h, fps, comment=RTSPLAT_COMMENT + json.dumps(info))
        with kept as frames_dir, mp4 as video, torch.inference_mode():
            for k, pose in enumerate(tqdm(poses, desc="video", disable=not progress)):
                start = time.perf_counter()
                camera = Camera(K_device, pose.to(device=run.device, dtype=torch.float32), frame_w, frame_h)
                result = run.render(camera)
                images = decompose(result, edits)
                if panels:
                    images["normal"] = normal_image(result.layers["normal"])
                    if depth_top is None:  # one scale for the whole video
                        depth_top = inverse_depth(result.layers["depth"], result.layers["alpha"]).max()
                    images["depth"] = depth_image(result.layers["depth"], result.layers["alpha"], top=depth_top)
                frame = torch.cat([images[layer].clamp(0, 1) for layer in layers], dim=1).cpu().numpy()
                render_seconds += time.perf_counter() - start
                start = time.perf_counter()
                video.write(frame)
                encode_seconds += time.perf_counter() - start
                if first is None:
                    first = frame
                if frames_dir is not None:
                    write_png(frames_dir / f"frame_{k:05d}.png", frame)
    except (MemoryError, torch.OutOfMemoryError) as exc:
        raise PipelineError(f"out of memory rendering video frames of {frame_w * len(layers)}x{frame_h} pixels on "
                            f"{info['device']}", fix="pass a smaller --width (video.width)") from exc
    usage = clock.read()
    if poster is not None:
        write_png(poster, first, software=POSTER_SOFTWARE)
    info.update({"render_seconds_per_frame": render_seconds / frames, "encode_seconds_per_frame":
                 encode_seconds / frames, "seconds_per_frame": (render_seconds + encode_seconds) / frames,
                 "cpu_seconds_per_frame": usage.cpu_seconds / frames, "timing": usage.to_dict()})
    return info


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser, __doc__, "the MP4 file to write (replaced atomically)")
    parser.add_argument("--path", choices=("orbit", "spiral", "interpolate"),
                        help="override video.path: the camera path (default orbit)")
    parser.add_argument("--frames", type=int, help="override video.frames: frames of the video (default 60)")
    parser.add_argument("--fps", type=float, help="override video.fps: frames per second of the MP4 (default 24)")
    parser.add_argument("--width", type=int, help="override video.width: frame width in pixels (default: the "
                        "training cameras' width)")
    parser.add_argument("--panels", action=argparse.BooleanOptionalAction, default=None,
                        help="override video.panels: image | reflection | transmission | normal | depth side by side")
    parser.add_argument("--poster", type=Path, help="also write the first frame to this PNG")
    parser.add_argument("--keep-frames", type=Path, metavar="DIR", help="also write every frame as a PNG into DIR")
    parser.add_argument("--edit", action="append", default=[], metavar="KEY=VALUE",
                        help="scene edit, repeatable: roughness=S, transparency=S, reflections=off, tint=R,G,B")
    parser.add_argument("--backend", default="auto",
                        help="rasterizer backend (auto: triton on a GPU, else cpu; cpu, triton, reference)")
    parser.add_argument("--device", help="override video.device: auto, cpu, cuda, cuda:N")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "video", {"path": args.path, "frames": args.frames, "fps": args.fps,
                                                 "width": args.width, "panels": args.panels, "device": args.device})
    edits = Edits.parse(args.edit)
    resolve_device(cfg.device, key="--device" if args.device is not None else "video.device")
    info = render_video(args.run, args.data, args.out, path=cfg.path, frames=cfg.frames, fps=cfg.fps,
                        width=cfg.width, panels=cfg.panels, edits=edits, backend=args.backend, device=cfg.device,
                        poster=args.poster, keep_frames=args.keep_frames, progress=not args.quiet)
    print(f"wrote {args.out}: {info['frames']} frames of {info['width']}x{info['height']} ({cfg.path} path), "
          f"{info['seconds_per_frame']:.3f} s per frame on {info['device']}")
    return 0
