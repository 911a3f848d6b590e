"""``rtsplat masks``: transparent-surface masks (white = see-through surface), one PNG per image.

Three ways (function API :func:`make_masks`; :func:`resolve_source` decides ``masks.source: auto``):

* **ingest** ``<scene>/transparent_masks/``: one mask per photo, named like the photo (``IMG_0001.JPG``),
  after its stem with any image extension (``IMG_0001.png``) or COLMAP's way (``IMG_0001.JPG.png``)
  (:func:`match_masks`); names and sizes are validated against the images, masks are binarised (JPEG
  masks with a tolerance for compression noise, :func:`interpret_mask`), coverage is reported; masks are
  read as given (white = see-through) unless ``masks.polarity: black``, and white covering most of the
  photos is flagged, never inverted (:func:`decide_polarity`);
* **propagate** the masks of a few marked photos (at least 3: mask files that fewer than half the photos
  have, and boxes and polygons drawn in ``masks.marks``, several per photo unioned, :func:`check_marks`,
  :func:`marks_to_masks`) to every photo through the SfM cameras of ``--sfm`` (:mod:`rtsplat.masks_propagate`);
  the summary records each mark's source (``mark_sources``: file, or the kinds of its shapes: polygon, box,
  filled box) and each mask's source (``mask_sources``: given, propagated, empty, unregistered);
* **segment** with a local ONNX model through onnxruntime (:class:`OnnxSegmenter`): the common SAM
  and SAM2 exports (an image encoder plus a prompted mask decoder; the kind is detected from the
  decoder's input names) prompted by the points/box of the config, or a plain "image in, mask
  logits out" model.

Output folder: ``<stem>.png`` masks (8-bit 0/255 PNGs whatever the input format; only when there are
masks) and ``summary.json`` with ``has_masks``, ``source``, per-image coverage and the content fingerprint
of each photo (``photos``, :func:`rtsplat.io.manifest.photo_fingerprints`: ``rtsplat prepare`` refuses masks
of other photos). A scene without
masks gets ``has_masks: false`` and is trained without transparency.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rtsplat.config import (
    MaskMark,
    MaskPropagationConfig,
    MasksConfig,
    OnnxSegmenterConfig,
    add_config_arguments,
    stage_config_from_args,
)
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.images import (
    IMAGE_EXTENSIONS,
    list_images,
    read_header,
    read_image,
    read_mask,
    validate_image_set,
    write_mask,
)
from rtsplat.io.manifest import photo_fingerprints, photos_fingerprint
from rtsplat.io.outputs import check_output_dir, output_dir


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


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
    mask_kinds: dict[str, int] = field(default_factory=dict)  # ingest: how many masks of each kind
    without_mask: list[str] = field(default_factory=list)  # ingest with allow_missing: photos given empty masks
    marked: list[str] = field(default_factory=list)  # propagate: the photos whose masks were given
    mark_sources: dict[str, str] = field(default_factory=dict)  # propagate: per marked photo file | polygon | box
    # (GrabCut's cut inside it) | filled box (GrabCut found no object inside it: the box as drawn); a mark of several
    # shapes lists their kinds joined by ", " (e.g. "polygon, polygon")
    mask_sources: dict[str, str] = field(default_factory=dict)  # propagate: per photo given | propagated | empty
    # | unregistered (rtsplat.masks_propagate.PropagatedMask.source)
    refined: list[str] = field(default_factory=list)  # propagate: photos whose propagated mask was refined
    refinement: str = ""  # propagate: what refined them, grabcut | watershed | onnx (<model kind>)
    scene_dir: str = ""  # the dataset scene they were made for (for messages)
    images_fingerprint: str = ""  # rtsplat.io.manifest.photos_fingerprint of its photos
    photos: dict[str, str] = field(default_factory=dict)  # rtsplat.io.manifest.photo_fingerprints of its photos


# ----------------------------------------------------------------------------------------------
# ONNX segmenter


def _onnx_dtype(type_str: str):
    return {
        "tensor(float)": np.float32,
        "tensor(float16)": np.float16,
        "tensor(double)": np.float64,
        "tensor(int64)": np.int64,
        "tensor(int32)": np.int32,
        "tensor(bool)": np.bool_,
    }.get(type_str, np.float32)


def _fixed(dim) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


class OnnxSegmenter:
    """Run a SAM, SAM2 or plain segmentation ONNX model on one image at a time.

    ``__call__(image)`` takes RGB float ``[H, W, 3]`` in [0, 1] and returns mask logits ``[H, W]``.

    SAM (original export): the decoder takes ``image_embeddings``, ``point_coords``,
    ``point_labels``, ``mask_input``, ``has_mask_input`` and usually ``orig_im_size``; the image is
    resized so its longest side is the encoder size (1024) and padded at the right/bottom.
    SAM2: the decoder takes ``image_embed`` and ``high_res_feats_0/1`` instead; the image is resized
    to the square encoder size without keeping the aspect ratio. Both normalise with ImageNet
    mean/std. Without ``orig_im_size`` the decoder returns low-resolution masks that are mapped back
    here (undoing the padding for SAM). Multi-mask outputs are reduced to the mask with the best
    predicted IoU.
    """

    def __init__(self, cfg: OnnxSegmenterConfig, boxes_per_image: bool = False) -> None:
        import onnxruntime as ort

        self.cfg = cfg
        if not cfg.model:
            raise PipelineError(
                "no ONNX model configured",
                path="config: masks.onnx.model",
                fix="set masks.onnx.model to a local .onnx file, or masks.source: none",
            )
        self.decoder = self._session(ort, cfg.model, "masks.onnx.model")
        self.inputs = {i.name: i for i in self.decoder.get_inputs()}
        self.kind = self.detect_kind() if cfg.kind == "auto" else cfg.kind
        self.encoder = None
        if self.kind in ("sam", "sam2"):
            if not cfg.encoder:
                raise PipelineError(
                    f"{cfg.model} is a {self.kind.upper()} mask decoder; it needs the image encoder too",
                    path="config: masks.onnx.encoder",
                    fix="set masks.onnx.encoder to the encoder .onnx of the same export",
                )
            self.encoder = self._session(ort, cfg.encoder, "masks.onnx.encoder")
            if not cfg.points and cfg.box is None and not boxes_per_image:
                raise PipelineError(
                    f"a {self.kind.upper()} model needs a prompt",
                    path="config: masks.onnx.points",
                    fix="set masks.onnx.points ([[x, y], ...] as fractions of the image) or masks.onnx.box",
                )
            if cfg.points and len(cfg.point_labels) not in (0, len(cfg.points)):
                raise PipelineError(
                    "masks.onnx.point_labels must have one label per point",
                    path="config: masks.onnx.point_labels",
                    fix="give one label (1 = glass, 0 = background) per point, or leave it empty for all 1",
                )

    @staticmethod
    def _session(ort, path: str, key: str):
        if not Path(path).is_file():
            raise PipelineError(
                "ONNX model file not found",
                path=path,
                fix=f"set {key} to an existing local .onnx file (no download is attempted)",
            )
        try:
            return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as exc:
            raise PipelineError(
                f"onnxruntime cannot load the model ({exc})", path=path, fix="export the model again (ONNX opset >= 13)"
            ) from exc

    def detect_kind(self) -> str:
        names = set(self.inputs)
        if "image_embeddings" in names:
            return "sam"
        if "image_embed" in names or any(n.startswith("high_res_feats") for n in names):
            return "sam2"
        if len(names) == 1 and len(next(iter(self.inputs.values())).shape) == 4:
            return "plain"
        raise PipelineError(
            f"cannot tell what kind of segmenter this is (inputs: {sorted(names)})",
            path=self.cfg.model,
            fix="use a SAM/SAM2 decoder export or a plain model with one [1, 3, H, W] input, or set masks.onnx.kind",
        )

    # -- plain models ------------------------------------------------------------------------
    def _plain(self, image: np.ndarray) -> np.ndarray:
        import cv2

        h, w = image.shape[:2]
        inp = next(iter(self.inputs.values()))
        th, tw = _fixed(inp.shape[2]) or h, _fixed(inp.shape[3]) or w
        x = cv2.resize(image, (tw, th), interpolation=cv2.INTER_AREA) if (th, tw) != (h, w) else image
        if self.cfg.normalize == "imagenet":
            x = (x - IMAGENET_MEAN) / IMAGENET_STD
        x = np.ascontiguousarray(x.transpose(2, 0, 1)[None]).astype(_onnx_dtype(inp.type))
        out = np.asarray(self.decoder.run(None, {inp.name: x})[0], dtype=np.float32)
        out = out.reshape((-1,) + out.shape[-2:])
        logits = out[0] if out.shape[0] == 1 else out[-1] - out[0]  # 2 classes: glass - background
        if logits.shape != (h, w):
            logits = cv2.resize(logits, (w, h), interpolation=cv2.INTER_LINEAR)
        return logits

    # -- SAM / SAM2 --------------------------------------------------------------------------
    def _encoder_size(self) -> tuple[int, int]:
        inp = self.encoder.get_inputs()[0]
        shape = inp.shape
        if len(shape) == 4:  # [1, 3, H, W]
            return _fixed(shape[2]) or 1024, _fixed(shape[3]) or 1024
        if len(shape) == 3:  # [H, W, 3]
            return _fixed(shape[0]) or 1024, _fixed(shape[1]) or 1024
        return 1024, 1024

    def _encode(self, image: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, tuple[int, int]]:
        """Encoder outputs by name, the per-axis scale original -> model pixels, the resized size."""
        import cv2

        h, w = image.shape[:2]
        sh, sw = self._encoder_size()
        if self.kind == "sam":
            s = min(sh / h, sw / w)
            nh, nw = int(round(h * s)), int(round(w * s))
            scale = np.array([s, s], dtype=np.float32)
        else:
            nh, nw = sh, sw
            scale = np.array([sw / w, sh / h], dtype=np.float32)
        resized = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR)
        inp = self.encoder.get_inputs()[0]
        if len(inp.shape) == 3:  # HWC 0..255: the model normalises itself; pad when its size is fixed
            fh, fw = _fixed(inp.shape[0]), _fixed(inp.shape[1])
            x = np.zeros((fh, fw, 3), np.float32) if fh and fw else np.zeros((nh, nw, 3), np.float32)
            x[:nh, :nw] = resized * 255.0
            x = x.astype(_onnx_dtype(inp.type))
        else:
            norm = (resized - IMAGENET_MEAN) / IMAGENET_STD
            padded = np.zeros((sh, sw, 3), np.float32)
            padded[:nh, :nw] = norm
            x = np.ascontiguousarray(padded.transpose(2, 0, 1)[None]).astype(_onnx_dtype(inp.type))
        outs = self.encoder.run(None, {inp.name: x})
        names = [o.name for o in self.encoder.get_outputs()]
        feats = dict(zip(names, outs, strict=True))
        embed_name = "image_embeddings" if self.kind == "sam" else "image_embed"
        if embed_name not in feats and len(outs) == 1:
            feats = {embed_name: outs[0]}
        return feats, scale, (nh, nw)

    def _prompt(self, h: int, w: int, scale: np.ndarray,
                box: tuple[float, float, float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        coords, labels = [], []
        for i, (x, y) in enumerate(cfg.points):
            coords.append([x * w, y * h])
            labels.append(cfg.point_labels[i] if cfg.point_labels else 1)
        if box is None and cfg.box is not None:
            box = (cfg.box[0] * w, cfg.box[1] * h, cfg.box[2] * w, cfg.box[3] * h)
        if box is not None:
            x0, y0, x1, y1 = box
            coords += [[x0, y0], [x1, y1]]
            labels += [2, 3]
        elif self.kind == "sam":
            coords.append([0.0, 0.0])  # SAM's padding point when there is no box
            labels.append(-1)
        pts = np.asarray(coords, dtype=np.float32) * scale[None]
        return pts[None], np.asarray(labels, dtype=np.float32)[None]

    def _sam(self, image: np.ndarray, box: tuple[float, float, float, float] | None = None) -> np.ndarray:
        import cv2

        h, w = image.shape[:2]
        feats, scale, (nh, nw) = self._encode(image)
        coords, labels = self._prompt(h, w, scale, box)
        feeds = dict(feats)
        feeds.update(
            point_coords=coords,
            point_labels=labels,
            mask_input=np.zeros((1, 1, 256, 256), np.float32),
            has_mask_input=np.zeros(1, np.float32),
            orig_im_size=np.array([h, w], np.float32),
        )
        missing = sorted(set(self.inputs) - set(feeds))
        if missing:
            raise PipelineError(
                f"the decoder needs inputs this pipeline cannot provide: {missing}",
                path=self.cfg.model,
                fix="use the encoder of the same export (its outputs must be named like the decoder inputs)",
            )
        feeds = {
            k: np.asarray(v).astype(_onnx_dtype(self.inputs[k].type)) for k, v in feeds.items() if k in self.inputs
        }
        outs = self.decoder.run(None, feeds)
        names = [o.name for o in self.decoder.get_outputs()]
        by_name = dict(zip(names, outs, strict=True))
        masks = np.asarray(by_name.get("masks", outs[0]), dtype=np.float32)
        masks = masks.reshape((-1,) + masks.shape[-2:])
        iou = by_name.get("iou_predictions", by_name.get("iou_scores"))
        best = int(np.argmax(np.asarray(iou).reshape(-1))) if iou is not None and masks.shape[0] > 1 else 0
        logits = masks[best]
        if logits.shape == (h, w):
            return logits
        # low-resolution masks cover the model input: undo the padding, then resize to the image
        sh, sw = self._encoder_size()
        full = cv2.resize(logits, (sw, sh), interpolation=cv2.INTER_LINEAR)
        return cv2.resize(full[:nh, :nw], (w, h), interpolation=cv2.INTER_LINEAR)

    def __call__(self, image: np.ndarray, box: tuple[float, float, float, float] | None = None) -> np.ndarray:
        """Mask logits of ``image``; ``box`` (x0, y0, x1, y1 in pixels) is the box prompt instead of the config's
        (SAM/SAM2; a plain model's logits outside it are set to -inf)."""
        if self.kind != "plain":
            return self._sam(image, box)
        logits = self._plain(image)
        if box is not None:
            inside = np.zeros(logits.shape, bool)
            x0, y0, x1, y1 = (int(round(c)) for c in box)
            inside[max(0, y0):max(0, y1), max(0, x0):max(0, x1)] = True
            logits = np.where(inside, logits, -np.inf)
        return logits


# ----------------------------------------------------------------------------------------------
# the stage


MASK_NAMING = "<photo name> (IMG_0001.JPG), <photo stem>.<image extension> (IMG_0001.png) or <photo name>.png"


def check_unique_stems(images: list[Path]) -> None:
    """Refuse photos that share a stem (``a.jpg``, ``a.png``): the stage writes one ``<stem>.png`` per photo."""
    by_stem: dict[str, Path] = {}
    for img in images:
        if img.stem in by_stem:
            raise PipelineError(
                f"two photos share a file stem: {by_stem[img.stem].name} and {img.name} "
                f"(their masks would both be {img.stem}.png)",
                path=img.parent,
                fix="rename the photos so their names without extension are unique",
            )
        by_stem[img.stem] = img


def match_masks(images: list[Path], mask_dir: Path) -> dict[Path, Path | None]:
    """Each photo's mask file in ``mask_dir`` (None: it has none); the one lookup of dataset masks by name.

    A mask file belongs to a photo when its name without the extension is the photo's stem or the photo's
    full name, with any image extension in any case (:data:`MASK_NAMING`): ``IMG_0001.JPG``,
    ``IMG_0001.jpg``, ``IMG_0001.png`` and ``IMG_0001.JPG.png`` all belong to ``IMG_0001.JPG``. Stems are
    compared exactly (case-sensitive, like the file system). Raises :class:`PipelineError` when two files
    belong to one photo, when a mask belongs to no photo (naming one expected and one found name), and when
    two photos share a stem (their masks would both be written as ``<stem>.png``).
    """
    images = sorted(images, key=lambda p: p.name)
    check_unique_stems(images)
    files = list_images(mask_dir)
    by_key: dict[str, list[Path]] = {}
    for mask in files:
        by_key.setdefault(mask.stem, []).append(mask)
    found: dict[Path, Path | None] = {}
    owner: dict[Path, Path] = {}
    for img in images:
        candidates = by_key.get(img.stem, []) + (by_key.get(img.name, []) if img.name != img.stem else [])
        if len(candidates) > 1:
            names = " and ".join(m.name for m in candidates)
            raise PipelineError(
                f"photo {img.name} has {len(candidates)} masks: {names}",
                path=mask_dir,
                fix=f"keep one mask per photo (delete or move {candidates[-1].name})",
            )
        mask = candidates[0] if candidates else None
        if mask is not None and mask in owner:
            raise PipelineError(
                f"mask {mask.name} belongs to two photos: {owner[mask].name} and {img.name}",
                path=mask,
                fix="rename the photos so no photo's name is another photo's stem",
            )
        if mask is not None:
            owner[mask] = img
        found[img] = mask
    unmatched = [m for m in files if m not in owner]
    if unmatched and not owner:
        photo = images[0]
        expected = photo.name if photo.suffix == ".png" else f"{photo.name} or {photo.stem}.png"
        raise PipelineError(
            f"none of the {len(files)} masks matches a photo: expected e.g. {expected} (for photo {photo.name}), "
            f"found e.g. {unmatched[0].name}",
            path=mask_dir,
            fix=f"name each mask after its photo: {MASK_NAMING}; or point masks.dir at the right folder",
        )
    if unmatched:
        stem = unmatched[0].stem
        photos = f"images/{stem}.*" + (f" or images/{stem}" if Path(stem).suffix.lower() in IMAGE_EXTENSIONS else "")
        raise PipelineError(
            f"mask has no matching image (expected a photo {photos})",
            path=unmatched[0],
            fix=f"name each mask after its photo ({MASK_NAMING}) or remove masks of deleted photos",
        )
    return found


MIDTONE_LIMIT = 0.25  # a colour mask with more pixels strictly between dark and bright is refused as a photo
LOSSY_EXTENSIONS = (".jpg", ".jpeg", ".webp")  # mask files whose pixels may carry compression noise
# lossy masks: largest difference between the colour channels of a pixel that still counts as grey. The
# black-and-white JPEG masks of a real capture (119 masks) have colour fringes of up to 0.14 on their
# edges (median 0.09); a coloured mask (one colour on black) differs by the brightness of its colour, far more
LOSSY_GREY_TOLERANCE = 0.25


def interpret_mask(pixels: np.ndarray, threshold: float, path: Path, lossy: bool = False) -> tuple[np.ndarray, str]:
    """A mask file's pixels (float [H, W, C] in the file's range scaled to [0, 1]) as (bool [H, W], kind):

    - ``label map``: the values 0 and 1 stored as integers (1/255 or 1/65535 once scaled): 1 is the surface;
    - ``alpha``: a flat colour with the mask in the alpha channel;
    - ``colour``: a coloured mask (e.g. green on black): the brightest colour channel against ``threshold``;
    - ``grey``: the first channel against ``threshold``.

    ``lossy`` (JPEG, WebP): compression leaves values near black and white and slightly coloured fringes at
    the edges, so channels that differ by up to :data:`LOSSY_GREY_TOLERANCE` still make a grey mask, read as
    the mean of the colour channels; ``threshold`` (``masks.threshold``, 0.5 by default: halfway between
    black and white) then cuts the ringing off on both sides. A 0/1 label map does not survive lossy
    compression; save those as PNG.

    A colour image that is mostly mid-tones (a photo saved as a mask) raises :class:`PipelineError`.
    """
    colour = pixels[..., :3] if pixels.shape[2] >= 3 else pixels[..., :1]
    values = np.unique(colour)
    if len(values) == 2 and values[0] == 0 and values[1] <= 1 / 255 + 1e-6:
        return colour.max(-1) > 0, "label map"
    channel, kind = pixels[..., 0], "grey"
    grey_tolerance = LOSSY_GREY_TOLERANCE if lossy else 1 / 255
    if pixels.shape[2] in (2, 4) and float(channel.max(initial=0.0)) == float(channel.min(initial=0.0)):
        channel, kind = pixels[..., -1], "alpha"
    elif pixels.shape[2] >= 3 and np.abs(colour - colour[..., :1]).max(initial=0.0) > grey_tolerance:
        channel, kind = colour.max(-1), "colour"
    elif lossy and pixels.shape[2] >= 3:
        channel = colour.mean(-1)
    midtones = float(((channel > 0.1) & (channel < 0.9)).mean())
    if kind == "colour" and midtones > MIDTONE_LIMIT:
        raise PipelineError(
            f"this does not look like a mask: {100 * midtones:.0f}% of its pixels are neither dark nor bright "
            f"({kind} image)", path=path,
            fix="save masks as black and white (white = see-through surface), a 0/1 label map, or one colour on black",
        )
    return channel >= threshold, kind


def ingest_masks(
    images: list[Path], mask_dir: Path, out: Path, cfg: MasksConfig, progress: bool
) -> tuple[dict[str, float], dict[str, int], list[str]]:
    """Masks of ``images`` found in ``mask_dir`` by :func:`match_masks`, written to ``out`` as ``<stem>.png``
    as they are (white = the value :func:`interpret_mask` finds). Returns the per-image coverage, how many
    masks of each kind, and the photos without a mask (empty masks; an error unless ``masks.allow_missing``)."""
    from tqdm import tqdm

    from rtsplat.io.images import read_raw_pixels

    masks = match_masks(images, mask_dir)
    missing = [img.name for img in images if masks[img] is None]
    if missing and not cfg.allow_missing:
        first = Path(missing[0])
        raise PipelineError(
            f"no mask for image {first.name} ({len(missing)} of {len(images)} photos have none): looked for "
            f"{first.name}, {first.stem}.<image extension> and {first.name}.png",
            path=mask_dir,
            fix="add the missing masks, set masks.allow_missing: true to read those photos as having no "
            "see-through surface (empty masks), or masks.source: propagate to carry the given masks to them "
            "through the SfM cameras",
        )
    coverage, kinds = {}, {}
    for img in tqdm(images, desc="masks", unit="img", disable=not progress):
        header = read_header(img)
        mpath = masks[img]
        if mpath is None:
            mask = np.zeros((header.height, header.width), bool)
        else:
            lossy = mpath.suffix.lower() in LOSSY_EXTENSIONS
            mask, kind = interpret_mask(read_raw_pixels(mpath), cfg.threshold, mpath, lossy)
            kinds[kind] = kinds.get(kind, 0) + 1
            if mask.shape != (header.height, header.width):
                raise PipelineError(
                    f"mask is {mask.shape[1]}x{mask.shape[0]} but image {img.name} is {header.width}x{header.height}",
                    path=mpath,
                    fix="export the mask at the image's resolution (masks of images_N folders do not fit images/)",
                )
        write_mask(out / f"{img.stem}.png", mask)
        coverage[img.stem] = float(mask.mean())
    return coverage, kinds, missing


@dataclass(frozen=True)
class PolarityDecision:
    """Which mask colour is read as see-through (``white`` or ``black``), why, and a warning (empty when
    there is none) for masks that look unusual: under ``masks.polarity: auto`` the masks are kept as given
    whatever they cover, and white covering more than ``masks.max_coverage`` of the photos on average is
    flagged, naming the photos it covers most of and the fix."""

    polarity: str
    reason: str
    warning: str = ""


HIGH_COVERAGE_EXAMPLES = 3  # photos a high-coverage warning names


def decide_polarity(coverage: dict[str, float], cfg: MasksConfig, what: str = "the mask files") -> PolarityDecision:
    """The polarity of mask files of these coverages (by photo stem or name): ``masks.polarity`` when set;
    ``auto`` keeps them as given (white = see-through) and never inverts on coverage, since glass that fills
    the view (a shop window, an aquarium, a windshield from the driver's seat) covers most of each photo just
    as an inverted mask of a small pane does; it warns when white covers more than ``masks.max_coverage`` on
    average. ``what`` names the masks in the messages."""
    mean = float(np.mean(list(coverage.values()))) if coverage else 0.0
    if cfg.polarity == "white":
        return PolarityDecision("white", f"masks.polarity: white: white = see-through (white covers "
                                f"{100 * mean:.1f}% of the photos on average in {what})")
    if cfg.polarity == "black":
        return PolarityDecision("black", f"masks.polarity: black: {what} inverted, black = see-through (black "
                                f"covers {100 * (1 - mean):.1f}% of the photos on average)")
    reason = (f"masks.polarity: auto: white = see-through, kept as given (white covers {100 * mean:.1f}% of the "
              f"photos on average in {what})")
    if mean <= cfg.max_coverage:
        return PolarityDecision("white", reason)
    most = sorted(coverage.items(), key=lambda item: (-item[1], item[0]))[:HIGH_COVERAGE_EXAMPLES]
    examples = ", ".join(f"{name} {100 * value:.0f}%" for name, value in most)
    warning = (f"white covers {100 * mean:.1f}% of the photos on average in {what} (more than masks.max_coverage "
               f"{100 * cfg.max_coverage:g}%; most: {examples}): kept as given, white = see-through. Right for "
               "glass that fills the view (a shop window, an aquarium, a windshield); if white marks what is "
               "not see-through instead, set masks.polarity: black (masks.polarity: white silences this)")
    return PolarityDecision("white", reason, warning)


def _logit(threshold: float) -> float:
    """The mask-logit cut of a probability threshold (0 at the ends, where it has none)."""
    return float(np.log(threshold / (1 - threshold))) if 0 < threshold < 1 else 0.0


def segment_masks(images: list[Path], out: Path, cfg: MasksConfig, progress: bool) -> tuple[dict, str]:
    from tqdm import tqdm

    seg = OnnxSegmenter(cfg.onnx)
    thr = _logit(cfg.threshold)
    coverage = {}
    for img in tqdm(images, desc=f"segment ({seg.kind})", unit="img", disable=not progress):
        mask = seg(read_image(img)) > thr
        write_mask(out / f"{img.stem}.png", mask)
        coverage[img.stem] = float(mask.mean())
    return coverage, seg.kind


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


def _shapes(mark: MaskMark) -> list[tuple[str, str, list]]:
    """A mark's boxes and polygons as (kind, config key below the photo's, corners or edges), in the order
    box, polygon, boxes, polygons."""
    shapes = [("box", "box", mark.box)] if mark.box is not None else []
    shapes += [("polygon", "polygon", mark.polygon)] if mark.polygon is not None else []
    shapes += [("box", f"boxes.{i}", box) for i, box in enumerate(mark.boxes or [])]
    shapes += [("polygon", f"polygons.{i}", polygon) for i, polygon in enumerate(mark.polygons or [])]
    return shapes


def check_marks(marks: dict[str, MaskMark | dict], images: list[Path]) -> dict[str, MaskMark]:
    """``masks.marks`` as :class:`MaskMark` by photo name, checked against the photos: a name that is no photo
    (the closest names suggested), no box or polygon, a polygon of fewer than 3 corners or no area, a box with
    x1 <= x0 or y1 <= y0, coordinates outside the photo. Errors name the photo and the shape's key (``box``,
    ``polygon``, ``boxes.<index>``, ``polygons.<index>``)."""
    import difflib

    from rtsplat.schema import from_dict, plain

    by_name = {img.name: img for img in images}
    checked = {}
    for name, mark in marks.items():
        key = f"config: masks.marks.{name}"
        if name not in by_name:
            close = difflib.get_close_matches(name, list(by_name), n=3, cutoff=0.5)
            raise PipelineError(
                f"marked view {name!r} is not a photo of the scene ({len(by_name)} photos"
                + (f"; closest names: {', '.join(close)})" if close else f", e.g. {', '.join(sorted(by_name)[:3])})"),
                path=key, fix="use the photo's file name as it is in images/ (with its extension)",
            )
        mark = mark if isinstance(mark, MaskMark) else from_dict(MaskMark, plain(mark), root=f"masks.marks.{name}")
        if not _shapes(mark):
            raise PipelineError(
                "a mark needs a box or a polygon", path=key,
                fix="give box: [x0, y0, x1, y1], polygon: [[x, y], ...], or several as boxes: [...] and "
                "polygons: [...] (pixels of the photo)",
            )
        header = read_header(by_name[name])
        w, h = header.width, header.height
        for kind, where, shape in _shapes(mark):
            if kind == "box":
                x0, y0, x1, y1 = (list(shape) + [0.0] * 4)[:4]
                if len(shape) != 4 or not (x1 > x0 and y1 > y0):
                    raise PipelineError(
                        f"box {list(shape)} is not [x0, y0, x1, y1] with x1 > x0 and y1 > y0", path=f"{key}.{where}",
                        fix="give the left, top, right and bottom edges in pixels (x to the right, y down)",
                    )
                corners = np.array([[x0, y0], [x1, y1]], np.float64)
            else:
                corners = np.asarray(shape, np.float64)
                if corners.ndim != 2 or corners.shape[1] != 2 or len(corners) < 3:
                    raise PipelineError(
                        f"polygon of {len(shape)} point(s): a polygon needs at least 3 corners [x, y]",
                        path=f"{key}.{where}", fix="give the outline's corners [[x, y], ...] in pixels of the photo",
                    )
                x, y = corners[:, 0], corners[:, 1]
                if abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))) < 1.0:
                    raise PipelineError(
                        "the polygon has no area (its corners lie on a line)", path=f"{key}.{where}",
                        fix="give the outline's corners in order around the see-through surface",
                    )
            outside = (corners[:, 0] < 0) | (corners[:, 0] > w) | (corners[:, 1] < 0) | (corners[:, 1] > h)
            if outside.any():
                raise PipelineError(
                    f"{kind} corner {corners[outside][0].tolist()} lies outside the photo ({w}x{h} pixels: x in "
                    f"0..{w}, y in 0..{h})", path=f"{key}.{where}",
                    fix=f"give coordinates in pixels of {name} as it is in images/ (not of a downsampled copy)",
                )
        checked[name] = mark
    return checked


