"""The whole DAG through `snakemake --profile profiles/slurm` on a real SLURM cluster (`make test-slurm`
brings up a one-node cluster with scripts/slurm_cluster.sh and tears it down; skipped without one).

One run on a small synthetic scene, compared with the same DAG run locally: every rule ran as a SLURM job
(the slurm log of each job names its rule, the cluster's job completion records its state), the training
job is stopped by SLURM (`scancel --signal=TERM`) part way and resumes from its checkpoint when it is
submitted again, the outputs equal the local run's bit for bit (one thread per job: deterministic), and a
second invocation has nothing to do."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))

from fixtures_pipeline import make_corner_scene  # noqa: E402

from rtsplat.model.checkpoint import read_checkpoint  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
SNAKEMAKE = BIN / "snakemake"
RULES = {"masks", "sfm", "prepare", "train", "render", "render_edit", "fps", "video", "metrics", "report"}
ITERATIONS = 150


def _cluster_up() -> bool:
    if shutil.which("sbatch") is None or shutil.which("scontrol") is None:
        return False
    ping = subprocess.run(["scontrol", "ping"], capture_output=True, text=True, timeout=30)
    return "is UP" in ping.stdout


pytestmark = [
    pytest.mark.slurm,
    # make test-slurm sets RTSPLAT_SLURM_REQUIRED: there a missing cluster fails the tests instead
    pytest.mark.skipif(not os.environ.get("RTSPLAT_SLURM_REQUIRED") and (not SNAKEMAKE.exists() or not _cluster_up()),
                       reason="no SLURM cluster (make test-slurm starts one: scripts/slurm_cluster.sh)"),
]

# one thread per job, in both runs: SfM, training and rendering are then deterministic
THREADS = ("--set-threads", "sfm=1", "train=1", "render=1", "render_edit=1", "video=1")
# sized for a small node (the profile's defaults are for a real cluster); the status checks start early
SLURM_ARGS = (
    "--profile", str(ROOT / "profiles" / "slurm"),
    "--default-resources", "mem_mb=1000", "cpus_per_task=1",
    "--set-resources", "sfm:mem_mb=1000", "sfm:cpus_per_task=1", "train:mem_mb=2000", "train:cpus_per_task=1",
    "--slurm-init-seconds-before-status-checks", "2", "--latency-wait", "10",
)


def _config(root: Path, results: str) -> Path:
    train = {
        "iterations": ITERATIONS,
        "options": {
            "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32},
            "schedule": {"volume_until": 20, "specular_from": 40, "densify_from": 30, "densify_every": 30,
                         "reset_every": 0, "eval_every": 0, "log_every": 1, "checkpoint_every": 0},
        },
    }
    cfg = {
        "data": str(root / "data"),
        "results": str(root / results),
        "methods": {"rtsplat": {"role": "main"}},
        "defaults": {"prepare": {"downsample": 2}, "train": train,
                     "render": {"warmup": 0, "edits": {"no-reflections": ["reflections=off"]}},
                     "video": {"frames": 6}},
        "slurm": {"gpus": 0},
    }
    path = root / f"{results}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _snakemake(root: Path, config: Path, *args: str) -> list[str]:
    return [str(SNAKEMAKE), "-s", str(ROOT / "Snakefile"), "-d", str(root), "--configfile", str(config), *args]


def _env() -> dict:
    return dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")


def _jobs_by_rule(root: Path) -> dict[str, list[str]]:
    """SLURM job ids per rule, from the plugin's job logs: .snakemake/slurm_logs/rule_<rule>/<wildcards>/<id>.log"""
    jobs: dict[str, list[str]] = {}
    for log in (root / ".snakemake" / "slurm_logs").rglob("*.log"):
        rule = next(p for p in log.relative_to(root / ".snakemake" / "slurm_logs").parts if p.startswith("rule_"))
        jobs.setdefault(rule.removeprefix("rule_"), []).append(log.stem)
    return jobs


def _completion_records() -> dict[str, dict[str, str]]:
    """The cluster's job completion records (jobcomp/filetxt): job id -> fields."""
    config = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True, check=True).stdout
    path = Path(re.search(r"^JobCompLoc\s*=\s*(\S+)", config, re.M).group(1))
    records = {}
    for line in path.read_text().splitlines():
        fields = dict(item.split("=", 1) for item in line.split() if "=" in item)
        records[fields["JobId"]] = fields
    return records


def _train_job(name: str) -> str | None:
    """The id of the running job of run ``name`` whose comment says it is a training job."""
    out = subprocess.run(["squeue", "-h", "--name", name, "-t", "RUNNING", "-o", "%i|%k"],
                         capture_output=True, text=True).stdout
    return next((line.split("|")[0] for line in out.splitlines() if "|rule_train" in line), None)


def _run_name(root: Path) -> str | None:
    """The job name the plugin gives every job of this run (a UUID), from squeue while one is queued."""
    out = subprocess.run(["squeue", "-h", "-o", "%j|%Z"], capture_output=True, text=True).stdout
    return next((line.split("|")[0] for line in out.splitlines() if line.split("|")[-1] == str(root)), None)


