"""The ``rtsplat masks`` stage: :func:`make_masks` ingests, propagates or segments the masks of a scene's
photos into the output folder with its ``summary.json`` (:class:`MasksSummary`); :func:`resolve_source`
decides ``masks.source: auto``; ``add_arguments`` and ``run`` are the CLI."""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.config import MasksConfig, add_config_arguments, stage_config_from_args
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.images import list_images, read_header, read_image, read_mask, validate_image_set, write_mask
from rtsplat.io.manifest import photo_fingerprints, photos_fingerprint
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.masks.ingest import (
    LOSSY_EXTENSIONS,
    MASK_NAMING,
    check_unique_stems,
    ingest_masks,
    interpret_mask,
    match_masks,
)
from rtsplat.masks.marks import check_marks, marks_to_masks
from rtsplat.masks.onnx import OnnxSegmenter, logit_threshold, segment_masks
from rtsplat.masks.polarity import PolarityDecision, decide_polarity

NEARLY_EMPTY = 0.001  # masks that cover less than this share of the photos on average are flagged


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def coverage_warning(coverage: dict[str, float], source: str, cfg: MasksConfig) -> str:
    """The warning for masks of ``source`` that cover almost nothing of the photos (less than
    :data:`NEARLY_EMPTY` on average), or, segmented by a model, more than ``masks.max_coverage`` (given masks
    get that one from :func:`rtsplat.masks.polarity.decide_polarity`); "" when they look usual."""
    if not coverage:
        return ""
    mean = float(np.mean(list(coverage.values())))
    kind = {"ingest": "given", "propagate": "propagated", "onnx": "segmented"}.get(source, source)
    if mean < NEARLY_EMPTY:
        fix = {"onnx": "check the model and its prompt (masks.onnx) and masks.threshold",
               "ingest": "check the mask files (masks.polarity: black if black marks the glass)",
               "propagate": "check the marked views' masks and marks"}.get(source, "check the masks")
        return (f"the {kind} masks cover {100 * mean:.2f}% of the photos on average: almost nothing is see-through; "
                f"{fix}, or set masks.source: none if the photos show no glass")
    if source == "onnx" and mean > cfg.max_coverage:
        return (f"the segmented masks cover {100 * mean:.1f}% of the photos on average (more than masks.max_coverage "
                f"{100 * cfg.max_coverage:g}%): almost everything is see-through; right for glass that fills the "
                "view, else check the model and its prompt (masks.onnx) and masks.threshold")
    return ""


@dataclass
class MasksSummary:
    has_masks: bool
    source: str  # "ingest" | "propagate" | "onnx" | "none"
    num_images: int
    mean_coverage: float = 0.0
    coverage: dict[str, float] = field(default_factory=dict)
    model_kind: str = ""
    polarity: str = "white"  # ingest, propagate: the mask files' colour read as see-through (decide_polarity)
    polarity_reason: str = ""
    polarity_warning: str = ""  # the masks look unusual (white covers most of the photos): check them; "" if not
    coverage_warning: str = ""  # the masks cover almost nothing (any source) or, segmented, almost everything
    mask_kinds: dict[str, int] = field(default_factory=dict)  # ingest: how many masks of each kind
    without_mask: list[str] = field(default_factory=list)  # ingest with allow_missing: photos given empty masks
    marked: list[str] = field(default_factory=list)  # propagate: the photos whose masks were given
    mark_sources: dict[str, str] = field(default_factory=dict)  # propagate: per marked photo file | polygon | box
    # (GrabCut's cut inside it) | filled box (GrabCut found no object inside it: the box as drawn); a mark of several
    # shapes lists their kinds joined by ", " (e.g. "polygon, polygon")
    mask_sources: dict[str, str] = field(default_factory=dict)  # propagate: per photo given | propagated | empty
    # | unregistered (rtsplat.masks.propagation.PropagatedMask.source)
    refined: list[str] = field(default_factory=list)  # propagate: photos whose propagated mask was refined
    refinement: str = ""  # propagate: what refined them, grabcut | watershed | onnx (<model kind>)
    propagation_method: str = ""  # propagate: how the marks reached the other photos, hull | plane
    propagation_reason: str = ""  # propagate: why (rtsplat.masks.propagation.carry_marks)
    glass_plane: dict = field(default_factory=dict)  # propagate through a plane: its fit (GlassPlane.record)
    glass_panes: list[dict] = field(default_factory=list)  # marks of several panes: each with its plane (Pane.record)
    scene_dir: str = ""  # the dataset scene they were made for (for messages)
    images_fingerprint: str = ""  # rtsplat.io.manifest.photos_fingerprint of its photos
    photos: dict[str, str] = field(default_factory=dict)  # rtsplat.io.manifest.photo_fingerprints of its photos


