# Training, rendering, metrics and the report: each rule calls one `rtsplat <stage>` CLI; what
# the arguments are is decided in rtsplat/config.py (train_json, section_json, render_edit_args).
# The torch device of train and render is in their --config-json (train.device, render.device).
import shlex
from pathlib import Path

from rtsplat.config import (
    main_method,
    method_roles,
    render_edit_args,
    roles_json,
    scene_config,
    train_json,
    video_methods,
)

MAIN_METHOD = main_method(CFG)  # the method with role main: the scene edits are rendered for it
METHOD_ROLES = method_roles(CFG)


def edit_names(scene):
    return sorted(scene_config(CFG, scene).render.edits)


def time_of_run(wildcards):
    """The run whose training time a method with `time_of` trains for (none for the others)."""
    other = METHOD_ROLES[wildcards.method].time_of
    return [f"{RESULTS}/{wildcards.scene}/runs/{other}"] if other else []


def train_arguments(wildcards):
    """The trainer config for --config-json, then, for a method with `time_of`, `--seconds-of <the other run>`
    (in this one parameter, so the rule's command reads the same for every other method)."""
    text = train_json(CFG, wildcards.scene, wildcards.method)
    other = time_of_run(wildcards)
    return f"{text} --seconds-of {shlex.quote(other[0])}" if other else text


rule train:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        time_of=time_of_run,
    output:
        directory(f"{RESULTS}/{{scene}}/runs/{{method}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/train_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/train_{{method}}.tsv"
    params:
        cfg=train_arguments,
        # outside the run folder, which Snakemake deletes when the job fails or is killed: the next
        # run resumes from the checkpoint there (rtsplat train --checkpoint-dir)
        checkpoints=f"{RESULTS}/{{scene}}/checkpoints/{{method}}",
    threads: 2
    resources:
        **slurm("train"),
        mem_mb=16000,
    conda:
        ENV
    # exec: the trainer is the job's process, so the SIGTERM of a time limit or scancel reaches it directly; it
    # checkpoints at the next iteration and exits non-zero, and the rerun resumes from the checkpoint
    shell:
        "exec {RTSPLAT} train --data {input.prepared:q} --out {output:q} --checkpoint-dir {params.checkpoints:q} "
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
        **slurm("render"),
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
    resources:
        **slurm("render_edit"),
    conda:
        ENV
    shell:
        "{RTSPLAT} render --data {input.prepared:q} --run {input.run:q} --out {output:q} {params.edits} "
        "--config-json {params.cfg} --warmup 0 --quiet > {log:q} 2>&1"


# A camera-path video (rtsplat/video.py) of the main method and of the baselines in video.baselines, all on the
# same path; the report embeds them with their first frame as the poster.
rule video:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        video=f"{RESULTS}/{{scene}}/videos/{{method}}.mp4",
        poster=f"{RESULTS}/{{scene}}/videos/{{method}}.png",
    log:
        f"{RESULTS}/{{scene}}/logs/video_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/video_{{method}}.tsv"
    params:
        cfg=stage_json("video"),
    threads: 2
    resources:
        **slurm("video"),
    conda:
        ENV
    shell:
        "{RTSPLAT} video --data {input.prepared:q} --run {input.run:q} --out {output.video:q} "
        "--poster {output.poster:q} --config-json {params.cfg} --quiet > {log:q} 2>&1"


def local_cores():
    """This run's --cores when its jobs run on this machine; None when an executor submits them elsewhere
    (a cluster, where each job has an allocation of its own) or the run has no core count."""
    from snakemake.exceptions import WorkflowError

    if not workflow.local_exec or workflow.remote_exec:
        return None
    try:
        return workflow.cores
    except WorkflowError:
        return None


def scheduled_alone_flag(wildcards, threads):
    """Params function: --scheduled-alone when the job holds every core of the run (its threads equal
    --cores), which Snakemake's scheduler guarantees no other job runs beside; nothing otherwise (a
    --set-threads below --cores, a cluster run)."""
    cores = local_cores()
    return "--scheduled-alone" if cores is not None and threads >= cores else ""


# The timing pass behind the report's FPS. It takes every core of the run: Snakemake keeps the sum of
# the threads of the running jobs at or below --cores, so nothing else of the workflow runs beside it
# (rtsplat/fps.py). On a cluster each job has its own allocation; add `slurm_extra: "'--exclusive'"`
# for fps in the profile to have the node to itself.
rule fps:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        f"{RESULTS}/{{scene}}/fps/{{method}}.json",
    log:
        f"{RESULTS}/{{scene}}/logs/fps_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/fps_{{method}}.tsv"
    params:
        cfg=stage_json("render"),
        alone=scheduled_alone_flag,
    threads: local_cores() or 1
    resources:
        **slurm("fps"),
        mem_mb=8000,
    conda:
        ENV
    shell:
        "{RTSPLAT} fps --data {input.prepared:q} --run {input.run:q} --out {output:q} "
        "--config-json {params.cfg} {params.alone} > {log:q} 2>&1"


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
    resources:
        **slurm("metrics"),
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
    inputs += expand(f"{RESULTS}/{{scene}}/fps/{{method}}.json", scene=SCENES, method=METHODS)
    for scene in SCENES:
        inputs += [f"{RESULTS}/{scene}/renders/{MAIN_METHOD}@{edit}" for edit in edit_names(scene)]
        inputs += [f"{RESULTS}/{scene}/videos/{method}.{ext}" for method in video_methods(CFG, scene)
                   for ext in ("mp4", "png")]
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
    resources:
        **slurm("report"),
    conda:
        ENV
    shell:
        "{RTSPLAT} report --results {params.results:q} --out {params.report:q} {params.config_files} "
        "--command {params.command} --roles-json {params.roles} > {log:q} 2>&1"
