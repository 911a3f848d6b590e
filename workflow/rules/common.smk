# Configuration, scene discovery and path helpers shared by the rules.
import re
import sys

from rtsplat.config import ConfigError, discover_scenes, load_config_dict, section_json

# Readable messages first (unknown keys, wrong types, with the fix), then Snakemake's own
# validation against the same schema (defaults come from the dataclasses).
try:
    CFG = load_config_dict(config, "config (config.yaml + --config)")
    SCENES = discover_scenes(CFG)
except ConfigError as _exc:
    sys.exit(f"rtsplat workflow: configuration error:\n{_exc}")
validate(config, "../schemas/config.schema.json", set_default=False)

DATA = CFG.data.rstrip("/")
RESULTS = CFG.results.rstrip("/")
METHODS = list(CFG.methods)
ENV = "../../envs/rtsplat.yaml"
RTSPLAT = "rtsplat"


wildcard_constraints:
    scene="|".join(map(re.escape, SCENES)) if SCENES else "a^",
    method="|".join(map(re.escape, METHODS)),
    edit="[A-Za-z0-9_.-]+",


def scene_dir(wildcards):
    return f"{DATA}/{wildcards.scene}"


def stage_json(section):
    """Params function: the scene's merged config section as shell-quoted JSON."""
    return lambda wildcards: section_json(CFG, wildcards.scene, section)


def out(scene, *parts):
    return "/".join([RESULTS, scene, *parts])
