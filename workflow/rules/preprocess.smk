# Masks, structure from motion and the prepared scene (the trainer's only input). The three rules
# read <data>/<scene> and take its manifest <results>/<scene>/inputs.json as an input (common.smk).
import shlex
from pathlib import Path

from rtsplat.config import ConfigError, scene_config
from rtsplat.io.colmap import dataset_model_dir
from rtsplat.masks import resolve_source


def propagates_masks(scene):
    """Whether the scene's masks are propagated from marked views (then the masks rule needs the SfM result)."""
    cfg = scene_config(CFG, scene)
    if resolve_source(Path(DATA, scene), cfg.masks) != "propagate":
        return False
    if cfg.sfm.use_masks:
        raise ConfigError(
            f"scene {scene}: masks propagated from marked views need the SfM cameras, and sfm.use_masks needs the masks",
            path="config: sfm.use_masks",
            fix="set sfm.use_masks: false for this scene, or give every photo a mask",
        )
    return True


def masks_inputs(wildcards):
    inputs = {"images": f"{DATA}/{wildcards.scene}/images", "manifest": inputs_manifest(wildcards)}
    cfg = scene_config(CFG, wildcards.scene).masks
    if Path(DATA, wildcards.scene, cfg.dir).is_dir():
        inputs["dataset_masks"] = f"{DATA}/{wildcards.scene}/{cfg.dir}"
    if propagates_masks(wildcards.scene):
        inputs["sfm"] = out(wildcards.scene, "sfm")
    onnx = cfg.onnx
    for key in ("model", "encoder"):
        if getattr(onnx, key):
            inputs[key] = getattr(onnx, key)
    return inputs


def sfm_inputs(wildcards):
    inputs = {"images": f"{DATA}/{wildcards.scene}/images", "manifest": inputs_manifest(wildcards)}
    model = dataset_model_dir(Path(DATA, wildcards.scene))  # sparse/0, or a model directly in sparse/
    if scene_config(CFG, wildcards.scene).sfm.use_dataset_model and model is not None:
        inputs["model"] = str(model)
    if scene_config(CFG, wildcards.scene).sfm.use_masks:
        inputs["masks"] = out(wildcards.scene, "masks")
    return inputs


def masks_sfm_arg(wildcards, input):
    return f"--sfm {shlex.quote(str(input.sfm))}" if "sfm" in input.keys() else ""


def sfm_masks_arg(wildcards, input):
    return f"--masks {shlex.quote(str(input.masks))}" if "masks" in input.keys() else ""


rule masks:
    input:
        unpack(masks_inputs),
    output:
        directory(f"{RESULTS}/{{scene}}/masks"),
    log:
        f"{RESULTS}/{{scene}}/logs/masks.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/masks.tsv"
    params:
        scene_dir=scene_dir,
        cfg=stage_json("masks"),
        sfm=masks_sfm_arg,
    resources:
        **slurm("masks"),
    conda:
        ENV
    shell:
        "{RTSPLAT} masks --scene-dir {params.scene_dir:q} --out {output:q} {params.sfm} --config-json {params.cfg} "
        "> {log:q} 2>&1"


rule sfm:
    input:
        unpack(sfm_inputs),
    output:
        directory(f"{RESULTS}/{{scene}}/sfm"),
    log:
        f"{RESULTS}/{{scene}}/logs/sfm.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/sfm.tsv"
    params:
        scene_dir=scene_dir,
        cfg=stage_json("sfm"),
        masks=sfm_masks_arg,
    threads: 8
    resources:
        **slurm("sfm"),
    conda:
        ENV
    shell:
        "{RTSPLAT} sfm --scene-dir {params.scene_dir:q} --out {output:q} {params.masks} "
        "--num-threads {threads} --config-json {params.cfg} > {log:q} 2>&1"


rule prepare:
    input:
        sfm=f"{RESULTS}/{{scene}}/sfm",
        masks=f"{RESULTS}/{{scene}}/masks",
        manifest=inputs_manifest,
    output:
        directory(f"{RESULTS}/{{scene}}/prepared"),
    log:
        f"{RESULTS}/{{scene}}/logs/prepare.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/prepare.tsv"
    params:
        scene_dir=scene_dir,
        cfg=stage_json("prepare"),
    resources:
        **slurm("prepare"),
    conda:
        ENV
    shell:
        "{RTSPLAT} prepare --scene-dir {params.scene_dir:q} --sfm {input.sfm:q} --masks {input.masks:q} "
        "--out {output:q} --config-json {params.cfg} > {log:q} 2>&1"


rule prepared_all:
    input:
        expand(f"{RESULTS}/{{scene}}/prepared", scene=SCENES),
