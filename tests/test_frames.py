"""Photos taken from a scene's video (rtsplat frames): the sharpest frame of each stretch, upright, named by its
index in the video, written to images/ once and atomically."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("av")
cv2 = pytest.importorskip("cv2")

from rtsplat.cli import main as cli_main  # noqa: E402
from rtsplat.config import FramesConfig  # noqa: E402
from rtsplat.frames import extract_frames, frames_for_scene, sharpness, upright, windows  # noqa: E402
from rtsplat.io.video import Mp4Writer  # noqa: E402

FPS = 10.0
SHARP = (3, 14, 27)  # the one sharp frame of each stretch of ten; the others are blurred


def _frames(n: int = 30) -> list[np.ndarray]:
    """Frames of a textured scene sliding to the right; all blurred but those of SHARP."""
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (8, 30, 3), dtype=np.uint8), (240, 64), interpolation=cv2.INTER_NEAREST)
    frames = []
    for i in range(n):
        frame = np.ascontiguousarray(texture[:, 3 * i: 3 * i + 96])
        frames.append(frame if i in SHARP else cv2.GaussianBlur(frame, (0, 0), 2.5))
    return frames


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("video") / "walk.mp4"
    with Mp4Writer(path, 96, 64, FPS) as writer:
        for frame in _frames():
            writer.write(frame)
    return path


def _scene(tmp_path: Path, video: Path, name: str = "walk.mp4") -> Path:
    scene = tmp_path / "scene"
    scene.mkdir()
    shutil.copy(video, scene / name)
    return scene


def test_the_sharpest_frame_of_each_stretch_is_written_by_its_index(video, tmp_path, capsys):
    scene = _scene(tmp_path, video)
    assert cli_main(["frames", "--scene-dir", str(scene), "--count", "3"]) == 0
    assert sorted(p.name for p in (scene / "images").iterdir()) == [f"frame_{i:05d}.jpg" for i in SHARP]
    assert "3 of 30 frames of walk.mp4 written to images/" in capsys.readouterr().out
    frames = _frames()
    for i in SHARP:
        written = cv2.imread(str(scene / "images" / f"frame_{i:05d}.jpg"))[..., ::-1]
        assert written.shape == (64, 96, 3)
        error = np.abs(written.astype(float) - frames[i]).mean()
        assert error < np.abs(written.astype(float) - frames[i - 1]).mean() / 2  # the sharp frame, not a neighbour
    # once: a second run leaves images/ as it is, and says how to extract again
    (scene / "images" / "frame_00003.jpg").unlink()
    assert cli_main(["frames", "--scene-dir", str(scene), "--count", "3"]) == 0
    assert "remove it to extract the video again" in capsys.readouterr().out
    assert len(list((scene / "images").iterdir())) == 2


def test_frames_every_so_many_seconds_and_the_same_names_each_time(video, tmp_path):
    first = extract_frames(video, tmp_path / "a" / "images", FramesConfig(every=1.0))
    again = extract_frames(video, tmp_path / "b" / "images", FramesConfig(every=1.0))
    assert first.names == again.names == [f"frame_{i:05d}.jpg" for i in SHARP]
    assert first.video_frames == 30 and first.fps == pytest.approx(FPS)
    assert min(first.sharpness) > 0
    assert windows(30, FPS, FramesConfig(every=0.5)).max() == 5  # six stretches of five frames
    assert windows(7, FPS, FramesConfig(count=20)).tolist() == list(range(7))  # never more frames than the video


def test_sharpness_is_larger_for_sharper_frames():
    frame = _frames()[SHARP[0]]
    assert sharpness(frame) > 2 * sharpness(cv2.GaussianBlur(frame, (0, 0), 1.5))


def test_the_rotation_tag_turns_the_frame_upright():
    frame = np.zeros((2, 3, 3), np.uint8)
    frame[0, 0] = 255  # the top-left pixel of a landscape frame
    portrait = upright(frame, -90)  # a phone held upright: the frame is turned clockwise
    assert portrait.shape == (3, 2, 3)
    assert portrait[0, 1].all() and portrait.sum() == 3 * 255  # top-left goes to the top-right corner
    assert upright(frame, 90)[2, 0].all()
    assert upright(frame, 180)[1, 2].all()
    assert upright(frame, 0) is frame


# where the stored frame's red (top-left) and green (top-right) corners are seen, by the display matrix's rotation
# (counter-clockwise degrees, as ffprobe prints it: -90 for a phone filming upright turns the frame clockwise)
SEEN_CORNERS = {-90: ("top-right", "bottom-right"), 90: ("bottom-left", "top-left"),
                180: ("bottom-right", "bottom-left")}


def _corner(image: np.ndarray, corner: str) -> np.ndarray:
    """The mean colour of a 6-pixel square inside ``corner`` of an RGB image."""
    rows = slice(2, 8) if corner.startswith("top") else slice(-8, -2)
    cols = slice(2, 8) if corner.endswith("left") else slice(-8, -2)
    return image[rows, cols].reshape(-1, 3).mean(0)


@pytest.mark.parametrize("rotation", sorted(SEEN_CORNERS))
def test_a_video_with_a_rotation_tag_gives_upright_photos(rotation, tmp_path, capsys):
    """A real MP4 whose stream carries a display matrix (PyAV writes it as a phone does): the photos written are
    the frames as a player shows them: the size turned, the red and green corners where the tag puts them, and
    the same pixels as OpenCV's own FFmpeg gives with its automatic rotation."""
    import av

    width, height = 64, 48
    frames = []
    for i in range(12):  # grey texture moving to the right, a red square top-left and a green one top-right
        rng = np.random.default_rng(i)
        frame = cv2.resize(rng.integers(60, 200, (6, 8, 3), dtype=np.uint8), (width, height),
                           interpolation=cv2.INTER_NEAREST)
        frame[:12, :12], frame[:12, -12:] = (255, 0, 0), (0, 255, 0)
        frames.append(frame)
    scene = tmp_path / "scene"
    scene.mkdir()
    with av.open(str(scene / "walk.mp4"), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.set_display_rotation(rotation)
        for frame in frames + [None]:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24") if frame is not None
                                        else None):
                container.mux(packet)
    with av.open(str(scene / "walk.mp4")) as container:  # the file carries the tag
        assert abs(next(container.decode(video=0)).rotation) == abs(rotation)
    assert cli_main(["frames", "--scene-dir", str(scene), "--count", "2"]) == 0
    written = sorted((scene / "images").iterdir())
    assert len(written) == 2
    turned = rotation % 180 != 0
    player = cv2.VideoCapture(str(scene / "walk.mp4"))  # rotates by the display matrix itself
    assert player.get(cv2.CAP_PROP_ORIENTATION_AUTO) == 1
    shown = []
    while (read := player.read())[0]:
        shown.append(read[1][..., ::-1])
    red, green = SEEN_CORNERS[rotation]
    for path in written:
        image = cv2.imread(str(path))[..., ::-1].astype(float)
        assert image.shape == ((width, height, 3) if turned else (height, width, 3)), path.name
        assert _corner(image, red)[0] > 200 and _corner(image, red)[1:].max() < 60, (path.name, red)
        assert _corner(image, green)[1] > 200 and _corner(image, green)[[0, 2]].max() < 60, (path.name, green)
        index = int(path.stem.split("_")[1])
        assert np.abs(image - shown[index]).mean() < 6, path.name  # as a player shows that frame


