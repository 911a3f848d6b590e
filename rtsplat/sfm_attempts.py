"""SfM attempts with pycolmap and the bounded ladder of retries that ``rtsplat sfm`` climbs.

One attempt is SIFT extraction, matching and mapping with one :class:`AttemptSettings`. Attempts
that share the feature settings share the extracted features, and those that also share the
matching settings share the matches, so a retry that changes only the mapper costs only the mapping.

When views are missing from the largest model, :func:`next_attempt` picks the next settings from
what went wrong:

* views that are matched to other views but not registered (the incremental chain broke, e.g. on
  matches to reflections that move with the viewer, or the views ended up in other models): first
  the other mapper (global mapping solves all views at once from the pairwise geometry; incremental
  mapping when the global one was first), then the incremental mapper with relaxed initial-pair and
  registration thresholds;
* views with too few verified matches (poorly connected in the match graph): exhaustive instead of
  sequential matching, then more and weaker SIFT features (lower peak threshold, upsampled first
  octave) with guided matching;
* no model at all: relaxed thresholds first.

Each step is tried at most once; the caller bounds the number of attempts.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

from rtsplat.config import SfmConfig

Mapper = Literal["incremental", "global"]


@dataclass(frozen=True)
class AttemptSettings:
    """Everything one SfM attempt varies."""

    mapper: Mapper
    matcher: Literal["exhaustive", "sequential"]
    sift_peak_threshold: float
    sift_first_octave: int
    max_num_features: int
    guided_matching: bool
    init_min_num_inliers: int
    init_max_error: float
    abs_pose_min_num_inliers: int
    abs_pose_min_inlier_ratio: float

    def features_key(self) -> tuple:
        return (self.sift_peak_threshold, self.sift_first_octave, self.max_num_features)

    def matches_key(self) -> tuple:
        return (*self.features_key(), self.matcher, self.guided_matching)


@dataclass
class AttemptResult:
    """What one attempt produced (the model itself stays in the work folder)."""

    name: str
    reason: str
    settings: dict
    registered: int = 0  # images in the largest model
    models: int = 0
    num_points: int = 0
    mean_reprojection_error: float | None = None
    median_points_per_image: float | None = None
    seconds: float = 0.0
    acceptable: bool = False
    verdict: str = ""  # why the model is (not) acceptable
    unregistered: list[str] = field(default_factory=list)
    pose_errors: dict | None = None  # against a reference model, when the scene has one


def first_settings(cfg: SfmConfig, num_images: int) -> AttemptSettings:
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "exhaustive" if num_images <= cfg.exhaustive_max_images else "sequential"
    return AttemptSettings(
        mapper=cfg.mapper,
        matcher=matcher,
        sift_peak_threshold=cfg.sift_peak_threshold,
        sift_first_octave=cfg.sift_first_octave,
        max_num_features=cfg.max_num_features,
        guided_matching=cfg.guided_matching,
        init_min_num_inliers=cfg.init_min_num_inliers,
        init_max_error=cfg.init_max_error,
        abs_pose_min_num_inliers=cfg.abs_pose_min_num_inliers,
        abs_pose_min_inlier_ratio=cfg.abs_pose_min_inlier_ratio,
    )


# --- the ladder -------------------------------------------------------------------------------------


def _other_mapper(s: AttemptSettings) -> tuple[str, str, AttemptSettings]:
    other: Mapper = "incremental" if s.mapper == "global" else "global"
    why = (
        "views are matched but not registered: global mapping solves every view at once from the pairwise "
        "geometry instead of growing one model view by view"
        if other == "global"
        else "views are matched but not registered: incremental mapping registers views one by one"
    )
    return f"{other}_mapping", why, replace(s, mapper=other)


def _relaxed_mapper(s: AttemptSettings) -> tuple[str, str, AttemptSettings]:
    relaxed = replace(
        s,
        mapper="incremental",
        init_min_num_inliers=max(15, min(s.init_min_num_inliers, 50)),
        init_max_error=max(s.init_max_error, 6.0),
        abs_pose_min_num_inliers=max(8, min(s.abs_pose_min_num_inliers, 15)),
        abs_pose_min_inlier_ratio=min(s.abs_pose_min_inlier_ratio, 0.1),
    )
    return (
        "relaxed_mapper",
        "the initial pair or the registration of further views failed the mapper's thresholds: fewer inliers "
        "for the initial pair and for each new view, a lower inlier ratio",
        relaxed,
    )


def _exhaustive(s: AttemptSettings) -> tuple[str, str, AttemptSettings]:
    return (
        "exhaustive_matching",
        "views have too few verified matches with sequential matching: match every pair",
        replace(s, matcher="exhaustive"),
    )


def denser_features(s: AttemptSettings) -> AttemptSettings:
    """``s`` with more, weaker SIFT features (half the peak threshold, upsampled first octave) and guided matching."""
    return replace(
        s,
        sift_peak_threshold=min(s.sift_peak_threshold, 0.02 / 3) / 2,
        sift_first_octave=min(s.sift_first_octave, -1),
        max_num_features=max(s.max_num_features, 8192),
        guided_matching=True,
    )


def _more_features(s: AttemptSettings) -> tuple[str, str, AttemptSettings]:
    return (
        "more_features",
        "views have too few verified matches: more, weaker SIFT features (half the peak threshold, "
        "upsampled first octave) and guided matching",
        denser_features(s),
    )


def next_attempt(
    tried: list[str], first: AttemptSettings, best: AttemptResult | None, poorly_matched: list[str]
) -> tuple[str, str, AttemptSettings] | None:
    """The next (name, reason, settings) to try, or None when every suitable step was tried.

    ``best``: the best attempt so far (None: no model at all); ``poorly_matched``: missing views with
    too few verified matches to register.
    """
    base = first
    mapping_steps = [_other_mapper, _relaxed_mapper]
    matching_steps = ([_exhaustive] if first.matcher == "sequential" else []) + [_more_features]
    if best is None or best.registered == 0:
        order = [_relaxed_mapper, _other_mapper, *matching_steps]
    elif poorly_matched and len(poorly_matched) * 2 >= len(best.unregistered):
        order = [*matching_steps, *mapping_steps]
    else:
        order = [*mapping_steps, *matching_steps]
    chosen: dict[str, AttemptSettings] = {}
    for step in order:
        name, reason, settings = step(base)
        if name in tried or name in chosen:
            continue
        # a matching step keeps the mapper that registered the most so far
        if step in matching_steps and best is not None:
            settings = replace(settings, mapper=best.settings["mapper"])
        return name, reason, settings
    return None


# --- one attempt ------------------------------------------------------------------------------------


class AttemptRunner:
    """Runs attempts in ``work``; reuses extracted features and matches between attempts."""

    def __init__(self, images_dir: Path, names: list[str], work: Path, cfg: SfmConfig, mask_dir: Path | None):
        self.images_dir = images_dir
        self.names = names
        self.work = work
        self.cfg = cfg
        self.mask_dir = mask_dir
        self._features: dict[tuple, Path] = {}
        self._matches: dict[tuple, Path] = {}

    def _extract(self, s: AttemptSettings) -> Path:
        import pycolmap

        key = s.features_key()
        if key in self._features:
            return self._features[key]
        db = self.work / f"features_{len(self._features)}.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = self.cfg.camera_model
        if self.mask_dir is not None:
            reader.mask_path = str(self.mask_dir)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = self.cfg.max_image_size
        extraction.num_threads = self.cfg.num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = s.max_num_features
        extraction.sift.peak_threshold = s.sift_peak_threshold
        extraction.sift.first_octave = s.sift_first_octave
        mode = pycolmap.CameraMode.SINGLE if self.cfg.single_camera else pycolmap.CameraMode.AUTO
        pycolmap.extract_features(
            db,
            self.images_dir,
            image_names=self.names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        self._features[key] = db
        return db

    def match_database(self, s: AttemptSettings) -> Path:
        import pycolmap

        key = s.matches_key()
        if key in self._matches:
            return self._matches[key]
        features = self._extract(s)
        db = self.work / f"matches_{len(self._matches)}.db"
        shutil.copyfile(features, db)
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = self.cfg.num_threads
        matching.guided_matching = s.guided_matching
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = self.cfg.seed
        if s.matcher == "exhaustive":
            pycolmap.match_exhaustive(
                db, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
            )
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = self.cfg.sequential_overlap
            pairing.loop_detection = False  # needs a vocabulary tree
            pycolmap.match_sequential(
                db,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        self._matches[key] = db
        return db

    def poorly_matched(
        self, s: AttemptSettings, names: list[str], min_inliers: int = 15, min_pairs: int = 2
    ) -> list[str]:
        """Of ``names``, those with fewer than ``min_pairs`` verified pairs of ``min_inliers`` inliers."""
        import pycolmap

        db = pycolmap.Database.open(str(self.match_database(s)))
        try:
            ids = {im.image_id: im.name for im in db.read_all_images()}
            pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        finally:
            db.close()
        good = dict.fromkeys(ids.values(), 0)
        for pair_id, n in zip(pair_ids, inliers, strict=True):
            if n >= min_inliers:
                a, b = pycolmap.pair_id_to_image_pair(pair_id)
                good[ids[a]] += 1
                good[ids[b]] += 1
        return [n for n in names if good.get(n, 0) < min_pairs]

    def run(self, index: int, name: str, reason: str, s: AttemptSettings):
        """Run one attempt; returns (AttemptResult, the largest pycolmap.Reconstruction or None)."""
        import pycolmap

        t0 = time.perf_counter()
        db = self.match_database(s)
        out = self.work / f"attempt_{index}"
        out.mkdir()
        if s.mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.num_threads = self.cfg.num_threads
            options.random_seed = self.cfg.seed
            options.min_model_size = 2
            recs = pycolmap.global_mapping(db, self.images_dir, out, options=options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.num_threads = self.cfg.num_threads
            options.random_seed = self.cfg.seed
            options.min_model_size = 2
            options.mapper.init_min_num_inliers = s.init_min_num_inliers
            options.mapper.init_max_error = s.init_max_error
            options.mapper.abs_pose_min_num_inliers = s.abs_pose_min_num_inliers
            options.mapper.abs_pose_min_inlier_ratio = s.abs_pose_min_inlier_ratio
            recs = pycolmap.incremental_mapping(db, self.images_dir, out, options=options)
        rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
        stats = model_stats(rec, self.names)
        result = AttemptResult(name=name, reason=reason, settings=asdict(s), models=len(recs), **asdict(stats))
        result.seconds = time.perf_counter() - t0
        result.acceptable, result.verdict = judge(stats, self.cfg)
        return result, rec


@dataclass
class ModelStats:
    """What :func:`judge` weighs in a model."""

    registered: int = 0
    num_points: int = 0
    mean_reprojection_error: float | None = None  # None: no point observations
    median_points_per_image: float | None = None
    unregistered: list[str] = field(default_factory=list)


def model_stats(rec, names: list[str]) -> ModelStats:
    """Registration, points and reprojection error of a pycolmap.Reconstruction (or None) over ``names``."""
    if rec is None or rec.num_reg_images() == 0:
        return ModelStats(unregistered=list(names))
    registered = {rec.image(i).name for i in rec.reg_image_ids()}
    per_image = sorted(rec.image(i).num_points3D for i in rec.reg_image_ids())
    return ModelStats(
        registered=len(registered),
        num_points=int(rec.num_points3D()),
        mean_reprojection_error=(
            float(rec.compute_mean_reprojection_error()) if rec.compute_num_observations() > 0 else None
        ),
        median_points_per_image=float(per_image[len(per_image) // 2]),
        unregistered=[n for n in names if n not in registered],
    )


def judge(r: ModelStats | AttemptResult, cfg: SfmConfig) -> tuple[bool, str]:
    """(acceptable, why) for a model's stats."""
    if r.registered == 0:
        return False, "no model"
    if r.mean_reprojection_error is None:
        return False, "the model has no 3D points"
    if r.mean_reprojection_error > cfg.max_reprojection_error:
        return False, (
            f"mean reprojection error {r.mean_reprojection_error:.3f} px is above "
            f"sfm.max_reprojection_error {cfg.max_reprojection_error:g}"
        )
    if r.median_points_per_image is not None and r.median_points_per_image < cfg.min_points_per_image:
        return False, (
            f"its images see a median of {r.median_points_per_image:.0f} 3D points, fewer than "
            f"sfm.min_points_per_image {cfg.min_points_per_image}"
        )
    return True, "acceptable"


