# Training, rendering, metrics and the report: each rule calls one `rtsplat <stage>` CLI; what
# the arguments are is decided in rtsplat/config.py (train_json, section_json, render_edit_args).
# The torch device of train and render is in their --config-json (train.device, render.device).
import shlex
from pathlib import Path

from rtsplat.config import main_method, render_edit_args, roles_json, scene_config, train_json

MAIN_METHOD = main_method(CFG)  # the method with role main: the scene edits are rendered for it


def edit_names(scene):
    return sorted(scene_config(CFG, scene).render.edits)


rule train:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
    output:
        directory(f"{RESULTS}/{{scene}}/runs/{{method}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/train_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/train_{{method}}.tsv"
    params:
        cfg=lambda wildcards: train_json(CFG, wildcards.scene, wildcards.method),
        # outside the run folder, which Snakemake deletes when the job fails or is killed: the next
        # run resumes from the checkpoint there (rtsplat train --checkpoint-dir)
        checkpoints=f"{RESULTS}/{{scene}}/checkpoints/{{method}}",
    threads: 2
    resources:
        gpu=1,
        runtime=720,
        mem_mb=16000,
    conda:
        ENV
    shell:
        "{RTSPLAT} train --data {input.prepared:q} --out {output:q} --checkpoint-dir {params.checkpoints:q} "
        "--config-json {params.cfg} --quiet > {log:q} 2>&1"


rule render:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        directory(f"{RESULTS}/{{scene}}/renders/{{method}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/render_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/render_{{method}}.tsv"
    params:
        cfg=stage_json("render"),
    threads: 2
    resources:
        gpu=1,
        runtime=120,
        mem_mb=8000,
    conda:
        ENV
    shell:
        "{RTSPLAT} render --data {input.prepared:q} --run {input.run:q} --out {output:q} "
        "--config-json {params.cfg} --quiet > {log:q} 2>&1"


rule render_edit:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        directory(f"{RESULTS}/{{scene}}/renders/{{method}}@{{edit}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/render_{{method}}@{{edit}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/render_{{method}}@{{edit}}.tsv"
    params:
        cfg=stage_json("render"),
        edits=lambda wildcards: render_edit_args(CFG, wildcards.scene, wildcards.edit),
    threads: 2
    conda:
        ENV
    shell:
        "{RTSPLAT} render --data {input.prepared:q} --run {input.run:q} --out {output:q} {params.edits} "
        "--config-json {params.cfg} --warmup 0 --quiet > {log:q} 2>&1"


rule metrics:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        renders=f"{RESULTS}/{{scene}}/renders/{{method}}",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        f"{RESULTS}/{{scene}}/metrics/{{method}}.json",
    log:
        f"{RESULTS}/{{scene}}/logs/metrics_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/metrics_{{method}}.tsv"
    params:
        cfg=stage_json("metrics"),
    conda:
        ENV
    shell:
        "{RTSPLAT} metrics --data {input.prepared:q} --renders {input.renders:q} --run {input.run:q} --out {output:q} "
        "--config-json {params.cfg} > {log:q} 2>&1"


def config_files_in_order():
    """The config files of this run, lowest precedence first: the Snakefile's own `configfile:`
    (unless the command line names it too), then the `--configfile` files in their order."""
    cli = [str(f) for f in (workflow.overwrite_configfiles or [])]
    on_cli = {Path(f).resolve() for f in cli}
    return [str(f) for f in workflow.configfiles if Path(f).resolve() not in on_cli] + cli


def reproduce_command():
    """The snakemake command line that reproduces this run, relative to the repository root (the
    Snakefile's own config file is implied; the core count is the one this run used)."""
    import os

    root = Path(workflow.basedir).resolve()
    words = ["snakemake", "-s", "Snakefile"]
    work_dir = os.path.relpath(Path.cwd().resolve(), root)
    if work_dir != ".":
        words += ["-d", work_dir]
    files = [os.path.relpath(Path(f).resolve(), root) for f in (workflow.overwrite_configfiles or [])]
    if files:
        words += ["--configfile", *files]
    from snakemake.exceptions import WorkflowError

    try:
        cores = str(workflow.cores)
    except WorkflowError:  # no core count defined (e.g. a cluster run)
        cores = "all"
    return shlex.join(words + ["--cores", cores])


def report_inputs(wildcards):
    inputs = expand(f"{RESULTS}/{{scene}}/metrics/{{method}}.json", scene=SCENES, method=METHODS)
    for scene in SCENES:
        inputs += [f"{RESULTS}/{scene}/renders/{MAIN_METHOD}@{edit}" for edit in edit_names(scene)]
    return inputs


rule report:
    input:
        report_inputs,
    output:
        f"{RESULTS}/report/index.html",
    log:
        f"{RESULTS}/logs/report.log",
    benchmark:
        f"{RESULTS}/benchmarks/report.tsv"
    params:
        results=RESULTS,
        report=f"{RESULTS}/report",
        config_files=" ".join(f"--config {shlex.quote(f)}" for f in config_files_in_order()),
        command=shlex.quote(reproduce_command()),
        roles=roles_json(CFG),
    conda:
        ENV
    shell:
        "{RTSPLAT} report --results {params.results:q} --out {params.report:q} {params.config_files} "
        "--command {params.command} --roles-json {params.roles} > {log:q} 2>&1"
