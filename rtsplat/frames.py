"""The ``rtsplat frames`` stage: a scene folder that holds a video (``*.mp4``, ``*.mov``) instead of ``images/``
gets its photos from it, once, so that every later stage reads ``images/`` as for photos.

The video is cut into equal stretches (``frames.count`` of them, or one per ``frames.every`` seconds) and the
sharpest frame of each stretch is kept (:func:`sharpness`, the variance of the Laplacian of its grey image at
most :data:`SHARPNESS_SIDE` pixels on its long side), so a frame blurred by the walk's motion gives way to a
sharper neighbour. Each kept frame is turned upright as the video's rotation tag says (a phone filming in
portrait stores landscape frames and the tag) and written as ``frame_<index>.jpg``, its index in the video
(from 0, five digits or more), so the same video and settings always give the same names: the names that
``masks.marks`` marks. The frames are written into a temporary folder renamed to ``images/`` at the end
(:func:`rtsplat.io.atomic.atomic_dir`), so a failed or interrupted extraction leaves no ``images/``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsplat.config import FramesConfig, PipelineConfig, add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.video import open_video

VIDEO_EXTENSIONS = (".mp4", ".mov")
SHARPNESS_SIDE = 480  # long side of the grey image whose Laplacian measures a frame's sharpness


@dataclass
class Extracted:
    """What :func:`extract_frames` wrote: the video, its frame count and rate, and per kept frame its name,
    index in the video and sharpness."""

    video: str
    video_frames: int
    fps: float
    names: list[str]
    indices: list[int]
    sharpness: list[float]


def find_video(scene_dir: str | Path) -> Path | None:
    """The scene's one video (a file ``*.mp4`` or ``*.mov`` directly in it, any case); None without one;
    :class:`PipelineError` naming them when there are several."""
    videos = sorted(p for p in Path(scene_dir).iterdir() if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS)
    if len(videos) > 1:
        raise PipelineError(
            f"{len(videos)} videos in the scene folder ({', '.join(p.name for p in videos)}): a scene is one capture",
            path=scene_dir, fix="keep one video per scene folder (put each other video in a scene folder of its own)",
        )
    return videos[0] if videos else None


def sharpness(rgb: np.ndarray) -> float:
    """The variance of the Laplacian of ``rgb``'s (uint8 [H, W, 3]) grey image scaled to at most
    :data:`SHARPNESS_SIDE` pixels on its long side: larger for sharper frames."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    scale = SHARPNESS_SIDE / max(grey.shape)
    if scale < 1.0:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def upright(rgb: np.ndarray, rotation: int) -> np.ndarray:
    """``rgb`` turned counter-clockwise by ``rotation`` degrees (a multiple of 90, as a video's display matrix
    gives it: -90 for a phone held upright)."""
    turns = int(round(rotation / 90.0)) % 4
    return np.ascontiguousarray(np.rot90(rgb, turns)) if turns else rgb


def _frame_count(video: Path) -> tuple[int, float]:
    """The video's frame count (its packets, counted when the container does not say) and frame rate."""
    container, stream = open_video(video)
    with container:
        rate = float(stream.average_rate or stream.base_rate or 0.0)
        count = int(stream.frames or 0)
        if count <= 0:
            count = sum(1 for packet in container.demux(stream) if packet.size)
    return count, rate


