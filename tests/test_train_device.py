"""The device of training and rendering: resolving ``auto``/``cpu``/``cuda[:N]`` with clear errors, the
config keys and flags that carry it, the device-friendly code paths of the model, and a few training
iterations through the ``triton`` backend (Triton's interpreter on CPU tensors, in a subprocess so that
``TRITON_INTERPRET=1`` does not leak into this process) compared with the ``cpu`` backend."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from rtsplat import cli
from rtsplat.config import load_config_dict, section_json, train_json
from rtsplat.devices import resolve_device
from rtsplat.errors import ConfigError
from rtsplat.train_config import TrainConfig

ROOT = Path(__file__).resolve().parent.parent


# -- resolving a device string ------------------------------------------------------------------


def _machine(monkeypatch, *, cuda_build: bool, gpus: int) -> None:
    monkeypatch.setattr(torch.version, "cuda", "12.4" if cuda_build else None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: gpus > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: gpus)


def test_auto_is_the_gpu_when_torch_sees_one_else_the_cpu(monkeypatch):
    _machine(monkeypatch, cuda_build=True, gpus=1)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("cuda:0") == torch.device("cuda:0")
    _machine(monkeypatch, cuda_build=True, gpus=0)
    assert resolve_device("auto") == torch.device("cpu")
    _machine(monkeypatch, cuda_build=False, gpus=0)
    assert resolve_device("AUTO") == torch.device("cpu")


def test_cuda_with_a_cpu_build_of_torch_names_the_fix(monkeypatch):
    _machine(monkeypatch, cuda_build=False, gpus=0)
    with pytest.raises(ConfigError) as err:
        resolve_device("cuda")
    message = str(err.value)
    assert "without CUDA" in message and "install the CUDA build of torch" in message
    assert "--device cpu" in message


def test_cuda_build_without_a_gpu_names_the_fix(monkeypatch):
    _machine(monkeypatch, cuda_build=True, gpus=0)
    with pytest.raises(ConfigError) as err:
        resolve_device("cuda:0", key="train.device")
    message = str(err.value)
    assert "sees no GPU" in message and "train.device cpu" in message and "CPU build of torch" in message


def test_a_gpu_index_out_of_range_and_unknown_names_are_errors(monkeypatch):
    _machine(monkeypatch, cuda_build=True, gpus=2)
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(ConfigError, match="sees 2 GPU"):
        resolve_device("cuda:2")
    for bad in ("gpu", "cuda:", "mps", ""):
        with pytest.raises(ConfigError, match="unknown device"):
            resolve_device(bad)


# -- config keys and flags ----------------------------------------------------------------------


def test_device_defaults_to_auto_and_the_pipeline_config_carries_it():
    assert TrainConfig().device == "auto"
    cfg = load_config_dict({"defaults": {"train": {"device": "cuda:1"}, "render": {"device": "cpu"}},
                            "overrides": {"glass": {"train": {"device": "cpu"}}}})
    assert json.loads(train_json(cfg, "__defaults__", "rtsplat", quote=False))["device"] == "cuda:1"
    assert json.loads(train_json(cfg, "glass", "rtsplat", quote=False))["device"] == "cpu"
    assert json.loads(section_json(cfg, "glass", "render", quote=False))["device"] == "cpu"
    assert json.loads(section_json(load_config_dict({}), "x", "render", quote=False))["device"] == "auto"


def test_a_bad_device_in_the_config_is_a_config_error():
    with pytest.raises(ConfigError, match="device"):
        load_config_dict({"defaults": {"train": {"device": "gpu"}}})
    with pytest.raises(ConfigError, match="device"):
        TrainConfig.from_dict({"device": "cuda0"})


@pytest.mark.parametrize("stage", ["train", "render"])
def test_device_flag_asking_for_missing_cuda_fails_before_any_work(monkeypatch, tmp_path, capsys, stage):
    _machine(monkeypatch, cuda_build=False, gpus=0)
    argv = [stage, "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out"), "--device", "cuda"]
    if stage == "render":
        argv += ["--run", str(tmp_path / "run")]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert "--device: cuda asked for" in err and "--device cpu" in err
    assert not (tmp_path / "out").exists()


# -- code paths the GPU takes, checked on the CPU ------------------------------------------------


def test_specular_of_every_pixel_equals_the_gathered_one():
    """Off the CPU the specular branch shades every pixel and masks the result; same values and gradients."""
    from specular_inputs import small_specular_model, specular_inputs

    H, W = 6, 7
    model = small_specular_model()
    camera, normal, alpha, gbuf, shade = specular_inputs(H, W)
    results = []
    for every_pixel in (False, True):
        spec, beta = model._specular(camera, normal, gbuf, alpha, shade, every_pixel=every_pixel)
        weights = torch.linspace(0.5, 1.5, H * W * 4).reshape(H, W, 4)
        loss = (torch.cat([spec, beta], -1) * weights).sum()
        leaves = [normal, *gbuf.values(), model.env.features, *model.specular_net.parameters()]
        grads = torch.autograd.grad(loss, leaves)
        results.append((spec.detach(), beta.detach(), grads))
    (s0, b0, g0), (s1, b1, g1) = results
    assert 0 < int(shade.sum()) < H * W
    torch.testing.assert_close(s1, s0, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(b1, b0, rtol=1e-5, atol=1e-6)
    assert torch.all(s1[~shade[..., 0]] == 0) and torch.all(b1[~shade[..., 0]] == 1)
    for a, b in zip(g0, g1, strict=True):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)


def test_environment_map_level_layout_matches_its_texel_table():
    from rtsplat.model.envmap import EnvironmentMap

    for height, width, levels in ((16, 32, 5), (9, 14, 6), (2, 6, 4), (512, 1024, 9)):
        env = EnvironmentMap(2, height, width, levels)
        _, layout = env.texel_table()
        assert env.level_layout.tolist() == [list(row) for row in layout]


# -- a few training iterations through the triton backend (Triton's interpreter) ---------------

ITERATIONS = 3


def _train_config(backend: str) -> dict:
    return {
        "backend": backend, "device": "cpu", "effects": {"transmission": "on", "specular": "on"},
        "schedule": {"iterations": ITERATIONS, "volume_until": 0, "specular_from": 0, "densify_from": 0,
                     "densify_every": ITERATIONS - 1, "densify_until": ITERATIONS, "reset_every": 0, "log_every": 1,
                     "checkpoint_every": 0},
        "densify": {"grad_threshold": 0.0},  # every surfel is cloned or split, at iteration ITERATIONS - 1
        # occupancy 0.9: the wall's surface alpha passes the shading threshold, so the specular branch
        # and the surface G-buffers receive gradients from the first iterations
        "model": {"env_height": 8, "env_width": 16, "env_levels": 3, "mlp_width": 16, "occupancy_init": 0.9},
    }


def _train_both_backends(scene_dir: str, out_dir: str) -> None:
    """Run in the subprocess: train the toy scene with each backend, print what the test compares."""
    from rtsplat.model.checkpoint import read_checkpoint
    from rtsplat.raster.gpu import kernels_interpreted
    from rtsplat.scene import PreparedScene
    from rtsplat.train.trainer import Trainer

    scene = PreparedScene.load(scene_dir)
    report = {}
    for backend in ("cpu", "triton"):
        run = Path(out_dir) / backend
        cfg = TrainConfig.from_dict(_train_config(backend))
        trainer = Trainer(scene, cfg, run, progress=False, log=lambda message: None)
        initial = {k: v.detach().clone() for k, v in trainer.model.surfels.tensors().items()}
        before_densify = {}
        density_step = trainer.density.step

        def recording_step(iteration, surfels, *args, before_densify=before_densify, density_step=density_step,
                           **kwargs):
            if iteration == ITERATIONS - 1:
                before_densify.update({k: v.detach().clone() for k, v in surfels.tensors().items()})
            return density_step(iteration, surfels, *args, **kwargs)

        trainer.density.step = recording_step
        summary = trainer.train(resume=False)
        final = read_checkpoint(run / "model.pt", "cpu")
        report[backend] = {
            "summary": summary,
            "log": [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines()],
            "initial": {k: v.tolist() for k, v in initial.items()},
            "before_densify": {k: v.tolist() for k, v in before_densify.items()},
            "final": {k: v.tolist() for k, v in final.surfels.items()},
            "env": final.buffers["env.features"].flatten().tolist(),
        }
    report["interpreted"] = kernels_interpreted()
    print(json.dumps(report))


@pytest.fixture(scope="module")
def triton_training(tmp_path_factory):
    triton = pytest.importorskip("triton")
    pinned = re.search(r'"triton==([^"]+)"', (ROOT / "pyproject.toml").read_text()).group(1)
    if triton.__version__ != pinned:
        # seen on a GPU image with triton 3.6.0: its interpreter reduces to a 1-element array where 3.9
        # gives a scalar, so a loop bound fails there; the compiled kernels are checked on such a machine
        # by tests/test_raster_triton.py instead
        pytest.skip(f"Triton's interpreter is tested with the pinned triton=={pinned}, not {triton.__version__}")
    from rtsplat.bench.toy_scene import write_scene
    from rtsplat.scene import Roi

    root = tmp_path_factory.mktemp("device")
    scene = write_scene(root / "scene", views=4, width=32, height=16, with_pane=False, n_side=3, test_every=4)
    scene.roi = Roi([0.0, 1.0, 0.0], 3.0, "config")  # the whole wall: every pixel is deferred-shaded
    scene.save(root / "scene")
    env = {**os.environ, "TRITON_INTERPRET": "1", "PYTHONPATH": os.pathsep.join(
        [str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    code = (f"import test_train_device as t; t._train_both_backends({str(root / 'scene')!r}, "
            f"{str(root / 'runs')!r})")
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_triton_backend_trains_under_the_interpreter(triton_training):
    assert triton_training["interpreted"]
    run = triton_training["triton"]
    losses = [r["loss"] for r in run["log"]]
    assert [r["iteration"] for r in run["log"]] == list(range(1, ITERATIONS + 1))
    assert all(torch.isfinite(torch.tensor(losses)))
    assert [r["stage"] for r in run["log"]] == ["full"] * ITERATIONS
    n0 = len(run["initial"]["means"])
    assert run["summary"]["surfels"] == len(run["final"]["means"]) > n0  # densification ran
    for name, before in run["initial"].items():
        # every parameter moved before densification (sh_rest: SH degree 0 all run, no gradient)
        moved = not torch.equal(torch.tensor(run["before_densify"][name]), torch.tensor(before))
        assert moved == (name != "sh_rest"), name
    assert torch.tensor(run["env"]).abs().sum() > 0  # the environment map learnt
    assert torch.isfinite(torch.tensor(run["summary"]["test_psnr"]))


def test_triton_backend_training_matches_the_cpu_backend(triton_training):
    cpu, tri = triton_training["cpu"], triton_training["triton"]
    for a, b in zip(cpu["log"], tri["log"], strict=True):
        assert b["loss"] == pytest.approx(a["loss"], rel=1e-3)
        assert b["psnr"] == pytest.approx(a["psnr"], abs=1e-2)
    assert tri["summary"]["surfels"] == cpu["summary"]["surfels"]
    for name, value in cpu["before_densify"].items():
        torch.testing.assert_close(torch.tensor(tri["before_densify"][name]), torch.tensor(value), rtol=1e-3,
                                   atol=1e-4, msg=lambda m, name=name: f"{name}: {m}")
    for name, value in cpu["final"].items():
        torch.testing.assert_close(torch.tensor(tri["final"][name]), torch.tensor(value), rtol=1e-2, atol=1e-3,
                                   msg=lambda m, name=name: f"{name}: {m}")
    torch.testing.assert_close(torch.tensor(tri["env"]), torch.tensor(cpu["env"]), rtol=1e-2, atol=1e-4)
