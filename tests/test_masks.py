"""rtsplat masks: ingesting masks and segmenting with tiny SAM / SAM2 / plain ONNX models."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from fixtures_pipeline import make_corner_scene  # noqa: E402

from rtsplat.cli import main as cli_main  # noqa: E402
from rtsplat.config import MasksConfig, OnnxSegmenterConfig  # noqa: E402
from rtsplat.errors import PipelineError  # noqa: E402
from rtsplat.io.images import read_image, read_mask, write_mask, write_png  # noqa: E402
from rtsplat.masks import OnnxSegmenter, make_masks  # noqa: E402

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytestmark = pytest.mark.filterwarnings("ignore")  # torch.onnx exporter deprecation/tracer chatter


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("masks") / "scene"
    make_corner_scene(d, n_views=4, width=80, height=60, with_masks=True)
    return d


def test_ingest_validates_and_reports_coverage(scene, tmp_path):
    s = make_masks(scene, tmp_path / "out", progress=False)
    assert s.has_masks and s.source == "ingest" and s.num_images == 4
    for stem, cov in s.coverage.items():
        gt = read_mask(scene / "transparent_masks" / f"{stem}.png")
        out = read_mask(tmp_path / "out" / f"{stem}.png")
        assert np.array_equal(gt, out)
        assert cov == pytest.approx(gt.mean())
    assert 0.0 < s.mean_coverage < 0.5
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["has_masks"] is True


def test_ingest_binarises_grey_masks(tmp_path):
    d = tmp_path / "s"
    make_corner_scene(d, n_views=2, width=40, height=30)
    (d / "transparent_masks").mkdir()
    grey = np.zeros((30, 40), np.float32)
    grey[:, :10] = 200 / 255  # counts as white
    grey[:, 10:20] = 100 / 255  # counts as black
    for stem in ("view_000", "view_001"):
        write_png(d / "transparent_masks" / f"{stem}.png", grey)
    make_masks(d, tmp_path / "out", progress=False)
    m = read_mask(tmp_path / "out" / "view_000.png")
    assert m[:, :10].all() and not m[:, 10:].any()


def test_no_masks_means_no_transparency(tmp_path):
    d = tmp_path / "s"
    make_corner_scene(d, n_views=2, width=40, height=30)
    s = make_masks(d, tmp_path / "out", progress=False)
    assert not s.has_masks and s.source == "none"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".rtsplat-output", "summary.json"]


@pytest.mark.parametrize("problem", ["size", "extra", "missing"])
def test_bad_masks_name_the_file_and_keep_old_output(scene, tmp_path, problem):
    d = tmp_path / "s"
    import shutil

    shutil.copytree(scene, d)
    out = tmp_path / "out"
    make_masks(d, out, progress=False)
    before = (out / "summary.json").read_text()
    if problem == "size":
        bad = d / "transparent_masks" / "view_001.png"
        write_mask(bad, np.zeros((10, 10), bool))
        expect = ["view_001.png", "10x10", "80x60"]
    elif problem == "extra":
        bad = d / "transparent_masks" / "view_999.png"
        write_mask(bad, np.zeros((60, 80), bool))
        expect = ["view_999.png", "no matching image"]
    else:
        (d / "transparent_masks" / "view_002.png").unlink()
        expect = ["view_002", "allow_missing"]
    with pytest.raises(PipelineError) as err:
        make_masks(d, out, progress=False)
    for text in expect:
        assert text in str(err.value)
    assert (out / "summary.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "s"]  # no temporary leftovers
    if problem == "missing":
        s = make_masks(d, out, MasksConfig(allow_missing=True), progress=False)
        assert s.coverage["view_002"] == 0.0


def test_masks_cli(scene, tmp_path, capsys):
    assert cli_main(["masks", "--scene-dir", str(scene), "--out", str(tmp_path / "o")]) == 0
    assert "4 masks ingested" in capsys.readouterr().out
    assert cli_main(["masks", "--scene-dir", str(tmp_path / "nothing"), "--out", str(tmp_path / "o2")]) == 1
    assert "image folder does not exist" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()


# ------------------------------------------------------------------------------------------------
# tiny ONNX models with the input/output names of the real exports


class PlainNet(torch.nn.Module):
    """Logits > 0 where the red channel > 0.5."""

    def forward(self, image):
        return 20.0 * (image[:, :1] - 0.5)


class SamEncoder(torch.nn.Module):
    """[1, 3, 1024, 1024] normalised image -> 64x64 'embeddings' (16x16 average pooling)."""

    def __init__(self, out_names=("image_embeddings",)):
        super().__init__()
        self.n = len(out_names)

    def forward(self, image):
        e = torch.nn.functional.avg_pool2d(image, 16)
        if self.n == 1:
            return e
        return torch.nn.functional.avg_pool2d(image, 4), torch.nn.functional.avg_pool2d(image, 8), e


class SamEncoderHWC(torch.nn.Module):
    """Exports that take the resized image as [1024, 1024, 3] in 0..255 and normalise it themselves."""

    def forward(self, image):
        mean = torch.tensor([123.675, 116.28, 103.53])
        std = torch.tensor([58.395, 57.12, 57.375])
        x = ((image - mean) / std).permute(2, 0, 1)[None]
        return torch.nn.functional.avg_pool2d(x, 16)


def _box_and_red(embed, point_coords, ys, xs):
    """Logits > 0 inside the box (first two prompt points, in model pixels) where red > mean."""
    x0, y0 = point_coords[0, 0, 0], point_coords[0, 0, 1]
    x1, y1 = point_coords[0, 1, 0], point_coords[0, 1, 1]
    inside = (ys[:, None] > y0) & (ys[:, None] < y1) & (xs[None, :] > x0) & (xs[None, :] < x1)
    iy = torch.clamp((ys / 16).floor().long(), 0, 63)
    ix = torch.clamp((xs / 16).floor().long(), 0, 63)
    red = embed[0, 0][iy][:, ix] > 0
    return torch.where(inside & red, 5.0, -5.0)[None, None]


class SamDecoder(torch.nn.Module):
    """SAM-style decoder with orig_im_size: masks at the original size (SAM's resize + no padding)."""

    def forward(self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size):
        h, w = orig_im_size[0], orig_im_size[1]
        s = 1024.0 / torch.maximum(h, w)
        ys = (torch.arange(h.to(torch.int64), dtype=torch.float32) + 0.5) * s
        xs = (torch.arange(w.to(torch.int64), dtype=torch.float32) + 0.5) * s
        m = _box_and_red(image_embeddings, point_coords, ys, xs) + 0 * point_labels.sum()
        m = m + 0 * mask_input.sum() + 0 * has_mask_input.sum()
        return torch.cat([-m, m], 1), torch.tensor([[0.1, 0.9]])  # the best-IoU mask is the 2nd


class Sam2Decoder(torch.nn.Module):
    """SAM2-style decoder without orig_im_size: 256x256 low-resolution masks over the model input."""

    def forward(
        self, image_embed, high_res_feats_0, high_res_feats_1, point_coords, point_labels, mask_input, has_mask_input
    ):
        c = (torch.arange(256, dtype=torch.float32) + 0.5) * 4.0
        m = _box_and_red(image_embed, point_coords, c, c)
        extra = 0 * (
            high_res_feats_0.mean()
            + high_res_feats_1.mean()
            + point_labels.sum()
            + mask_input.sum()
            + has_mask_input.sum()
        )
        return m + extra, torch.tensor([[0.9]])


def _export(module, args, names, outputs, path, dynamic=None):
    torch.onnx.export(
        module,
        args,
        str(path),
        input_names=names,
        output_names=outputs,
        dynamic_axes=dynamic or {},
        dynamo=False,
        opset_version=17,
    )
    return str(path)


@pytest.fixture(scope="module")
def onnx_models(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    plain = _export(
        PlainNet(),
        (torch.zeros(1, 3, 32, 32),),
        ["input"],
        ["logits"],
        d / "plain.onnx",
        {"input": {2: "h", 3: "w"}, "logits": {2: "h", 3: "w"}},
    )
    img = (torch.zeros(1, 3, 1024, 1024),)
    sam_enc = _export(SamEncoder(), img, ["image"], ["image_embeddings"], d / "sam_enc.onnx")
    pts = torch.zeros(1, 3, 2)
    lab = torch.zeros(1, 3)
    mi, hm = torch.zeros(1, 1, 256, 256), torch.zeros(1)
    sam_dec = _export(
        SamDecoder(),
        (torch.zeros(1, 3, 64, 64), pts, lab, mi, hm, torch.tensor([60.0, 80.0])),
        ["image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size"],
        ["masks", "iou_predictions"],
        d / "sam_dec.onnx",
        {"point_coords": {1: "n"}, "point_labels": {1: "n"}, "masks": {2: "h", 3: "w"}},
    )
    sam_enc_hwc = _export(
        SamEncoderHWC(), (torch.zeros(1024, 1024, 3),), ["input_image"], ["image_embeddings"], d / "sam_enc_hwc.onnx"
    )
    names2 = ("high_res_feats_0", "high_res_feats_1", "image_embed")
    sam2_enc = _export(SamEncoder(names2), img, ["image"], list(names2), d / "sam2_enc.onnx")
    sam2_dec = _export(
        Sam2Decoder(),
        (torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 256, 256), torch.zeros(1, 3, 128, 128), pts, lab, mi, hm),
        [
            "image_embed",
            "high_res_feats_0",
            "high_res_feats_1",
            "point_coords",
            "point_labels",
            "mask_input",
            "has_mask_input",
        ],
        ["masks", "iou_predictions"],
        d / "sam2_dec.onnx",
        {"point_coords": {1: "n"}, "point_labels": {1: "n"}},
    )
    return {
        "plain": (plain, None),
        "sam": (sam_dec, sam_enc),
        "sam2": (sam2_dec, sam2_enc),
        "sam_hwc": (sam_dec, sam_enc_hwc),
    }


def _test_image(h=150, w=200):
    """Dark image with a bright red rectangle: columns 60..140, rows 30..110."""
    img = np.full((h, w, 3), 0.1, np.float32)
    img[30:110, 60:140, 0] = 0.95
    return img


BOX = [0.2, 0.1, 0.55, 0.9]  # x0, y0, x1, y1 fractions -> columns 40..110, rows 15..135


def _expected(h=150, w=200):
    m = np.zeros((h, w), bool)
    m[30:110, 60:110] = True  # red rectangle inside the box
    return m


def test_plain_model_end_to_end(onnx_models):
    seg = OnnxSegmenter(OnnxSegmenterConfig(model=onnx_models["plain"][0]))
    assert seg.kind == "plain"
    mask = seg(_test_image()) > 0
    assert np.array_equal(mask, _test_image()[..., 0] > 0.5)


@pytest.mark.parametrize("kind", ["sam", "sam2", "sam_hwc"])
def test_sam_like_models_with_box_prompt(onnx_models, kind):
    dec, enc = onnx_models[kind]
    seg = OnnxSegmenter(OnnxSegmenterConfig(model=dec, encoder=enc, box=BOX))
    assert seg.kind == kind.removesuffix("_hwc")  # detected from the decoder's input names
    mask = seg(_test_image()) > 0
    gt = _expected()
    iou = (mask & gt).sum() / (mask | gt).sum()
    assert iou > 0.9, iou
    # nothing outside the prompt box (a wrong coordinate transform would leak or shift the mask)
    outside = np.ones_like(gt)
    outside[13:138, 38:113] = False
    assert not mask[outside].any()


def test_sam_needs_encoder_and_prompt(onnx_models):
    dec, enc = onnx_models["sam"]
    with pytest.raises(PipelineError, match="masks.onnx.encoder"):
        OnnxSegmenter(OnnxSegmenterConfig(model=dec))
    with pytest.raises(PipelineError, match="prompt"):
        OnnxSegmenter(OnnxSegmenterConfig(model=dec, encoder=enc))
    with pytest.raises(PipelineError, match="not found"):
        OnnxSegmenter(OnnxSegmenterConfig(model=str(Path(dec).with_name("missing.onnx"))))


def test_segment_stage_writes_masks(onnx_models, tmp_path):
    d = tmp_path / "s"
    (d / "images").mkdir(parents=True)
    for i in range(3):
        image = _test_image().copy()
        image[0, 0] = i / 10  # three photos, not one photo three times (byte-identical photos are refused)
        write_png(d / "images" / f"img{i}.png", image)
    dec, enc = onnx_models["sam2"]
    cfg = MasksConfig(onnx=OnnxSegmenterConfig(model=dec, encoder=enc, box=BOX))
    s = make_masks(d, tmp_path / "out", cfg, progress=False)  # source auto: no mask folder -> onnx
    assert s.source == "onnx" and s.model_kind == "sam2" and s.has_masks
    m = read_mask(tmp_path / "out" / "img1.png")
    gt = _expected()
    assert (m & gt).sum() / (m | gt).sum() > 0.9
    assert s.mean_coverage == pytest.approx(m.mean())


def _scene_with_masks(tmp_path, masks: dict[str, np.ndarray]) -> Path:
    """A 2-view 40x30 scene whose transparent_masks/<stem>.png are the given uint8 arrays."""
    import cv2

    d = tmp_path / "s"
    make_corner_scene(d, n_views=2, width=40, height=30)
    (d / "transparent_masks").mkdir()
    for stem, data in masks.items():
        cv2.imwrite(str(d / "transparent_masks" / f"{stem}.png"), data)
    return d


def _window(value, channels: int = 1) -> np.ndarray:
    """A 30x40 uint8 mask: ``value`` (a number or a BGR triple) on a 10x12 window, 0 elsewhere."""
    out = np.zeros((30, 40, channels) if channels > 1 else (30, 40), np.uint8)
    out[5:15, 8:20] = value
    return out


WINDOW = _window(1).astype(bool)


@pytest.mark.parametrize("kind, data", [
    ("label map", _window(1)),
    ("colour", _window((0, 255, 0), 3)),  # green on black (BGR)
    ("colour", _window((40, 30, 200), 3)),  # red-ish on black
    ("grey", _window(255)),
])
def test_ingest_recognises_label_maps_and_colour_masks(tmp_path, kind, data):
    d = _scene_with_masks(tmp_path, {"view_000": data, "view_001": data})
    s = make_masks(d, tmp_path / "out", progress=False)
    assert s.mask_kinds == {kind: 2} and s.polarity == "white"
    for stem in ("view_000", "view_001"):
        assert np.array_equal(read_mask(tmp_path / "out" / f"{stem}.png"), WINDOW)
    assert s.mean_coverage == pytest.approx(WINDOW.mean())


def _pane_filling_the_view() -> np.ndarray:
    """A 30x40 uint8 mask of glass that fills the view (a shop window): white but for a strip of wall above
    and at the left, 88% of the photo."""
    out = np.full((30, 40), 255, np.uint8)
    out[:3] = 0
    out[:, :1] = 0
    return out


def test_glass_that_fills_the_view_keeps_its_masks_and_is_flagged(tmp_path, capsys):
    pane = _pane_filling_the_view()
    d = _scene_with_masks(tmp_path, {"view_000": pane, "view_001": pane})
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    for stem in ("view_000", "view_001"):  # white stays the see-through surface
        assert np.array_equal(read_mask(tmp_path / "out" / f"{stem}.png"), pane > 0)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["polarity"] == "white" and "kept as given" in summary["polarity_reason"]
    assert summary["mean_coverage"] == pytest.approx((pane > 0).mean())
    warning = summary["polarity_warning"]
    assert "87.8%" in warning and "view_000.png 88%" in warning and "masks.polarity: black" in warning
    assert f"WARNING: {warning}" in captured.err  # said loudly in the log, not only in the summary
    assert "kept as given" in captured.out
    # the user's own choice: no warning when white is confirmed, the masks inverted with black
    s = make_masks(d, tmp_path / "white", MasksConfig(polarity="white"), progress=False)
    assert s.polarity == "white" and not s.polarity_warning
    assert np.array_equal(read_mask(tmp_path / "white" / "view_000.png"), pane > 0)
    s = make_masks(d, tmp_path / "black", MasksConfig(polarity="black"), progress=False)
    assert s.polarity == "black" and not s.polarity_warning
    assert np.array_equal(read_mask(tmp_path / "black" / "view_000.png"), pane == 0)


def test_inverted_masks_are_flagged_with_the_fix_and_read_inverted_with_polarity_black(tmp_path, capsys):
    inverted = np.where(WINDOW, 0, 255).astype(np.uint8)  # black = the small window: an inverted mask set
    d = _scene_with_masks(tmp_path, {"view_000": inverted, "view_001": inverted})
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["polarity"] == "white" and summary["mean_coverage"] == pytest.approx(1 - WINDOW.mean())
    coverage = f"{100 * (1 - WINDOW.mean()):.0f}%"
    assert f"view_000.png {coverage}, view_001.png {coverage}" in summary["polarity_warning"]
    assert "set masks.polarity: black" in err and "view_001.png" in err
    assert np.array_equal(read_mask(tmp_path / "out" / "view_000.png"), ~WINDOW)  # as given, until told
    argv = ["masks", "--scene-dir", str(d), "--out", str(tmp_path / "fixed"), "--config-json", '{"polarity": "black"}']
    assert cli_main(argv) == 0
    summary = json.loads((tmp_path / "fixed" / "summary.json").read_text())
    assert summary["polarity"] == "black" and summary["polarity_warning"] == ""
    assert summary["mean_coverage"] == pytest.approx(WINDOW.mean())
    assert np.array_equal(read_mask(tmp_path / "fixed" / "view_000.png"), WINDOW)


class PooledNet(torch.nn.Module):
    """A valid ONNX model whose output is no mask: the image's mean colour, [1, 3]."""

    def forward(self, image):
        return image.mean(dim=(2, 3))


class EverywhereNet(torch.nn.Module):
    """Mask logits that call every pixel glass."""

    def forward(self, image):
        return 0.0 * image[:, :1] + 5.0


def _photos(d: Path, count: int = 3) -> Path:
    (d / "images").mkdir(parents=True)
    for i in range(count):
        image = _test_image().copy()
        image[0, 0] = i / 10  # distinct photos (byte-identical photos are refused)
        write_png(d / "images" / f"img{i}.png", image)
    return d


def _onnx_config(path: Path, model: str) -> Path:
    path.write_text(f"defaults:\n  masks:\n    source: onnx\n    onnx: {{model: {model}, kind: plain}}\n")
    return path


def test_a_segmenter_whose_output_is_no_mask_is_an_error_naming_the_model_and_its_shape(tmp_path, capsys):
    model = _export(PooledNet(), (torch.zeros(1, 3, 32, 32),), ["input"], ["colour"], tmp_path / "pooled.onnx",
                    {"input": {2: "h", 3: "w"}})
    d = _photos(tmp_path / "s")
    config = _onnx_config(tmp_path / "config.yaml", model)
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out"), "--config", str(config)]) == 1
    err = capsys.readouterr().err
    assert f"{model}: the model's output has shape [1, 3], which is no mask" in err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_segmented_masks_that_cover_everything_are_flagged(tmp_path, capsys):
    model = _export(EverywhereNet(), (torch.zeros(1, 3, 32, 32),), ["input"], ["logits"], tmp_path / "all.onnx",
                    {"input": {2: "h", 3: "w"}, "logits": {2: "h", 3: "w"}})
    d = _photos(tmp_path / "s")
    config = _onnx_config(tmp_path / "config.yaml", model)
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out"), "--config", str(config)]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["mean_coverage"] == 1.0
    assert "segmented masks cover 100.0% of the photos" in summary["coverage_warning"]
    assert f"WARNING: {summary['coverage_warning']}" in err


def test_given_masks_that_cover_nothing_are_flagged(tmp_path, capsys):
    black = np.zeros((30, 40), np.uint8)
    d = _scene_with_masks(tmp_path, {"view_000": black, "view_001": black})
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["mean_coverage"] == 0.0
    warning = summary["coverage_warning"]
    assert "given masks cover 0.00% of the photos" in warning and "masks.source: none" in warning
    assert f"WARNING: {warning}" in err
    # usual masks: no coverage warning
    d = _scene_with_masks(tmp_path / "usual", {"view_000": _window(255), "view_001": _window(255)})
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "usual_out")]) == 0
    assert json.loads((tmp_path / "usual_out" / "summary.json").read_text())["coverage_warning"] == ""
    assert "WARNING" not in capsys.readouterr().err


