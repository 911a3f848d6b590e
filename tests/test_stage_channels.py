"""A training render rasterizes only the G-buffer channels its stage reads (the volume stage the blended opacity,
the subsurface stage no specular input), and the trainer hands Adam zero gradients for the parameters behind the
others: the training is the one that rasterizes every channel in every stage, bit for bit (the ``cpu`` backend
composites each channel on its own, so leaving one out changes no other output or gradient)."""

from __future__ import annotations

import torch
from specular_inputs import small_specular_model

from rtsplat.bench.toy_scene import write_scene
from rtsplat.model.rtmodel import GBUFFER_PARAMETERS, GBUFFER_WIDTHS
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig


def _config() -> TrainConfig:
    return TrainConfig.from_dict({
        "backend": "cpu",
        "schedule": {"iterations": 14, "volume_until": 4, "specular_from": 8, "densify_from": 5, "densify_every": 3,
                     "densify_until": 12, "reset_every": 0, "log_every": 5, "checkpoint_every": 0},
        "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32},
    })


def test_stage_channels_train_the_model_of_every_channel_bit_for_bit(tmp_path):
    scene = write_scene(tmp_path / "scene", views=6, width=32, height=24)
    trainers, channels_seen = [], []
    for every_channel in (False, True):
        trainer = Trainer(scene, _config(), tmp_path / f"run{int(every_channel)}", progress=False, log=lambda m: None)
        model = trainer.model
        full = model.gbuffer_channels()
        if every_channel:  # the training before stage channels: every channel in every stage
            model.gbuffer_channels = lambda stage="full", full=full: full
        seen = []
        render = model.render
        def recording(camera, render=render, seen=seen, **kwargs):
            result = render(camera, **kwargs)
            if torch.is_grad_enabled():
                seen.append((kwargs["stage"], tuple(result.gbuffer)))
            return result
        model.render = recording
        trainer.train()
        trainers.append(trainer)
        channels_seen.append(seen)
    staged, every = trainers
    assert set(staged.model.gbuffer_channels()) == set(GBUFFER_WIDTHS)  # the toy glass calls for every effect
    stages = {stage: channels for stage, channels in channels_seen[0]}
    assert set(stages) == {"volume", "subsurface", "full"}
    assert stages["volume"] == ("opacity",)
    assert set(stages["subsurface"]) == {"scatter", "tau", "roi", "opacity"}
    assert set(stages["full"]) == set(GBUFFER_WIDTHS)
    assert all(channels == tuple(GBUFFER_WIDTHS) for _, channels in channels_seen[1])
    assert len(staged.model.surfels) == len(every.model.surfels)
    for (name, a), (_, b) in zip(staged.model.named_parameters(), every.model.named_parameters(), strict=True):
        assert torch.equal(a, b), name
    # the optimizer took the same steps: the parameters behind the channels a stage left out stepped with it
    state_a, state_b = staged.optimizer.state_dict()["state"], every.optimizer.state_dict()["state"]
    assert state_a.keys() == state_b.keys()
    for key in state_a:
        for field in state_a[key]:
            assert torch.equal(state_a[key][field], state_b[key][field]), (key, field)
    # every surfel parameter, read from the first iteration or not, took a step in every iteration
    for name, p in staged.model.surfels.named_parameters():
        assert float(staged.optimizer.state[p]["step"]) == 14, name


def test_the_parameters_of_the_channels_a_stage_leaves_out():
    model = small_specular_model()  # transmission and specular on, every ablation off: every channel
    names = lambda stage: {  # noqa: E731
        name for name, p in model.surfels.named_parameters()
        if any(p is q for q in model.unread_channel_parameters(stage))}
    assert names("full") == set()
    assert names("subsurface") == {GBUFFER_PARAMETERS[c] for c in ("roughness", "material", "reflectance")}
    assert names("volume") == {GBUFFER_PARAMETERS[c] for c in ("roughness", "material", "reflectance", "scatter",
                                                                "tau")}
