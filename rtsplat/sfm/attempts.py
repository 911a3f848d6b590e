"""SfM attempts with pycolmap and the bounded ladder of retries that ``rtsplat sfm`` climbs.

One attempt is SIFT extraction, matching and mapping with one :class:`AttemptSettings`
(:func:`run_attempt`). The features and matches come from a :class:`rtsplat.sfm.matching.FeatureStore`,
so a retry that changes only the mapper costs only the mapping.

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

import time
from dataclasses import asdict, dataclass, field, replace
from typing import Literal

from rtsplat.config import SfmConfig
from rtsplat.sfm.matching import FeatureStore
from rtsplat.sfm.stats import judge, model_stats

Mapper = Literal["incremental", "global"]


@dataclass(frozen=True)
class AttemptSettings:
    """Everything one SfM attempt varies."""

    mapper: Mapper
    matcher: Literal["exhaustive", "sequential", "vocabtree"]
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
    mean_track_length: float | None = None
    num_observations: int = 0
    seconds: float = 0.0
    step_seconds: dict[str, float] = field(default_factory=dict)  # the steps it ran (see rtsplat.sfm.stats.STEPS)
    acceptable: bool = False
    verdict: str = ""  # why the model is (not) acceptable
    unregistered: list[str] = field(default_factory=list)
    pose_errors: dict | None = None  # against a reference model, when the scene has one


def first_settings(cfg: SfmConfig, matcher: str) -> AttemptSettings:
    """The configured settings with ``matcher`` (:func:`rtsplat.sfm.matching.choose_matcher`)."""
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
        f"views have too few verified matches with {s.matcher} matching: match every pair",
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
    matching_steps = ([_exhaustive] if first.matcher != "exhaustive" else []) + [_more_features]
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


def run_attempt(store: FeatureStore, index: int, name: str, reason: str, s: AttemptSettings):
    """Run one attempt in ``store``'s work folder; returns (AttemptResult, the largest pycolmap.Reconstruction or None).

    The result's ``step_seconds`` are the extraction and matching it was the first to need, and its mapping.
    """
    import pycolmap

    t0 = time.perf_counter()
    before = store.times.as_dict()
    cfg = store.cfg
    db = store.matches(s, s.matcher)
    out = store.work / f"attempt_{index}"
    out.mkdir()
    with store.times.step("mapping"):
        if s.mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.num_threads = cfg.num_threads
            options.random_seed = cfg.seed
            options.min_model_size = 2
            recs = pycolmap.global_mapping(db, store.images_dir, out, options=options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.num_threads = cfg.num_threads
            options.random_seed = cfg.seed
            options.min_model_size = 2
            options.mapper.init_min_num_inliers = s.init_min_num_inliers
            options.mapper.init_max_error = s.init_max_error
            options.mapper.abs_pose_min_num_inliers = s.abs_pose_min_num_inliers
            options.mapper.abs_pose_min_inlier_ratio = s.abs_pose_min_inlier_ratio
            recs = pycolmap.incremental_mapping(db, store.images_dir, out, options=options)
    rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
    stats = model_stats(rec, store.names)
    result = AttemptResult(name=name, reason=reason, settings=asdict(s), models=len(recs), **asdict(stats))
    result.seconds = time.perf_counter() - t0
    result.step_seconds = store.times.since(before)
    result.acceptable, result.verdict = judge(stats, cfg)
    return result, rec


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
    "AttemptSettings",
    "better",
    "denser_features",
    "describe",
    "first_settings",
    "next_attempt",
    "run_attempt",
]
