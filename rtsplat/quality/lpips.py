"""LPIPS-VGG (Zhang et al. 2018) with *real* weights only.

Two weight files are needed: torchvision's VGG16 ImageNet weights (``vgg16-397923af.pth``,
keys ``features.N.weight/bias``) and the LPIPS linear heads (``vgg.pth`` of the ``lpips``
package, keys ``linK.model.1.weight``). Neither can be downloaded by this project: they are
looked up in a user-given directory, then in the torch hub cache (``torch.hub.get_dir()``) and
an installed ``lpips`` package. When they are missing, :func:`load_lpips` returns ``None`` and
says where it looked; callers turn the perceptual term off (never random weights).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

VGG_FILE = "vgg16-397923af.pth"
LIN_FILE = "vgg.pth"
# VGG16 "features" conv layers (index in torchvision's Sequential, out channels); taps after the
# ReLU of conv indices 2, 7, 14, 21, 28 (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3)
VGG_CONVS = [(0, 64), (2, 64), (5, 128), (7, 128), (10, 256), (12, 256), (14, 256), (17, 512), (19, 512),
             (21, 512), (24, 512), (26, 512), (28, 512)]
TAPS = {2, 7, 14, 21, 28}
POOL_BEFORE = {5, 10, 17, 24}
TAP_CHANNELS = (64, 128, 256, 512, 512)


class LPIPSVGG(nn.Module):
    def __init__(self):
        super().__init__()
        convs, in_ch = {}, 3
        for index, out_ch in VGG_CONVS:
            convs[str(index)] = nn.Conv2d(in_ch, out_ch, 3, padding=1)
            in_ch = out_ch
        self.convs = nn.ModuleDict(convs)
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in TAP_CHANNELS])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.requires_grad_(False)

    def _features(self, x: Tensor) -> list[Tensor]:
        taps = []
        for index, _ in VGG_CONVS:
            if index in POOL_BEFORE:
                x = F.max_pool2d(x, 2)
            x = F.relu(self.convs[str(index)](x))
            if index in TAPS:
                taps.append(x)
        return taps

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        """LPIPS distance of two [H,W,3] images in [0,1] (a scalar)."""
        def prep(img: Tensor) -> Tensor:
            return ((img.permute(2, 0, 1)[None] * 2 - 1) - self.shift) / self.scale

        total = a.new_zeros(())
        for fa, fb, lin in zip(self._features(prep(a)), self._features(prep(b)), self.lins, strict=True):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((na - nb) ** 2).mean()
        return total

    def distance_map(self, a: Tensor, b: Tensor) -> Tensor:
        """Per-pixel LPIPS [H,W]: each layer's map upsampled (bilinear) to the image size and summed
        (the ``spatial`` variant of the lpips package); its mean over a region scores that region."""
        H, W = a.shape[:2]

        def prep(img: Tensor) -> Tensor:
            return ((img.permute(2, 0, 1)[None] * 2 - 1) - self.shift) / self.scale

        total = a.new_zeros(H, W)
        for fa, fb, lin in zip(self._features(prep(a)), self._features(prep(b)), self.lins, strict=True):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            layer = lin((na - nb) ** 2)
            total = total + F.interpolate(layer, size=(H, W), mode="bilinear", align_corners=False)[0, 0]
        return total

    def load_weights(self, vgg_state: dict, lin_state: dict) -> LPIPSVGG:
        for index, _ in VGG_CONVS:
            self.convs[str(index)].weight.data.copy_(vgg_state[f"features.{index}.weight"])
            self.convs[str(index)].bias.data.copy_(vgg_state[f"features.{index}.bias"])
        for k, lin in enumerate(self.lins):
            lin.weight.data.copy_(lin_state[f"lin{k}.model.1.weight"])
        return self


def _candidates(user_path: str) -> tuple[list[Path], list[Path]]:
    vgg, lin = [], []
    if user_path:
        p = Path(user_path).expanduser()
        vgg.append(p / VGG_FILE if p.is_dir() or not p.suffix else p)
        lin.append(p / LIN_FILE if p.is_dir() or not p.suffix else p.with_name(LIN_FILE))
    vgg.append(Path(torch.hub.get_dir()) / "checkpoints" / VGG_FILE)
    lin.append(Path(torch.hub.get_dir()) / "checkpoints" / LIN_FILE)
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin:
        lin.append(Path(spec.origin).parent / "weights" / "v0.1" / LIN_FILE)
    return vgg, lin


def load_lpips(user_path: str = "", device: str | torch.device = "cpu") -> tuple[LPIPSVGG | None, str]:
    """(model, note). ``None`` with a note naming the places searched when weights are missing."""
    vgg_paths, lin_paths = _candidates(user_path)
    vgg = next((p for p in vgg_paths if p.is_file()), None)
    lin = next((p for p in lin_paths if p.is_file()), None)
    if vgg is None or lin is None:
        looked = ", ".join(str(p) for p in (vgg_paths if vgg is None else lin_paths))
        return None, f"off: LPIPS-VGG weights not found (looked for {looked})"
    model = LPIPSVGG().load_weights(torch.load(vgg, map_location="cpu"), torch.load(lin, map_location="cpu"))
    return model.to(device).eval(), f"on: VGG16 {vgg}, LPIPS heads {lin}"