def better(a: AttemptResult, b: AttemptResult | None) -> bool:
    """Whether ``a`` is a better choice than ``b``: acceptable first, then more views, then lower error."""
    if b is None:
        return True
    if a.acceptable != b.acceptable:
        return a.acceptable
    if a.registered != b.registered:
        return a.registered > b.registered
    ea = a.mean_reprojection_error if a.mean_reprojection_error is not None else float("inf")
    eb = b.mean_reprojection_error if b.mean_reprojection_error is not None else float("inf")
    return ea < eb


def describe(r: AttemptResult, total: int) -> str:
    """One line for the log and error messages."""
    err = "n/a" if r.mean_reprojection_error is None else f"{r.mean_reprojection_error:.3f} px"
    s = r.settings
    knobs = (
        f"mapper {s['mapper']}, {s['matcher']} matching{' (guided)' if s['guided_matching'] else ''}, "
        f"SIFT peak {s['sift_peak_threshold']:.4g} first octave {s['sift_first_octave']}"
    )
    if s["mapper"] == "incremental":
        knobs += (
            f", init {s['init_min_num_inliers']} inliers / {s['init_max_error']:g} px, "
            f"abs pose {s['abs_pose_min_num_inliers']} inliers / ratio {s['abs_pose_min_inlier_ratio']:g}"
        )
    pose = ""
    if r.pose_errors:
        pose = (
            f", vs reference: rotation {r.pose_errors['rotation_error_deg_mean']:.3f} deg mean, "
            f"centre {100 * r.pose_errors['center_error_relative']:.2f}%"
        )
    verdict = "" if r.acceptable else f" [not acceptable: {r.verdict}]"
    return (
        f"{r.name}: {r.registered}/{total} registered (largest of {r.models} models), {err}, "
        f"{r.num_points} points, {r.seconds:.1f} s{pose}{verdict} ({knobs})"
    )


__all__ = [
    "AttemptResult",
    "AttemptRunner",
    "AttemptSettings",
    "ModelStats",
    "better",
    "denser_features",
    "describe",
    "first_settings",
    "judge",
    "model_stats",
    "next_attempt",
]
