"""The pipeline configuration: one dataclass tree that mirrors ``config.yaml``.

``config.yaml`` layout::

    data: data                 # dataset directory: <data>/<scene>/images/*
    results: results           # where every stage writes
    scenes: []                 # empty: every <data>/<scene> that has images/
    methods:                   # name -> trainer config overrides; trained / rendered / evaluated per scene
      rtsplat: {role: main}    # role (main | baseline | ablation | repeat, see method_roles) is not a
      rtsplat_seed1: {role: repeat, of: rtsplat, seed: 1}   # trainer key; a repeat names what it reruns
      rtsplat_at_2dgs_time: {time_of: 2dgs}   # trains for as long as the 2dgs run on the scene took
    defaults:                  # a SceneConfig: sfm, masks, prepare, train, render, video, metrics
      prepare: {downsample: 4}
    overrides:                 # per-scene SceneConfig fragments merged over the defaults
      sedan: {prepare: {downsample: 8}}

The JSON schema that Snakemake's ``validate`` uses (``workflow/schemas/config.schema.json``) is
generated from these dataclasses by :func:`json_schema` (``python -m rtsplat.config --write-schema``)
and a test checks that the file is up to date, so the two cannot drift. :func:`validate_config`
turns schema violations into messages that name the key and the fix.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import re
import shlex
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from rtsplat.devices import DEVICE_PATTERN
from rtsplat.errors import ConfigError, run_command
from rtsplat.io.atomic import write_text_atomic
from rtsplat.schema import build, check, dataclass_schema
from rtsplat.schema import setting as _f

SCHEMA_PATH = Path(__file__).resolve().parent.parent / "workflow" / "schemas" / "config.schema.json"


@dataclass
class SfmConfig:
    """Structure from motion (pycolmap)."""

    matcher: Literal["auto", "exhaustive", "sequential", "vocabtree"] = _f(
        "auto",
        help="feature matching: exhaustive (every pair), sequential (neighbours in capture order, cyclic) or "
        "vocabtree (retrieval, needs vocab_tree_path); auto: exhaustive up to exhaustive_max_images images, "
        "sequential for larger captures whose EXIF times or numbered names order them, else vocabtree when "
        "vocab_tree_path is set, else exhaustive",
    )
    exhaustive_max_images: int = _f(60, help="auto matcher: exhaustive up to this many images", minimum=2)
    sequential_overlap: int = _f(
        10,
        help="sequential matcher: each image with this many successors (and those at power-of-two distances beyond)",
        minimum=1,
    )
    vocab_tree_path: str | None = _f(
        None,
        help="COLMAP vocabulary tree file for the vocabtree matcher (none ships with pycolmap; nothing is downloaded)",
    )
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = _f(
        "SIMPLE_RADIAL", help="COLMAP camera model; models with distortion are undistorted to PINHOLE"
    )
    single_camera: bool = _f(True, help="all images share one camera")
    max_image_size: int = _f(1600, help="images are resized to this size for feature extraction", minimum=64)
    max_num_features: int = _f(8192, help="SIFT features per image", minimum=64)
    min_registered_fraction: float = _f(
        0.5, help="fail when fewer than this fraction of images register", minimum=0.0, maximum=1.0
    )
    min_registered_images: int = _f(3, help="fail when fewer images register", minimum=2)
    use_masks: bool = _f(False, help="suppress features on transparent surfaces using the masks")
    use_dataset_model: bool = _f(
        True,
        help="use <scene>/sparse/0 when the dataset has one; false: always run "
        "SfM (e.g. synthetic scenes that ship ground-truth cameras)",
    )
    num_threads: int = _f(-1, help="threads for pycolmap (-1: all cores)")
    seed: int = _f(0, help="random seed of the mapper", minimum=0)
    mapper: Literal["incremental", "global"] = _f(
        "incremental", help="first attempt's mapper: incremental (COLMAP) or global (GLOMAP-style, pycolmap)"
    )
    sift_peak_threshold: float = _f(
        0.02 / 3, help="first attempt: SIFT peak threshold (lower: more, weaker features)", exclusiveMinimum=0.0
    )
    sift_first_octave: int = _f(-1, help="first attempt: SIFT first octave (-1 upsamples the image twice)", minimum=-4)
    guided_matching: bool = _f(False, help="first attempt: guided matching (re-match with the two-view geometry)")
    init_min_num_inliers: int = _f(100, help="first attempt: inliers the mapper's initial pair needs", minimum=1)
    init_max_error: float = _f(
        4.0, help="first attempt: initial pair's max reprojection error (px)", exclusiveMinimum=0.0
    )
    abs_pose_min_num_inliers: int = _f(
        30, help="first attempt: 2D-3D inliers an image needs to register (incremental mapper)", minimum=1
    )
    abs_pose_min_inlier_ratio: float = _f(
        0.25, help="first attempt: 2D-3D inlier ratio an image needs to register", minimum=0.0, maximum=1.0
    )
    max_attempts: int = _f(
        4,
        help="SfM attempts at most: while views are missing, retry with settings suited to the failure "
        "(another mapper, relaxed mapper thresholds, more features with guided matching); 1: no retries",
        minimum=1,
    )
    max_reprojection_error: float = _f(
        2.0, help="an attempt's model is acceptable up to this mean reprojection error (px)", exclusiveMinimum=0.0
    )
    min_points_per_image: int = _f(
        30,
        help="an attempt's model is acceptable when its registered images see a median of at least this many 3D "
        "points (the bar incremental mapping sets for registering one image); fewer: too little evidence, "
        "as in models that global mapping assembles from few wide-baseline matches",
        minimum=0,
    )
    refine: bool = _f(
        True,
        help="after the chosen attempt: tracks rebuilt with its poses (see refine_features), then rounds of robust "
        "global bundle adjustment, track completion and outlier filtering; kept when it keeps every view at a lower "
        "mean reprojection error",
    )
    refine_skip_reprojection_error: float = _f(
        0.25,
        help="refinement: skipped when the chosen attempt registers every view at a mean reprojection error at most "
        "this (px), about what the refinement reaches from attempts at 0.3-0.6 px; 0: always refine",
        minimum=0.0,
    )
    refine_features: Literal["auto", "attempt", "denser"] = _f(
        "auto",
        help="refinement tracks: attempt = the chosen attempt's features and matches (no extraction or matching); "
        "denser = more, weaker SIFT features matched (guided) on the pairs that share points or are neighbours by "
        "pose; auto = denser where the attempt found few features per image (refine_denser_max_features), "
        "which small or plain photos give and which make cheap, sparse tracks, else attempt",
    )
    refine_denser_max_features: int = _f(
        1000,
        help="refine_features auto: denser when the chosen attempt's images hold at most this many SIFT features on "
        "average (guided matching of the denser features costs about the square of their number per pair)",
        minimum=0,
    )
    refine_pose_neighbours: int = _f(
        8, help="refine_features denser: each view is matched with this many nearest views by camera centre", minimum=0
    )
    refine_max_reprojection_error: float = _f(
        1.0,
        help="refinement: observations reprojecting farther than this (px) are dropped after each bundle adjustment",
        exclusiveMinimum=0.0,
    )
    refine_rounds: int = _f(
        5, help="refinement: rounds of bundle adjustment, track completion and filtering at most", minimum=1
    )


@dataclass
class OnnxSegmenterConfig:
    """A local ONNX segmenter: SAM / SAM2 (encoder + prompted decoder) or a plain image-to-logits net."""

    model: str | None = _f(None, help="ONNX file: the SAM/SAM2 mask decoder or a plain segmentation model")
    encoder: str | None = _f(None, help="ONNX file of the SAM/SAM2 image encoder (not used by plain models)")
    kind: Literal["auto", "sam", "sam2", "plain"] = _f(
        "auto", help="auto detects the kind from the model's input names"
    )
    points: list[list[float]] = _f(
        help="prompt points [[x, y], ...] as fractions of the image width/height", factory=list
    )
    point_labels: list[int] = _f(help="1 = on the glass, 0 = background; one per point", factory=list)
    box: list[float] | None = _f(
        None, help="prompt box [x0, y0, x1, y1] as fractions of the image size", minItems=4, maxItems=4
    )
    normalize: Literal["unit", "imagenet"] = _f(
        "unit", help="plain models: input in [0, 1] (unit) or ImageNet mean/std normalised"
    )
    providers: list[str] = _f(help="onnxruntime execution providers", factory=lambda: ["CPUExecutionProvider"])


@dataclass
class MaskPropagationConfig:
    """Masks carried from a few marked views to the others through the SfM cameras (masks.source: propagate)."""

    method: Literal["auto", "hull", "plane"] = _f(
        "auto", help="how the marks reach the other views: hull: through the marked views' visual hull (views from "
        "around the object); plane: through the glass's plane, fitted to the SfM points on the marks' outlines (flat "
        "glass seen from one side, e.g. a walk past a shop window); auto: hull when the marked views' directions "
        "differ by at least 10 degrees, else plane"
    )
    grid: int = _f(128, help="voxels along the longest side of the marked object's box (visual hull)", minimum=16)
    plane_band: float = _f(
        0.03, help="plane: how far outside a mark its outline's SfM points are looked for, as a fraction of the "
        "photo's longest side", exclusiveMinimum=0.0, maximum=0.5,
    )
    refine: Literal["auto", "grabcut", "watershed", "onnx", "none"] = _f(
        "auto", help="grabcut: each projected hull refined on its image with OpenCV GrabCut; watershed: its "
        "outline moved to the image's strongest edges within snap_band (OpenCV watershed); onnx: segmented with "
        "the masks.onnx model, prompted by the projected hull's box; none: kept as projected; auto: onnx when "
        "masks.onnx.model is set, else whichever of grabcut, watershed and none matches the marked masks best "
        "when each marked view is left out in turn"
    )
    grabcut_iterations: int = _f(4, help="GrabCut iterations", minimum=1)
    ring: float = _f(
        0.15, help="GrabCut: probable-background ring around the projected hull, as a fraction of its size",
        exclusiveMinimum=0.0,
    )
    min_kept: float = _f(
        0.5, help="a GrabCut or watershed result keeping less than this fraction of the projected hull is dropped "
        "for the projection (glass that looks like what is behind it)", minimum=0.0, maximum=1.0,
    )
    snap_band: float = _f(
        0.02, help="watershed: how far inside the projected hull's outline the edge is looked for, as a fraction "
        "of its size (at least one pixel)", exclusiveMinimum=0.0, maximum=0.5,
    )
    occlusion: bool = _f(
        True, help="SfM points on a surface (with neighbours in the image at about their depth) in front of the "
        "marked object hide it: they keep a marked view from carving what they hide, and leave it out of the "
        "propagated masks; points scattered in depth (triangulated through glass) hide nothing"
    )
    work_size: int = _f(1024, help="longest image side the projection and its refinement work at", minimum=64)
    min_part: float = _f(
        0.05, help="hull parts smaller than this fraction of the largest part are dropped", minimum=0.0, maximum=1.0
    )


_CORNER = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}  # [x, y]


@dataclass
class MaskMark:
    """A marked view's see-through surface drawn in the config: the union of its boxes and polygons."""

    box: list[float] | None = _f(
        None, help="[x0, y0, x1, y1] in pixels of the photo as it is in images/ (x to the right, y down; x1 > x0, "
        "y1 > y0); loose is fine: GrabCut finds the object inside it", minItems=4, maxItems=4
    )
    polygon: list[list[float]] | None = _f(
        None, help="[[x, y], ...] in pixels of the photo, at least 3 corners, the outline of the see-through "
        "surface (taken as drawn)", minItems=3, items=_CORNER
    )
    boxes: list[list[float]] | None = _f(
        None, help="several boxes like box, e.g. one per pane of an object of several panes", minItems=1,
        items={"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4}
    )
    polygons: list[list[list[float]]] | None = _f(
        None, help="several polygons like polygon, e.g. one outline per pane of an object of several panes",
        minItems=1, items={"type": "array", "items": _CORNER, "minItems": 3}
    )


@dataclass
class MasksConfig:
    """Transparent-surface masks (white = see-through surface)."""

    source: Literal["auto", "ingest", "propagate", "onnx", "none"] = _f(
        "auto", help="auto: with marks, propagate; when <scene>/<dir> has masks, propagate them if fewer than half "
        "the photos have one (the marked views; not with allow_missing), else ingest them; without masks segment "
        "when onnx.model is set, else none"
    )
    dir: str = _f(
        "transparent_masks",
        help="mask folder inside the scene, one mask per photo named like the photo (IMG_0001.JPG), after its "
        "stem with any image extension (IMG_0001.png) or <photo name>.png",
    )
    threshold: float = _f(
        0.5, help="binarisation threshold (of the mask value or segmenter probability); 0.5 also cuts JPEG "
        "masks' compression noise near black and white", minimum=0.0, maximum=1.0
    )
    allow_missing: bool = _f(
        False, help="ingest: a photo without a mask gets an empty mask (no see-through surface) instead of an error"
    )
    polarity: Literal["auto", "white", "black"] = _f(
        "auto", help="the mask files' colour of the see-through surface (ingest, and the marked views' masks of "
        "propagate); black reads inverted masks; auto: white, the masks as given (never inverted on coverage: "
        "glass that fills the view covers most of each photo), with a warning when white covers more than "
        "max_coverage of the photos on average"
    )
    max_coverage: float = _f(0.5, help="a larger mean coverage is flagged (log, masks/summary.json, the report): "
                             "of the mask files under polarity auto (polarity_warning), of segmented masks "
                             "(coverage_warning); the masks are kept as given",
                             exclusiveMinimum=0.0, maximum=1.0)
    marks: dict[str, MaskMark] = _f(
        help="marked views drawn in the config, by photo name (e.g. IMG_0001.jpg: {box: [x0, y0, x1, y1]}, "
        "{polygon: [[x, y], ...]} or {polygons: [[[x, y], ...], ...]}; a view's boxes and polygons are unioned): "
        "marked views like the mask files of <dir>, carried to the other photos "
        "(source propagate; auto chooses it when marks are given)", factory=dict
    )
    onnx: OnnxSegmenterConfig = _f(help="the ONNX segmenter", factory=OnnxSegmenterConfig)
    propagate: MaskPropagationConfig = _f(
        help="masks of the marked views carried to the others (source propagate)", factory=MaskPropagationConfig
    )


@dataclass
class RoiConfig:
    """Spherical region of interest."""

    center: list[float] = _f(
        help="sphere centre [x, y, z] in SfM coordinates", factory=lambda: [0.0, 0.0, 0.0], minItems=3, maxItems=3
    )
    radius: float = _f(1.0, help="sphere radius in SfM units", exclusiveMinimum=0.0)


@dataclass
class PrepareConfig:
    """Downsampling, region of interest and train/test split."""

    downsample: int = _f(
        1, help="integer image downsample factor (area filter); not used when resolution is set", minimum=1
    )
    resolution: int | None = _f(
        None,
        help="longest side of the prepared images in pixels, at most (e.g. 800): the smallest integer downsample "
        "factor that meets it is chosen per scene (1 for smaller images) and recorded in scene.json; when set, it "
        "decides the factor and downsample is not used; null: downsample decides",
        minimum=1,
    )
    roi: RoiConfig | None = _f(
        None,
        help="region of interest; when not given: around the transparent masks' visual hull, else from the SfM points",
    )
    roi_from_masks: bool = _f(
        True, help="on a scene with transparent masks, the ROI is the sphere around the masks' visual hull"
    )
    roi_mask_agreement: float = _f(
        0.9, help="mask ROI: fraction of the views seeing a point that must see it inside the mask",
        exclusiveMinimum=0.0, maximum=1.0,
    )
    transparent_surface: bool = _f(
        True, help="on a scene with transparent masks, write the camera-facing surface of the masks' visual hull "
        "(transparent_surface.npz), where training seeds surfels for the see-through surface",
    )
    roi_percentile: float = _f(
        95.0, help="estimated ROI: radius covers this percentile of the SfM points", exclusiveMinimum=0.0, maximum=100.0
    )
    test_every: int = _f(8, help="every n-th image of the name-sorted list is a test view (llffhold)", minimum=2)
    bit_depth: Literal[8, 16] = _f(8, help="bit depth of the prepared PNG images")
    use_prescaled: bool = _f(True, help="use <scene>/images_<factor> when present instead of resizing")


def _trainer_config_class() -> type:
    from rtsplat.train_config import TrainConfig as TrainerConfig  # imports torch: only when needed

    return TrainerConfig


@dataclass
class TrainConfig:
    """Training: the trainer's config tree (``rtsplat train --help``, rtsplat/train_config.py)."""

    iterations: int | None = _f(None, help="schedule.iterations (null: the trainer's default)", minimum=1)
    backend: str = _f("auto", help="rasterizer backend: auto (triton on a GPU, else cpu) | cpu | triton | reference")
    device: str = _f("auto", help="torch device of rtsplat train: auto (the GPU when torch sees one, else the "
                     "CPU) | cpu | cuda | cuda:N", pattern=DEVICE_PATTERN)
    options: dict[str, Any] = _f(
        help="trainer config keys (schedule, lr, losses, ablations, effects, model, ...) merged under the "
        "method's own overrides; checked against the trainer's config tree",
        factory=dict,
        schema_of=_trainer_config_class,
    )


DEFAULT_EDITS = {
    "no-reflections": ["reflections=off"],
    "sharper-reflections": ["roughness=0.25"],
    "clearer-glass": ["transparency=0.3"],
    "tinted": ["tint=1,0.75,0.45"],
}


@dataclass
class RenderConfig:
    """Rendering (``rtsplat render``)."""

    warmup: int = _f(2, help="untimed renders before the FPS measurement", minimum=0)
    fps_rounds: int = _f(3, help="rtsplat fps: times every test view is rendered in the timing pass that the "
                         "workflow runs alone (frames / wall seconds over all of them)", minimum=1)
    device: str = _f("auto", help="torch device of rtsplat render: auto (the GPU when torch sees one, else the "
                     "CPU) | cpu | cuda | cuda:N", pattern=DEVICE_PATTERN)
    edits: dict[str, list[str]] = _f(
        help="scene edits rendered for the main method: name -> list of rtsplat render --edit values",
        factory=lambda: copy.deepcopy(DEFAULT_EDITS),
    )


@dataclass
class FramesConfig:
    """Photos taken from a video (``rtsplat frames``): a scene folder holding a video instead of ``images/``."""

    count: int = _f(0, help="frames to extract, one per equal stretch of the video; 0: one per 'every' seconds",
                    minimum=0)
    every: float = _f(0.5, help="seconds of video per extracted frame (when count is 0)", exclusiveMinimum=0.0)
    quality: int = _f(95, help="JPEG quality of the extracted frames", minimum=50, maximum=100)


@dataclass
class VideoConfig:
    """Camera-path videos (``rtsplat video``)."""

    enabled: bool = _f(True, help="the workflow renders a video of the main method (and of the baselines listed in "
                       "baselines) for every scene, and the report shows it")
    path: Literal["orbit", "spiral", "interpolate"] = _f(
        "orbit", help="camera path from the training cameras: orbit (a circle around the region of interest at "
        "their mean distance and elevation), spiral (around their mean position, for forward-facing captures), "
        "interpolate (through their poses in capture order)")
    frames: int = _f(60, help="frames of the video", minimum=2)
    fps: float = _f(24.0, help="frames per second of the MP4", exclusiveMinimum=0.0)
    width: int | None = _f(None, help="frame width in pixels (the height keeps the training cameras' aspect; both "
                           "rounded down to even numbers for H.264); null: the training cameras' width", minimum=2)
    panels: bool = _f(True, help="image | reflection | transmission | normal | depth side by side in each frame; "
                      "false: the image alone")
    baselines: list[str] = _f(help="methods besides the main one that get a video of the same path, where they are "
                              "among the methods", factory=lambda: ["2dgs"])
    device: str = _f("auto", help="torch device of rtsplat video: auto (the GPU when torch sees one, else the CPU) | "
                     "cpu | cuda | cuda:N", pattern=DEVICE_PATTERN)


@dataclass
class MetricsConfig:
    """Evaluation (``rtsplat metrics``)."""

    lpips_weights: str = _f(
        "",
        help="directory with the LPIPS-VGG weights (vgg16-397923af.pth, vgg.pth); "
        "empty: the torch hub cache; missing weights give n/a, never a number",
    )


@dataclass
class SceneConfig:
    """Every stage's settings for one scene (defaults, then per-scene overrides)."""

    frames: FramesConfig = _f(help="photos taken from a video", factory=FramesConfig)
    sfm: SfmConfig = _f(help="structure from motion", factory=SfmConfig)
    masks: MasksConfig = _f(help="transparent masks", factory=MasksConfig)
    prepare: PrepareConfig = _f(help="prepared scene", factory=PrepareConfig)
    train: TrainConfig = _f(help="training", factory=TrainConfig)
    render: RenderConfig = _f(help="rendering", factory=RenderConfig)
    video: VideoConfig = _f(help="camera-path videos", factory=VideoConfig)
    metrics: MetricsConfig = _f(help="metrics", factory=MetricsConfig)


SLURM_RULES = ("masks", "sfm", "prepare", "train", "render", "render_edit", "fps", "video", "metrics", "report")
SLURM_GPU_RULES = ("train", "render", "fps", "video")  # the jobs whose torch device is the GPU when they have one
SLURM_MINUTES = {"masks": 30, "sfm": 240, "prepare": 60, "render": 120, "render_edit": 60, "fps": 30, "video": 60,
                 "metrics": 30, "report": 15}


@dataclass
class SlurmRuleConfig:
    """One rule's SLURM job settings; each unset key comes from the ``slurm`` section."""

    partition: str | None = _f(None, help="partition of this rule's jobs; null: the slurm section's")
    account: str | None = _f(None, help="account of this rule's jobs; null: the slurm section's")
    minutes: int | None = _f(None, help="time limit of this rule's jobs in minutes; null: the default "
                             "(train: scaled with its iterations)", minimum=1)


@dataclass
class SlurmConfig:
    """What each job asks SLURM for when the workflow runs with the SLURM executor (profiles/slurm);
    nothing of it changes a local run."""

    gpus: int = _f(1, help="GPUs each train, render and fps job asks for (the executor's gpu resource); 0 on a "
                   "cluster without GPUs: every job runs on CPU partitions", minimum=0)
    partition: str | None = _f(None, help="partition of every job; null: the cluster's default partition")
    gpu_partition: str | None = _f(None, help="partition of the jobs that ask for a GPU; null: partition")
    account: str | None = _f(None, help="account charged for every job; null: the executor's guess, or none")
    train_minutes: int = _f(15, help="time limit of a training job: this many minutes plus "
                            "train_minutes_per_1000_iterations for each 1000 of its iterations", minimum=1)
    train_minutes_per_1000_iterations: float = _f(
        60.0, help="see train_minutes; about one CPU's pace on a real capture, a GPU needs far less", minimum=0.0)
    rules: dict[str, SlurmRuleConfig] = _f(
        help=f"per rule ({', '.join(SLURM_RULES)}): partition, account and minutes over the ones above; "
        f"default minutes: {SLURM_MINUTES}", factory=dict, propertyNames={"enum": list(SLURM_RULES)})


MethodRoleName = Literal["main", "baseline", "ablation", "repeat"]
ROLE_KEYS = ("role", "of", "time_of")  # keys of a method that describe its role, not the trainer


@dataclass(frozen=True)
class MethodRole:
    """What a method is for: the report's tables and the workflow's "main method" read this."""

    role: MethodRoleName
    of: str | None = None  # role repeat: the method it reruns
    time_of: str | None = None  # trains for as long as this method's run on the same scene took


@dataclass
class PipelineConfig:
    """The whole ``config.yaml``."""

    data: str = _f("data", help="dataset directory: <data>/<scene>/images/*")
    results: str = _f("results", help="output directory")
    scenes: list[str] = _f(help="scenes to run; empty: every <data>/<scene> with an images/ folder", factory=list)
    methods: dict[str, dict[str, Any]] = _f(
        help="methods trained, rendered and evaluated per scene: name -> trainer config overrides "
        "(e.g. 2dgs: {role: baseline, effects: {transmission: 'off', specular: 'off'}}) plus the method's "
        "role in the report: main (one method; default: the first listed), baseline (the default), "
        "ablation (compared with the main method), repeat (a rerun of the method named by 'of', with that "
        "method's options and the same or another seed: the report's noise measurement)",
        factory=lambda: {"rtsplat": {"role": "main"}},
        minProperties=1,
        additionalProperties={
            "type": "object",
            "properties": {
                "role": {"type": "string", "enum": list(typing.get_args(MethodRoleName)),
                         "description": "the method's role in the report and the workflow"},
                "of": {"type": "string", "description": "role repeat: the method this one reruns; the repeat "
                       "trains that method's options with its own keys (a seed) merged over them"},
                "time_of": {"type": "string", "description": "train for as long as this other method's run on "
                            "the same scene took (its training steps' wall seconds, the time budget "
                            "schedule.seconds): the run to compare with it at equal time. The workflow trains "
                            "that method first; no budget beside it"},
            },
            "additionalProperties": True,
        },
    )
    defaults: SceneConfig = _f(help="settings for every scene", factory=SceneConfig)
    overrides: dict[str, SceneConfig] = _f(help="per-scene settings merged over the defaults", factory=dict)
    slurm: SlurmConfig = _f(help="SLURM job resources (snakemake --profile profiles/slurm)", factory=SlurmConfig)


STAGE_SECTIONS: dict[str, type] = typing.get_type_hints(SceneConfig)


# ----------------------------------------------------------------------------------------------
# JSON schema generated from the dataclasses


def json_schema() -> dict[str, Any]:
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "rtsplat config"}
    schema.update(dataclass_schema(PipelineConfig))
    return schema


