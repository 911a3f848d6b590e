"""A catalogue of bad inputs, by stage: each case runs ``rtsplat <stage>`` in-process on a copy of a
tiny scene and its stage outputs, and checks the exit status 1, that the message names the file or
key at fault, and that no file or folder under the copy changed (inputs and earlier outputs intact,
nothing partial left behind). The write failures (a read-only folder, a full disk, a file or a folder
in the way) are simulated with :mod:`write_faults`; training writes its run folder in place (what a
killed run resumes from), so there only that folder may appear, without temporary files."""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from fixtures_pipeline import make_corner_scene  # noqa: E402
from write_faults import no_space, read_only  # noqa: E402

from rtsplat.cli import main  # noqa: E402
from rtsplat.io.outputs import mark_output  # noqa: E402


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """``scene/`` (4 views of 40x30, sparse/0, transparent_masks) and its stage outputs under ``res/``:
    masks, sfm, prepared and a run folder marked as the train stage's."""
    root = tmp_path_factory.mktemp("bad_inputs")
    make_corner_scene(root / "scene", n_views=4, width=40, height=30, with_model=True, with_masks=True)
    assert main(["masks", "--scene-dir", str(root / "scene"), "--out", str(root / "res/masks")]) == 0
    assert main(["sfm", "--scene-dir", str(root / "scene"), "--out", str(root / "res/sfm")]) == 0
    assert main(["prepare", "--scene-dir", str(root / "scene"), "--sfm", str(root / "res/sfm"), "--masks",
                 str(root / "res/masks"), "--out", str(root / "res/prepared")]) == 0
    (root / "res/run").mkdir()
    mark_output(root / "res/run", "train")
    (root / "res/run/model.pt").write_bytes(b"a trained model")
    (root / "user").mkdir()
    (root / "user/notes.txt").write_text("the user's own file")
    (root / "a_file").write_text("not a folder")
    make_corner_scene(root / "other_scene", n_views=2, width=40, height=30)
    # another scene (other photos: JPEGs of other views) and its stage outputs under res/other/
    make_corner_scene(root / "scene_b", n_views=5, width=40, height=30, with_model=True, with_masks=True, ext=".jpg")
    assert main(["masks", "--scene-dir", str(root / "scene_b"), "--out", str(root / "res/other/masks")]) == 0
    assert main(["sfm", "--scene-dir", str(root / "scene_b"), "--out", str(root / "res/other/sfm")]) == 0
    assert main(["prepare", "--scene-dir", str(root / "scene_b"), "--sfm", str(root / "res/other/sfm"), "--masks",
                 str(root / "res/other/masks"), "--out", str(root / "res/other/prepared")]) == 0
    # a real run of two iterations on res/prepared, its resumable checkpoint kept as a killed run leaves it
    assert main(["train", "--data", str(root / "res/prepared"), "--out", str(root / "res/trained"), "--quiet",
                 "--config-json", TINY_TRAINING]) == 0
    assert main(["render", "--run", str(root / "res/trained"), "--data", str(root / "res/prepared"), "--out",
                 str(root / "res/renders"), "--quiet"]) == 0
    for args, out in ((METRICS_ARGS, "res/metrics.json"), (FPS_ARGS, "res/fps.json")):
        assert main([a.replace("{R}", str(root)) for a in args] + [str(root / out)]) == 0
    results = root / "results/corner"  # the workflow's layout, for the report
    for src, dst in (("res/trained", "runs/rtsplat"), ("res/renders", "renders/rtsplat"), ("res/prepared", "prepared")):
        shutil.copytree(root / src, results / dst)
    (results / "metrics").mkdir()
    shutil.copy(root / "res/metrics.json", results / "metrics/rtsplat.json")
    (root / "ro").mkdir()
    return root


TINY_TRAIN = ('{"schedule": {"iterations": 2, "checkpoint_every": 1, "eval_every": 0}, '
              '"cameras": {"test_fit_steps": 0, "final_fit_steps": 0}}')


def tree_state(root: Path) -> dict[str, str]:
    """Every file (by content hash) and folder under ``root``."""
    state = {}
    for path in sorted(root.rglob("*")):
        rel = str(path.relative_to(root))
        state[rel] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "<dir>"
    return state


@dataclass
class Case:
    argv: list[str]  # "{R}" stands for the copy's root
    expect: list[str]  # each appears in the error message ("{R}" substituted)
    setup: Callable[[Path], None] | None = None
    marks: list = field(default_factory=list)
    fault: str | None = None  # a key of FAULTS: how writing fails
    fault_at: str = "ro"  # the folder (relative to the root) where it fails
    may_create: str | None = None  # a folder (relative) that may appear: a training run written in place
    entry: str = "rtsplat"  # the command: "rtsplat" (rtsplat.cli) or a module of `python -m`, e.g. rtsplat.demo


def patch(rel: str, offset: int, fmt: str, *values) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        data = bytearray((root / rel).read_bytes())
        struct.pack_into(fmt, data, offset, *values)
        (root / rel).write_bytes(bytes(data))
    return apply


def truncate(rel: str, keep: float | int) -> Callable[[Path], None]:
    """Keep the first ``keep`` bytes (an int) or that fraction of the file (a float)."""
    def apply(root: Path) -> None:
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: keep if isinstance(keep, int) else int(len(data) * keep)])
    return apply


def write(rel: str, text: str) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return apply


TINY_TRAINING = json.dumps({
    "schedule": {"iterations": 2, "volume_until": 1, "specular_from": 2, "densify_from": 1000, "reset_every": 0,
                 "checkpoint_every": 1, "eval_every": 0, "log_every": 1},
    "model": {"env_height": 8, "env_width": 16, "env_levels": 2, "mlp_width": 8},
    "cameras": {"final_fit_steps": 0, "test_fit_steps": 0},
})
METRICS_ARGS = ["metrics", "--renders", "{R}/res/renders", "--data", "{R}/res/prepared", "--out"]
FPS_ARGS = ["fps", "--run", "{R}/res/trained", "--data", "{R}/res/prepared", "--rounds", "1", "--warmup", "0", "--out"]
SFM = ["sfm", "--scene-dir", "{R}/scene", "--out"]
MASKS = ["masks", "--scene-dir", "{R}/scene", "--out"]
PREPARE = ["prepare", "--scene-dir", "{R}/scene", "--sfm", "{R}/res/sfm", "--masks", "{R}/res/masks", "--out"]
TRAIN = ["train", "--data", "{R}/res/prepared", "--quiet", "--out"]
RENDER = ["render", "--run", "{R}/res/run", "--data", "{R}/res/prepared", "--quiet", "--out"]
REPORT = ["report", "--results", "{R}/res", "--out"]
MODEL = "scene/sparse/0"
# offsets in the binary files the fixture writes: cameras.bin holds one PINHOLE camera
# (count u64, id i32, model i32, width u64, height u64, fx fy cx cy f64), images.bin starts with
# (count u64, id i32, qvec, tvec f64 x 7, camera id i32), points3D.bin with (count u64, id u64, xyz f64 x 3)
CAM_FX, CAM_CX, CAM_MODEL, IMAGE_CAMERA, POINT_X = 32, 48, 12, 68, 16