def resolve_source(scene_dir: str | Path, cfg: MasksConfig, images: list[Path] | None = None) -> str:
    """``masks.source`` with ``auto`` decided: propagate when ``masks.marks`` marks views, or when fewer than
    half the photos have a mask in
    ``<scene>/<masks.dir>`` (the marked views; not with ``masks.allow_missing``), ingest when more have one
    (a missing mask is then an error, or an empty mask with ``masks.allow_missing``), else onnx when a model
    is set, else none."""
    if cfg.source != "auto":
        return cfg.source
    if cfg.marks:
        return "propagate"
    mask_dir = Path(scene_dir) / cfg.dir
    if not list_images(mask_dir):
        return "onnx" if cfg.onnx.model else "none"
    if cfg.allow_missing:
        return "ingest"
    images = images if images is not None else list_images(Path(scene_dir) / "images")
    found = match_masks(images, mask_dir)
    return "propagate" if 2 * sum(m is not None for m in found.values()) < len(found) else "ingest"


@dataclass
class Propagation:
    """What :func:`propagate_from_marked` wrote: per-image coverage, each photo's mask source, each marked
    photo's mark source, the photos whose propagated mask was refined and by what, the polarity of the
    mask files (:func:`decide_polarity`) and how the marks reached the other photos (hull or plane, and why)."""

    coverage: dict[str, float]
    sources: dict[str, str]
    mark_sources: dict[str, str]
    refined: list[str]
    refinement: str  # what refined them: grabcut | watershed | onnx (<model kind>); empty when none was
    polarity: PolarityDecision
    carried: dict  # how the marks reached the other photos (rtsplat.masks.propagation.Carrier.record)