def json_schema_text() -> str:
    return json.dumps(json_schema(), indent=2) + "\n"


# ----------------------------------------------------------------------------------------------
# validation with readable messages


def validate_config(data: Any, source: str = "config") -> None:
    """Raise :class:`ConfigError` listing every problem in ``data`` (a parsed config.yaml)."""
    check(PipelineConfig, {} if data is None else data, source=source)


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in (override or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_config_dict(data: dict[str, Any] | None, source: str = "config") -> PipelineConfig:
    data = data or {}
    validate_config(data, source)
    cfg = build(PipelineConfig, data)
    check_methods(cfg, cfg.scenes)
    return cfg


def load_config(path: str | Path) -> PipelineConfig:
    """Read and validate a config.yaml."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError("config file not found", path=path, fix="pass an existing config.yaml")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML ({exc})", path=path, fix="fix the YAML syntax") from exc
    return load_config_dict(data, str(path))


def scene_config(cfg: PipelineConfig, scene: str) -> SceneConfig:
    """The defaults with ``overrides[scene]`` merged over them."""
    merged = deep_merge(dataclasses.asdict(cfg.defaults), cfg.overrides.get(scene, {}))
    return build(SceneConfig, merged)


def section_from_dict(section: str, data: dict[str, Any] | None, source: str = "--config-json") -> Any:
    """Build one stage section (``sfm``, ``masks``, ...) from a dict, validating it against the schema."""
    if section not in STAGE_SECTIONS:
        raise ConfigError(f"unknown config section '{section}'", fix=f"use one of {sorted(STAGE_SECTIONS)}")
    check(STAGE_SECTIONS[section], data or {}, source=source, root=f"defaults.{section}")
    return build(SceneConfig, {section: data or {}}).__getattribute__(section)


def check_results_beside_data(cfg: PipelineConfig) -> None:
    """``results`` must be a folder of its own: neither the ``data`` folder nor inside one of its scenes
    (the stages never write into a dataset and would refuse every output there)."""
    data, results = Path(cfg.data).expanduser().resolve(), Path(cfg.results).expanduser().resolve()
    fix = "set 'results' to a folder of its own beside the datasets, e.g. results: results"
    if results == data:
        raise ConfigError(f"'results' ({cfg.results}) is the 'data' folder ({cfg.data}); every output would be "
                          "written among the datasets", fix=fix)
    for folder in (results, *results.parents):
        if folder.parent == data and any((folder / part).is_dir() for part in ("images", "sparse")):
            raise ConfigError(f"'results' ({cfg.results}) lies inside the scene {folder.name} of the 'data' "
                              f"folder ({cfg.data}); dataset folders are never written", fix=fix)


def discover_scenes(cfg: PipelineConfig) -> list[str]:
    """Scenes listed in the config, else every ``<data>/<scene>`` with an ``images/`` folder; ``results``
    checked first (:func:`check_results_beside_data`)."""
    check_results_beside_data(cfg)
    data = Path(cfg.data)
    if cfg.scenes:
        missing = [s for s in cfg.scenes if not (data / s / "images").is_dir()]
        if missing:
            raise ConfigError(
                f"listed scenes have no images/ folder: {', '.join(missing)}",
                path=data,
                fix="check the scene names in 'scenes' or the 'data' directory (a scene folder holds its photos in "
                "images/, or one video, *.mp4 or *.mov)",
            )
        return list(cfg.scenes)
    if not data.is_dir():
        raise ConfigError("dataset directory not found", path=data, fix="set 'data' in config.yaml")
    scenes = sorted(p.name for p in data.iterdir() if (p / "images").is_dir())
    if not scenes:
        raise ConfigError(
            "no scenes found (no <scene>/images folder)",
            path=data,
            fix="put each scene's photos in <data>/<scene>/images/ (or its video in <data>/<scene>/), or set 'data' "
            "in config.yaml",
        )
    unknown = sorted(set(cfg.overrides) - set(scenes))
    if unknown:
        raise ConfigError(
            f"overrides given for unknown scenes: {', '.join(unknown)}",
            fix=f"rename them to one of: {', '.join(scenes)}",
        )
    return scenes


def trainer_options(cfg: PipelineConfig, scene: str, method: str) -> dict[str, Any]:
    """The trainer config tree of ``method`` on ``scene``: the scene's ``train.options`` and
    ``iterations``, the method's overrides (:func:`method_overrides`) merged over them (a method's own
    ``schedule.iterations`` wins), ``backend`` and ``device``; then a method's ``budget: F`` scales every
    iteration count by F (:func:`rtsplat.train_config.scale_budget`), and ``budget: 300s`` sets the time budget
    ``schedule.seconds`` (:func:`budget_seconds`). A method's ``time_of`` is not in the tree: its seconds are
    known once the other run has finished (``rtsplat train --seconds-of``). Validated: an unknown or bad key is
    a ConfigError."""
    from rtsplat.train_config import TrainConfig as TrainerConfig
    from rtsplat.train_config import scale_budget

    if method not in cfg.methods:
        raise ConfigError(f"unknown method {method!r}", fix=f"add it under 'methods' (known: {sorted(cfg.methods)})")
    train = scene_config(cfg, scene).train
    overrides = method_overrides(cfg, method)
    budget = overrides.pop("budget", None)
    tree = copy.deepcopy(train.options)
    if train.iterations is not None:
        tree = deep_merge(tree, {"schedule": {"iterations": train.iterations}})
    tree = deep_merge(tree, overrides)
    tree["backend"] = train.backend
    tree["device"] = train.device
    label = "defaults" if scene == "__defaults__" else f"scene {scene}"
    where = f"methods.{method} ({label}, merged with train.options)"
    try:
        trainer = TrainerConfig.from_dict(tree).validate()
        if budget is not None:
            seconds = budget_seconds(budget)
            if seconds is not None:
                tree = dataclasses.replace(trainer, schedule=dataclasses.replace(trainer.schedule, seconds=seconds))
                tree = tree.validate().to_dict()
            else:
                tree = scale_budget(trainer, float(budget)).validate().to_dict()
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}", fix="use the trainer's keys (rtsplat/train_config.py) and a budget > 0: "
                          "a factor (budget: 2) or a time (budget: 300s, budget: 5min)") from exc
    return tree


BUDGET_TIME = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(s|min|h)\s*$")
BUDGET_UNITS = {"s": 1.0, "min": 60.0, "h": 3600.0}


def budget_seconds(budget: Any) -> float | None:
    """A method's ``budget`` as seconds when it is a time (``300s``, ``5min``, ``1.5h``: the trainer's
    ``schedule.seconds``), None when it is a factor on every iteration count (a number); anything else is a
    ConfigError."""
    if isinstance(budget, str):
        match = BUDGET_TIME.match(budget)
        if match is None or float(match.group(1)) <= 0:
            raise ConfigError(f"budget {budget!r} is not a time: write a number of seconds, minutes or hours with "
                              "its unit, e.g. 300s, 5min or 1.5h")
        return float(match.group(1)) * BUDGET_UNITS[match.group(2)]
    if isinstance(budget, bool) or not isinstance(budget, (int, float)):
        raise ConfigError(f"budget must be a number (a factor on every iteration count) or a time such as 300s, got "
                          f"{budget!r}")
    return None


def slurm_resources(cfg: PipelineConfig, rule: str, scene: str | None = None, method: str | None = None) -> dict:
    """The SLURM resources of a job of ``rule`` (the executor plugin's names): ``runtime`` in minutes (a
    training job's from its method's iterations, or its time budget, on ``scene``), ``slurm_partition`` and
    ``slurm_account`` ("" leaves the choice to the cluster) and ``gpu`` (0 for the rules that do not use one)."""
    from rtsplat.train_config import TrainConfig as TrainerConfig

    slurm = cfg.slurm
    own = build(SlurmRuleConfig, dict(slurm.rules.get(rule) or {}))  # the tree keeps the rules' entries as dicts
    gpus = slurm.gpus if rule in SLURM_GPU_RULES else 0
    if own.minutes is not None:
        minutes = own.minutes
    elif rule == "train":
        # a run with the time of another method's: that method's length
        method = method_roles(cfg)[method].time_of or method
        schedule = TrainerConfig.from_dict(trainer_options(cfg, scene, method)).schedule
        if schedule.seconds is not None:  # a time budget: twice it (evaluations and checkpoints are not in it)
            minutes = slurm.train_minutes + math.ceil(2 * schedule.seconds / 60)
        else:
            minutes = slurm.train_minutes + math.ceil(slurm.train_minutes_per_1000_iterations * schedule.iterations
                                                      / 1000)
    else:
        minutes = SLURM_MINUTES[rule]
    partition = own.partition or (gpus and slurm.gpu_partition) or slurm.partition or ""
    return {"runtime": int(minutes), "slurm_partition": partition, "slurm_account": own.account or slurm.account or "",
            "gpu": int(gpus)}


def method_overrides(cfg: PipelineConfig, method: str) -> dict[str, Any]:
    """The trainer overrides of ``method`` (its keys less the role keys, ``budget`` included). A repeat
    reruns the method it names with ``of``: its own keys are merged over that method's, so ``{role: repeat,
    of: 2dgs, seed: 1}`` trains 2DGS's config with seed 1."""
    own = {key: value for key, value in (cfg.methods[method] or {}).items() if key not in ROLE_KEYS}
    role = method_roles(cfg)[method]
    if role.role != "repeat":
        return own
    rerun = {key: value for key, value in (cfg.methods[role.of] or {}).items() if key not in ROLE_KEYS}
    return deep_merge(rerun, own)


