"""How far the reconstructed see-through surface is from the true one, on a synthetic scene:
``python -m rtsplat.bench.glass_normals``.

A reflection leaves the surface at twice the angle its normal is off, so the normals of the glass
decide whether a reflection can line up with what it reflects. For a scene made by ``rtsplat synth``
the true surface is known (:func:`rtsplat.synth.catalog.see_through_any`: analytic for the named scenes,
sampled from the geometry for a member of the scene family). The prepared cameras
are mapped onto the dataset's ground-truth cameras by the least-squares similarity of their centres
(:func:`rtsplat.pose_eval.similarity`), which carries the surfels into the scene's world. A surfel
within ``--tolerance`` (world units) of the true surface counts as glass; its error is the angle
between its normal and the true normal there, up to sign. Printed per source: the surfels on the
glass, their mean occupancy, the median, the occupancy-weighted median and the 90th percentile of
the angle. The sources are the mask hull's surface points (``transparent_surface.npz``, where
training starts surfels on the glass) and each run's ``model.pt``.

    python -m rtsplat.bench.glass_normals --dataset demo/data/dome --prepared demo/results/dome/prepared \\
        --run demo/results/dome/runs/rtsplat --run demo/results/dome/runs/2dgs
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rtsplat.errors import PipelineError


@dataclass
class NormalErrors:
    """Angles (degrees) between the normals of the points on the glass and the true normals."""

    on_glass: int
    occupancy_mean: float
    median: float
    weighted_median: float
    p90: float


def normal_errors(points: np.ndarray, normals: np.ndarray, glass_points: np.ndarray, glass_normals: np.ndarray,
                  tolerance: float, weights: np.ndarray | None = None) -> NormalErrors | None:
    """Compare ``normals`` [N,3] at ``points`` [N,3] with the normal of the nearest sample of the true
    surface (``glass_points``, ``glass_normals``), for the points within ``tolerance`` of it. None when no
    point is. ``weights`` (default 1) weigh the weighted median (the surfels' occupancy)."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(glass_points).query(points)
    near = distance < tolerance
    if not near.any():
        return None
    unit = normals[near] / np.maximum(np.linalg.norm(normals[near], axis=1, keepdims=True), 1e-12)
    angle = np.degrees(np.arccos(np.clip(np.abs((unit * glass_normals[index[near]]).sum(1)), 0.0, 1.0)))
    w = np.ones(len(angle)) if weights is None else np.asarray(weights, dtype=np.float64)[near]
    order = np.argsort(angle)
    cumulative = np.cumsum(w[order]) / max(float(w.sum()), 1e-12)
    return NormalErrors(on_glass=int(near.sum()), occupancy_mean=float(w.mean()), median=float(np.median(angle)),
                        weighted_median=float(angle[order][min(np.searchsorted(cumulative, 0.5), len(angle) - 1)]),
                        p90=float(np.percentile(angle, 90)))


def to_scene_world(prepared: Path, dataset: Path) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) with world ~ s R x + t: the prepared cameras' centres fitted to the dataset's ground-truth
    cameras (``cameras.json``, written by ``rtsplat synth``)."""
    from rtsplat.pose_eval import camera_center, similarity
    from rtsplat.scene import PreparedScene

    truth_file = dataset / "cameras.json"
    if not truth_file.exists():
        raise PipelineError("no ground-truth cameras", path=truth_file,
                            fix="use a dataset made by `rtsplat synth`, which writes cameras.json")
    truth = {Path(c["name"]).stem: np.asarray(c["world_to_camera"], dtype=np.float64)
             for c in json.loads(truth_file.read_text())["cameras"]}
    scene = PreparedScene.load(prepared)
    records = [r for r in scene.train_cameras + scene.test_cameras if Path(r.image or r.name).stem in truth]
    if len(records) < 3:
        raise PipelineError("fewer than 3 prepared cameras match the dataset's cameras.json by name", path=prepared,
                            fix="prepare the scene from this dataset")
    ours = np.stack([camera_center(r.w2c_array) for r in records])
    theirs = np.stack([camera_center(truth[Path(r.image or r.name).stem]) for r in records])
    return similarity(ours, theirs)


def surfels_of_run(run: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres [N,3], normals [N,3] and occupancies [N] of the surfels in ``run``/model.pt."""
    import torch

    from rtsplat.model.checkpoint import read_checkpoint
    from rtsplat.raster.projection import quat_to_rotmat

    surfels = read_checkpoint(run / "model.pt").surfels
    quats = torch.nn.functional.normalize(surfels["quats"].double(), dim=-1)
    normals = quat_to_rotmat(quats)[:, :, 2]
    return (surfels["means"].double().numpy(), normals.numpy(),
            torch.sigmoid(surfels["occupancy_logit"].double()).reshape(-1).numpy())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True, help="the synthetic dataset (scene.json, cameras.json)")
    parser.add_argument("--prepared", type=Path, required=True, help="the prepared scene the runs trained on")
    parser.add_argument("--run", type=Path, action="append", default=[], help="a run folder with model.pt (repeatable)")
    parser.add_argument("--tolerance", type=float, default=0.03,
                        help="how close to the true surface a surfel counts as glass (world units, default 0.03)")
    args = parser.parse_args(argv)

    from rtsplat.synth.catalog import see_through_any

    description = json.loads((args.dataset / "scene.json").read_text())
    name = description["scene"]
    glass_points, glass_normals = see_through_any(name, description["params"], spacing=args.tolerance / 2)
    if not len(glass_points):
        raise PipelineError(f"scene {name!r} has no see-through surface", path=args.dataset / "scene.json")
    s, R, t = to_scene_world(args.prepared, args.dataset)
    sources: list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]] = []
    hull = args.prepared / "transparent_surface.npz"
    if hull.exists():
        data = np.load(hull)
        sources.append(("mask hull (start)", data["xyz"].astype(np.float64), data["normal"].astype(np.float64), None))
    for run in args.run:
        sources.append((run.name, *surfels_of_run(run)))
    print(f"{name}: true surface {len(glass_points)} samples; surfels within {args.tolerance} of it; angles in degrees")
    print(f"{'source':<24} {'on glass':>8} {'occupancy':>9} {'median':>7} {'weighted':>8} {'p90':>6}")
    for label, points, normals, weights in sources:
        errors = normal_errors(s * points @ R.T + t, normals @ R.T, glass_points, glass_normals, args.tolerance,
                               weights)
        if errors is None:
            print(f"{label:<24} {0:>8}")
            continue
        occupancy = f"{errors.occupancy_mean:9.3f}" if weights is not None else f"{'-':>9}"
        print(f"{label:<24} {errors.on_glass:>8} {occupancy} {errors.median:7.1f} {errors.weighted_median:8.1f} "
              f"{errors.p90:6.1f}")


if __name__ == "__main__":
    from rtsplat.errors import run_command

    raise SystemExit(run_command("python -m rtsplat.bench.glass_normals", main))
