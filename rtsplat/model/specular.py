"""Specular shading network (Ref-GS style): environment feature x material feature -> C_spec, beta."""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor, nn

from rtsplat.raster.numba_runtime import load_numba_module, numba_threads

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
        out = self.mlp_outputs(env_features, material)
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

    def mlp_outputs(self, env_features: Tensor, material: Tensor) -> Tensor:
        """The MLP's outputs [M, outputs] for the environment [M, C] and material [M, 4] features. With autograd
        on, bfloat16 products on a CPU and float32 features, :class:`BFloat16Network` computes them (numba
        kernels for the input rows and the ReLUs); elsewhere :meth:`mlp_outputs_reference`. Both give the same
        values and weight gradients; the features' gradients differ in rounding only."""
        if (torch.is_grad_enabled() and env_features.device.type == "cpu" and self.uses_bfloat16(env_features.device)
                and env_features.dtype == material.dtype == torch.float32
                and all(p.dtype == torch.float32 for p in self.mlp.parameters())
                and load_numba_module("rtsplat.model.specular_kernels") is not None):
            first, _, hidden, _, last = self.mlp
            return BFloat16Network.apply(env_features, material, first.weight, first.bias, hidden.weight,
                                         hidden.bias, last.weight, last.bias)
        return self.mlp_outputs_reference(env_features, material)

    def mlp_outputs_reference(self, env_features: Tensor, material: Tensor) -> Tensor:
        """:meth:`mlp_outputs` in torch ops: the input rows (the outer product of the features, flattened,
        then the environment feature) through the MLP, under bfloat16 autocast where :meth:`uses_bfloat16`
        (on a CPU, on zero-padded rows: :func:`bucketed_rows`). :class:`BFloat16Network`'s oracle."""
        outer = (env_features[:, :, None] * material[:, None, :]).flatten(1)
        x = torch.cat([outer, env_features], -1)
        if not self.uses_bfloat16(x.device):
            return self._run_mlp(x)
        rows = x.shape[0]
        if x.device.type == "cpu":  # zero rows up to a bucket (bucketed_rows); their outputs are dropped
            x = nn.functional.pad(x, (0, 0, 0, bucketed_rows(rows) - rows))
        with torch.autocast(x.device.type, dtype=torch.bfloat16):
            out = self._run_mlp(x)
        return out[:rows].to(x.dtype)

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


PARALLEL_ROWS = 16384  # fewer network rows than this: the kernels run on the calling thread
PARALLEL_CHUNK = 64  # parallel iterations per chunk: 64 rows of the ReLU kernels, 64 x ROWS of the input kernels


class _KernelSet:
    """The four kernels of :mod:`rtsplat.model.specular_kernels`, parallel or serial."""

    def __init__(self, module, parallel: bool):
        suffix = "" if parallel else "_serial"
        for name in ("network_input_kernel", "network_input_grad_kernel", "relu_kernel", "relu_grad_kernel"):
            setattr(self, name, getattr(module, name + suffix))


def _specular_kernels(threads: int, rows: int) -> _KernelSet:
    """The kernels for ``rows`` network rows on ``threads`` numba threads: parallel only with more than one
    thread and at least :data:`PARALLEL_ROWS` rows; a parallel call costs some 0.06 ms before any work, more than
    the whole serial ReLU of 4096 rows of 256 (0.04 ms, docs/performance.md)."""
    return _KernelSet(load_numba_module("rtsplat.model.specular_kernels"), threads > 1 and rows >= PARALLEL_ROWS)


def _bits(t: Tensor) -> np.ndarray:
    """A contiguous bfloat16 tensor's 16-bit patterns as a numpy int16 array (shared memory)."""
    return t.view(torch.int16).numpy()


class BFloat16Network(torch.autograd.Function):
    """The specular network's MLP (``Linear, ReLU, Linear, ReLU, Linear``) on a CPU with bfloat16 products:
    ``apply(env [M, C], material [M, K], w1, b1, w2, b2, w3, b3)`` -> outputs [M, outputs], float32.

    The operations of :meth:`SpecularNetwork.mlp_outputs_reference` under autocast, in its order: weights and
    biases rounded to bfloat16, the input rows padded to :func:`bucketed_rows`, ``addmm`` products, the
    outputs rounded back to float32; the backward is autocast's (``AddmmBackward0``'s products and bias sums in
    bfloat16, the weights' gradients rounded to float32). Numba kernels (:mod:`rtsplat.model.specular_kernels`)
    replace the torch ops that cost more than the products: building the input rows (outer product, cat, pad
    and rounding, one pass), the ReLUs and their gradients (torch's bfloat16 element-wise ops convert every
    value to float32 and back), and the features' gradient from the input rows' (summed in float64 instead of
    torch's broadcast float32 sums). So the outputs and the weights' gradients are the reference's bit for bit,
    and the features' gradients equal it up to rounding."""

    @staticmethod
    def forward(ctx, env: Tensor, material: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor,
                w3: Tensor, b3: Tensor) -> Tensor:
        env, material = env.detach().contiguous(), material.detach().contiguous()
        m = env.shape[0]
        rows = bucketed_rows(m)
        x = torch.empty(rows, w1.shape[1], dtype=torch.bfloat16)
        weights = [w.detach().to(torch.bfloat16) for w in (w1, w2, w3)]
        biases = [b.detach().to(torch.bfloat16) for b in (b1, b2, b3)]
        with numba_threads(PARALLEL_CHUNK) as threads:
            kernels = _specular_kernels(threads, rows)
            kernels.network_input_kernel(env.numpy(), material.numpy(), rows, _bits(x).view(np.uint16))
            h1 = torch.addmm(biases[0], x, weights[0].t())
            kernels.relu_kernel(_bits(h1))
            h2 = torch.addmm(biases[1], h1, weights[1].t())
            kernels.relu_kernel(_bits(h2))
        out = torch.addmm(biases[2], h2, weights[2].t())
        ctx.save_for_backward(env, material, x, h1, h2, *weights)
        return out[:m].float()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        env, material, x, h1, h2, w1, w2, w3 = ctx.saved_tensors
        g3 = grad.new_zeros(x.shape[0], grad.shape[1], dtype=torch.bfloat16)
        g3[: grad.shape[0]] = grad
        grads = [None] * 8
        with numba_threads(PARALLEL_CHUNK) as threads:
            kernels = _specular_kernels(threads, x.shape[0])
            g2 = g3.mm(w3)
            kernels.relu_grad_kernel(_bits(g2), _bits(h2))
            g1 = g2.mm(w2)
            kernels.relu_grad_kernel(_bits(g1), _bits(h1))
            for slot, (g, inputs) in zip((2, 4, 6), ((g1, x), (g2, h1), (g3, h2)), strict=True):
                if ctx.needs_input_grad[slot]:
                    grads[slot] = g.t().mm(inputs).float()
                if ctx.needs_input_grad[slot + 1]:
                    grads[slot + 1] = g.sum(0).float()
            if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
                gx = g1.mm(w1).float()
                g_env = torch.empty_like(env)
                g_material = torch.empty_like(material)
                kernels.network_input_grad_kernel(gx.numpy(), env.numpy(), material.numpy(), g_env.numpy(),
                                                  g_material.numpy())
                grads[0], grads[1] = g_env, g_material
        return tuple(grads)