OUTPUT_CASES = {
    # sfm
    "sfm out is the scene": Case([*SFM, "{R}/scene"], ["{R}/scene", "is the sfm input"]),
    "sfm out is the scene's sparse/0": Case([*SFM, "{R}/scene/sparse/0"], ["{R}/scene/sparse/0", "inside"]),
    "sfm out contains the scene": Case([*SFM, "{R}"], ["contains the sfm input"]),
    "sfm out is the masks output": Case([*SFM, "{R}/res/masks"], ["{R}/res/masks", "'rtsplat masks'"]),
    "sfm out inside the prepared output": Case([*SFM, "{R}/res/prepared/sfm"], ["'rtsplat prepare'"]),
    "sfm out is a user folder": Case([*SFM, "{R}/user"], ["{R}/user", ".rtsplat-output"]),
    "sfm out is a file": Case([*SFM, "{R}/a_file"], ["{R}/a_file", "not a folder"]),
    "sfm out is another dataset": Case([*SFM, "{R}/other_scene"], ["{R}/other_scene", "dataset folder"]),
    "sfm masks input inside out": Case([*SFM, "{R}/res", "--masks", "{R}/res/masks"], ["contains the sfm input"]),
    # masks
    "masks out is the scene's masks": Case([*MASKS, "{R}/scene/transparent_masks"],
                                           ["{R}/scene/transparent_masks", "inside the masks input"]),
    "masks out is the scene": Case([*MASKS, "{R}/scene"], ["is the masks input"]),
    "masks out is the sfm output": Case([*MASKS, "{R}/res/sfm"], ["'rtsplat sfm'"]),
    "masks out inside another dataset": Case([*MASKS, "{R}/other_scene/masks"], ["dataset folder {R}/other_scene"]),
    "masks out is a user folder": Case([*MASKS, "{R}/user"], [".rtsplat-output"]),
    "masks out is the results root": Case([*MASKS, "{R}/res"], ["{R}/res", "not empty"]),
    # prepare
    "prepare out is the scene": Case([*PREPARE, "{R}/scene"], ["{R}/scene", "is the prepare input"]),
    "prepare out is the sfm output": Case([*PREPARE, "{R}/res/sfm"], ["is the prepare input {R}/res/sfm"]),
    "prepare out is the masks output": Case([*PREPARE, "{R}/res/masks"], ["is the prepare input {R}/res/masks"]),
    "prepare out inside the sfm output": Case([*PREPARE, "{R}/res/sfm/prepared"], ["inside the prepare input"]),
    "prepare out contains its inputs": Case([*PREPARE, "{R}/res"], ["contains the prepare input"]),
    "prepare out inside the scene": Case([*PREPARE, "{R}/scene/prepared"], ["inside the prepare input"]),
    "prepare out is the run": Case([*PREPARE, "{R}/res/run"], ["'rtsplat train'"]),
    # train
    "train out is the prepared scene": Case([*TRAIN, "{R}/res/prepared"], ["is the train input"]),
    "train out inside the prepared scene": Case([*TRAIN, "{R}/res/prepared/run"], ["inside the train input"]),
    "train out is the dataset": Case([*TRAIN, "{R}/scene"], ["{R}/scene", "dataset folder"]),
    "train out is the sfm output": Case([*TRAIN, "{R}/res/sfm"], ["'rtsplat sfm'"]),
    "train out is a user folder": Case([*TRAIN, "{R}/user"], [".rtsplat-output"]),
    # render
    "render out is the run": Case([*RENDER, "{R}/res/run"], ["{R}/res/run", "is the render input"]),
    "render out is the prepared scene": Case([*RENDER, "{R}/res/prepared"], ["is the render input"]),
    "render out inside the run": Case([*RENDER, "{R}/res/run/renders"], ["inside the render input"]),
    "render out contains the run": Case([*RENDER, "{R}/res"], ["contains the render input"]),
    "render out inside the dataset": Case([*RENDER, "{R}/scene/renders"], ["dataset folder {R}/scene"]),
    # report
    "report out is the results": Case([*REPORT, "{R}/res"], ["is the report input"]),
    "report out contains the results": Case(["report", "--results", "{R}/res/sfm", "--out", "{R}/res"],
                                            ["contains the report input"]),
    "report out inside the dataset": Case([*REPORT, "{R}/scene/report"], ["dataset folder {R}/scene"]),
    "report out is the masks output": Case([*REPORT, "{R}/res/masks"], ["'rtsplat masks'"]),
}