def train_json(cfg: PipelineConfig, scene: str, method: str, quote: bool = True) -> str:
    """:func:`trainer_options` as JSON for ``rtsplat train --config-json`` (shell-quoted unless ``quote=False``)."""
    text = json.dumps(trainer_options(cfg, scene, method), sort_keys=True)
    return shlex.quote(text) if quote else text


def method_roles(cfg: PipelineConfig) -> dict[str, MethodRole]:
    """Every method's :class:`MethodRole`, in the order of ``methods``.

    A method without ``role`` is a baseline, except that the first method listed is the main one when
    no method says ``role: main``. Exactly one main method; a repeat names with ``of`` another method
    that is not a repeat itself; ``of`` belongs to repeats only. Anything else is a ConfigError."""
    explicit = {name: (opts or {}).get("role") for name, opts in cfg.methods.items()}
    mains = [name for name, role in explicit.items() if role == "main"]
    if len(mains) > 1:
        raise ConfigError(f"several methods have role main: {', '.join(mains)}",
                          fix="give exactly one method 'role: main' (the others: baseline, ablation or repeat)")
    main = mains[0] if mains else next(iter(cfg.methods))
    roles = {}
    for name, opts in cfg.methods.items():
        role = explicit[name] or ("main" if name == main else "baseline")
        of = (opts or {}).get("of")
        if role == "repeat":
            if of not in cfg.methods or of == name or explicit.get(of) == "repeat":
                raise ConfigError(f"methods.{name}.of is {of!r}; a repeat must name the method it reruns",
                                  fix=f"set 'of' to one of {sorted(m for m in cfg.methods if m != name)} "
                                  "that is not a repeat itself")
        elif of is not None:
            raise ConfigError(f"methods.{name}.of is set but its role is {role}",
                              fix="remove 'of', or set 'role: repeat' when the method reruns another one")
        roles[name] = MethodRole(role, of, _time_of(cfg, name, of))
    return roles


