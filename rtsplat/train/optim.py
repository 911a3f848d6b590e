"""Adam over per-surfel parameters, with the row surgery that density control needs
(append rows, keep a subset, reset rows), keeping each row's Adam moments with its row."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from rtsplat.model.surfels import PARAMETERS, SurfelParameters
from rtsplat.train_config import LearningRates

LR_OF = {
    "means": "position_init", "quats": "rotation", "log_scales": "scaling", "occupancy_logit": "occupancy",
    "opacity_logit": "opacity", "sh_dc": "sh_dc", "sh_rest": "sh_rest", "scatter_logit": "scatter",
    "transmissivity_logit": "transmissivity", "roughness_logit": "roughness", "material_raw": "material",
    "reflectance_logit": "reflectance",
}


# the learning rates of the groups besides the surfels' (build_optimizer)
LR_OF_MODULE = {"env_map": "env_map", "mlp": "mlp", "background": "background"}


def learning_rate_key(group: str) -> str:
    """The config key (``lr.<name>``) of a parameter group's learning rate."""
    if group == "means":
        return "lr.position_init"
    return "lr." + {**LR_OF, **LR_OF_MODULE}[group]


def surfel_learning_rate(name: str, lr: LearningRates, extent: float) -> float:
    if name == "sh_rest" and lr.sh_rest is None:
        return lr.sh_dc / 20.0
    value = getattr(lr, LR_OF[name])
    if name == "means":
        value *= extent
    return value


def position_lr(iteration: int, lr: LearningRates, extent: float) -> float:
    """Log-linear decay from position_init to position_final over position_max_steps (x extent)."""
    t = min(max(iteration / max(lr.position_max_steps, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(lr.position_init) + t * math.log(lr.position_final))


def build_optimizer(model: nn.Module, surfels: SurfelParameters, lr: LearningRates, extent: float) -> torch.optim.Adam:
    groups = [{"name": name, "params": [getattr(surfels, name)], "lr": surfel_learning_rate(name, lr, extent)}
              for name in PARAMETERS]
    env = getattr(model, "env", None)
    if env is not None:
        groups.append({"name": "env_map", "params": list(env.parameters()), "lr": lr.env_map})
    net = getattr(model, "specular_net", None)
    if net is not None:
        groups.append({"name": "mlp", "params": list(net.parameters()), "lr": lr.mlp})
    background = getattr(model, "background_map", None)
    if background is not None:
        groups.append({"name": "background", "params": list(background.parameters()), "lr": lr.background})
    # fused: one kernel per step over all parameters (matters for the 8M-value environment map on
    # a CPU); same update rule as the default implementation
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict) -> None:
    """``optimizer.load_state_dict(state)``, then every moment laid out in memory as its parameter is. torch's
    fused Adam pairs a parameter's values with its gradient's and its moments' in memory order, not by index,
    so a moment saved in another layout would update the wrong values: the environment map is kept channels
    last (:class:`rtsplat.model.envmap.EnvironmentMap`), and a checkpoint may hold its moments contiguous."""
    optimizer.load_state_dict(state)
    for group in optimizer.param_groups:
        for param in group["params"]:
            moments = optimizer.state.get(param, {})
            for key, value in moments.items():
                if torch.is_tensor(value) and value.shape == param.shape and value.stride() != param.stride():
                    moments[key] = torch.empty_like(param).copy_(value)


def _group(optimizer: torch.optim.Optimizer, name: str) -> dict:
    return next(g for g in optimizer.param_groups if g.get("name") == name)


def _swap(optimizer, surfels: SurfelParameters, name: str, new_value: Tensor, state_fn) -> None:
    group = _group(optimizer, name)
    old = group["params"][0]
    state = optimizer.state.pop(old, None)
    param = nn.Parameter(new_value.contiguous())
    group["params"][0] = param
    setattr(surfels, name, param)
    if state:
        optimizer.state[param] = {
            k: (state_fn(v) if torch.is_tensor(v) and v.dim() > 0 and v.shape == old.shape else v)
            for k, v in state.items()
        }


def append_rows(optimizer, surfels: SurfelParameters, rows: dict[str, Tensor]) -> None:
    """Add surfels; their Adam moments start at zero."""
    for name in PARAMETERS:
        extra = rows[name].to(getattr(surfels, name).dtype)
        value = torch.cat([getattr(surfels, name).detach(), extra])
        _swap(optimizer, surfels, name, value, lambda v, e=extra: torch.cat([v, torch.zeros_like(e)]))


def keep_rows(optimizer, surfels: SurfelParameters, keep: Tensor) -> None:
    for name in PARAMETERS:
        _swap(optimizer, surfels, name, getattr(surfels, name).detach()[keep], lambda v: v[keep])


def reset_rows(optimizer, surfels: SurfelParameters, name: str, new_value: Tensor) -> None:
    """Replace a parameter's values and zero its Adam moments (3DGS opacity reset)."""
    _swap(optimizer, surfels, name, new_value, torch.zeros_like)