MODEL_CASES = {
    "empty cameras.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/cameras.bin", "empty"],
                              write(f"{MODEL}/cameras.bin", "")),
    "empty images.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/images.bin", "empty"],
                             write(f"{MODEL}/images.bin", "")),
    "empty points3D.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/points3D.bin", "empty"],
                               write(f"{MODEL}/points3D.bin", "")),
    "truncated cameras.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/cameras.bin", "truncated"],
                                  truncate(f"{MODEL}/cameras.bin", 0.7)),
    "truncated images.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/images.bin", "truncated"],
                                 truncate(f"{MODEL}/images.bin", 0.5)),
    "truncated points3D.bin": Case([*SFM, "{R}/res/new"], [f"{MODEL}/points3D.bin", "truncated"],
                                   truncate(f"{MODEL}/points3D.bin", 0.5)),
    "points3D.bin with a count and nothing else": Case([*SFM, "{R}/res/new"], [f"{MODEL}/points3D.bin", "declares"],
                                                       truncate(f"{MODEL}/points3D.bin", 8)),
    "huge declared point count": Case([*SFM, "{R}/res/new"], [f"{MODEL}/points3D.bin", "declares 1000000000000"],
                                      patch(f"{MODEL}/points3D.bin", 0, "<Q", 10**12)),
    "unknown camera model id": Case([*SFM, "{R}/res/new"], [f"{MODEL}/cameras.bin", "unknown camera model id 999"],
                                    patch(f"{MODEL}/cameras.bin", CAM_MODEL, "<i", 999)),
    "image with an unknown camera": Case([*SFM, "{R}/res/new"], [f"{MODEL}/images.bin", "refers to camera 7"],
                                         patch(f"{MODEL}/images.bin", IMAGE_CAMERA, "<i", 7)),
    "negative focal length": Case([*SFM, "{R}/res/new"], [MODEL, "camera 1", "focal length"],
                                  patch(f"{MODEL}/cameras.bin", CAM_FX, "<d", -50.0)),
    "zero focal length": Case([*SFM, "{R}/res/new"], [MODEL, "focal length"],
                              patch(f"{MODEL}/cameras.bin", CAM_FX, "<d", 0.0)),
    "NaN focal length": Case([*SFM, "{R}/res/new"], [MODEL, "camera 1", "non-finite"],
                             patch(f"{MODEL}/cameras.bin", CAM_FX, "<d", float("nan"))),
    "principal point outside the image": Case([*SFM, "{R}/res/new"], [MODEL, "principal point"],
                                              patch(f"{MODEL}/cameras.bin", CAM_CX, "<d", 5000.0)),
    "negative principal point": Case([*SFM, "{R}/res/new"], [MODEL, "principal point"],
                                     patch(f"{MODEL}/cameras.bin", CAM_CX, "<d", -3.0)),
    "NaN 3D point": Case([*SFM, "{R}/res/new"], [MODEL, "non-finite position"],
                         patch(f"{MODEL}/points3D.bin", POINT_X, "<d", float("nan"))),
    "infinite 3D point": Case([*SFM, "{R}/res/new"], [MODEL, "non-finite position"],
                              patch(f"{MODEL}/points3D.bin", POINT_X, "<d", float("inf"))),
    "NaN pose": Case([*SFM, "{R}/res/new"], [MODEL, "pose", "not finite"],
                     patch(f"{MODEL}/images.bin", IMAGE_CAMERA - 8, "<d", float("nan"))),
    "prepare: truncated sfm points3D.bin": Case([*PREPARE, "{R}/res/new"],
                                                ["res/sfm/sparse/0/points3D.bin", "truncated"],
                                                truncate("res/sfm/sparse/0/points3D.bin", 0.5)),
    "prepare: empty sfm cameras.bin": Case([*PREPARE, "{R}/res/new"], ["res/sfm/sparse/0/cameras.bin", "empty"],
                                           write("res/sfm/sparse/0/cameras.bin", "")),
}

TRAIN_NEW = [*TRAIN, "{R}/res/new_run"]


def train_yaml(text: str) -> Callable[[Path], None]:
    return write("train.yaml", "train:\n" + text)


def train_yaml_case(expected: list[str], text: str) -> Case:
    """A new training run whose --config file has ``train:`` followed by ``text``."""
    return Case([*TRAIN_NEW, "--config", "{R}/train.yaml"], expected, train_yaml(text))


CONFIG_CASES = {
    "iterations NaN": train_yaml_case(["train.schedule.iterations", "nan"], "  schedule: {iterations: .nan}\n"),
    "iterations infinite": train_yaml_case(["train.schedule.iterations", "inf"], "  schedule: {iterations: .inf}\n"),
    "iterations 10.5": train_yaml_case(["train.schedule.iterations", "integer"], "  schedule: {iterations: 10.5}\n"),
    "iterations 0": train_yaml_case(["train.schedule.iterations", "minimum"], "  schedule: {iterations: 0}\n"),
    "iterations a word": train_yaml_case(["train.schedule.iterations", "ten"], "  schedule: {iterations: ten}\n"),
    "lr infinite": train_yaml_case(["train.lr.occupancy", "inf"], "  lr: {occupancy: .inf}\n"),
    "lr NaN": train_yaml_case(["train.lr.opacity", "nan"], "  lr: {opacity: .nan}\n"),
    "lr negative": train_yaml_case(["train.lr.scaling", "minimum"], "  lr: {scaling: -0.001}\n"),
    "position lr zero": train_yaml_case(["train.lr.position_init"], "  lr: {position_init: 0}\n"),
    "lr -inf in JSON": Case([*TRAIN_NEW, "--config-json", '{"lr": {"mlp": -Infinity}}'], ["train.lr.mlp", "-inf"]),
    "unknown lr key": Case([*TRAIN_NEW, "--config-json", '{"lr": {"means": 0.1}}'],
                           ["train.lr.means", "position_init"]),
    "negative seed": Case([*TRAIN_NEW, "--config-json", '{"seed": -1}'], ["train.seed"]),
    "bogus backend in config": Case([*TRAIN_NEW, "--config-json", '{"backend": "bogus"}'],
                                    ["train.backend", "bogus", "reference", "cpu"]),
    "bogus --backend": Case([*TRAIN_NEW, "--backend", "bogus"], ["train.backend", "bogus", "reference"]),
    "--iterations 0": Case([*TRAIN_NEW, "--iterations", "0"], ["train.schedule.iterations"]),
    "--config-json not JSON": Case([*TRAIN_NEW, "--config-json", "{lr"], ["--config-json", "JSON"]),
    "--config missing": Case([*TRAIN_NEW, "--config", "{R}/nowhere.yaml"], ["{R}/nowhere.yaml"]),
    "volume_until after specular_from": Case(
        [*TRAIN_NEW, "--config-json", '{"schedule": {"volume_until": 50, "specular_from": 10}}'],
        ["volume_until", "specular_from"]),
    "render --backend bogus": Case([*RENDER, "{R}/res/new", "--backend", "bogus"],
                                   ["--backend", "bogus", "reference", "cpu"]),
    "ROI NaN centre": Case([*PREPARE, "{R}/res/new", "--config-json",
                            '{"roi": {"center": [NaN, 0, 0], "radius": 1.0}}'], ["roi.center", "nan"]),
    "ROI infinite radius": Case([*PREPARE, "{R}/res/new", "--config-json",
                                 '{"roi": {"center": [0, 0, 0], "radius": Infinity}}'], ["roi.radius", "inf"]),
    "ROI negative radius": Case([*PREPARE, "{R}/res/new", "--config-json",
                                 '{"roi": {"center": [0, 0, 0], "radius": -1}}'], ["roi.radius"]),
    "ROI centre of 2 numbers": Case([*PREPARE, "{R}/res/new", "--config-json",
                                     '{"roi": {"center": [0, 0], "radius": 1}}'], ["roi.center"]),
    "prepare downsample 0": Case([*PREPARE, "{R}/res/new", "--downsample", "0"], ["downsample"]),
    "prepare downsample larger than the images": Case([*PREPARE, "{R}/res/new", "--downsample", "100"],
                                                      ["prepare.downsample 100", "40x30", "at most 30"]),
    "prepare resolution 0": Case([*PREPARE, "{R}/res/new", "--resolution", "0"], ["prepare.resolution", "minimum"]),
    "prepare resolution -5 in the config": Case([*PREPARE, "{R}/res/new", "--config-json", '{"resolution": -5}'],
                                                ["resolution", "minimum"]),
    "prepare test_every 1": Case([*PREPARE, "{R}/res/new", "--config-json", '{"test_every": 1}'], ["test_every"]),
    "masks threshold NaN": Case([*MASKS, "{R}/res/new", "--config-json", '{"threshold": NaN}'], ["threshold", "nan"]),
}