def _time_of(cfg: PipelineConfig, name: str, of: str | None) -> str | None:
    """The method whose run's training time ``name`` trains for (its ``time_of``; a repeat without one: that of
    the method it reruns), checked: another method that has no ``time_of`` itself, and no ``budget`` beside it."""
    opts = cfg.methods[name] or {}
    time_of = opts.get("time_of", (cfg.methods[of] or {}).get("time_of") if of else None)
    if time_of is None:
        return None
    if time_of not in cfg.methods or time_of == name or (cfg.methods[time_of] or {}).get("time_of") is not None:
        others = sorted(m for m in cfg.methods if m != name)
        raise ConfigError(f"methods.{name}.time_of is {time_of!r}; it must name another method, one that does not "
                          "take its time from a third", fix=f"set it to one of {others}")
    if "budget" in opts or (of and "budget" in (cfg.methods[of] or {})):
        raise ConfigError(f"methods.{name} has both time_of and budget; time_of sets the time budget",
                          fix="drop one of them")
    return time_of


def main_method(cfg: PipelineConfig) -> str:
    """The method with role main (:func:`method_roles`): the one the workflow renders the edits for."""
    return next(name for name, r in method_roles(cfg).items() if r.role == "main")


def video_methods(cfg: PipelineConfig, scene: str) -> list[str]:
    """The methods the workflow renders a camera-path video of on ``scene``: the main method, then the
    scene's ``video.baselines`` that are among the methods; none when ``video.enabled`` is false."""
    video = scene_config(cfg, scene).video
    if not video.enabled:
        return []
    main = main_method(cfg)
    return [main, *(m for m in dict.fromkeys(video.baselines) if m in cfg.methods and m != main)]