def test_a_photo_as_a_mask_is_refused(tmp_path):
    import cv2

    d = _scene_with_masks(tmp_path, {})
    photo = cv2.imread(str(d / "images" / "view_000.png"))
    for stem in ("view_000", "view_001"):
        cv2.imwrite(str(d / "transparent_masks" / f"{stem}.png"), photo)
    with pytest.raises(PipelineError, match="does not look like a mask") as err:
        make_masks(d, tmp_path / "out", progress=False)
    assert "view_000.png" in str(err.value)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------------
# masks found by the photo's own name


NAMING_STYLES = {
    # photo extension, mask file name from (photo name, index), mask file format
    "same name .JPG": (".JPG", lambda name, i: name, "jpg"),
    "same name .jpg": (".jpg", lambda name, i: name, "jpg"),
    "same name .png": (".png", lambda name, i: name, "png"),
    "stem.png for .JPG photos": (".JPG", lambda name, i: Path(name).stem + ".png", "png"),
    "stem.jpg for .JPG photos": (".JPG", lambda name, i: Path(name).stem + ".jpg", "jpg"),
    "mixed case extensions": (".JPG", lambda name, i: Path(name).stem + (".jpg", ".PNG", ".JPG")[i],
                              ("jpg", "png", "jpg")),
    "<photo name>.png": (".JPG", lambda name, i: name + ".png", "png"),
}


