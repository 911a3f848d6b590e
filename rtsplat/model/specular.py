"""Specular shading network (Ref-GS style): environment feature x material feature -> C_spec, beta."""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor, nn

LOG_HALF = math.log(0.5)
NEAR_WEIGHT_START_LOGIT = 2.0  # sigmoid(2) = 0.88
MAX_LOG_SPECULAR = 8.0  # exp() argument cap: keeps C_spec finite under any learning rate
INFERENCE_ROWS = 4096  # rows per slice of the MLP without autograd: its [rows, width] activations stay in cache
ATTENUATION_WIDTH = 16  # hidden units of the attenuation head (attenuation="material")
ATTENUATION_START = 0.9  # the head's beta at the start: a clear thin surface lets about 90% of the light through
ATTENUATION_SOURCES = ("network", "material")


def bucketed_rows(rows: int) -> int:
    """``rows`` rounded up to a multiple of ``max(1024, 2**(b - 5))``, ``b`` its bit length: at most 1023
    rows or 6.25% more. The row counts the bfloat16 products on a CPU run at. oneDNN compiles a bfloat16
    kernel for every new matrix shape (about 17 ms for the network's forward and backward here), and
    the shaded pixels, the network's rows, change with every view and iteration, so unpadded it
    compiles on nearly every step; with these buckets a 100x75 image has eight row counts."""
    if rows <= 0:
        return rows
    step = max(1024, 1 << max(rows.bit_length() - 5, 0))
    return -(-rows // step) * step


@functools.cache
def cpu_has_bfloat16_matmul() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (AVX512-BF16); elsewhere bfloat16 is emulated
    and slower than float32. Probed once per process: the network asks on every forward."""
    try:
        return bool(torch.cpu._is_avx512_bf16_supported())
    except AttributeError:  # a torch without the probe
        return False


@functools.cache
def cpu_has_amx_tiles() -> bool:
    """Whether this CPU has AMX tile units (Intel Xeon since Sapphire Rapids), on which torch's bfloat16 matrix
    products run several times as fast as on AVX512-BF16 alone: the network's backward is then cheap enough that
    sampling its gradient (``schedule.specular_gradient_share``) costs more than it saves. Probed once per process."""
    try:
        return bool(torch.cpu._is_amx_tile_supported())
    except AttributeError:  # a torch without the probe
        return False


class SpecularNetwork(nn.Module):
    """Input: outer product of the env feature (C) and the blended material feature (4), flattened,
    concatenated with the env feature: C*4 + C (= 80 for C = 16). MLP 80 -> 256 -> 256 -> 4.
    With ``mirror`` a fifth output ``m`` (sigmoid) blends a given mirror radiance into C_spec:
    ``reflectance (m mirror + (1 - m) exp(out + log 0.5))``.
    The model may append channels to the env feature (:class:`rtsplat.model.settings.ModelSettings`:
    the angle of incidence, the background at the reflected direction); C counts them.

    ``attenuation``: where beta comes from. ``network``: a fourth output of the MLP, as in the paper, so beta
    sees every input of the network (the environment feature, the background at the reflected direction);
    ``material``: a small head of its own (:data:`ATTENUATION_WIDTH` hidden units) on the blended material
    feature and |cos| of the angle of incidence alone, the two things that decide how much light a thin
    surface lets through, starting near :data:`ATTENUATION_START`. The MLP then has no beta output.

    ``precision``: the dtype of the MLP's matrix products. float32, or bfloat16 (autocast: float32
    weights and outputs, bfloat16 products; forward and backward), or auto: bfloat16 on a CPU with
    native bfloat16 products (:func:`cpu_has_bfloat16_matmul`), float32 elsewhere. On a CPU the bfloat16
    products run on zero-padded rows (:func:`bucketed_rows`).

    Without autograd (inference, ``torch.no_grad``) the MLP runs on slices of :data:`INFERENCE_ROWS` rows
    with its ReLUs in place (:meth:`_mlp_inference`): the same products row by row, so the same values,
    in about half the time on a CPU."""

    def __init__(self, env_channels: int = 16, material_channels: int = 4, width: int = 256,
                 precision: str = "float32", mirror: bool = False, near_weight: bool = False,
                 attenuation: str = "network"):
        super().__init__()
        if precision not in ("float32", "bfloat16", "auto"):
            raise ValueError(f"precision must be float32, bfloat16 or auto, got {precision!r}")
        if attenuation not in ATTENUATION_SOURCES:
            raise ValueError(f"attenuation must be one of {ATTENUATION_SOURCES}, got {attenuation!r}")
        in_dim = env_channels * material_channels + env_channels
        self.precision = precision
        self.mirror = mirror
        self.near_weight = near_weight
        # output columns: C_spec (3), then beta (attenuation="network"), the mirror weight, the near weight
        self.mirror_column = 3 + int(attenuation == "network")
        outputs = self.mirror_column + int(mirror) + int(near_weight)
        self.mlp = nn.Sequential(
            nn.Linear(in_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, outputs)
        )
        self.attenuation_head = (
            nn.Sequential(nn.Linear(material_channels + 1, ATTENUATION_WIDTH), nn.ReLU(),
                          nn.Linear(ATTENUATION_WIDTH, 1))
            if attenuation == "material" else None
        )
        if self.attenuation_head is not None:
            with torch.no_grad():
                self.attenuation_head[-1].bias.fill_(math.log(ATTENUATION_START / (1.0 - ATTENUATION_START)))
        if near_weight:  # the near reflection's weight starts near 1: the mirrored render is trusted first
            with torch.no_grad():
                self.mlp[-1].bias[-1] = NEAR_WEIGHT_START_LOGIT

    def uses_bfloat16(self, device: torch.device) -> bool:
        if self.precision == "auto":
            return device.type == "cpu" and cpu_has_bfloat16_matmul()
        return self.precision == "bfloat16"

    def forward(self, env_features: Tensor, material: Tensor, reflectance: Tensor,
                mirror: Tensor | None = None, near: tuple[Tensor, Tensor] | None = None,
                cos_incidence: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """[M,C], [M,4] (unit), [M,1], [M,3] (a network with ``mirror`` only) -> (C_spec [M,3], beta [M,1]).
        ``near``: the near reflection's premultiplied colour [M,3] and coverage [M,1], composited over the
        network's (far) light before the reflectance scales it: ``reflectance (C_near + (1 - A_near) L)``.
        ``cos_incidence``: |cos| of the angle of incidence [M,1], which the attenuation head needs
        (``attenuation="material"``)."""
        if (mirror is None) == self.mirror:
            raise ValueError("a network with mirror needs the mirror radiance, one without takes none")
        if self.attenuation_head is not None and cos_incidence is None:
            raise ValueError("a network with attenuation='material' needs cos_incidence")
        outer = (env_features[:, :, None] * material[:, None, :]).flatten(1)
        x = torch.cat([outer, env_features], -1)
        if self.uses_bfloat16(x.device):
            rows = x.shape[0]
            if x.device.type == "cpu":  # zero rows up to a bucket (bucketed_rows); their outputs are dropped
                x = nn.functional.pad(x, (0, 0, 0, bucketed_rows(rows) - rows))
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                out = self._run_mlp(x)
            out = out[:rows].to(x.dtype)
        else:
            out = self._run_mlp(x)
        specular = torch.exp((out[:, :3] + LOG_HALF).clamp_max(MAX_LOG_SPECULAR))
        if mirror is not None:
            weight = torch.sigmoid(out[:, self.mirror_column:self.mirror_column + 1])
            specular = weight * mirror + (1.0 - weight) * specular
        if near is not None:
            weight = torch.sigmoid(out[:, -1:]) if self.near_weight else 1.0
            specular = weight * near[0] + (1.0 - weight * near[1]) * specular
        specular = specular * reflectance
        if self.attenuation_head is None:
            beta = torch.sigmoid(out[:, 3:4])
        else:
            head_input = torch.cat([material, cos_incidence.to(material.dtype)], -1)
            beta = torch.sigmoid(self.attenuation_head(head_input)).to(specular.dtype)
        return specular, beta

    def _run_mlp(self, x: Tensor) -> Tensor:
        return self.mlp(x) if torch.is_grad_enabled() else self._mlp_inference(x)

    def _mlp_inference(self, x: Tensor) -> Tensor:
        """``self.mlp(x)`` without autograd: slices of :data:`INFERENCE_ROWS` rows, the ReLUs in place.
        Outside autocast each layer writes into one buffer per layer that every slice reuses (and the
        last layer straight into the output): ``torch.addmm`` with ``out``, the product ``nn.Linear``
        computes, so the same bits; a fresh [rows, width] result per layer and slice cost about as
        much as the product itself on a CPU (new pages for every 4 MB result)."""
        first, _, hidden, _, last = self.mlp
        out = x.new_empty(x.shape[0], last.out_features)
        fused = not torch.is_autocast_enabled(x.device.type) and all(
            layer.bias is not None and layer.weight.dtype == x.dtype for layer in (first, hidden, last))
        if fused:
            slice_rows = min(INFERENCE_ROWS, x.shape[0])
            h1 = x.new_empty(slice_rows, first.out_features)
            h2 = x.new_empty(slice_rows, hidden.out_features)
        for rows, result in zip(x.split(INFERENCE_ROWS), out.split(INFERENCE_ROWS), strict=True):
            if fused:
                k = rows.shape[0]
                h = torch.addmm(first.bias, rows, first.weight.T, out=h1[:k]).relu_()
                h = torch.addmm(hidden.bias, h, hidden.weight.T, out=h2[:k]).relu_()
                torch.addmm(last.bias, h, last.weight.T, out=result)
            else:
                h = first(rows).relu_()
                h = hidden(h).relu_()
                result.copy_(last(h))
        return out