def roles_json(cfg: PipelineConfig, quote: bool = True) -> str:
    """:func:`method_roles` as JSON for ``rtsplat report --roles-json`` (shell-quoted unless ``quote=False``)."""
    text = json.dumps({name: dataclasses.asdict(r) for name, r in method_roles(cfg).items()})
    return shlex.quote(text) if quote else text


def check_methods(cfg: PipelineConfig, scenes: typing.Iterable[str] = ()) -> None:
    """Check the methods' roles and build every method's trainer config for the defaults and each given or
    overridden scene, so a bad key fails when the config is loaded, not hours later when its job starts."""
    method_roles(cfg)
    for scene in dict.fromkeys([*scenes, *cfg.overrides, "__defaults__"]):
        for method in cfg.methods:
            trainer_options(cfg, scene, method)


def render_edit_args(cfg: PipelineConfig, scene: str, edit: str) -> str:
    """``--edit ...`` arguments of a named edit of the scene's render section (shell-quoted)."""
    edits = scene_config(cfg, scene).render.edits
    if edit not in edits:
        raise ConfigError(f"unknown edit {edit!r}", fix=f"define it under render.edits (known: {sorted(edits)})")
    return " ".join(f"--edit {shlex.quote(value)}" for value in edits[edit])


def section_json(cfg: PipelineConfig, scene: str, section: str, quote: bool = True) -> str:
    """One stage section of a scene's config as JSON (shell-quoted), for the rules' ``--config-json``."""
    text = json.dumps(dataclasses.asdict(getattr(scene_config(cfg, scene), section)), sort_keys=True)
    return shlex.quote(text) if quote else text