def propagate_from_marked(images: list[Path], mask_dir: Path, sfm_dir: Path | None, out: Path, cfg: MasksConfig,
                          progress: bool) -> Propagation:
    """The marked views (photos with a mask in ``mask_dir``, and the boxes and polygons of ``masks.marks``,
    :func:`check_marks`, :func:`marks_to_masks`) carried to every photo through the cameras of
    ``<sfm_dir>/sparse/0`` (:func:`rtsplat.masks.propagation.propagate_masks`), written to ``out``."""
    from tqdm import tqdm

    from rtsplat.io.colmap import is_model_dir, load_model
    from rtsplat.io.images import read_raw_pixels
    from rtsplat.masks.propagation import carry_marks, propagate_masks

    marks = check_marks(cfg.marks, images)
    found = match_masks(images, mask_dir) if mask_dir.is_dir() else {img: None for img in images}
    both = {img.name: m for img, m in found.items() if m is not None and img.name in marks}
    if both:
        name = sorted(both)[0]
        raise PipelineError(
            f"{name} has a mask file ({both[name].name}) and a mark in the config ({len(both)} photo(s) have "
            f"both: {', '.join(sorted(both)[:5])})", path=f"config: masks.marks.{name}",
            fix=f"keep one of them: remove the mark from masks.marks or the mask file from {mask_dir.name}/",
        )
    where = f"{mask_dir.name}/" + (" or masks.marks" if marks else "")
    if sfm_dir is None or not is_model_dir(Path(sfm_dir) / "sparse" / "0"):
        given = sum(m is not None for m in found.values()) + len(marks)
        raise PipelineError(
            f"{given} of {len(images)} photos have a mask in {where}: propagating them to the others "
            "needs the SfM cameras (sfm/sparse/0)",
            path=sfm_dir if sfm_dir is not None else "--sfm",
            fix="run 'rtsplat sfm' first and pass its folder as --sfm (the workflow does this for masks.source "
            "propagate; sfm.use_masks must then be false)",
        )
    model = load_model(Path(sfm_dir) / "sparse" / "0")
    by_name = {img.name: img for img in images}
    marked = {}
    for img, mpath in found.items():
        if mpath is None:
            continue
        mask, _ = interpret_mask(read_raw_pixels(mpath), cfg.threshold, mpath, mpath.suffix.lower() in LOSSY_EXTENSIONS)
        header = read_header(img)
        if mask.shape != (header.height, header.width):
            raise PipelineError(
                f"mask is {mask.shape[1]}x{mask.shape[0]} but image {img.name} is {header.width}x{header.height}",
                path=mpath,
                fix="export the mask at the image's resolution (masks of images_N folders do not fit images/)",
            )
        marked[img.name] = mask
    polarity = PolarityDecision("white", "masks.marks: drawn marks are the see-through surface")
    if marked:
        polarity = decide_polarity({n: float(m.mean()) for n, m in marked.items()}, cfg, "the marked views' masks")
    if polarity.polarity == "black":
        marked = {n: ~m for n, m in marked.items()}
    mark_sources = dict.fromkeys(marked, "file")
    drawn, drawn_sources = marks_to_masks(marks, images, cfg)
    marked.update(drawn)
    mark_sources.update(drawn_sources)

    def size_of(name: str) -> tuple[int, int]:
        header = read_header(by_name[name])
        return header.width, header.height

    segment, refinement = None, ""
    if cfg.propagate.refine == "onnx" or (cfg.propagate.refine == "auto" and cfg.onnx.model):
        segmenter = OnnxSegmenter(cfg.onnx, boxes_per_image=True)
        threshold = logit_threshold(cfg.threshold)

        def segment(image: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
            return segmenter(image, box) > threshold

        refinement = f"onnx ({segmenter.kind})"
    coverage, sources, refined = {}, {}, []
    where = str(mask_dir) + (" or config: masks.marks" if marks else "")
    carrier = carry_marks(model, marked, cfg.propagate, where)
    results = propagate_masks(model, marked, sorted(by_name), lambda n: read_image(by_name[n]), cfg.propagate,
                              size_of, where, segment, carrier)
    for result in tqdm(results, total=len(by_name), desc="propagate", unit="img", disable=not progress):
        stem = by_name[result.name].stem
        write_mask(out / f"{stem}.png", result.mask)
        coverage[stem] = float(result.mask.mean())
        sources[result.name] = result.source
        if result.refined:
            refined.append(result.name)
            refinement = refinement or result.refinement
    return Propagation(coverage, sources, dict(sorted(mark_sources.items())), refined, refinement if refined else "",
                       polarity, carrier.record())


def make_masks(
    scene_dir: str | Path, out_dir: str | Path, cfg: MasksConfig | None = None, progress: bool = True,
    sfm_dir: str | Path | None = None,
) -> MasksSummary:
    """Ingest, propagate (with the SfM result ``sfm_dir``) or segment the masks of ``<scene_dir>/images`` into
    ``out_dir`` (atomically)."""
    cfg = cfg or MasksConfig()
    scene_dir = Path(scene_dir)
    check_output_dir(out_dir, "masks", inputs=[scene_dir, sfm_dir])
    images = [h.path for h in validate_image_set(scene_dir / "images", decode=False, log=_log)]
    mask_dir = scene_dir / cfg.dir
    source = resolve_source(scene_dir, cfg, images)
    if cfg.marks and source != "propagate":
        raise PipelineError(
            f"masks.marks marks {len(cfg.marks)} view(s) but masks.source is {source}: marks are carried to the "
            "other photos by source propagate", path="config: masks.marks",
            fix="set masks.source: propagate (or auto), or remove masks.marks",
        )
    if (source == "ingest" or (source == "propagate" and not cfg.marks)) and not mask_dir.is_dir():
        raise PipelineError(
            "mask folder not found",
            path=mask_dir,
            fix=f"put one mask per photo there ({MASK_NAMING}), set masks.dir, or masks.source: auto",
        )
    if source != "none":
        check_unique_stems(images)
    photos = photo_fingerprints(scene_dir / "images")
    with output_dir(out_dir, "masks", inputs=[scene_dir, sfm_dir]) as tmp:
        kind, kinds, missing, sources, refined, mark_sources = "", {}, [], {}, [], {}
        polarity, refinement, carried = PolarityDecision("white", ""), "", {}
        if source == "ingest":
            coverage, kinds, missing = ingest_masks(images, mask_dir, tmp, cfg, progress)
            without = {Path(name).stem for name in missing}
            polarity = decide_polarity({img.name: coverage[img.stem] for img in images if img.stem not in without},
                                       cfg)
            if polarity.polarity == "black":  # photos without a mask stay empty (no see-through surface)
                for stem in set(coverage) - without:
                    write_mask(tmp / f"{stem}.png", ~read_mask(tmp / f"{stem}.png"))
                    coverage[stem] = 1.0 - coverage[stem]
        elif source == "propagate":
            propagation = propagate_from_marked(
                images, mask_dir, None if sfm_dir is None else Path(sfm_dir), tmp, cfg, progress)
            coverage, sources, refined = propagation.coverage, propagation.sources, propagation.refined
            refinement = propagation.refinement
            polarity, mark_sources, carried = propagation.polarity, propagation.mark_sources, propagation.carried
        elif source == "onnx":
            coverage, kind = segment_masks(images, tmp, cfg, progress)
        else:
            coverage = {}
        summary = MasksSummary(
            has_masks=source != "none",
            source=source,
            num_images=len(images),
            mean_coverage=float(np.mean(list(coverage.values()))) if coverage else 0.0,
            coverage=coverage,
            model_kind=kind,
            polarity=polarity.polarity,
            polarity_reason=polarity.reason,
            polarity_warning=polarity.warning,
            coverage_warning=coverage_warning(coverage, source, cfg),
            mask_kinds=kinds,
            without_mask=missing,
            marked=sorted(n for n, s in sources.items() if s == "given"),
            mark_sources=mark_sources,
            mask_sources=sources,
            refined=refined,
            refinement=refinement,
            propagation_method=carried.get("method", ""),
            propagation_reason=carried.get("reason", ""),
            glass_plane=carried.get("plane") or {},
            glass_panes=carried.get("panes") or [],
            scene_dir=str(scene_dir.resolve()),
            images_fingerprint=photos_fingerprint(photos),
            photos=photos,
        )
        write_json_atomic(tmp / "summary.json", asdict(summary))
    for warning in (summary.polarity_warning, summary.coverage_warning):
        if warning:
            _log(f"masks {scene_dir}: WARNING: {warning}")
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene-dir", type=Path, required=True, help="dataset scene (<data>/<scene>)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (results/<scene>/masks)")
    parser.add_argument("--source", choices=["auto", "ingest", "propagate", "onnx", "none"],
                        help="override masks.source")
    parser.add_argument("--sfm", type=Path, help="output of 'rtsplat sfm' (needed by masks.source propagate)")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "masks", {"source": args.source})
    s = make_masks(args.scene_dir, args.out, cfg, sfm_dir=args.sfm)
    if s.has_masks:
        how = {"ingest": "ingested", "propagate": f"propagated from {len(s.marked)} marked views"}.get(
            s.source, f"segmented with ONNX ({s.model_kind})")
        cover = f"{100 * s.mean_coverage:.2f}%"
        print(f"masks {args.scene_dir}: {s.num_images} masks {how}, mean coverage {cover}")
        if s.source == "ingest":
            kinds = ", ".join(f"{n} {kind}" for kind, n in s.mask_kinds.items())
            print(f"masks {args.scene_dir}: mask files: {kinds or 'none'}; {s.polarity_reason}")
            if s.without_mask:
                print(f"masks {args.scene_dir}: {len(s.without_mask)} photo(s) without a mask read as having no "
                      f"see-through surface (masks.allow_missing), e.g. {s.without_mask[0]}")
        if s.source == "propagate":
            counts = {src: sum(v == src for v in s.mask_sources.values()) for src in set(s.mask_sources.values())}
            marked = ", ".join(f"{n} ({s.mark_sources.get(n, 'file')})" for n in s.marked)
            refined = f"{len(s.refined)} refined" + (f" with {s.refinement}" if s.refined else "")
            print(f"masks {args.scene_dir}: marked {marked}; " + ", ".join(
                f"{n} {src}" for src, n in sorted(counts.items())) + f"; {refined}")
            print(f"masks {args.scene_dir}: carried through the {s.propagation_method}: {s.propagation_reason}")
            for src, why in (("empty", "the marked region does not project into them"),
                             ("unregistered", "SfM gave them no pose")):
                names = [n for n, v in s.mask_sources.items() if v == src]
                if names:
                    print(f"masks {args.scene_dir}: empty masks for {len(names)} photo(s), {why}: "
                          + ", ".join(names[:10]) + (" ..." if len(names) > 10 else ""))
    else:
        print(f"masks {args.scene_dir}: no masks (the scene is trained without transparency)")
    return 0
