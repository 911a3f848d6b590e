"""Numba kernels of the specular network's bfloat16 pass on a CPU (:class:`rtsplat.model.specular.BFloat16Network`).

Imported lazily (through :func:`rtsplat.raster.numba_runtime.load_numba_module`), never by ``import rtsplat``.
bfloat16 tensors reach the kernels as their 16-bit patterns (``tensor.view(torch.int16).numpy()``): the sign
bit on top, then the float32 exponent and the top 7 bits of its mantissa. Every kernel comes twice: parallel
(the input kernels take :data:`ROWS` rows per parallel iteration, the ReLU kernels one row) and ``*_serial``, on
the calling thread, for one thread or few rows, where starting numba's parallel loop (some 0.06 ms a call here)
costs more than the work.

* :func:`network_input_kernel`: the network's input row, the outer product of the environment feature and the
  material feature (flattened, environment-major) followed by the environment feature, rounded to bfloat16 as
  ``Tensor.to(torch.bfloat16)`` rounds (to nearest, ties to even; a NaN stays a NaN, 0x7FC0, where torch's
  vector path may keep its sign and payload), and zero rows after the last sample (the bucket's padding).
* :func:`network_input_grad_kernel`: the gradient of the environment and material features from the input
  rows' gradient (summed in float64).
* :func:`relu_kernel`, :func:`relu_grad_kernel`: ``relu`` and its gradient in place, bit for bit those of
  ``torch.relu`` and ``threshold_backward`` (one comparison of the int16 pattern each, which vectorises; torch's
  bfloat16 element-wise ops convert every value to float32 and back).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_JIT = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)

_NAN_BFLOAT16 = 0x7FC0
NEGATIVE_INFINITY = -128  # 0xFF80, bfloat16's -inf, as int16: every pattern from -32768 to it is a number <= -0


@njit(inline="always", **_JIT)
def _rounded_bfloat16(bits):
    """The bfloat16 pattern (0..0xFFFF) nearest the float32 with pattern ``bits`` (0..0xFFFFFFFF)."""
    if (bits & 0x7FFFFFFF) > 0x7F800000:
        return _NAN_BFLOAT16
    return (bits + 0x7FFF + ((bits >> 16) & 1)) >> 16


ROWS = 64  # rows per parallel iteration of the parallel input kernels: one scratch row per iteration, not per row


@njit(inline="always", **_JIT)
def _input_rows(env, material, out, lo, hi, row):
    """Rows ``lo`` to ``hi`` of :func:`network_input_kernel`; ``row``: float32 scratch of the row's width."""
    m_count, c_count = env.shape
    k_count = material.shape[1]
    bits = row.view(np.uint32)
    for m in range(lo, hi):
        if m >= m_count:
            for k in range(out.shape[1]):
                out[m, k] = 0
            continue
        for i in range(c_count):
            e = env[m, i]
            for j in range(k_count):
                row[i * k_count + j] = e * material[m, j]
            row[c_count * k_count + i] = e
        for k in range(out.shape[1]):
            out[m, k] = _rounded_bfloat16(np.int64(bits[k]))


@njit(parallel=True, **_JIT)
def network_input_kernel(env, material, rows, out):
    """``out`` [R, C*K + C] (uint16 view of bfloat16): for a sample m < ``env.shape[0]``, the bfloat16 of
    ``env[m, i] * material[m, j]`` at column i*K + j and of ``env[m, i]`` at column C*K + i; zeros in the rows
    after the samples. ``env`` [M, C] and ``material`` [M, K] are float32; ``rows``: R."""
    for chunk in prange((rows + ROWS - 1) // ROWS):
        _input_rows(env, material, out, chunk * ROWS, min(rows, (chunk + 1) * ROWS),
                    np.empty(out.shape[1], dtype=np.float32))


@njit(**_JIT)
def network_input_kernel_serial(env, material, rows, out):
    """:func:`network_input_kernel` on the calling thread."""
    _input_rows(env, material, out, 0, rows, np.empty(out.shape[1], dtype=np.float32))


@njit(inline="always", **_JIT)
def _input_grad_rows(grad, env, material, g_env, g_material, lo, hi, sums):
    """Rows ``lo`` to ``hi`` of :func:`network_input_grad_kernel`; ``sums``: float64 scratch [K]."""
    c_count = env.shape[1]
    k_count = material.shape[1]
    for m in range(lo, hi):
        for j in range(k_count):
            sums[j] = 0.0
        for i in range(c_count):
            e = np.float64(env[m, i])
            total = np.float64(grad[m, c_count * k_count + i])
            for j in range(k_count):
                g = np.float64(grad[m, i * k_count + j])
                total += g * np.float64(material[m, j])
                sums[j] += g * e
            g_env[m, i] = total
        for j in range(k_count):
            g_material[m, j] = sums[j]


@njit(parallel=True, **_JIT)
def network_input_grad_kernel(grad, env, material, g_env, g_material):
    """From the input rows' gradient ``grad`` [R, C*K + C] (float32; rows past ``env``'s ignored): ``g_env``
    [M, C] = sum_j grad[m, i*K + j] material[m, j] + grad[m, C*K + i] and ``g_material`` [M, K] =
    sum_i grad[m, i*K + j] env[m, i], summed in float64."""
    m_count = env.shape[0]
    for chunk in prange((m_count + ROWS - 1) // ROWS):
        _input_grad_rows(grad, env, material, g_env, g_material, chunk * ROWS, min(m_count, (chunk + 1) * ROWS),
                         np.empty(material.shape[1], dtype=np.float64))


@njit(**_JIT)
def network_input_grad_kernel_serial(grad, env, material, g_env, g_material):
    """:func:`network_input_grad_kernel` on the calling thread."""
    _input_grad_rows(grad, env, material, g_env, g_material, 0, env.shape[0],
                     np.empty(material.shape[1], dtype=np.float64))


@njit(inline="always", **_JIT)
def _relu_row(h, r):
    for k in range(h.shape[1]):
        v = h[r, k]
        h[r, k] = 0 if v <= NEGATIVE_INFINITY else v


@njit(parallel=True, **_JIT)
def relu_kernel(h):
    """``h`` [R, W] (int16 view of bfloat16) := relu(h) in place, as ``torch.relu`` does: the patterns from
    0x8000 (-0) to 0xFF80 (-inf), int16 -32768 to :data:`NEGATIVE_INFINITY`, are the negative numbers and become
    +0; a NaN of either sign stays."""
    for r in prange(h.shape[0]):
        _relu_row(h, r)


@njit(**_JIT)
def relu_kernel_serial(h):
    """:func:`relu_kernel` on the calling thread."""
    for r in range(h.shape[0]):
        _relu_row(h, r)


@njit(inline="always", **_JIT)
def _relu_grad_row(grad, h, r):
    for k in range(h.shape[1]):
        v = h[r, k]
        grad[r, k] = 0 if (v == 0) | (v <= NEGATIVE_INFINITY) else grad[r, k]


@njit(parallel=True, **_JIT)
def relu_grad_kernel(grad, h):
    """``grad`` [R, W] (int16 view of bfloat16) := 0 where the ReLU's output ``h`` (int16 view) is a number at
    or below zero (+0 and the negative numbers), in place, as ``threshold_backward(grad, h, 0)`` does (a NaN
    output keeps its gradient: NaN <= 0 is false)."""
    for r in prange(h.shape[0]):
        _relu_grad_row(grad, h, r)


@njit(**_JIT)
def relu_grad_kernel_serial(grad, h):
    """:func:`relu_grad_kernel` on the calling thread."""
    for r in range(h.shape[0]):
        _relu_grad_row(grad, h, r)
