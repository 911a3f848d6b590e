"""Checks of a SLURM cluster against what the workflow's jobs ask of it (profiles/slurm).

A job that asks for a GPU on a cluster without one is refused by sbatch at best ("Invalid generic resource
(gres) specification") and pends forever at worst (a partition that lists GPUs it never gets); the
workflow checks before it submits anything, with a message that names the setting.
"""

from __future__ import annotations

import subprocess

from rtsplat.errors import ConfigError


def gpus_in_gres(gres_lines: str) -> int:
    """The most GPUs one node has, from ``sinfo -h -o %G`` output (one GRES list per line, e.g.
    ``gpu:a100:4(S:0-1),shard:8`` or ``(null)``)."""
    most = 0
    for line in gres_lines.split():
        for item in line.split(","):
            parts = item.split("(")[0].split(":")
            if parts[0] != "gpu":
                continue
            count = parts[-1] if len(parts) > 1 else "1"
            most = max(most, int(count) if count.isdigit() else 1)
    return most


def check_cluster_gpus(requested: int, sinfo: str = "sinfo") -> None:
    """Raise ConfigError when the jobs ask for ``requested`` GPUs and no node of the cluster has that many
    (``sinfo -h -o %G``); nothing when ``requested`` is 0."""
    if requested <= 0:
        return
    try:
        result = subprocess.run([sinfo, "-h", "-o", "%G"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ConfigError(f"cannot ask the SLURM cluster for its GPUs ({sinfo} -h -o %G: {exc})",
                          fix="run from a machine with the SLURM client commands, or set slurm.gpus: 0") from exc
    if result.returncode != 0:
        raise ConfigError(f"cannot ask the SLURM cluster for its GPUs ({sinfo} -h -o %G: {result.stderr.strip()})",
                          fix="check that sinfo reaches the cluster, or set slurm.gpus: 0")
    most = gpus_in_gres(result.stdout)
    if most < requested:
        found = "has no GPUs" if most == 0 else f"has at most {most} GPU(s) on a node"
        raise ConfigError(
            f"slurm.gpus is {requested}: the train, render and fps jobs ask for {requested} GPU(s), but this "
            f"cluster {found} (sinfo -o %G: {' '.join(sorted(set(result.stdout.split()))) or 'nothing'})",
            fix="set slurm.gpus: 0 in the config for a CPU-only cluster (config.yaml, or a file with "
            "'slurm: {gpus: 0}' given with --configfile), or run on a cluster with GPUs")