def windows(total: int, fps: float, cfg: FramesConfig) -> np.ndarray:
    """The stretch [total] each frame belongs to: ``cfg.count`` equal stretches, or one per ``cfg.every`` seconds
    (at least one)."""
    count = cfg.count or max(1, int(round(total / max(fps * cfg.every, 1.0))))
    count = max(1, min(count, total))
    return np.minimum((np.arange(total) * count) // max(total, 1), count - 1)


def _sharpest(video: Path, stretch: np.ndarray) -> Iterator[tuple[int, float, np.ndarray]]:
    """(index, sharpness, upright RGB) of the sharpest frame of each stretch, in order, as the decoding passes it
    (one stretch's best frame held at a time)."""
    container, stream = open_video(video)
    with container:
        best = None
        for index, frame in enumerate(container.decode(stream)):
            if index >= len(stretch):
                break
            if best is not None and stretch[best[0]] != stretch[index]:
                yield best
                best = None
            rgb = frame.to_ndarray(format="rgb24")
            score = sharpness(rgb)
            if best is None or score > best[1]:
                best = (index, score, upright(rgb, int(getattr(frame, "rotation", 0) or 0)))
        if best is not None:
            yield best


def extract_frames(video: str | Path, images_dir: str | Path, cfg: FramesConfig | None = None,
                   log=None) -> Extracted:
    """The sharpest frame of each stretch of ``video`` written upright as JPEG into ``images_dir`` (atomically)."""
    import cv2

    from rtsplat.io.atomic import atomic_dir, write_bytes_atomic

    cfg = cfg or FramesConfig()
    video, images_dir = Path(video), Path(images_dir)
    total, rate = _frame_count(video)
    if total == 0:
        raise PipelineError("the video has no frames", path=video, fix="use the video file of the capture")
    digits = max(5, len(str(total - 1)))
    names, indices, scores = [], [], []
    with atomic_dir(images_dir) as tmp:
        for index, score, rgb in _sharpest(video, windows(total, rate, cfg)):
            name = f"frame_{index:0{digits}d}.jpg"
            ok, data = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, cfg.quality])
            if not ok:
                raise PipelineError(f"cannot encode frame {index} as JPEG", path=video,
                                    fix="check the video decodes (e.g. play it)")
            write_bytes_atomic(tmp / name, data.tobytes())
            names.append(name)
            indices.append(index)
            scores.append(score)
    if log:
        log(f"frames {video}: {len(names)} of {total} frames ({rate:.3g} fps) written to {images_dir}, the sharpest "
            "of each stretch")
    return Extracted(video.name, total, rate, names, indices, scores)


def frames_for_scene(scene_dir: str | Path, cfg: FramesConfig | None = None, log=None) -> Extracted | None:
    """Extract the scene's video into ``<scene_dir>/images`` when the folder holds a video and no ``images/``
    (:func:`extract_frames`); None when there is nothing to do (``images/`` exists, or no video)."""
    scene_dir = Path(scene_dir)
    if (scene_dir / "images").exists():
        return None
    video = find_video(scene_dir)
    if video is None:
        return None
    return extract_frames(video, scene_dir / "images", cfg, log)


def extract_video_scenes(cfg: PipelineConfig, log=None) -> list[str]:
    """Before the workflow finds its scenes: every scene folder of ``cfg.data`` (the listed scenes, else every
    folder) that holds a video and no ``images/`` gets its frames (:func:`frames_for_scene`, with the scene's
    ``frames`` settings); returns the scenes extracted."""
    from rtsplat.config import scene_config

    data = Path(cfg.data)
    if cfg.scenes:
        folders = [data / scene for scene in cfg.scenes]
    else:
        folders = sorted(p for p in data.iterdir() if p.is_dir()) if data.is_dir() else []
    done = []
    for folder in folders:
        if folder.is_dir() and frames_for_scene(folder, scene_config(cfg, folder.name).frames, log) is not None:
            done.append(folder.name)
    return done


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True,
                        help="dataset scene (<data>/<scene>) holding one video (*.mp4, *.mov) and no images/")
    parser.add_argument("--count", type=int, help="override frames.count")
    parser.add_argument("--every", type=float, help="override frames.every (seconds)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "frames", {"count": args.count, "every": args.every})
    if not args.scene_dir.is_dir():
        raise PipelineError("scene folder not found", path=args.scene_dir,
                            fix="pass the folder that holds the video as --scene-dir")
    if (args.scene_dir / "images").exists():
        print(f"frames {args.scene_dir}: images/ exists, nothing to extract (remove it to extract the video again)")
        return 0
    extracted = frames_for_scene(args.scene_dir, cfg)
    if extracted is None:
        raise PipelineError("no video in the scene folder", path=args.scene_dir,
                            fix=f"put the capture's video ({', '.join(VIDEO_EXTENSIONS)}) there, or its photos in "
                            "images/")
    print(f"frames {args.scene_dir}: {len(extracted.names)} of {extracted.video_frames} frames of "
          f"{extracted.video} written to images/ ({extracted.names[0]} ... {extracted.names[-1]})")
    return 0