# ----------------------------------------------------------------------------------------------
# shared CLI options of the stages


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("configuration (defaults apply when none is given)")
    group.add_argument("--config", type=Path, help="config.yaml to read this stage's settings from")
    group.add_argument("--scene", help="scene name whose overrides apply (with --config)")
    group.add_argument("--config-json", help="this stage's config section as JSON (used by the workflow)")


def stage_config_from_args(args: argparse.Namespace, section: str, overrides: dict[str, Any] | None = None) -> Any:
    """A stage's config section from ``--config-json``, else ``--config``/``--scene``, else the defaults;
    then :func:`apply_overrides` with ``overrides`` (the stage's own flags: config key -> value)."""
    if getattr(args, "config_json", None):
        try:
            data = json.loads(args.config_json)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--config-json is not valid JSON ({exc})", fix="pass a JSON object") from exc
        cfg = section_from_dict(section, data)
    elif getattr(args, "config", None):
        pipeline = load_config(args.config)
        cfg = getattr(scene_config(pipeline, args.scene) if args.scene else pipeline.defaults, section)
    else:
        cfg = STAGE_SECTIONS[section]()
    return apply_overrides(section, cfg, overrides or {})


def apply_overrides(section: str, cfg: Any, overrides: dict[str, Any]) -> Any:
    """``cfg`` (a stage section) with the keys of ``overrides`` replaced, validated like config values.

    ``overrides`` maps a key of the section (dotted for nested keys, e.g. ``onnx.model``) to its
    command-line value; ``None`` means the flag was not given. A bad value is a :class:`ConfigError`
    naming the key."""
    given: dict[str, Any] = {}
    for key, value in overrides.items():
        if value is None:
            continue
        *parents, leaf = key.split(".")
        node = given
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    if not given:
        return cfg
    flags = ", ".join(f"{section}.{key}" for key, value in overrides.items() if value is not None)
    data = deep_merge(dataclasses.asdict(cfg), given)
    return section_from_dict(section, data, source=f"command-line override of {flags}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="rtsplat config tools")
    parser.add_argument("--write-schema", action="store_true", help=f"regenerate {SCHEMA_PATH}")
    parser.add_argument("--check", type=Path, help="validate a config.yaml")
    args = parser.parse_args(argv)

    def work() -> None:
        if args.write_schema:  # the project's own file, not a path the user names
            write_text_atomic(SCHEMA_PATH, json_schema_text())
            print(f"wrote {SCHEMA_PATH}")
        if args.check:
            load_config(args.check)
            print(f"{args.check}: OK")

    return run_command("rtsplat.config", work)


if __name__ == "__main__":
    sys.exit(main())
