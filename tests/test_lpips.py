"""LPIPS-VGG loader: real-format weight files are found and used; missing weights switch the term off."""

from __future__ import annotations

import torch

from rtsplat.quality.lpips import LIN_FILE, TAP_CHANNELS, VGG_CONVS, VGG_FILE, load_lpips


def write_weights(folder, seed=0):
    """Files with the key layout of torchvision's VGG16 and of the lpips package's heads.

    The values are random (these tests check the loading path and the metric's algebra, not
    perceptual quality); the heads are non-negative like the trained ones.
    """
    g = torch.Generator().manual_seed(seed)
    vgg, in_ch = {}, 3
    for index, out_ch in VGG_CONVS:
        vgg[f"features.{index}.weight"] = torch.randn(out_ch, in_ch, 3, 3, generator=g) * (2.0 / (9 * in_ch)) ** 0.5
        vgg[f"features.{index}.bias"] = torch.zeros(out_ch)
        in_ch = out_ch
    lin = {f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for k, c in enumerate(TAP_CHANNELS)}
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(vgg, folder / VGG_FILE)
    torch.save(lin, folder / LIN_FILE)
    return vgg, lin


def test_missing_weights_turn_the_term_off_and_say_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    model, note = load_lpips(str(tmp_path / "nothing_here"))
    assert model is None
    assert note.startswith("off") and str(tmp_path / "nothing_here" / VGG_FILE) in note


def test_weights_from_a_user_directory_are_loaded_exactly(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    vgg, lin = write_weights(tmp_path / "weights")
    model, note = load_lpips(str(tmp_path / "weights"))
    assert model is not None and note.startswith("on")
    torch.testing.assert_close(model.convs["28"].weight, vgg["features.28.weight"], rtol=0, atol=0)
    torch.testing.assert_close(model.lins[4].weight, lin["lin4.model.1.weight"], rtol=0, atol=0)


def test_weights_in_the_torch_hub_cache_are_found(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    write_weights(tmp_path / "hub" / "checkpoints")
    model, note = load_lpips("")
    assert model is not None and str(tmp_path / "hub") in note


def test_distance_is_zero_on_identical_images_positive_otherwise_and_symmetric(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    write_weights(tmp_path / "weights")
    model, _ = load_lpips(str(tmp_path / "weights"))
    g = torch.Generator().manual_seed(1)
    a = torch.rand(48, 64, 3, generator=g)
    b = (a + 0.2 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    assert model(a, a).item() == 0.0
    d_ab, d_ba = model(a, b), model(b, a)
    assert d_ab.item() > 0
    torch.testing.assert_close(d_ab, d_ba)
    # more noise, larger distance
    c = (a + 0.5 * torch.randn(48, 64, 3, generator=g)).clamp(0, 1)
    assert model(a, c).item() > d_ab.item()
    # differentiable with respect to the rendered image, as the perceptual loss needs
    x = b.clone().requires_grad_(True)
    model(x, a).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
