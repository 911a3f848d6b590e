# Configuration, scene discovery and path helpers shared by the rules.
import re
import shlex
import sys
from pathlib import Path

from rtsplat.config import ConfigError, discover_scenes, load_config_dict, section_json, slurm_resources
from rtsplat.errors import PipelineError
from rtsplat.frames import extract_video_scenes
from rtsplat.io.manifest import refresh_manifest
from rtsplat.slurm import check_cluster_gpus

# Readable messages first (unknown keys, wrong types, with the fix), then Snakemake's own
# validation against the same schema (defaults come from the dataclasses). A scene folder holding a video
# and no images/ gets its frames first (rtsplat frames), so every rule reads images/ as for photos.
try:
    CFG = load_config_dict(config, "config (config.yaml + --config)")
    extract_video_scenes(CFG, log=lambda message: print(message, file=sys.stderr))
    SCENES = discover_scenes(CFG)
except ConfigError as _exc:
    sys.exit(f"rtsplat workflow: configuration error:\n{_exc}")
except PipelineError as _exc:
    sys.exit(f"rtsplat workflow: {_exc}")
validate(config, "../schemas/config.schema.json", set_default=False)

DATA = CFG.data.rstrip("/")
RESULTS = CFG.results.rstrip("/")
METHODS = list(CFG.methods)
ENV = "../../envs/rtsplat.yaml"


def _rtsplat_command():
    """How rules call the CLI. With `--sdm conda` the env (envs/rtsplat.yaml) has the dependencies and
    the package comes from this repository via PYTHONPATH; otherwise the `rtsplat` next to the Python
    that runs Snakemake (the venv), so no PATH setup is needed, else `rtsplat` from PATH."""
    methods = getattr(getattr(workflow, "deployment_settings", None), "deployment_method", None) or ()
    if any(str(getattr(m, "name", m)).lower() == "conda" for m in methods):
        return f"PYTHONPATH={shlex.quote(str(Path(workflow.basedir).resolve()))} python -m rtsplat.cli"
    exe = Path(sys.executable).parent / "rtsplat"
    return shlex.quote(str(exe)) if exe.is_file() else "rtsplat"


RTSPLAT = _rtsplat_command()


# Before the first job is submitted to SLURM (onstart runs once the executor is chosen, not in dry runs): the
# GPUs the jobs ask for must exist on the cluster, else the run stops here instead of leaving jobs that
# cannot start.
onstart:
    if getattr(workflow.executor_plugin, "name", None) == "slurm" and not workflow.remote_exec:
        try:
            check_cluster_gpus(CFG.slurm.gpus)
        except ConfigError as _exc:
            sys.exit(f"rtsplat workflow: SLURM pre-flight:\n{_exc}")


wildcard_constraints:
    scene="|".join(map(re.escape, SCENES)) if SCENES else "a^",
    method="|".join(map(re.escape, METHODS)),
    edit="[A-Za-z0-9_.-]+",


def scene_dir(wildcards):
    return f"{DATA}/{wildcards.scene}"


def inputs_manifest(wildcards):
    """Input function: <results>/<scene>/inputs.json, the size and modification time of every file
    under <data>/<scene> (rtsplat/io/manifest.py), rewritten only when one of them changed. The rules
    that read the dataset take it as an input, so an image edited in place reruns them."""
    return str(refresh_manifest(scene_dir(wildcards), out(wildcards.scene, "inputs.json")))


def stage_json(section):
    """Params function: the scene's merged config section as shell-quoted JSON."""
    return lambda wildcards: section_json(CFG, wildcards.scene, section)


def out(scene, *parts):
    return "/".join([RESULTS, scene, *parts])


def slurm(rule):
    """The resources of ``rule``'s SLURM jobs as resource functions (runtime, slurm_partition, slurm_account,
    gpu; rtsplat.config.slurm_resources, from the config's slurm section). A local run ignores them."""

    def resource(key):
        return lambda wildcards: slurm_resources(
            CFG, rule, getattr(wildcards, "scene", None), getattr(wildcards, "method", None)
        )[key]

    return {key: resource(key) for key in ("runtime", "slurm_partition", "slurm_account", "gpu")}
