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
  :func:`marks_to_masks`) to every photo through the SfM cameras of ``--sfm`` (:mod:`rtsplat.masks.propagation`);
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

The package:

* :mod:`rtsplat.masks.stage`: the orchestrator :func:`make_masks`, :class:`MasksSummary`,
  :func:`resolve_source`, the propagate step's file handling (:func:`propagate_from_marked`) and the CLI
  (``add_arguments``, ``run``);
* :mod:`rtsplat.masks.ingest`: a dataset's mask files found by photo name, read whatever their kind, ingested;
* :mod:`rtsplat.masks.polarity`: which colour of the mask files is see-through (``masks.polarity``);
* :mod:`rtsplat.masks.marks`: the boxes and polygons of ``masks.marks`` checked and turned into masks;
* :mod:`rtsplat.masks.propagation`: the marked views' visual hull projected into every other view, refined;
* :mod:`rtsplat.masks.onnx`: the ONNX segmenter (SAM, SAM2, plain models).

onnxruntime and OpenCV are imported inside the functions that use them, so importing the package stays cheap.
"""

from rtsplat.masks.ingest import MASK_NAMING, check_unique_stems, ingest_masks, interpret_mask, match_masks
from rtsplat.masks.marks import check_marks, mark_to_mask, marks_to_masks
from rtsplat.masks.onnx import OnnxSegmenter, segment_masks
from rtsplat.masks.polarity import PolarityDecision, decide_polarity
from rtsplat.masks.stage import (
    MasksSummary,
    Propagation,
    add_arguments,
    make_masks,
    propagate_from_marked,
    resolve_source,
    run,
)

__all__ = [
    "MASK_NAMING", "MasksSummary", "OnnxSegmenter", "PolarityDecision", "Propagation", "add_arguments",
    "check_marks", "check_unique_stems", "decide_polarity", "ingest_masks", "interpret_mask", "make_masks",
    "mark_to_mask", "marks_to_masks", "match_masks", "propagate_from_marked", "resolve_source", "run",
    "segment_masks",
]
