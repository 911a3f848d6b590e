"""The ONNX segmenter of ``masks.source: onnx`` (and of propagated masks' ``refine: onnx``): SAM, SAM2 or a plain
"image in, mask logits out" model run through onnxruntime on the CPU, one image at a time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rtsplat.config import MasksConfig, OnnxSegmenterConfig
from rtsplat.errors import PipelineError
from rtsplat.io.images import read_image, write_mask

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


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
        out = self._mask_output(self.decoder.run(None, {inp.name: x})[0], classes=2)
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

    def _mask_output(self, output, classes: int | None = None) -> np.ndarray:
        """The model's mask output as ``[N, H, W]`` logits, or a :class:`PipelineError` naming the model and the
        shape it produced when that is no mask (fewer than 2 dimensions, a side of 1 pixel, more than ``classes``
        masks) or holds values that are not numbers."""
        out = np.asarray(output, dtype=np.float32)
        count = int(np.prod(out.shape[:-2])) if out.ndim >= 2 else 0
        if out.ndim < 2 or min(out.shape[-2:]) < 2 or count < 1 or (classes is not None and count > classes):
            raise PipelineError(
                f"the model's output has shape {list(out.shape)}, which is no mask (expected [1, H, W] or "
                f"[1, 1, H, W] mask logits{', or [1, 2, H, W] for background and glass' if classes == 2 else ''})",
                path=self.cfg.model,
                fix="use a segmentation model whose first output is per-pixel mask logits (masks.onnx.model), "
                "or set masks.onnx.kind to what the model is",
            )
        if not np.isfinite(out).all():
            bad = int((~np.isfinite(out)).sum())
            raise PipelineError(
                f"the model's output (shape {list(out.shape)}) holds {bad} values that are not finite numbers "
                "(NaN or infinite)", path=self.cfg.model,
                fix="check the model's export and masks.onnx.normalize (the input scaling it expects)",
            )
        return out.reshape((-1,) + out.shape[-2:])

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
        masks = self._mask_output(by_name.get("masks", outs[0]))
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


def logit_threshold(threshold: float) -> float:
    """The mask-logit cut of a probability threshold (0 at the ends, where it has none)."""
    return float(np.log(threshold / (1 - threshold))) if 0 < threshold < 1 else 0.0


def segment_masks(images: list[Path], out: Path, cfg: MasksConfig, progress: bool) -> tuple[dict, str]:
    """Each photo's mask segmented by the model of ``masks.onnx``, written to ``out`` as ``<stem>.png`` (logits
    above the logit of ``masks.threshold``); returns the per-image coverage and the model's kind."""
    from tqdm import tqdm

    seg = OnnxSegmenter(cfg.onnx)
    thr = logit_threshold(cfg.threshold)
    coverage = {}
    for img in tqdm(images, desc=f"segment ({seg.kind})", unit="img", disable=not progress):
        mask = seg(read_image(img)) > thr
        write_mask(out / f"{img.stem}.png", mask)
        coverage[img.stem] = float(mask.mean())
    return coverage, seg.kind
