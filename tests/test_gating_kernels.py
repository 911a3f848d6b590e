"""The gating factor's numba kernel (rtsplat/model/gating_kernels.py) against the torch version it replaces on the
CPU (rtsplat.model.gating.gate_factor_reference)."""

import math

import pytest
import torch

from rtsplat.model.gating import gate_factor, gate_factor_reference
from rtsplat.raster.numba_runtime import load_numba_module

pytestmark = pytest.mark.skipif(load_numba_module("rtsplat.model.gating_kernels") is None, reason="needs numba")

MODES = ("weighted_std", "variance")


def _images(h, w, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    spec = torch.rand(h, w, 3, generator=g, dtype=torch.float64).to(dtype)
    alpha = (torch.rand(h, w, 1, generator=g, dtype=torch.float64) * 1.3).to(dtype)  # some above 1: weight 0
    return spec, alpha


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("size", [(2, 2), (2, 7), (3, 5), (75, 100)])
def test_kernel_matches_the_torch_version(mode, size):
    spec, alpha = _images(*size)
    got = gate_factor(spec, alpha, 4.0, mode)
    want = gate_factor_reference(spec, alpha, 4.0, mode)
    assert got.dtype == want.dtype and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=0, atol=3e-7)


@pytest.mark.parametrize("mode", MODES)
def test_kernel_matches_in_float64_and_at_other_strengths(mode):
    spec, alpha = _images(9, 11, torch.float64, seed=1)
    for k in (0.0, 1.0, 40.0):
        torch.testing.assert_close(gate_factor(spec, alpha, k, mode), gate_factor_reference(spec, alpha, k, mode),
                                   rtol=0, atol=1e-12)


def test_opaque_windows_weigh_nothing_and_give_one():
    """Where every pixel of a window has surface alpha 1 (or more), the weights sum to 0: the total is held at
    1e-8, the mean and deviation are 0 and the factor is 1, in both versions."""
    spec, _ = _images(6, 6)
    alpha = torch.ones(6, 6, 1)
    alpha[0, 0] = 1.5
    got = gate_factor(spec, alpha, 4.0, "weighted_std")
    assert torch.equal(got, torch.ones_like(got))
    torch.testing.assert_close(got, gate_factor_reference(spec, alpha, 4.0, "weighted_std"), rtol=0, atol=0)


def test_a_flat_window_gives_exactly_one():
    spec = torch.full((5, 6, 3), 0.3)
    alpha = torch.rand(5, 6, 1, generator=torch.Generator().manual_seed(2))
    for mode in MODES:
        assert torch.equal(gate_factor(spec, alpha, 4.0, mode), torch.ones(5, 6, 3))


@pytest.mark.parametrize("mode", MODES)
def test_a_nan_spoils_the_windows_that_hold_it(mode):
    spec, alpha = _images(8, 9, seed=3)
    # each in one channel, which only that channel's measure reads. Reflect padding: the pixel of row 0 is in the
    # windows of rows 0 and 1 (row 0's window is rows 1, 0, 1), that of the last column in those of the last two
    spec[0, 4, 1] = math.nan
    spec[5, 8, 0] = math.nan
    got = gate_factor(spec, alpha, 4.0, mode)
    want = gate_factor_reference(spec, alpha, 4.0, mode)
    assert torch.equal(torch.isnan(got), torch.isnan(want))
    assert int(torch.isnan(got).sum()) == 2 * 3 + 3 * 2
    assert bool(torch.isnan(got[0:2, 3:6, 1]).all()) and bool(torch.isnan(got[4:7, 7:9, 0]).all())
    finite = ~torch.isnan(want)
    torch.testing.assert_close(got[finite], want[finite], rtol=0, atol=3e-7)


def test_a_nan_alpha_spoils_only_the_weighted_measure():
    spec, alpha = _images(6, 6, seed=4)
    alpha[3, 3] = math.nan
    weighted = gate_factor(spec, alpha, 4.0, "weighted_std")
    assert torch.equal(torch.isnan(weighted), torch.isnan(gate_factor_reference(spec, alpha, 4.0, "weighted_std")))
    assert bool(torch.isnan(weighted[2:5, 2:5]).all())
    assert not bool(torch.isnan(gate_factor(spec, alpha, 4.0, "variance")).any())


def test_images_too_small_to_pad_and_other_devices_take_the_torch_version():
    spec, alpha = _images(1, 5)
    with pytest.raises(RuntimeError):  # reflect padding needs two rows, as in the torch version
        gate_factor(spec, alpha)
    spec, alpha = _images(4, 6, torch.bfloat16)  # a float type the kernel does not take: the torch version itself
    assert torch.equal(gate_factor(spec, alpha), gate_factor_reference(spec, alpha))


def test_unknown_mode_is_refused():
    spec, alpha = _images(4, 4)
    with pytest.raises(ValueError, match="unknown gating mode"):
        gate_factor(spec, alpha, 4.0, "range")


def test_the_factor_carries_no_gradient():
    spec, alpha = _images(5, 5)
    spec.requires_grad_(True)
    alpha.requires_grad_(True)
    got = gate_factor(spec, alpha)
    assert not got.requires_grad
