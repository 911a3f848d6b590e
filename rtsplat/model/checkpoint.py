"""Checkpoints and model files (``checkpoints/last.pt``, ``model.pt``): the one writer and the one reader.

A file holds what rebuilds the model without the trainer's config, and optionally the trainer's
resume state::

    {"version": 2,
     "model": {"effects", "ablations", "settings", "raster",   # dicts of the model's dataclasses
               "surfels": {name: tensor}, "buffers": {name: tensor}},   # buffers: the rest of state_dict
     "training": {"iteration", "elapsed", "config", "optimizer", ...}}  # {} when there is none

Files are written atomically (:func:`rtsplat.io.atomic.atomic_file`). Version-1 files (the model's
settings inside the trainer's config) are read too. A file whose surfel parameters or model buffers hold
NaN or infinite values is refused when read, naming the file and the parameter.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from rtsplat import schema
from rtsplat.errors import ConfigError, PipelineError
from rtsplat.io.atomic import atomic_file
from rtsplat.model.rtmodel import ActiveEffects, RTModel
from rtsplat.model.settings import Ablations, ModelSettings
from rtsplat.model.surfels import SurfelParameters
from rtsplat.raster import RasterSettings

CHECKPOINT_VERSION = 2
# version 1 kept the resume state at the top level, next to the model
_V1_TRAINING_KEYS = ("iteration", "elapsed", "config", "optimizer", "density", "frozen", "order", "rng", "torch_rng")
# specular-network inputs added after the first models were written; absent from a model: off
OPTIONAL_SPECULAR_INPUTS = ("specular_view_angle", "specular_background", "specular_fresnel", "specular_mirror")


class CheckpointError(PipelineError):
    """A checkpoint or model file that cannot be read or does not fit the run."""


@dataclass
class Checkpoint:
    """A read checkpoint: the model's description and tensors, and the trainer's resume state."""

    effects: ActiveEffects
    ablations: Ablations
    settings: ModelSettings
    raster: RasterSettings
    surfels: dict[str, Tensor]
    buffers: dict[str, Tensor]  # the model's state_dict without the surfels (env map, network, ROI, ...)
    training: dict[str, Any] = field(default_factory=dict)

    def build_model(self, device: str | torch.device = "cpu", *, ablations: Ablations | None = None,
                    settings: ModelSettings | None = None) -> RTModel:
        """The trained model on ``device`` (``ablations`` / ``settings`` replace the stored ones)."""
        surfels = SurfelParameters({k: v.to(device) for k, v in self.surfels.items()})
        roi_center = self.buffers.get("roi_center", torch.zeros(3))
        roi_radius = self.buffers.get("roi_radius", torch.tensor(1e9))
        model = RTModel(surfels, effects=self.effects, ablations=ablations or self.ablations,
                        settings=settings or self.settings, roi_center=roi_center,
                        roi_radius=float(roi_radius)).to(device)
        if "mirror_planes" in self.buffers:  # its row count is the scene's: size the buffer before loading
            model.set_mirror_planes(self.buffers["mirror_planes"])
        model.load_state_dict(self.buffers, strict=False)
        return model


def write_checkpoint(path: str | Path, model: RTModel, raster: RasterSettings,
                     training: dict[str, Any] | None = None) -> Path:
    """Write ``model`` (and the trainer's resume state) to ``path`` atomically."""
    state = {
        "version": CHECKPOINT_VERSION,
        "model": {
            "effects": model.effects.to_dict(),
            "ablations": dataclasses.asdict(model.ablations),
            "settings": dataclasses.asdict(model.settings),
            "raster": dataclasses.asdict(raster),
            "surfels": {k: v.detach().cpu() for k, v in model.surfels.tensors().items()},
            "buffers": {k: v for k, v in model.state_dict().items() if not k.startswith("surfels.")},
        },
        "training": dict(training or {}),
    }
    path = Path(path)
    with atomic_file(path, "wb") as fh:
        torch.save(state, fh)
    return path


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu", *, lazy: bool = False) -> Checkpoint:
    """Read a checkpoint or model file; :class:`CheckpointError` names the file and the fix. ``lazy``:
    memory-map the file, so that only the tensors used are read from it (a run's ``model.pt`` also holds
    the optimizer's state, about two thirds of its bytes, which a render never reads); a file that cannot
    be mapped is read whole."""
    path = Path(path)
    try:
        try:
            state = torch.load(path, map_location=device, weights_only=False, mmap=True) if lazy else None
        except Exception:  # not mappable (an old serialization format): read it whole below
            state = None
        if state is None:
            state = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # truncated or foreign files
        raise CheckpointError(f"cannot read checkpoint ({exc.__class__.__name__}: {exc}); delete it to start over",
                              path=path) from exc
    version = state.get("version") if isinstance(state, dict) else None
    if version == 1:
        config = state.get("config", {})
        model = {"effects": state["effects"], "ablations": config.get("ablations", {}),
                 "settings": config.get("model", {}), "raster": config.get("raster", {}),
                 "surfels": state["surfels"], "buffers": state["model"]}
        training = {k: state[k] for k in _V1_TRAINING_KEYS if k in state}
    elif version == CHECKPOINT_VERSION:
        model, training = state["model"], state["training"]
    else:
        raise CheckpointError(f"not an rtsplat checkpoint (version {CHECKPOINT_VERSION}); delete it", path=path)
    model = {**model, "settings": _settings_of_older_models(dict(model.get("settings", {})))}
    _check_finite(path, model)
    try:
        return Checkpoint(
            effects=ActiveEffects(**model["effects"]),
            ablations=schema.from_dict(Ablations, model["ablations"], source=str(path), root="ablations"),
            settings=schema.from_dict(ModelSettings, model["settings"], source=str(path), root="settings"),
            raster=schema.from_dict(RasterSettings, model["raster"], source=str(path), root="raster"),
            surfels=model["surfels"], buffers=model["buffers"], training=training,
        )
    except (ConfigError, KeyError, TypeError) as exc:
        raise CheckpointError(f"the model description does not fit this version of rtsplat ({exc})", path=path,
                              fix="retrain with this version, or use the version that wrote it") from exc


def _check_finite(path: Path, model: dict) -> None:
    """Refuse a model whose parameters or buffers hold NaN or infinite values (it would render flat grey)."""
    for group in ("surfels", "buffers"):
        tensors = model.get(group)
        if not isinstance(tensors, dict):
            continue
        for name, value in tensors.items():
            if not isinstance(value, Tensor) or not value.is_floating_point() or value.numel() == 0:
                continue
            bad = int((~torch.isfinite(value)).sum())
            if bad:
                raise CheckpointError(
                    f"the model's {group[:-1] if group == 'buffers' else 'surfel'} parameter {name!r} holds {bad} "
                    f"non-finite value(s) of {value.numel()} (NaN or infinity): the model is broken",
                    path=path,
                    fix="retrain (the trainer never writes a diverged state; this file was damaged or written "
                    "elsewhere), or use an earlier copy of the model",
                )


def _settings_of_older_models(settings: dict) -> dict:
    """Model settings as this version reads them, from what older versions wrote:

    * a constant RGB background colour (before the background became a mode): black and white map to
      their modes (other colours are left for the schema to refuse);
    * no ``specular_view_angle`` / ``specular_background`` (before the specular network had these
      inputs): off, which is the network shape such a model was trained with;
    * no ``view_independent_roi``, ``near_reflection_on_surface`` or ``near_reflection_trains_surfels``: the
      colour and the near reflections such a model was trained with (no degree-0 region, the near term on every
      pixel whose ray meets a pane, trained through the mirrored pass);
    * no ``attenuation_from``: beta from the specular network, the only source such a model had;
    * no ``shade_coverage``: the shaded colour over the whole pixel, as such a model was trained."""
    for name in (*OPTIONAL_SPECULAR_INPUTS, "view_independent_roi", "near_reflection_on_surface", "shade_coverage"):
        settings.setdefault(name, False)
    settings.setdefault("near_reflection_trains_surfels", True)
    settings.setdefault("attenuation_from", "network")
    colour = settings.get("background")
    if isinstance(colour, (list, tuple)) and len(colour) == 3 and len(set(map(float, colour))) == 1:
        mode = {0.0: "black", 1.0: "white"}.get(float(colour[0]))
        if mode is not None:
            settings["background"] = mode
    return settings