def test_whole_dag_on_slurm_equals_the_local_run_and_resumes_a_stopped_training(tmp_path):
    make_corner_scene(tmp_path / "data" / "glass", n_views=9, width=80, height=60, with_model=True, with_masks=True)
    local_cfg, slurm_cfg = _config(tmp_path, "local"), _config(tmp_path, "slurm")

    started = time.time()
    local = subprocess.run(_snakemake(tmp_path, local_cfg, "--cores", "2", *THREADS), cwd=tmp_path, env=_env(),
                           capture_output=True, text=True, timeout=600)
    assert local.returncode == 0, local.stderr[-4000:]
    print(f"local DAG: {time.time() - started:.0f} s")

    started = time.time()
    log = (tmp_path / "slurm.log").open("w")
    proc = subprocess.Popen(_snakemake(tmp_path, slurm_cfg, *SLURM_ARGS, *THREADS), cwd=tmp_path, env=_env(),
                            stdout=log, stderr=subprocess.STDOUT, text=True)
    # stop the training job part way: SIGTERM to its processes, as a time limit or a preemption sends
    train_log = tmp_path / "slurm" / "glass" / "runs" / "rtsplat" / "train_log.jsonl"
    stopped_job, seen_at = None, 0
    deadline = time.time() + 400
    while proc.poll() is None and time.time() < deadline:
        name = _run_name(tmp_path)
        job = _train_job(name) if name else None
        if job and train_log.exists():
            seen_at = len(train_log.read_text().splitlines())
            if seen_at >= 20:
                subprocess.run(["scancel", "--signal=TERM", job], check=True)
                stopped_job = job
                break
        time.sleep(0.1)
    assert stopped_job is not None, "the training job was not seen running"
    try:
        proc.wait(timeout=600)
    finally:
        proc.kill() if proc.poll() is None else None
        log.close()
    output = (tmp_path / "slurm.log").read_text()
    assert proc.returncode == 0, output[-6000:]
    print(f"SLURM DAG (with the stopped and resumed training): {time.time() - started:.0f} s")

    # every rule ran as SLURM jobs, all completed but the stopped training job
    jobs = _jobs_by_rule(tmp_path)
    assert set(jobs) == RULES, jobs
    records = _completion_records()
    states = {job: records[job]["JobState"] for ids in jobs.values() for job in ids}
    assert states.pop(stopped_job) == "FAILED"
    assert set(states.values()) == {"COMPLETED"}, states
    assert len(jobs["train"]) == 2 and stopped_job in jobs["train"]

    # the stopped job checkpointed; its second submission resumed there, not at iteration 0
    train_err = (tmp_path / "slurm" / "glass" / "logs" / "train_rtsplat.log").read_text()
    resumed = re.search(r"resumed from \S+ at iteration (\d+)", train_err)
    assert resumed and seen_at <= int(resumed.group(1)) < ITERATIONS, train_err[-2000:]
    lines = (tmp_path / "slurm" / "glass" / "runs" / "rtsplat" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(line)["iteration"] for line in lines] == list(range(1, ITERATIONS + 1))

    # the outputs equal the local run's: the model (stopped and resumed on SLURM, straight through locally),
    # every render, the metrics
    a = read_checkpoint(tmp_path / "local" / "glass" / "runs" / "rtsplat" / "model.pt").surfels
    b = read_checkpoint(tmp_path / "slurm" / "glass" / "runs" / "rtsplat" / "model.pt").surfels
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    for renders in ("rtsplat", "rtsplat@no-reflections"):
        pngs = sorted((tmp_path / "local" / "glass" / "renders" / renders).rglob("*.png"))
        assert pngs
        for png in pngs:
            twin = tmp_path / "slurm" / png.relative_to(tmp_path / "local")
            assert png.read_bytes() == twin.read_bytes(), png
    poster = Path("glass") / "videos" / "rtsplat.png"  # the video's first frame
    assert (tmp_path / "local" / poster).read_bytes() == (tmp_path / "slurm" / poster).read_bytes()
    metrics = [json.loads((tmp_path / run / "glass" / "metrics" / "rtsplat.json").read_text())["mean"]
               for run in ("local", "slurm")]
    assert metrics[0] == metrics[1]
    assert (tmp_path / "slurm" / "report" / "index.html").is_file()

    again = subprocess.run(_snakemake(tmp_path, slurm_cfg, *SLURM_ARGS, *THREADS), cwd=tmp_path, env=_env(),
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-4000:]
    assert "Nothing to be done" in again.stdout + again.stderr
    assert set(_jobs_by_rule(tmp_path)) == RULES and sum(map(len, _jobs_by_rule(tmp_path).values())) == sum(
        map(len, jobs.values()))  # no job submitted


def test_asking_for_a_gpu_on_a_cluster_without_one_stops_before_submitting(tmp_path):
    make_corner_scene(tmp_path / "data" / "glass", n_views=4, width=40, height=30)
    cfg = yaml.safe_load(_config(tmp_path, "results").read_text())
    cfg["slurm"] = {"gpus": 1}
    path = tmp_path / "gpu.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = subprocess.run(_snakemake(tmp_path, path, *SLURM_ARGS), cwd=tmp_path, env=_env(), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode != 0
    err = r.stdout + r.stderr
    assert "this cluster has no GPUs" in err and "slurm.gpus: 0" in err, err[-3000:]
    assert not (tmp_path / ".snakemake" / "slurm_logs").exists()  # nothing was submitted