EXISTING_CASES = {
    "sfm without images": Case([*SFM, "{R}/res/new"], ["{R}/scene/images"],
                               lambda root: shutil.rmtree(root / "scene/images")),
    "sfm with a corrupt image": Case([*SFM, "{R}/res/new"], ["view_001.png"],
                                     write("scene/images/view_001.png", "not a png")),
    "sfm model lists a missing image": Case([*SFM, "{R}/res/new"], ["view_002.png"],
                                            lambda root: (root / "scene/images/view_002.png").unlink()),
    "masks ingest without the mask folder": Case([*MASKS, "{R}/res/new", "--source", "ingest"],
                                                 ["{R}/scene/transparent_masks"],
                                                 lambda root: shutil.rmtree(root / "scene/transparent_masks")),
    "masks ingest with a mask missing": Case([*MASKS, "{R}/res/new"], ["view_003"],
                                             lambda root: (root / "scene/transparent_masks/view_003.png").unlink()),
    "masks: a photo as a mask": Case([*MASKS, "{R}/res/new"], ["view_001.png", "does not look like a mask"],
                                     lambda root: shutil.copy(root / "scene/images/view_001.png",
                                                              root / "scene/transparent_masks/view_001.png")),
    "masks: a mask of the wrong size": Case([*MASKS, "{R}/res/new"], ["view_002.png", "30x20"],
                                            lambda root: _crop(root / "scene/transparent_masks/view_002.png")),
    "masks: a mask without an image": Case([*MASKS, "{R}/res/new"], ["extra.png", "no matching image"],
                                           lambda root: shutil.copy(root / "scene/transparent_masks/view_000.png",
                                                                    root / "scene/transparent_masks/extra.png")),
    "masks: two masks for one photo": Case([*MASKS, "{R}/res/new"], ["view_001.jpg and view_001.png"],
                                           lambda root: shutil.copy(root / "scene/transparent_masks/view_001.png",
                                                                    root / "scene/transparent_masks/view_001.jpg")),
    "masks: no mask matches a photo": Case([*MASKS, "{R}/res/new"],
                                           ["none of the 4 masks matches a photo", "view_000.png", "mask_0.png"],
                                           lambda root: _rename_masks(root / "scene/transparent_masks")),
    "masks: unknown polarity": Case([*MASKS, "{R}/res/new", "--config-json", '{"polarity": "inverted"}'],
                                    ["polarity", "white"]),
    "masks: max_coverage 0": Case([*MASKS, "{R}/res/new", "--config-json", '{"max_coverage": 0}'],
                                  ["max_coverage"]),
    "prepare sfm folder without summary": Case([*PREPARE, "{R}/res/new"], ["{R}/res/sfm"],
                                               lambda root: (root / "res/sfm/summary.json").unlink()),
    "prepare image changed since sfm": Case([*PREPARE, "{R}/res/new"], ["--sfm {R}/res/sfm", "view_000.png (changed)"],
                                            lambda root: _crop(root / "scene/images/view_000.png")),
    "train data not prepared": Case(["train", "--data", "{R}/scene", "--out", "{R}/res/new_run", "--quiet"],
                                    ["{R}/scene"]),
    "render run without a model": Case([*RENDER, "{R}/res/new"], ["{R}/res/run/model.pt"],
                                       lambda root: (root / "res/run/model.pt").unlink()),
    "report of a missing results folder": Case(["report", "--results", "{R}/nowhere", "--out", "{R}/res/report"],
                                               ["{R}/nowhere"]),
}


def sideways_jpeg(rel: str, orientation: int, like: str = "scene/images/view_000.png") -> Callable[[Path], None]:
    """Write ``rel``: the photo ``like`` as a phone stores a photo taken sideways (the pixels turned a
    quarter, an EXIF Orientation tag ``orientation`` saying how to turn them back for display)."""
    def apply(root: Path) -> None:
        from PIL import Image

        image = Image.open(root / like).convert("RGB")
        stored = image.transpose(Image.Transpose.ROTATE_90 if orientation == 6 else Image.Transpose.ROTATE_270)
        exif = Image.Exif()
        exif[0x0112] = orientation
        stored.save(root / rel, exif=exif, quality=95)
    return apply


def only_heic(root: Path) -> None:
    for path in (root / "scene/images").iterdir():
        path.with_suffix(".HEIC").write_bytes(b"\0\0\0\x18ftypheic")
        path.unlink()


def nan_surfels(rel: str) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        import torch

        state = torch.load(root / rel, weights_only=False)
        state["model"]["surfels"]["means"][0, 0] = float("nan")
        torch.save(state, root / rel)
    return apply


def roi_center(value: float) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        path = root / "res/prepared/scene.json"
        data = json.loads(path.read_text())
        data["roi"]["center"][0] = value
        path.write_text(json.dumps(data))
    return apply


PHOTO_CASES = {
    "sfm: a photo stored sideways (EXIF orientation 6)": Case(
        [*SFM, "{R}/res/new"], ["{R}/scene/images/view_004.jpg", "Orientation tag is 6", "exiftran -ai"],
        sideways_jpeg("scene/images/view_004.jpg", 6)),
    "sfm: a photo stored sideways (EXIF orientation 8)": Case(
        [*SFM, "{R}/res/new"], ["{R}/scene/images/view_004.jpg", "Orientation tag is 8", "mogrify -auto-orient"],
        sideways_jpeg("scene/images/view_004.jpg", 8)),
    "masks: a photo stored sideways": Case(
        [*MASKS, "{R}/res/new", "--source", "none"], ["{R}/scene/images/view_004.jpg", "Orientation tag is 6"],
        sideways_jpeg("scene/images/view_004.jpg", 6)),
    "masks: a mask stored sideways": Case(
        [*MASKS, "{R}/res/new"], ["{R}/scene/transparent_masks/view_001.jpg", "Orientation tag is 8"],
        lambda root: (sideways_jpeg("scene/transparent_masks/view_001.jpg", 8,
                                    "scene/transparent_masks/view_001.png")(root),
                      (root / "scene/transparent_masks/view_001.png").unlink())),
    "sfm: a HEIC photo beside the others": Case(
        [*SFM, "{R}/res/new"], ["{R}/scene/images", "IMG_0042.HEIC", "HEIC/HEIF", "beside", "heif-convert"],
        write("scene/images/IMG_0042.HEIC", "ftypheic")),
    "masks: a RAW photo beside the others": Case(
        [*MASKS, "{R}/res/new"], ["IMG_0042.dng", "camera RAW", "darktable-cli"],
        write("scene/images/IMG_0042.dng", "raw")),
    "sfm: only HEIC photos": Case([*SFM, "{R}/res/new"], ["view_000.HEIC", "HEIC/HEIF", "no readable images",
                                                          "heif-convert"], only_heic),
    "sfm: byte-identical photos": Case(
        [*SFM, "{R}/res/new"], ["view_001.png and view_009.png", "byte-identical", "delete one"],
        lambda root: shutil.copy(root / "scene/images/view_001.png", root / "scene/images/view_009.png")),
    "masks: byte-identical photos": Case(
        [*MASKS, "{R}/res/new"], ["view_002.png and view_002_copy.png", "byte-identical"],
        lambda root: shutil.copy(root / "scene/images/view_002.png", root / "scene/images/view_002_copy.png")),
}

