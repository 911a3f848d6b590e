"""Real spherical harmonics up to degree 3 (the 3DGS colour model)."""

from __future__ import annotations

import torch
from torch import Tensor

from rtsplat.raster.numba_runtime import SURFEL_CHUNK, kernels_take, load_numba_module, numba_threads

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


MAX_DEGREE = 3


def num_coefficients(degree: int) -> int:
    return (degree + 1) ** 2


def check_degree(degree: int) -> None:
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """Basis values [..., (degree+1)^2] at unit ``directions`` [..., 3]."""
    check_degree(degree)
    x, y, z = directions.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, -1)


def eval_sh(coefficients: Tensor, directions: Tensor, degree: int) -> Tensor:
    """Colour [N,3] from SH ``coefficients`` [N, K, 3] at unit ``directions`` [N,3] (+0.5 offset, >= 0).

    On CPU tensors of float32 or float64 the numba kernels of :mod:`rtsplat.model.sh_kernels` compute it
    (one pass per surfel, forward and backward; :func:`eval_sh_reference` is their oracle), elsewhere
    :func:`eval_sh_reference`."""
    return eval_sh_parts(coefficients[:, :1], coefficients[:, 1:], directions, degree)


def eval_sh_parts(dc: Tensor, rest: Tensor, directions: Tensor, degree: int) -> Tensor:
    """:func:`eval_sh` of the coefficients ``dc`` [N, 1, 3] followed by ``rest`` [N, K - 1, 3], without joining
    them into one tensor (the surfels keep them apart; at a million surfels the join would copy some 200 MB
    forward and again backward)."""
    check_degree(degree)  # here too: the kernels do not call sh_basis
    if (dc.dim() == 3 and dc.shape[1:] == (1, 3)
            and rest.dim() == 3 and rest.shape[1:] == (num_coefficients(MAX_DEGREE) - 1, 3)
            and kernels_take("rtsplat.model.sh_kernels", dc, rest, directions)):
        return _ShColour.apply(dc, rest, directions, degree)
    return eval_sh_reference(torch.cat([dc, rest], 1), directions, degree)


def eval_sh_reference(coefficients: Tensor, directions: Tensor, degree: int) -> Tensor:
    """:func:`eval_sh` in plain torch (autograd; any device)."""
    k = num_coefficients(degree)
    basis = sh_basis(directions, degree)  # [N,k]
    rgb = (basis[..., None] * coefficients[:, :k]).sum(-2)
    return (rgb + 0.5).clamp_min(0.0)


def _kernels():
    return load_numba_module("rtsplat.model.sh_kernels")


class _ShColour(torch.autograd.Function):
    """:func:`eval_sh_reference`'s values and gradients from the numba kernels."""

    @staticmethod
    def forward(ctx, dc, rest, directions, degree):
        dc_ = dc.detach().contiguous()
        rest_ = rest.detach().contiguous()
        dirs = directions.detach().contiguous()
        rgb = torch.empty(dc_.shape[0], 3, dtype=dc_.dtype)
        basis = torch.empty(dc_.shape[0], num_coefficients(MAX_DEGREE), dtype=torch.float64)
        with numba_threads(SURFEL_CHUNK):
            _kernels().sh_forward_kernel(dc_.numpy(), rest_.numpy(), dirs.numpy(), int(degree), rgb.numpy(),
                                         basis.numpy())
        ctx.save_for_backward(dc_, rest_, dirs, rgb, basis)
        ctx.degree = int(degree)
        return rgb

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_rgb):
        dc, rest, dirs, rgb, basis = ctx.saved_tensors
        grad = grad_rgb.detach().to(dc.dtype).contiguous()
        grad_dc = torch.empty_like(dc)
        grad_rest = torch.empty_like(rest)
        grad_dirs = torch.empty_like(dirs)
        scratch = torch.empty_like(basis)
        with numba_threads(SURFEL_CHUNK):
            _kernels().sh_backward_kernel(dc.numpy(), rest.numpy(), dirs.numpy(), ctx.degree, rgb.numpy(),
                                          basis.numpy(), grad.numpy(), grad_dc.numpy(), grad_rest.numpy(),
                                          grad_dirs.numpy(), scratch.numpy())
        needs = ctx.needs_input_grad
        return (grad_dc if needs[0] else None, grad_rest if needs[1] else None, grad_dirs if needs[2] else None,
                None)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / C0
