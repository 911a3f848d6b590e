"""MP4 (H.264) writing and reading with PyAV (FFmpeg's libraries, bundled in its wheels with libx264);
:func:`open_video` opens any video PyAV reads (a phone's MP4 or MOV).

:class:`Mp4Writer` encodes RGB frames one at a time into a temporary sibling of the output file that is
renamed into place when the writer closes without error (:func:`rtsplat.io.atomic.atomic_path`), so a
failed or interrupted video leaves no partial MP4 and keeps a previous one. The stream is H.264 in
yuv420p (what browsers play; both sides of the frame must be even) with the index at the front of the
file (``movflags=faststart``), so an HTML5 ``<video>`` starts before the whole file has arrived. The
writer stores ``comment`` in the container's metadata; :func:`mp4_comment` reads it back.
"""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError
from rtsplat.io.atomic import atomic_path
from rtsplat.io.images import to_uint

CODEC = "libx264"
RTSPLAT_COMMENT = "rtsplat video "  # how the comment of an MP4 that rtsplat video wrote begins (then its settings)
QUALITY_CRF = 18  # x264's constant rate factor: 18 is visually close to lossless


def _av():
    try:
        import av
    except ImportError:
        raise PipelineError("writing MP4 videos needs PyAV, which is not installed",
                            fix="pip install 'av>=18.1' (part of the pipeline extra: pip install -e '.[pipeline]')"
                            ) from None
    return av


class Mp4Writer:
    """``with Mp4Writer(path, width, height, fps) as video: video.write(frame)``; frames are float RGB
    ``[height, width, 3]`` in [0, 1] (clipped) or uint8."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float, comment: str = ""):
        if width % 2 or height % 2 or width <= 0 or height <= 0:
            raise ValueError(f"H.264 frames need an even, positive size, got {width}x{height}")
        self.path, self.width, self.height, self.fps, self.comment = Path(path), width, height, fps, comment
        self.frames = 0
        self._stack = ExitStack()

    def __enter__(self) -> Mp4Writer:
        av = _av()
        from fractions import Fraction

        tmp = self._stack.enter_context(atomic_path(self.path))
        try:
            self._container = av.open(str(tmp), "w", format="mp4", options={"movflags": "faststart"})
            if self.comment:
                self._container.metadata["comment"] = self.comment
            self._stream = self._container.add_stream(CODEC, rate=Fraction(self.fps).limit_denominator(1001))
            self._stream.width, self._stream.height, self._stream.pix_fmt = self.width, self.height, "yuv420p"
            self._stream.options = {"crf": str(QUALITY_CRF)}
        except BaseException as err:
            self._stack.__exit__(type(err), err, err.__traceback__)  # removes the temporary file
            raise
        return self

    def write(self, frame: np.ndarray) -> None:
        av = _av()
        frame = np.asarray(frame)
        if frame.shape != (self.height, self.width, 3):
            raise ValueError(f"frame of shape {frame.shape}, the video is {self.height}x{self.width}x3")
        pixels = frame if frame.dtype == np.uint8 else to_uint(np.clip(frame, 0.0, 1.0), 8)
        for packet in self._stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(pixels), format="rgb24")):
            self._container.mux(packet)
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if exc_type is None:
                for packet in self._stream.encode():  # flush the encoder's delayed frames
                    self._container.mux(packet)
            self._container.close()
        except BaseException as err:
            self._stack.__exit__(type(err), err, err.__traceback__)  # removes the temporary file
            raise
        return bool(self._stack.__exit__(exc_type, exc, tb))


def open_video(path: str | Path):
    """``(container, stream)``: the opened video file and its first video stream (close the container, e.g. ``with
    container:``); :class:`PipelineError` naming the file when it is no video PyAV can read."""
    av = _av()
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError, ValueError) as err:
        raise PipelineError(f"cannot read the video ({err})", path=path,
                            fix="check the file is a complete MP4 or MOV video (copy it again)") from None
    if not container.streams.video:
        container.close()
        raise PipelineError("the file has no video stream", path=path, fix="use the video file of the capture")
    return container, container.streams.video[0]


def read_mp4(path: str | Path) -> tuple[np.ndarray, float]:
    """Every frame of the first video stream as uint8 RGB ``[frames, height, width, 3]`` and the frame rate."""
    av = _av()
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
        rate = float(stream.average_rate or stream.base_rate or 0)
    return np.stack(frames), rate


def mp4_comment(path: str | Path) -> str | None:
    """The ``comment`` metadata of an MP4, None when the file is not a video PyAV can open."""
    av = _av()
    try:
        with av.open(str(path)) as container:
            return container.metadata.get("comment")
    except (av.error.FFmpegError, OSError, ValueError):
        return None