MISMATCH_CASES = {
    "prepare --sfm of another scene": Case(
        ["prepare", "--scene-dir", "{R}/scene", "--sfm", "{R}/res/other/sfm", "--masks", "{R}/res/masks", "--out",
         "{R}/res/new"], ["--sfm {R}/res/other/sfm", "belongs to other photos", "{R}/scene_b", "{R}/scene/images"]),
    "prepare --masks of another scene": Case(
        ["prepare", "--scene-dir", "{R}/scene", "--sfm", "{R}/res/sfm", "--masks", "{R}/res/other/masks", "--out",
         "{R}/res/new"], ["--masks {R}/res/other/masks", "belongs to other photos", "{R}/scene_b"]),
    "sfm --masks of another scene": Case(
        [*SFM, "{R}/res/new", "--masks", "{R}/res/other/masks"], ["--masks {R}/res/other/masks", "other photos"]),
    "prepare after a photo was removed": Case(
        [*PREPARE, "{R}/res/new"], ["--sfm {R}/res/sfm", "view_003.png (removed)"],
        lambda root: (root / "scene/images/view_003.png").unlink()),
    "train resumes a run killed on another preparation": Case(
        ["train", "--data", "{R}/res/other/prepared", "--out", "{R}/res/trained", "--quiet", "--config-json",
         TINY_TRAINING, "--iterations", "4"],
        ["{R}/res/trained/checkpoints/last.pt", "another prepared scene", "res/prepared",
         "{R}/res/other/prepared"]),
    "render a run of another scene": Case(
        ["render", "--run", "{R}/res/trained", "--data", "{R}/res/other/prepared", "--quiet", "--out", "{R}/res/new"],
        ["the run {R}/res/trained", "res/prepared", "{R}/res/other/prepared", "photos"]),
    "render a model with NaN parameters": Case(
        ["render", "--run", "{R}/res/trained", "--data", "{R}/res/prepared", "--quiet", "--out", "{R}/res/new"],
        ["{R}/res/trained/model.pt", "'means'", "non-finite"], nan_surfels("res/trained/model.pt")),
    "train on a prepared scene with a NaN ROI centre": Case(
        [*TRAIN_NEW], ["{R}/res/prepared/scene.json", "roi.center", "finite"], roi_center(float("nan"))),
    "render on a prepared scene with an infinite ROI centre": Case(
        ["render", "--run", "{R}/res/trained", "--data", "{R}/res/prepared", "--quiet", "--out", "{R}/res/new"],
        ["{R}/res/prepared/scene.json", "roi.center", "finite"], roi_center(float("inf"))),
}


METRICS = [*METRICS_ARGS]
FPS = [*FPS_ARGS]
TRAINED_RENDER = ["render", "--run", "{R}/res/trained", "--data", "{R}/res/prepared", "--quiet", "--out"]
SYNTH = ["synth", "--scene", "dome", "--views", "40", "--width", "16", "--height", "16", "--spp", "1", "--out"]
STAGE_OUTPUTS = {  # stage -> its argv up to --out and the name of its output there
    "sfm": (SFM, "sfm"), "masks": (MASKS, "masks"), "prepare": (PREPARE, "prepared"), "train": (TRAIN, "run"),
    "render": (TRAINED_RENDER, "renders"), "fps": (FPS, "fps.json"), "metrics": (METRICS, "m.json"),
    "report": (["report", "--results", "{R}/results", "--out"], "report"), "synth": (SYNTH, "dome"),
}
READ_ONLY = ["read-only", "{R}/ro/"]  # the cause and the path (what follows depends on the stage)


def _cases_per_stage() -> dict[str, Case]:
    cases = {}
    for stage, (argv, name) in STAGE_OUTPUTS.items():
        train = "res/new" if stage == "train" else None
        cases[f"{stage}: read-only folder"] = Case([*argv, f"{{R}}/ro/{name}"], READ_ONLY, fault="read-only")
        cases[f"{stage}: a file where a folder is needed"] = Case(
            [*argv, f"{{R}}/a_file/{name}"], ["{R}/a_file", "a file where a folder is needed"])
        if stage != "synth":  # a full disk shows only after rendering the views: the other stages cover it
            cases[f"{stage}: no space left"] = Case([*argv, f"{{R}}/res/new/{name}"],
                                                    ["{R}/res/new/", "no space left on device"],
                                                    fault="no space", fault_at="res/new", may_create=train)
    return cases


def _folder_named(rel: str, stage: str) -> Callable[[Path], None]:
    """An output folder of ``stage`` with a folder named ``rel`` inside, where the stage writes a file."""
    def apply(root: Path) -> None:
        folder = root / "res/new"
        (folder / rel).mkdir(parents=True)
        mark_output(folder, stage)
    return apply