def test_a_failed_extraction_leaves_no_images_folder(video, tmp_path, monkeypatch):
    scene = _scene(tmp_path, video)
    calls = []

    def failing(ext, image, params=None):
        calls.append(ext)
        if len(calls) == 2:
            raise RuntimeError("disk gone")
        return real(ext, image, params)

    real = cv2.imencode
    monkeypatch.setattr(cv2, "imencode", failing)
    with pytest.raises(RuntimeError, match="disk gone"):
        frames_for_scene(scene, FramesConfig(count=3))
    assert not (scene / "images").exists()
    assert [p.name for p in scene.iterdir()] == ["walk.mp4"]


@pytest.mark.parametrize("case", ["two videos", "no video", "not a video"])
def test_bad_scene_folders_are_named(case, video, tmp_path, capsys):
    scene = _scene(tmp_path, video)
    if case == "two videos":
        shutil.copy(video, scene / "again.MOV")
    elif case == "no video":
        (scene / "walk.mp4").unlink()
    else:
        (scene / "walk.mp4").write_bytes(b"not a video at all")
    assert cli_main(["frames", "--scene-dir", str(scene)]) == 1
    err = capsys.readouterr().err
    expected = {"two videos": "2 videos in the scene folder (again.MOV, walk.mp4)",
                "no video": "no video in the scene folder", "not a video": "cannot read the video"}[case]
    assert expected in err and "Fix:" in err
    assert not (scene / "images").exists()