def mark_to_mask(mark: MaskMark, image: Path, settings: MaskPropagationConfig) -> tuple[np.ndarray, str]:
    """The mask of one view's checked mark at the photo's size, the union of its shapes: a polygon filled, a
    box cut out with GrabCut (:func:`rtsplat.masks_propagate.box_mask`), and the mark's source: its shapes'
    kinds (``polygon``, ``box``, ``filled box`` where GrabCut found no object inside the box) joined by
    commas, e.g. ``polygon, polygon``."""
    from rtsplat.masks_propagate import box_mask, polygon_mask

    header = read_header(image)
    mask = np.zeros((header.height, header.width), bool)
    pixels, kinds = None, []
    for kind, _, shape in _shapes(mark):
        if kind == "polygon":
            mask |= polygon_mask(np.asarray(shape), header.width, header.height)
            kinds.append("polygon")
            continue
        pixels = read_image(image) if pixels is None else pixels
        cut, kept = box_mask(pixels, tuple(shape), settings)
        mask |= cut
        kinds.append("box" if kept else "filled box")
    return mask, ", ".join(kinds)


def marks_to_masks(marks: dict[str, MaskMark], images: list[Path],
                   cfg: MasksConfig) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The masks of the config's marks (checked by :func:`check_marks`) at their photos' sizes and each mark's
    source (:func:`mark_to_mask`)."""
    by_name = {img.name: img for img in images}
    masks, sources = {}, {}
    for name, mark in marks.items():
        masks[name], sources[name] = mark_to_mask(mark, by_name[name], cfg.propagate)
    return masks, sources


@dataclass
class Propagation:
    """What :func:`propagate_from_marked` wrote: per-image coverage, each photo's mask source, each marked
    photo's mark source, the photos whose propagated mask was refined and by what, and the polarity of the
    mask files (:func:`decide_polarity`)."""

    coverage: dict[str, float]
    sources: dict[str, str]
    mark_sources: dict[str, str]
    refined: list[str]
    refinement: str  # what refined them: grabcut | watershed | onnx (<model kind>); empty when none was
    polarity: PolarityDecision


def propagate_from_marked(images: list[Path], mask_dir: Path, sfm_dir: Path | None, out: Path, cfg: MasksConfig,
                          progress: bool) -> Propagation:
    """The marked views (photos with a mask in ``mask_dir``, and the boxes and polygons of ``masks.marks``,
    :func:`check_marks`, :func:`marks_to_masks`) carried to every photo through the cameras of
    ``<sfm_dir>/sparse/0`` (:func:`rtsplat.masks_propagate.propagate_masks`), written to ``out``."""
    from tqdm import tqdm

    from rtsplat.io.colmap import is_model_dir, load_model
    from rtsplat.io.images import read_raw_pixels
    from rtsplat.masks_propagate import propagate_masks

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
        threshold = _logit(cfg.threshold)

        def segment(image: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
            return segmenter(image, box) > threshold

        refinement = f"onnx ({segmenter.kind})"
    coverage, sources, refined = {}, {}, []
    results = propagate_masks(model, marked, sorted(by_name), lambda n: read_image(by_name[n]), cfg.propagate,
                              size_of, str(mask_dir) + (" or config: masks.marks" if marks else ""), segment)
    for result in tqdm(results, total=len(by_name), desc="propagate", unit="img", disable=not progress):
        stem = by_name[result.name].stem
        write_mask(out / f"{stem}.png", result.mask)
        coverage[stem] = float(result.mask.mean())
        sources[result.name] = result.source
        if result.refined:
            refined.append(result.name)
            refinement = refinement or result.refinement
    return Propagation(coverage, sources, dict(sorted(mark_sources.items())), refined, refinement if refined else "",
                       polarity)


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
        polarity, refinement = PolarityDecision("white", ""), ""
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
            polarity, mark_sources = propagation.polarity, propagation.mark_sources
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
            mask_kinds=kinds,
            without_mask=missing,
            marked=sorted(n for n, s in sources.items() if s == "given"),
            mark_sources=mark_sources,
            mask_sources=sources,
            refined=refined,
            refinement=refinement,
            scene_dir=str(scene_dir.resolve()),
            images_fingerprint=photos_fingerprint(photos),
            photos=photos,
        )
        write_json_atomic(tmp / "summary.json", asdict(summary))
    if summary.polarity_warning:
        _log(f"masks {scene_dir}: WARNING: {summary.polarity_warning}")
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
            for src, why in (("empty", "the marked region does not project into them"),
                             ("unregistered", "SfM gave them no pose")):
                names = [n for n, v in s.mask_sources.items() if v == src]
                if names:
                    print(f"masks {args.scene_dir}: empty masks for {len(names)} photo(s), {why}: "
                          + ", ".join(names[:10]) + (" ..." if len(names) > 10 else ""))
    else:
        print(f"masks {args.scene_dir}: no masks (the scene is trained without transparency)")
    return 0