WRITE_CASES = {
    **_cases_per_stage(),
    "train: --checkpoint-dir read-only": Case([*TRAIN, "{R}/res/new", "--checkpoint-dir", "{R}/ro/ckpt"],
                                              ["read-only", "{R}/ro/ckpt"], fault="read-only"),
    "train: no space for the checkpoint": Case([*TRAIN, "{R}/res/new", "--config-json", TINY_TRAIN],
                                               ["{R}/res/new/checkpoints/last.pt", "no space left on device"],
                                               fault="no space for .pt", fault_at="res/new", may_create="res/new"),
    "train: no space for the log": Case([*TRAIN, "{R}/res/new", "--config-json", TINY_TRAIN],
                                        ["{R}/res/new/train_log.jsonl", "no space left on device"],
                                        fault="no space for the log", fault_at="res/new", may_create="res/new"),
    "train: a folder where config.json goes": Case(
        [*TRAIN, "{R}/res/new"], ["{R}/res/new/config.json", "a folder where a file is to be written"],
        _folder_named("config.json", "train")),
    "metrics onto a folder": Case([*METRICS, "{R}/user"], ["{R}/user", "is a folder"]),
    "metrics onto the renders": Case([*METRICS, "{R}/res/renders"], ["{R}/res/renders", "metrics input"]),
    "metrics onto a render PNG": Case([*METRICS, "{R}/res/renders/color/view_000.png"],
                                      ["{R}/res/renders/color/view_000.png", "metrics input"]),
    "metrics onto a user's file": Case([*METRICS, "{R}/user/notes.txt"],
                                       ["{R}/user/notes.txt", "not a result of 'rtsplat metrics'"]),
    "metrics onto the fps JSON": Case([*METRICS, "{R}/res/fps.json"],
                                      ["{R}/res/fps.json", "not a result of 'rtsplat metrics'"]),
    "fps onto the metrics JSON": Case([*FPS, "{R}/res/metrics.json"],
                                      ["{R}/res/metrics.json", "not a result of 'rtsplat fps'"]),
    "fps onto a folder": Case([*FPS, "{R}/user"], ["{R}/user", "is a folder"]),
    "metrics into the sfm output": Case([*METRICS, "{R}/res/sfm/m.json"],
                                        ["{R}/res/sfm/m.json", "lies inside the output of 'rtsplat sfm'"]),
    "train --checkpoint-dir is another stage's output": Case(
        [*TRAIN, "{R}/res/new", "--checkpoint-dir", "{R}/res/sfm"],
        ["{R}/res/sfm", "the --checkpoint-dir folder was written by 'rtsplat sfm'", "pass a --checkpoint-dir"]),
    "train --checkpoint-dir is a user folder": Case(
        [*TRAIN, "{R}/res/new", "--checkpoint-dir", "{R}/user"], ["{R}/user", "the --checkpoint-dir folder"]),
    "sfm: 2 images with a model": Case(
        ["sfm", "--scene-dir", "{R}/two", "--out", "{R}/res/new"],
        ["{R}/two/images", "2 image(s)", "sfm.min_registered_images is 3"],
        lambda root: make_corner_scene(root / "two", n_views=2, width=40, height=30, with_model=True)),
}


def entry_point(entry: str) -> Callable[[list[str]], int]:
    """The ``main`` of a command: ``rtsplat`` or the module that ``python -m`` runs."""
    import importlib

    return main if entry == "rtsplat" else importlib.import_module(entry).main


def user_png(rel: str) -> Callable[[Path], None]:
    """A PNG of the user's own (a photo of the scene, written by no rtsplat command) at ``rel``."""
    def apply(root: Path) -> None:
        shutil.copy(root / "scene/images/view_000.png", root / rel)
    return apply


def report_json(text: str) -> Callable[[Path], None]:
    """A report folder ``rep/`` whose report.json holds ``text``."""
    return write("rep/report.json", text)


def grey_renders(root: Path) -> None:
    import cv2

    for path in (root / "res/renders/color").glob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))


VIDEO = ["video", "--run", "{R}/res/trained", "--data", "{R}/res/prepared", "--quiet", "--frames", "2"]
VIEW = ["view", "--run", "{R}/res/trained", "--data", "{R}/res/prepared"]
RESULTS_PAGE = "rtsplat.results_page"
A_REPORT = report_json('{"tables": [], "scenes": ["corner"]}')
# every file a command writes where the user names it, and every input checked at the edge
ENTRY_CASES = {
    "video --poster onto a user's PNG": Case([*VIDEO, "--out", "{R}/res/v.mp4", "--poster", "{R}/user/cover.png"],
                                             ["{R}/user/cover.png", "--poster file exists and is not a result of "
                                              "'rtsplat video'"], user_png("user/cover.png")),
    "video --poster not a PNG": Case([*VIDEO, "--out", "{R}/res/v.mp4", "--poster", "{R}/user/notes.txt"],
                                     ["{R}/user/notes.txt", "--poster is written as PNG"]),
    "video --poster inside the run": Case([*VIDEO, "--out", "{R}/res/v.mp4", "--poster", "{R}/res/trained/p.png"],
                                          ["{R}/res/trained/p.png", "input {R}/res/trained"]),
    "video --keep-frames a user folder": Case([*VIDEO, "--out", "{R}/res/v.mp4", "--keep-frames", "{R}/user"],
                                              ["{R}/user", "the --keep-frames folder exists"]),
    "video --width 100000": Case([*VIDEO, "--out", "{R}/res/v.mp4", "--width", "100000", "--no-panels"],
                                 ["100000 pixels wide", "larger than the H.264 encoder takes", "--width of at most"]),
    "view --port 70000": Case([*VIEW, "--port", "70000"], ["--port 70000 is not a TCP port", "--port 8080"]),
    "view --port 0": Case([*VIEW, "--port", "0"], ["--port 0 is not a TCP port"]),
    "metrics on grey renders": Case([*METRICS, "{R}/res/new.json"],
                                    ["{R}/res/renders/color/", "the render is grey (1 channel)", "rtsplat render"],
                                    grey_renders),
    "config: near_reflection on unquoted": train_yaml_case(
        ["train.effects.near_reflection", "YAML reads an unquoted on, off, yes, no", 'near_reflection: "on"'],
        "  effects: {near_reflection: on}\n"),
    "config: a device yes": train_yaml_case(["train.device", "YAML reads", 'device: "the text"'],
                                            "  device: yes\n"),
    "results_page --out a user's notes": Case(
        ["--report", "{R}/rep", "--out", "{R}/user/notes.txt"],
        ["{R}/user/notes.txt", "is not a result of 'python -m rtsplat.results_page'", "a new <name>.md"],
        A_REPORT, entry=RESULTS_PAGE),
    "results_page --out its own report.json": Case(
        ["--report", "{R}/rep", "--out", "{R}/rep/report.json"], ["{R}/rep/report.json", "input {R}/rep"],
        A_REPORT, entry=RESULTS_PAGE),
    "results_page --out a folder": Case(["--report", "{R}/rep", "--out", "{R}/user"], ["{R}/user", "is a folder"],
                                        A_REPORT, entry=RESULTS_PAGE),
    "results_page of a report.json holding []": Case(
        ["--report", "{R}/rep", "--out", "{R}/page.md"], ["{R}/rep/report.json", "holds a JSON list"],
        report_json("[]"), entry=RESULTS_PAGE),
    "results_page of a report.json with a table of numbers": Case(
        ["--report", "{R}/rep"], ["{R}/rep/report.json", "table 1 is not an object"],
        report_json('{"tables": [[1, 2]]}'), entry=RESULTS_PAGE),
    "config_reference --out a user's notes": Case(
        ["--out", "{R}/user/notes.txt"], ["{R}/user/notes.txt", "not a result of 'python -m rtsplat.config_reference'"],
        entry="rtsplat.config_reference"),
    "demo --out a user folder": Case(["--out", "{R}/user", "--width", "16", "--height", "16"],
                                     ["{R}/user", "not written by 'rtsplat demo'"], entry="rtsplat.demo"),
    "rtsplat demo --out a dataset": Case(["demo", "--out", "{R}/scene"], ["{R}/scene", "dataset folder"]),
    "bench.layer_strip --out a user's PNG": Case(
        ["--data", "{R}/res/prepared", "--renders", "{R}/res/renders", "--out", "{R}/user/cover.png"],
        ["{R}/user/cover.png", "not a result of 'python -m rtsplat.bench.layer_strip'"], user_png("user/cover.png"),
        entry="rtsplat.bench.layer_strip"),
    "bench.mask_propagation --figure a user's PNG": Case(
        ["--data", "{R}/scene", "--figure", "{R}/user/cover.png"],
        ["{R}/user/cover.png", "--figure file exists"], user_png("user/cover.png"),
        entry="rtsplat.bench.mask_propagation"),
    "bench.iteration --state-dir a user folder": Case(
        ["--scene", "{R}/res/prepared", "--state-dir", "{R}/user"], ["{R}/user", "the --state-dir folder exists"],
        entry="rtsplat.bench.iteration"),
    "bench.iteration --methods an unknown name": Case(
        ["--scene", "{R}/res/prepared", "--methods", "rtsplat,rtsplat_mlp96", "--state-dir", "{R}/new_state"],
        ["--methods", "unknown rtsplat_mlp96", "choose from", "rtsplat_mlp128"], entry="rtsplat.bench.iteration"),
}


