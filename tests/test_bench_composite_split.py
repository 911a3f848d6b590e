"""The compositing split between an RT-Splatting run and a baseline run (rtsplat.bench.composite_split)."""

from __future__ import annotations

import re

import pytest
import torch

import rtsplat.raster.cpu as cpu
from rtsplat.bench import composite_split
from rtsplat.bench.toy_scene import write_scene
from rtsplat.model.rtmodel import GBUFFER_WIDTHS
from rtsplat.render import load_run
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig

SMALL_MODEL = {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}


def _train(scene, out, effects: dict) -> None:
    cfg = TrainConfig.from_dict({
        "schedule": {"iterations": 6, "volume_until": 1, "specular_from": 2, "densify_from": 100, "reset_every": 0,
                     "eval_every": 0, "checkpoint_every": 0},
        "model": SMALL_MODEL, "effects": effects, "cameras": {"final_fit_steps": 0},
    })
    Trainer(scene, cfg, out, progress=False, log=lambda m: None).train()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("split")
    scene = write_scene(root / "prepared", views=6, width=32, height=24)
    _train(scene, root / "rtsplat", {"transmission": "on", "specular": "on"})
    _train(scene, root / "2dgs", {"transmission": "off", "specular": "off"})
    return root


def test_the_variants_differ_only_in_the_channels_and_the_opacity(runs):
    run = load_run(runs / "rtsplat", runs / "prepared", split="train", backend="cpu", device="cpu")
    width = sum(GBUFFER_WIDTHS[name] for name in run.model.gbuffer_channels())
    (full, camera), = composite_split.view_surfels(run, 1, None, False)
    (bare, _), = composite_split.view_surfels(run, 1, (), False)
    (opaque, _), = composite_split.view_surfels(run, 1, (), True)
    assert full.features.shape[1] == width > 0 and bare.features.shape[1] == opaque.features.shape[1] == 0
    assert (full.opacity < 1).any() and torch.equal(opaque.opacity, torch.ones_like(opaque.opacity))
    for name in ("means", "quats", "scales", "occupancy", "colors"):
        assert torch.equal(getattr(full, name), getattr(bare, name)) and torch.equal(getattr(bare, name),
                                                                                   getattr(opaque, name))
    assert camera is run.cameras[0]


def test_the_split_prints_every_variant_and_leaves_the_compositing_unwrapped(runs, capsys):
    forward, backward = cpu._Composite.forward, cpu._Composite.backward
    threads = torch.get_num_threads()
    assert composite_split.main(["--run", str(runs / "rtsplat"), "--baseline", str(runs / "2dgs"), "--data",
                                 str(runs / "prepared"), "--views", "2", "--rounds", "2"]) == 0
    assert cpu._Composite.forward is forward and cpu._Composite.backward is backward
    assert torch.get_num_threads() == threads
    out = capsys.readouterr().out
    rows = {variant: [float(v) for v in re.findall(r"\d+\.\d+", line[len(variant):])]
            for line in out.splitlines() for variant in composite_split.VARIANTS if line.startswith(variant + " ")}
    assert set(rows) == set(composite_split.VARIANTS)
    assert all(len(v) == 3 and all(x > 0 for x in v) and v[2] == pytest.approx(v[0] + v[1], abs=0.011)
               for v in rows.values())
    run = load_run(runs / "rtsplat", runs / "prepared", split="train", backend="cpu", device="cpu")
    baseline = load_run(runs / "2dgs", runs / "prepared", split="train", backend="cpu", device="cpu")
    assert f"surfels: run {len(run.model.surfels)}, baseline {len(baseline.model.surfels)}" in out
    assert ", ".join(run.model.gbuffer_channels()) in out


def test_the_split_refuses_no_views():
    with pytest.raises(SystemExit):
        composite_split.main(["--run", "a", "--baseline", "b", "--data", "c", "--views", "0"])
