"""Export surfels to a PLY that 3DGS viewers open (binary little endian).

Standard 3DGS properties: x y z, nx ny nz (0), f_dc_0..2, f_rest_* (channel-major as 3DGS
writes them), opacity (logit of the effective opacity occupancy x opacity), scale_0..2 (log;
scale_2 is a tiny thickness so 3D viewers draw a flat disk), rot_0..3 (w x y z). RT-Splatting
attributes follow as extra properties: occupancy, optical_opacity, transmissivity, roughness,
reflectance, scatter_0..2, material_0..3 (activated values).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from rtsplat.io.atomic import atomic_file
from rtsplat.model.surfels import SurfelParameters

FLAT_LOG_SCALE = float(np.log(1e-7))


def surfel_ply_arrays(surfels: SurfelParameters, uses_opacity: bool = True) -> dict[str, np.ndarray]:
    with torch.no_grad():
        n = len(surfels)
        occupancy = surfels.occupancy
        opacity = surfels.opacity if uses_opacity else torch.ones_like(occupancy)
        effective = (occupancy * opacity).clamp(1e-6, 1 - 1e-6)
        cols: dict[str, torch.Tensor] = {}
        for i, axis in enumerate("xyz"):
            cols[axis] = surfels.means[:, i]
        for axis in ("nx", "ny", "nz"):
            cols[axis] = torch.zeros(n)
        for i in range(3):
            cols[f"f_dc_{i}"] = surfels.sh_dc[:, 0, i]
        rest = surfels.sh_rest.transpose(1, 2).reshape(n, -1)  # [N, 3*K] channel-major
        for i in range(rest.shape[1]):
            cols[f"f_rest_{i}"] = rest[:, i]
        cols["opacity"] = torch.logit(effective)
        cols["scale_0"], cols["scale_1"] = surfels.log_scales[:, 0], surfels.log_scales[:, 1]
        cols["scale_2"] = torch.full((n,), FLAT_LOG_SCALE)
        quats = torch.nn.functional.normalize(surfels.quats, dim=-1)
        for i in range(4):
            cols[f"rot_{i}"] = quats[:, i]
        cols["occupancy"] = occupancy
        cols["optical_opacity"] = opacity
        cols["transmissivity"] = surfels.transmissivity
        cols["roughness"] = surfels.roughness
        cols["reflectance"] = surfels.reflectance
        for i in range(3):
            cols[f"scatter_{i}"] = surfels.scatter[:, i]
        for i in range(4):
            cols[f"material_{i}"] = surfels.material[:, i]
        return {k: v.detach().cpu().float().numpy() for k, v in cols.items()}


def write_surfel_ply(path: str | Path, surfels: SurfelParameters, uses_opacity: bool = True) -> Path:
    cols = surfel_ply_arrays(surfels, uses_opacity)
    n = len(surfels)
    data = np.empty(n, dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        data[k] = v
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {k}\n" for k in cols) + "end_header\n"
    path = Path(path)
    with atomic_file(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(data.tobytes())
    return path


def read_surfel_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read back the float properties of a PLY written by :func:`write_surfel_ply`."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    n = next(int(x.split()[2]) for x in lines if x.startswith("element vertex"))
    names = [x.split()[2] for x in lines if x.startswith("property float")]
    data = np.frombuffer(raw[end:], dtype=[(k, "<f4") for k in names], count=n)
    return {k: np.array(data[k]) for k in names}