@pytest.mark.parametrize("style", list(NAMING_STYLES))
def test_masks_are_found_by_the_photos_name_in_every_naming_style(tmp_path, style):
    photo_ext, mask_name, fmt = NAMING_STYLES[style]
    formats = fmt if isinstance(fmt, tuple) else (fmt,) * 3
    import cv2

    d = tmp_path / "s"
    views = make_corner_scene(d, n_views=3, width=80, height=60, ext=photo_ext, with_masks=True)
    truth = {}
    for i, v in enumerate(views):
        stem = Path(v.name).stem
        png = d / "transparent_masks" / f"{stem}.png"
        truth[stem] = read_mask(png)
        png.unlink()
        data = np.repeat(truth[stem][..., None].astype(np.uint8) * 255, 3, axis=2)  # black and white, RGB
        ok, encoded = cv2.imencode(f".{formats[i]}", data)
        assert ok
        (d / "transparent_masks" / mask_name(v.name, i)).write_bytes(encoded.tobytes())
    out = tmp_path / "out"
    s = make_masks(d, out, progress=False)
    assert s.source == "ingest" and s.mask_kinds == {"grey": 3} and not s.without_mask
    # the stage writes <stem>.png PNGs whatever the masks' names and formats
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [".rtsplat-output", "summary.json"] + [f"{stem}.png" for stem in truth])
    for stem, mask in truth.items():
        assert (out / f"{stem}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        got = read_mask(out / f"{stem}.png")
        assert got.shape == mask.shape and np.array_equal(got, mask), (stem, int((got != mask).sum()))
    assert s.mean_coverage == pytest.approx(np.mean([m.mean() for m in truth.values()]))


@pytest.mark.parametrize("quality", [95, 60, 30])
def test_jpeg_masks_are_thresholded_through_their_compression_noise(tmp_path, quality):
    """Black-and-white masks saved as colour JPEGs, not quite grey (a few levels of colour noise, as masks
    painted in an editor have): ringing at the edges and channels that differ, still read as grey masks;
    at the default threshold 0.5 they come back as the drawn masks."""
    import cv2

    d = _scene_with_masks(tmp_path, {})
    disc = np.zeros((30, 40), np.uint8)
    cv2.circle(disc, (20, 15), 9, 255, -1)
    tint = np.random.default_rng(0).integers(-8, 9, (30, 40, 3))
    data = np.clip(disc[..., None].astype(int) + tint, 0, 255).astype(np.uint8)
    for stem in ("view_000", "view_001"):
        cv2.imwrite(str(d / "transparent_masks" / f"{stem}.jpg"), data, [cv2.IMWRITE_JPEG_QUALITY, quality])
    noisy = cv2.imread(str(d / "transparent_masks" / "view_000.jpg"))
    assert len(np.unique(noisy)) > 2  # really lossy
    if quality == 95:  # coloured fringes (lower qualities quantise the faint colour away)
        assert np.abs(noisy.astype(int) - noisy[..., :1]).max() > 1
    s = make_masks(d, tmp_path / "out", progress=False)
    assert s.mask_kinds == {"grey": 2}
    got = read_mask(tmp_path / "out" / "view_000.png")
    assert (got != (disc > 0)).mean() <= 0.005, int((got != (disc > 0)).sum())  # at most 6 of 1200 pixels


def test_a_coloured_jpeg_mask_is_still_a_colour_mask(tmp_path):
    import cv2

    d = _scene_with_masks(tmp_path, {})
    for stem in ("view_000", "view_001"):
        cv2.imwrite(str(d / "transparent_masks" / f"{stem}.jpg"), _window((0, 255, 0), 3))  # green on black
    s = make_masks(d, tmp_path / "out", progress=False)
    assert s.mask_kinds == {"colour": 2}
    assert np.array_equal(read_mask(tmp_path / "out" / "view_000.png"), WINDOW)


def test_two_masks_for_one_photo_are_refused_naming_both(tmp_path, capsys):
    d = _scene_with_masks(tmp_path, {"view_000": _window(255), "view_001": _window(255)})
    (d / "transparent_masks" / "view_001.JPG").write_bytes((d / "transparent_masks" / "view_001.png").read_bytes())
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "photo view_001.png has 2 masks: view_001.JPG and view_001.png" in err and "Fix:" in err
    assert not (tmp_path / "out").exists()


def test_a_mask_set_that_matches_no_photo_shows_an_expected_and_a_found_name(tmp_path, capsys):
    d = _scene_with_masks(tmp_path, {"IMG_7039": _window(255), "IMG_7040": _window(255)})
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "none of the 2 masks matches a photo" in err
    assert "expected e.g. view_000.png" in err and "found e.g. IMG_7039.png" in err
    assert str(d / "transparent_masks") in err and "Fix:" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # nothing written


def test_photos_without_masks_are_an_error_or_empty_masks_with_allow_missing(tmp_path, capsys):
    inverted = np.where(WINDOW, 0, 255).astype(np.uint8)  # read inverted (polarity black)
    d = _scene_with_masks(tmp_path, {"view_000": inverted})
    out = tmp_path / "out"
    assert cli_main(["masks", "--scene-dir", str(d), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "no mask for image view_001.png (1 of 2 photos have none)" in err and "masks.allow_missing" in err
    assert not out.exists()
    argv = ["masks", "--scene-dir", str(d), "--out", str(out), "--config-json",
            '{"allow_missing": true, "polarity": "black"}']
    assert cli_main(argv) == 0
    assert "1 photo(s) without a mask" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["without_mask"] == ["view_001.png"] and summary["polarity"] == "black"
    assert np.array_equal(read_mask(out / "view_000.png"), WINDOW)
    assert not read_mask(out / "view_001.png").any()  # no see-through surface, also with inverted masks


def test_photos_sharing_a_stem_are_refused(tmp_path):
    d = _scene_with_masks(tmp_path, {"view_000": _window(255), "view_001": _window(255)})
    import cv2

    cv2.imwrite(str(d / "images" / "view_001.jpg"), cv2.imread(str(d / "images" / "view_001.png")))
    with pytest.raises(PipelineError, match="two photos share a file stem: view_001.jpg and view_001.png"):
        make_masks(d, tmp_path / "out", progress=False)


@pytest.mark.parametrize("kind", ["sam", "sam2"])
def test_propagation_prompts_the_onnx_model_with_the_projected_box(onnx_models, tmp_path, kind):
    # the ring scene's glass painted red, and a red patch in the corner of every photo: the toy decoders mark
    # the red inside the prompt box, so the patch shows up only when the box prompt is not the glass's
    from masks_scene import render, ring_model

    from rtsplat.config import MaskPropagationConfig
    from rtsplat.io.colmap import ColmapImage, ColmapPoints, write_sparse_model
    from rtsplat.masks.propagation import suggest_views

    model = ring_model(12)
    truth = {v.name: render(v)[1] for v in model.views}
    marked = suggest_views(model, 5)
    scene = tmp_path / "scene"
    (scene / "transparent_masks").mkdir(parents=True)
    (scene / "images").mkdir()
    patch = (slice(0, 8), slice(0, 12))
    for name, mask in truth.items():
        image = np.full(mask.shape + (3,), 0.1, np.float32)
        image[mask] = (0.95, 0.1, 0.1)
        image[patch] = (0.95, 0.1, 0.1)
        assert not mask[patch].any()
        write_png(scene / "images" / name, image)
        if name in marked:
            write_mask(scene / "transparent_masks" / name, mask)
    write_sparse_model(tmp_path / "sfm" / "sparse" / "0",
                       [ColmapImage(v.name, v.K, v.world_to_camera, v.width, v.height) for v in model.views],
                       ColmapPoints(model.xyz, np.full((len(model.xyz), 3), 128, np.uint8), [[] for _ in model.xyz]))
    dec, enc = onnx_models[kind]
    onnx = OnnxSegmenterConfig(model=dec, encoder=enc)  # no prompt in the config: the projection gives it
    cfg = MasksConfig(onnx=onnx, propagate=MaskPropagationConfig(grid=64))
    summary = make_masks(scene, tmp_path / "masks", cfg, progress=False, sfm_dir=tmp_path / "sfm")
    propagated = [n for n, s in summary.mask_sources.items() if s == "propagated"]
    assert len(propagated) == 12 - 5 and sorted(summary.refined) == sorted(propagated)
    assert summary.refinement == f"onnx ({kind})"
    whole = OnnxSegmenter(onnx, boxes_per_image=True)(read_image(scene / "images" / propagated[0]), (0, 0, 96, 72))
    assert (whole[1:7, 1:11] > 0).all()  # prompted with the whole photo the decoder takes the patch too
    scores = []
    for name in propagated:
        mask = read_mask(tmp_path / "masks" / name)
        assert not mask[patch].any()
        scores.append((mask & truth[name]).sum() / (mask | truth[name]).sum())
    assert min(scores) >= 0.85, scores
