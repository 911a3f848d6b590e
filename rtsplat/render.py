"""``rtsplat render``: test views, the decomposed layers and the rendering speed of a trained run.

Writes, for every view of the chosen split, into ``<out>/``:

* ``color/<name>.png``          the final image;
* ``reflection/<name>.png``     ``C_spec`` inside the region of interest (black where none);
* ``transmission/<name>.png``   ``beta * tau * C_trans`` (plus the plain radiance outside the ROI);
* ``scatter/<name>.png``        the rest, ``beta * (1 - tau) * C_scatter``: the three layers sum to ``color``;
* ``normal/<name>.png``         world normals mapped to [0,1];  ``depth/<name>.png``: inverse depth;
* ``render.json``               views and their split, device, backend, edits, frames per second and the
                                run's ``training_provenance`` (:mod:`rtsplat.provenance`).

The run must have been trained on a scene prepared from the same photos and SfM model as ``--data``
(:meth:`rtsplat.scene.PreparedScene.check_run_belongs`); a model with non-finite parameters is refused
when read (:func:`rtsplat.model.checkpoint.read_checkpoint`).

Each view is rendered from its prepared pose moved by the run's pose correction for that view
(``train.cameras``, saved in ``model.pt``: learnt for training views, fitted to the image for test
views), and where the run learnt per-view appearance (``train.effects.appearance``) the final image
gets that view's exposure and white-balance correction (the layers stay in the scene's own colours,
so they then sum to the uncorrected image); the renders are those the trainer evaluated.

FPS is measured over the views after ``--warmup`` untimed renders (inference mode, no files written
while timing), on the device the model is on, by :func:`time_renders`; ``render.json`` keeps it with its
wall and CPU seconds, threads and how busy the other cores were (``timing``, see :mod:`rtsplat.usage`).
This FPS is timed inside the render job, beside whatever else runs (``timing.scheduled_alone`` is
false); ``rtsplat fps`` (:mod:`rtsplat.fps`) times the same renders in a job of their own, which the
workflow runs with nothing beside it.

Scene edits (the paper's applications) are exact operations on the trained model:
``roughness=S`` scales every surfel's roughness (blurrier or sharper reflections),
``transparency=S`` scales the optical opacity of the surfels (S < 1: clearer glass),
``reflections=off`` removes ``C_spec`` from the image, ``tint=R,G,B`` multiplies the transmission layer.
Everything is written into a temporary directory that replaces ``<out>`` only when all views are
done (:func:`rtsplat.io.atomic.atomic_dir`), so a failed run leaves no partial output.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor

from rtsplat.config import add_config_arguments, stage_config_from_args
from rtsplat.devices import resolve_device
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.model.appearance import apply_appearance
from rtsplat.model.composite import compose_layers, scatter_layer
from rtsplat.provenance import cpu_model, training_record
from rtsplat.usage import UsageClock

LAYER_DIRS = ("color", "reflection", "transmission", "scatter", "normal", "depth")


@dataclass
class Edits:
    roughness: float = 1.0  # multiply roughness (clamped to [0, 1])
    transparency: float = 1.0  # multiply the optical opacity (clamped to [0, 1])
    reflections: bool = True  # False: remove C_spec from the image
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # multiply the transmission layer

    @property
    def is_identity(self) -> bool:
        return self == Edits()

    @classmethod
    def parse(cls, items: list[str]) -> Edits:
        """``["roughness=2", "reflections=off", "tint=1,0.8,0.6"]`` -> Edits; clear errors otherwise."""
        edits = cls()
        for item in items:
            key, sep, value = item.partition("=")
            key = key.strip()
            try:
                if not sep:
                    raise ValueError("expected key=value")
                if key in ("roughness", "transparency"):
                    number = float(value)
                    if not math.isfinite(number) or number < 0:
                        raise ValueError("must be a finite number >= 0")
                    setattr(edits, key, number)
                elif key == "reflections":
                    if value not in ("on", "off"):
                        raise ValueError("must be 'on' or 'off'")
                    edits.reflections = value == "on"
                elif key == "tint":
                    rgb = tuple(float(v) for v in value.split(","))
                    if len(rgb) != 3 or not all(math.isfinite(v) and v >= 0 for v in rgb):
                        raise ValueError("must be three numbers >= 0, e.g. tint=1,0.8,0.6")
                    edits.tint = rgb
                else:
                    raise ValueError("unknown edit; use roughness=S, transparency=S, reflections=off, tint=R,G,B")
            except ValueError as exc:
                raise PipelineError(f"bad --edit {item!r}: {exc}") from None
        return edits


def apply_parameter_edits(model, edits: Edits) -> None:
    """Edit the surfels in place (roughness and optical opacity live in logit space)."""
    p = model.surfels
    with torch.no_grad():
        if edits.roughness != 1.0:
            p.roughness_logit.copy_(torch.logit((p.roughness * edits.roughness).clamp(1e-6, 1 - 1e-6)))
        if edits.transparency != 1.0:
            p.opacity_logit.copy_(torch.logit((p.opacity * edits.transparency).clamp(1e-6, 1 - 1e-6)))


def decompose(result, edits: Edits) -> dict[str, Tensor]:
    """Colour and its three additive layers, after the image-space edits."""
    color = result.color
    zero = torch.zeros_like(color)
    reflection = result.layers.get("reflection", zero)
    transmission = result.layers.get("transmission", color)
    scatter = scatter_layer(color, reflection, transmission)
    if not edits.reflections:
        reflection = zero
    transmission = transmission * torch.as_tensor(edits.tint, dtype=color.dtype, device=color.device)
    return {"color": compose_layers(reflection, transmission, scatter), "reflection": reflection,
            "transmission": transmission, "scatter": scatter}


def normal_image(normal: Tensor) -> Tensor:
    """World normals [H, W, 3] mapped to [0, 1]."""
    return normal * 0.5 + 0.5


def inverse_depth(depth: Tensor, alpha: Tensor) -> Tensor:
    """1 / depth where the surface is opaque (alpha > 0.5), 0 elsewhere."""
    return torch.where(alpha > 0.5, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))


def depth_image(depth: Tensor, alpha: Tensor, top: Tensor | float | None = None) -> Tensor:
    """Inverse depth divided by ``top`` (None: its largest value in this image), clipped to [0, 1], as RGB."""
    inv = inverse_depth(depth, alpha)
    top = inv.max() if top is None else torch.as_tensor(top, dtype=inv.dtype, device=inv.device)
    return (inv / top.clamp_min(1e-12)).clamp(0, 1).expand(*inv.shape[:2], 3)


def corrected_cameras(records, corrections: dict[str, list[float]], device) -> list:
    """The cameras of ``records`` moved by the run's pose corrections (view name -> [6], see
    :mod:`rtsplat.train.cameras`); a view without one keeps its prepared pose."""
    cameras = []
    for rec in records:
        camera = rec.to_camera(device=device)
        if rec.name in corrections:
            camera = camera.corrected(torch.as_tensor(corrections[rec.name], device=device))
        cameras.append(camera)
    return cameras


@dataclass
class LoadedRun:
    """A trained run ready to render: the views, their corrected cameras, the edited model."""

    records: list
    cameras: list
    model: object
    checkpoint: object
    device: torch.device
    backend: str
    appearance: dict  # view name -> its appearance correction [6] (rtsplat.model.appearance); empty: none

    def render(self, camera, stage: str = "full"):
        """The model's render of ``camera``, the surfels outside its view left out before the rasterizer
        (:meth:`rtsplat.model.rtmodel.RTModel.in_view`: the same image)."""
        return self.model.render(camera, stage=stage, raster_settings=self.checkpoint.raster, backend=self.backend,
                                 frustum_cull=True)


def load_run(run_dir: str | Path, data_dir: str | Path | None, *, split: str = "test", edits: Edits | None = None,
             backend: str = "auto", device: str = "auto") -> LoadedRun:
    """The model of ``run_dir`` on ``device`` (:func:`rtsplat.devices.resolve_device`; a checkpoint saved
    on another device is moved there) with ``edits`` applied, and the ``split`` views of the prepared scene
    ``data_dir`` with the run's pose corrections. ``data_dir`` None: the prepared scene the run recorded
    it was trained on."""
    from rtsplat.model.checkpoint import read_checkpoint
    from rtsplat.raster import check_backend_name
    from rtsplat.scene import PreparedScene

    device = resolve_device(device)
    run_dir = Path(run_dir)
    check_backend_name(backend, "--backend")
    model_path = run_dir / "model.pt"
    if not model_path.is_file():
        raise PipelineError("no trained model here", path=model_path,
                            fix="run `rtsplat train` to completion for this run directory first")
    if data_dir is None:
        checkpoint = read_checkpoint(model_path, device=device, lazy=True)
        data_dir = (checkpoint.training.get("data") or {}).get("path")
        if not data_dir or not Path(data_dir).is_dir():
            raise PipelineError(f"the prepared scene this run was trained on is not at {data_dir!r}",
                                path=model_path, fix="pass the prepared scene with --data")
        scene = PreparedScene.load(data_dir)
    else:
        scene = PreparedScene.load(data_dir)
        checkpoint = None
    records = scene.test_cameras if split == "test" else scene.train_cameras if split == "train" else scene.cameras
    if not records:
        raise PipelineError(f"the prepared scene has no {split!r} views", path=data_dir)
    checkpoint = checkpoint or read_checkpoint(model_path, device=device, lazy=True)
    scene.check_run_belongs(checkpoint.training.get("data"), run_dir)
    model = checkpoint.build_model(device)
    model.eval()
    apply_parameter_edits(model, edits or Edits())
    cameras = corrected_cameras(records, checkpoint.training.get("camera_corrections", {}), device)
    appearance = checkpoint.training.get("appearance_corrections", {})
    return LoadedRun(list(records), cameras, model, checkpoint, device, backend, appearance)


COLOR_LAYERS = ("color", "reflection", "transmission", "scatter")  # the layers that need the specular pass


def render_images(run: LoadedRun, camera, edits: Edits, appearance=None,
                  layers: tuple[str, ...] = LAYER_DIRS) -> dict[str, Tensor]:
    """The ``layers`` (default: every one of :data:`LAYER_DIRS`; [H, W, 3], not clamped) of one render of
    ``camera``, after the image-space ``edits`` (the parameter edits are already in ``run.model``);
    ``appearance`` (a view's [6] correction, :mod:`rtsplat.model.appearance`) gives the final image that
    photo's exposure and white balance. Only what the asked layers need is computed: normals and depth alone
    come from the model's volume stage (the rasterizer's output, no specular network), and each layer is
    the same as in a render of all of them."""
    unknown = set(layers) - set(LAYER_DIRS)
    if unknown:
        raise ValueError(f"unknown layers {sorted(unknown)}; choose from {LAYER_DIRS}")
    needs_color = any(layer in COLOR_LAYERS for layer in layers)
    result = run.render(camera, stage="full" if needs_color else "volume")
    images = decompose(result, edits) if needs_color else {}
    if appearance is not None and "color" in layers:
        images["color"] = apply_appearance(images["color"], torch.as_tensor(appearance, device=run.device))
    if "normal" in layers:
        images["normal"] = normal_image(result.layers["normal"])
    if "depth" in layers:
        images["depth"] = depth_image(result.layers["depth"], result.layers["alpha"])
    return {layer: images[layer] for layer in layers}


def time_renders(run: LoadedRun, *, warmup: int, rounds: int = 1, scheduled_alone: bool = False) -> dict:
    """Render every view ``rounds`` times after ``warmup`` untimed renders (inference mode, nothing
    written) and return ``fps`` (frames / wall seconds) with ``timing``: the :class:`rtsplat.usage.Usage`
    of the timed renders, CPU seconds per frame and ``scheduled_alone`` (what the caller says: whether the
    job ran with nothing of its workflow beside it)."""
    with torch.inference_mode():
        for camera in run.cameras[: max(warmup, 0)]:
            run.render(camera)
        _wait_for(run.device)
        clock = UsageClock()
        for _ in range(rounds):
            for camera in run.cameras:
                run.render(camera)
        _wait_for(run.device)  # the renders are queued on a GPU: time them to the end
        usage = clock.read()
    frames = rounds * len(run.cameras)
    return {"fps": frames / max(usage.wall_seconds, 1e-12), "seconds": usage.wall_seconds, "frames": frames,
            "warmup": warmup, "timing": {**usage.to_dict(), "cpu_seconds_per_frame": usage.cpu_seconds / frames,
                                         "scheduled_alone": scheduled_alone}}


def render_run(run_dir: str | Path, data_dir: str | Path, out_dir: str | Path, *, split: str = "test",
               edits: Edits | None = None, backend: str = "auto", warmup: int = 2, device: str = "auto",
               progress: bool = True) -> dict:
    """Render ``split`` views of the prepared scene with the model of ``run_dir`` on ``device`` (auto, cpu,
    cuda, cuda:N; :func:`rtsplat.devices.resolve_device`); returns render.json."""
    from tqdm.auto import tqdm

    from rtsplat.io.images import write_png

    run_dir, out_dir = Path(run_dir), Path(out_dir)
    check_output_dir(out_dir, "render", inputs=[run_dir, data_dir])
    edits = edits or Edits()
    run = load_run(run_dir, data_dir, split=split, edits=edits, backend=backend, device=device)
    timed = time_renders(run, warmup=warmup)

    with output_dir(out_dir, "render", inputs=[run_dir, data_dir]) as tmp:
        for layer in LAYER_DIRS:
            (tmp / layer).mkdir()
        with torch.inference_mode():
            for rec, camera in tqdm(list(zip(run.records, run.cameras, strict=True)), desc="render",
                                    disable=not progress):
                images = render_images(run, camera, edits, appearance=run.appearance.get(rec.name))
                for layer in LAYER_DIRS:
                    write_png(tmp / layer / f"{rec.name}.png", images[layer].clamp(0, 1).cpu().numpy())
        info = {
            "views": [rec.name for rec in run.records], "split": split, "device": device_name(run.device),
            "backend": backend, "edits": asdict(edits), **timed, "surfels": len(run.model.surfels),
            "width": run.records[0].width, "height": run.records[0].height,
            "effects": run.checkpoint.effects.to_dict(), "run": str(run_dir),
            "training_provenance": training_record(run_dir),
        }
        write_json_atomic(tmp / "render.json", info)
    return info


def _wait_for(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU {cpu_model()}, {torch.get_num_threads()} torch threads"


def add_run_arguments(parser: argparse.ArgumentParser, description: str, out_help: str) -> None:
    """The stage's ``--help`` text and the arguments of every stage that renders a trained run: ``--run``,
    ``--data`` and ``--out`` (``out_help`` says what is written there)."""
    parser.description = description
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--run", type=Path, required=True, help="run directory of `rtsplat train` (has model.pt)")
    parser.add_argument("--data", type=Path, required=True, help="the prepared scene the run was trained on")
    parser.add_argument("--out", type=Path, required=True, help=out_help)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_arguments(parser, __doc__, "output directory (replaced atomically)")
    parser.add_argument("--split", choices=("test", "train", "all"), default="test")
    parser.add_argument("--edit", action="append", default=[], metavar="KEY=VALUE",
                        help="scene edit, repeatable: roughness=S, transparency=S, reflections=off, tint=R,G,B")
    parser.add_argument("--backend", default="auto",
                        help="rasterizer backend (auto: triton on a GPU, else cpu; cpu, triton, reference)")
    parser.add_argument("--warmup", type=int, help="override render.warmup (untimed renders before measuring FPS)")
    parser.add_argument("--device", help="override render.device: auto (the GPU when torch sees one), cpu, cuda, "
                        "cuda:N")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_arguments(parser)


def run(args: argparse.Namespace) -> int:
    cfg = stage_config_from_args(args, "render", {"warmup": args.warmup, "device": args.device})
    edits = Edits.parse(args.edit)
    resolve_device(cfg.device, key="--device" if args.device is not None else "render.device")
    info = render_run(args.run, args.data, args.out, split=args.split, edits=edits, backend=args.backend,
                      warmup=cfg.warmup, device=cfg.device, progress=not args.quiet)
    print(f"rendered {len(info['views'])} {info['split']} views to {args.out}: {info['fps']:.2f} FPS on "
          f"{info['device']}")
    return 0