def _rename_masks(folder: Path) -> None:
    for i, path in enumerate(sorted(folder.iterdir())):
        path.rename(folder / f"mask_{i}.png")


def _crop(path: Path) -> None:
    from rtsplat.io.images import read_image, write_png

    write_png(path, read_image(path)[:20, :30])


CASES = {
    **{f"output: {k}": v for k, v in OUTPUT_CASES.items()},
    **{f"model: {k}": v for k, v in MODEL_CASES.items()},
    **{f"config: {k}": v for k, v in CONFIG_CASES.items()},
    **{f"existing: {k}": v for k, v in EXISTING_CASES.items()},
    **{f"photos: {k}": v for k, v in PHOTO_CASES.items()},
    **{f"mismatch: {k}": v for k, v in MISMATCH_CASES.items()},
    **{f"write: {k}": v for k, v in WRITE_CASES.items()},
    **{f"entry: {k}": v for k, v in ENTRY_CASES.items()},
}

FAULTS = {
    "read-only": lambda monkeypatch, folder: read_only(monkeypatch, folder),
    "no space": lambda monkeypatch, folder: no_space(monkeypatch, folder, lambda p: ".rtsplat-output" not in p.name),
    "no space for .pt": lambda monkeypatch, folder: no_space(monkeypatch, folder, lambda p: ".pt" in p.name),
    "no space for the log": lambda monkeypatch, folder: no_space(monkeypatch, folder,
                                                                 lambda p: p.name == "train_log.jsonl"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_is_refused_and_changes_nothing(name, base, tmp_path, capsys, monkeypatch):
    case = CASES[name]
    root = tmp_path / "copy"
    shutil.copytree(base, root, symlinks=True)
    for summary in root.rglob("*.json"):  # stage summaries record absolute paths
        summary.write_text(summary.read_text().replace(str(base), str(root)))
    if case.setup is not None:
        case.setup(root)
    before = tree_state(root)
    argv = [a.replace("{R}", str(root)) for a in case.argv]
    restore = lambda: None  # noqa: E731
    if case.fault is not None:
        (root / case.fault_at).mkdir(parents=True, exist_ok=True)
        before = tree_state(root)
        restore = FAULTS[case.fault](monkeypatch, root / case.fault_at) or restore
    try:
        status = entry_point(case.entry)(argv)
    finally:
        monkeypatch.undo()
        restore()
    assert status == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    for text in case.expect:
        assert text.replace("{R}", str(root)) in err, f"{text!r} not in the message:\n{err}"
    after = tree_state(root)
    if case.may_create is not None:
        created = {rel for rel in set(after) - set(before)}
        assert all(Path(rel).is_relative_to(case.may_create) for rel in created), created
        assert not [rel for rel in created if ".tmp-" in rel], created
        after = {rel: state for rel, state in after.items() if rel in before}
    assert after == before


def test_a_stage_replaces_its_own_output_and_fills_an_empty_folder(base, tmp_path):
    """The other side of the output checks: re-running a stage over its own output replaces it, and an
    existing empty folder is accepted; both end up marked as that stage's."""
    scene = tmp_path / "scene"
    shutil.copytree(base / "scene", scene)
    out = tmp_path / "masks"
    out.mkdir()
    assert main(["masks", "--scene-dir", str(scene), "--out", str(out)]) == 0
    (out / "stale.txt").write_text("from an earlier run")
    assert main(["masks", "--scene-dir", str(scene), "--out", str(out)]) == 0
    assert not (out / "stale.txt").exists()
    assert (out / ".rtsplat-output").is_file() and (out / "view_000.png").is_file()


def test_photos_stored_upright_pass_and_a_raw_twin_is_named(base, tmp_path, capsys):
    """The other side of the photo checks: a JPEG whose EXIF orientation says upright (1) is read, and a RAW
    file beside the JPEG of the same name (a camera's RAW+JPEG pair) is skipped with a line naming it."""
    from PIL import Image

    scene = tmp_path / "scene"
    shutil.copytree(base / "scene", scene)
    exif = Image.Exif()
    exif[0x0112] = 1
    Image.open(scene / "images/view_000.png").convert("RGB").save(scene / "images/view_000.jpg", exif=exif)
    (scene / "images/view_000.png").unlink()
    (scene / "images/view_000.dng").write_bytes(b"raw sensor data")
    assert main(["masks", "--scene-dir", str(scene), "--out", str(tmp_path / "masks")]) == 0
    err = capsys.readouterr().err
    assert "view_000.dng" in err and "skipped 1 file" in err
    assert (tmp_path / "masks/view_000.png").is_file()


def test_inputs_that_belong_together_pass_wherever_they_are(base, tmp_path, capsys):
    """Fingerprints are of contents, not paths: the scene and its sfm and masks outputs copied elsewhere
    still prepare, and the run renders on that new preparation of the same photos and SfM model."""
    root = tmp_path / "moved"
    for rel in ("scene", "res/sfm", "res/masks", "res/trained"):
        shutil.copytree(base / rel, root / rel)
    for summary in (root / "res").rglob("*.json"):
        summary.write_text(summary.read_text().replace(str(base), str(root)))
    assert main(["prepare", "--scene-dir", str(root / "scene"), "--sfm", str(root / "res/sfm"), "--masks",
                 str(root / "res/masks"), "--out", str(root / "res/prepared2")]) == 0
    assert main(["render", "--run", str(root / "res/trained"), "--data", str(root / "res/prepared2"), "--quiet",
                 "--out", str(root / "res/renders"), "--warmup", "0"]) == 0
    assert (root / "res/renders/color/view_000.png").is_file()
    # a resume on the very folder it was trained on (copied: same contents) is accepted
    shutil.copytree(base / "res/prepared", root / "res/prepared")
    assert main(["train", "--data", str(root / "res/prepared"), "--out", str(root / "res/trained"), "--quiet",
                 "--config-json", TINY_TRAINING, "--iterations", "3"]) == 0
    assert "resumed from" in capsys.readouterr().err


def test_a_half_written_last_log_line_is_dropped_on_resume(base, tmp_path, capsys):
    """A run stopped while appending to train_log.jsonl (killed, or a full disk) resumes: the partial
    last line is dropped and said so, and the log ends as whole records."""
    run = tmp_path / "run"
    shutil.copytree(base / "res/trained", run)
    (run / "model.pt").unlink()
    (run / "summary.json").unlink()
    log = run / "train_log.jsonl"
    whole = [line for line in log.read_text().splitlines() if line.strip()]
    assert whole
    log.write_text(log.read_text() + '{"iteration": 2, "seconds": 0.1, "lo')
    argv = ["train", "--data", str(base / "res/prepared"), "--out", str(run), "--quiet", "--config-json", TINY_TRAINING,
            "--iterations", "3"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert f"{log}: dropped its half-written last line" in err
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["iteration"] for r in records][-1] == 3


def test_a_model_directly_in_sparse_is_used_with_a_note(base, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(base / "scene", scene)
    for path in (scene / "sparse/0").iterdir():
        path.rename(scene / "sparse" / path.name)
    (scene / "sparse/0").rmdir()
    assert main(["sfm", "--scene-dir", str(scene), "--out", str(tmp_path / "sfm")]) == 0
    assert f"{scene / 'sparse'} holds a COLMAP model directly (no sparse/0 folder); using it" in capsys.readouterr().out
    assert json.loads((tmp_path / "sfm/summary.json").read_text())["source"] == "dataset"


def test_results_equal_to_data_is_a_config_error(tmp_path):
    from rtsplat.config import discover_scenes, load_config_dict
    from rtsplat.errors import ConfigError

    make_corner_scene(tmp_path / "data" / "glass", n_views=2, width=40, height=30)
    for results, words in ((tmp_path / "data", "is the 'data' folder"),
                           (tmp_path / "data" / "glass" / "out", "lies inside the scene glass")):
        cfg = load_config_dict({"data": str(tmp_path / "data"), "results": str(results)})
        with pytest.raises(ConfigError) as info:
            discover_scenes(cfg)
        message = str(info.value)
        assert "'results'" in message and "'data'" in message and words in message, message


def test_a_command_replaces_its_own_file_and_its_committed_page(base, tmp_path, capsys):
    """The other side of the output rule for files: a poster, a results page and the configuration page that
    their command wrote are replaced by it (also the committed docs pages), and the user's files never."""
    from rtsplat.config_reference import main as config_reference
    from rtsplat.results_page import main as results_page

    root = Path(__file__).resolve().parent.parent
    (tmp_path / "rep").mkdir()
    (tmp_path / "rep/report.json").write_text('{"tables": [], "scenes": ["corner"]}')
    for committed in ("results.md", "results_family.md"):  # the placeholder and a page the command wrote
        page = tmp_path / committed
        shutil.copy(root / "docs" / committed, page)
        assert results_page(["--report", str(tmp_path / "rep"), "--out", str(page)]) == 0
        assert page.read_text().startswith("# Results\n\nWritten by `python -m rtsplat.results_page --report")
        assert results_page(["--report", str(tmp_path / "rep"), "--out", str(page)]) == 0  # its own, again
    shutil.copy(root / "docs/configuration.md", tmp_path / "configuration.md")
    assert config_reference(["--out", str(tmp_path / "configuration.md")]) == 0
    assert (tmp_path / "configuration.md").read_text() == (root / "docs/configuration.md").read_text()
    poster = tmp_path / "poster.png"
    video = [*(a.replace("{R}", str(base)) for a in VIDEO), "--no-panels", "--out", str(tmp_path / "v.mp4"),
             "--poster", str(poster)]
    assert main(video) == 0
    first = poster.read_bytes()
    poster.write_bytes(first[:33] + first[33:].replace(b"rtsplat video", b"rtsplat viDeo"))  # as if another's
    assert main(video) == 1 and "--poster file exists" in capsys.readouterr().err
    poster.write_bytes(first)
    assert main(video) == 0 and poster.read_bytes() == first  # its own: replaced by the same frame


def test_the_report_drops_a_half_written_last_log_line_and_says_so(base, tmp_path, capsys):
    """A run killed while appending to train_log.jsonl: `rtsplat report` reads its whole records, as a resumed
    training does, and names the line it dropped."""
    results = tmp_path / "results"
    shutil.copytree(base / "results", results)
    log = results / "corner/runs/rtsplat/train_log.jsonl"
    whole = len([line for line in log.read_text().splitlines() if line.strip()])
    log.write_text(log.read_text() + '{"iteration": 3, "seconds": 0.1, "lo')
    assert main(["report", "--results", str(results), "--out", str(tmp_path / "report")]) == 0
    err = capsys.readouterr().err
    assert f"{log}: dropped its half-written last line" in err and "Traceback" not in err
    assert (tmp_path / "report/index.html").is_file() and whole >= 1


def test_view_on_a_busy_port_is_an_error_naming_it(base, tmp_path, capsys):
    """A port another program listens on: an error naming it, before the run is loaded (never a silent
    move to the next port, where a forwarded port would reach the other program)."""
    import socket

    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        argv = [a.replace("{R}", str(base)) for a in VIEW]
        assert main([*argv, "--port", str(port)]) == 1
    err = capsys.readouterr().err
    assert f"port {port} is in use by another program on 127.0.0.1" in err and "pass another --port" in err


def test_a_video_out_of_memory_is_an_error_naming_the_frame_size(base, tmp_path, capsys, monkeypatch):
    from rtsplat.render import LoadedRun

    def no_memory(self, camera):
        raise MemoryError

    monkeypatch.setattr(LoadedRun, "render", no_memory)
    out = tmp_path / "v.mp4"
    assert main([*(a.replace("{R}", str(base)) for a in VIDEO), "--no-panels", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "out of memory rendering video frames of 40x30 pixels" in err and "smaller --width" in err
    assert list(tmp_path.iterdir()) == []
