"""The Snakemake DAG: dry runs (local and SLURM profiles), config errors, and a real run to the
prepared scenes on a two-scene fixture dataset (one scene with masks + a COLMAP model, one with
images only). Train/render/metrics/report run for real in the slow test_whole_dag_to_the_report."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))

from fixtures_pipeline import make_corner_scene  # noqa: E402

from rtsplat.io.images import read_header, read_mask  # noqa: E402
from rtsplat.scene import PreparedScene  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
SNAKEMAKE = BIN / "snakemake"

pytestmark = pytest.mark.skipif(not SNAKEMAKE.exists(), reason="snakemake is not installed here")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("wf")
    make_corner_scene(root / "data" / "glass", n_views=9, width=160, height=120, with_model=True, with_masks=True)
    make_corner_scene(root / "data" / "plain", n_views=9, width=160, height=120)
    return root


def _config(root: Path, **extra) -> Path:
    cfg = {
        "data": str(root / "data"),
        "results": str(root / "results"),
        "defaults": {"prepare": {"downsample": 2}, "train": {"iterations": 10}},
        "overrides": {"plain": {"prepare": {"downsample": 4}}},
    }
    cfg.update(extra)
    path = root / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def snakemake(root: Path, *args: str, config: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    cmd = [
        str(SNAKEMAKE),
        "-s",
        str(ROOT / "Snakefile"),
        "-d",
        str(root),
        "--configfile",
        str(config or _config(root)),
        *args,
    ]
    return subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=600)


def _job_counts(output: str) -> dict[str, int]:
    table = output.split("Job stats:")[1]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)$", table, re.M)}


def _jobs(output: str) -> list[str]:
    """The dry-run's per-job blocks."""
    return re.split(r"\n(?=(?:local)?rule \w+:)", output)


EXPECTED = {
    "masks": 2,
    "sfm": 2,
    "prepare": 2,
    "train": 2,
    "render": 2,
    "render_edit": 8,
    "fps": 2,
    "metrics": 2,
    "video": 2,
    "report": 1,
    "all": 1,
}


def test_dry_run_builds_the_whole_dag(dataset):
    r = snakemake(dataset, "-n", "-p")
    assert r.returncode == 0, r.stderr + r.stdout
    out = r.stdout + r.stderr
    counts = _job_counts(out)
    assert {k: counts[k] for k in EXPECTED} == EXPECTED
    assert "rtsplat prepare --scene-dir" in out and "rtsplat train --data" in out
    assert "--edit reflections=off" in out and "rtsplat report --results" in out
    # the checkpoint folder lies beside the run folder that Snakemake deletes when a job fails
    for block in (b for b in _jobs(out) if b.startswith("rule train")):
        command = shlex.split(next(line for line in block.splitlines() if " train --data" in line).strip())
        scene, method = re.search(r"scene=(\w+)", block).group(1), re.search(r"method=(\w+)", block).group(1)
        results = dataset / "results" / scene
        assert command[command.index("--out") + 1] == str(results / "runs" / method)
        assert command[command.index("--checkpoint-dir") + 1] == str(results / "checkpoints" / method)
    # per-scene overrides reach the commands
    prep = {re.search(r"--scene-dir \S+/(\w+)", b).group(1): b for b in _jobs(out) if b.startswith("rule prepare")}
    assert '"downsample": 2' in prep["glass"] and '"downsample": 4' in prep["plain"]
    for block in _jobs(out):
        if block.startswith("rule ") and not block.startswith("rule all"):
            assert "log: " in block and "benchmark: " in block, block
    sfm = [b for b in _jobs(out) if b.startswith("rule sfm")]
    assert len(sfm) == 2 and all("--num-threads " in b for b in sfm)  # Snakemake's threads reach pycolmap
    # the report prints each config file once (here the Snakefile's config.yaml is the --configfile)
    # and a reproduce command with the core count of this run
    report = next(b for b in _jobs(out) if b.startswith("localrule report") or b.startswith("rule report"))
    assert report.count("config.yaml") == 2, report  # one --config for the report, one in the command
    assert re.search(r"--cores \d+'", report), report  # a number, not "all"


def test_a_method_with_time_of_trains_after_the_other_run_for_its_time(dataset):
    methods = {"rtsplat": {"role": "main"}, "2dgs": {"effects": {"specular": "off", "transmission": "off"}},
               "rtsplat_eq": {"time_of": "2dgs"}}
    cfg = _config(dataset, scenes=["glass"], methods=methods)
    r = snakemake(dataset, "-n", "-p", str(dataset / "results" / "glass" / "runs" / "rtsplat_eq"),
                  str(dataset / "results" / "glass" / "runs" / "rtsplat"), config=cfg)
    assert r.returncode == 0, r.stderr + r.stdout
    trains = {re.search(r"method=(\w+)", b).group(1): b for b in _jobs(r.stdout + r.stderr)
              if b.startswith("rule train")}
    assert sorted(trains) == ["2dgs", "rtsplat", "rtsplat_eq"]  # the 2dgs run is trained first, as an input
    other = dataset / "results" / "glass" / "runs" / "2dgs"
    command = shlex.split(next(line for line in trains["rtsplat_eq"].splitlines() if " train --data" in line))
    assert command[command.index("--seconds-of") + 1] == str(other)
    assert str(other) in trains["rtsplat_eq"].split("output:")[0]  # among the job's inputs
    assert "--seconds-of" not in trains["rtsplat"] and "--seconds-of" not in trains["2dgs"]


def test_videos_are_rendered_for_the_main_method_and_the_listed_baselines_on_the_same_path(dataset):
    methods = {"rtsplat": {"role": "main"}, "2dgs": {"role": "baseline", "effects": {"specular": "off"}},
               "refgs": {"role": "baseline"}}
    cfg = _config(dataset, scenes=["glass"], methods=methods,
                  defaults={"prepare": {"downsample": 2}, "video": {"frames": 8, "path": "spiral"}})
    r = snakemake(dataset, "-n", "-p", config=cfg)
    assert r.returncode == 0, r.stderr + r.stdout
    videos = [b for b in _jobs(r.stdout + r.stderr) if b.startswith("rule video:")]
    assert sorted(re.search(r"method=(\w+)", b).group(1) for b in videos) == ["2dgs", "rtsplat"]
    for block in videos:
        command = shlex.split(next(line for line in block.splitlines() if " video --data" in line).strip())
        method = re.search(r"method=(\w+)", block).group(1)
        assert command[command.index("--out") + 1] == str(dataset / "results" / "glass" / "videos" / f"{method}.mp4")
        assert json.loads(command[command.index("--config-json") + 1])["path"] == "spiral"
    report = next(b for b in _jobs(r.stdout + r.stderr) if "rule report" in b)
    assert "videos/rtsplat.mp4" in report and "videos/2dgs.png" in report and "videos/refgs" not in report
    off = _config(dataset, scenes=["glass"], methods=methods, defaults={"video": {"enabled": False}})
    r = snakemake(dataset, "-n", config=off)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "video" not in _job_counts(r.stdout + r.stderr)


def test_fps_jobs_hold_every_core_of_the_run_and_only_then_say_they_ran_alone(dataset):
    """The timing pass takes --cores threads, so Snakemake runs nothing beside it, and records that; with
    fewer threads (--set-threads) it runs beside other jobs and does not claim to be alone."""
    for extra, threads, alone in ((["--cores", "3"], 3, True), (["--cores", "3", "--set-threads", "fps=1"], 1, False)):
        r = snakemake(dataset, "-n", "-p", *extra)
        assert r.returncode == 0, r.stderr + r.stdout
        fps = [b for b in _jobs(r.stdout + r.stderr) if b.startswith("rule fps:")]
        assert len(fps) == 2
        for block in fps:
            shown = re.search(r"^\s*threads: (\d+)$", block, re.M)  # Snakemake leaves out "threads: 1"
            assert (int(shown.group(1)) if shown else 1) == threads, block
            assert (" fps --data " in block) and (("--scheduled-alone" in block) is alone), block


def _jobs_beside(output: str, rule: str) -> list[tuple[str, set[str]]]:
    """For every job of ``rule`` in a real run's log: (its jobid, the other jobs that were running at any
    time while it ran), from the order of Snakemake's "rule X: ... jobid: N" and "Finished jobid: N" lines."""
    running: dict[str, str] = {}  # jobid -> rule
    watched: dict[str, set[str]] = {}  # jobid of a `rule` job -> the others seen running beside it
    done = []
    events = re.finditer(r"^(?:local)?rule (\w+):\n(?:.*\n)*?\s*jobid: (\d+)$|^Finished jobid: (\d+)", output, re.M)
    for event in events:
        if event.group(3) is not None:
            finished = event.group(3)
            running.pop(finished, None)
            if finished in watched:
                done.append((finished, watched.pop(finished)))
            continue
        name, jobid = event.group(1), event.group(2)
        for other in watched:
            watched[other].add(f"{name} {jobid}")
        if name == rule:
            watched[jobid] = {f"{n} {j}" for j, n in running.items()}
        running[jobid] = name
    return done


def test_paths_with_spaces_are_quoted(tmp_path):
    root = tmp_path / "my data"
    make_corner_scene(root / "data" / "scene one", n_views=2, width=40, height=30, with_masks=True)
    r = snakemake(root, "-n", "-p", "prepared_all", config=_config(root, overrides={}))
    assert r.returncode == 0, r.stderr + r.stdout
    cmds = [line.strip() for line in (r.stdout + r.stderr).splitlines() if " prepare --scene-dir" in line]
    assert len(cmds) == 1
    args = shlex.split(cmds[0])
    assert args[args.index("--scene-dir") + 1] == str(root / "data" / "scene one")
    assert args[args.index("--out") + 1] == str(root / "results" / "scene one" / "prepared")


def test_slurm_profile_dry_run_gives_gpu_to_training(dataset):
    r = snakemake(dataset, "-n", "--profile", str(ROOT / "profiles" / "slurm"))
    assert r.returncode == 0, r.stderr + r.stdout
    out = r.stdout + r.stderr
    assert {k: _job_counts(out)[k] for k in EXPECTED} == EXPECTED
    train = [b for b in _jobs(out) if b.startswith("rule train")]
    assert len(train) == 2 and all("gpu=1" in b for b in train)
    masks = [b for b in _jobs(out) if b.startswith("rule masks")]
    assert masks and all("gpu=0" in b for b in masks)
    # the profile sizes the training jobs; their time limit is the config's, 15 + 60 minutes per 1000
    # iterations by default (10 iterations here)
    assert "cpus_per_task=8" in train[0] and "runtime=16," in train[0] and "runtime=240," in _jobs_of(out, "sfm")[0]


def _jobs_of(output: str, rule: str) -> list[str]:
    return [b for b in _jobs(output) if b.startswith(f"rule {rule}:")]


def test_slurm_settings_of_the_config_reach_the_jobs(dataset, tmp_path):
    """slurm.gpus 0 (a CPU-only cluster) takes the GPU from every job; partitions, account and time limits
    come from the slurm section, per rule where given; the training time limit follows its iterations."""
    cfg = yaml.safe_load(_config(dataset).read_text())
    cfg["defaults"]["train"]["iterations"] = 3000
    cfg["slurm"] = {"gpus": 0, "partition": "cpu", "account": "lab", "train_minutes": 10,
                    "train_minutes_per_1000_iterations": 20, "rules": {"sfm": {"partition": "big", "minutes": 99}}}
    path = tmp_path / "cpu.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = snakemake(dataset, "-n", "--profile", str(ROOT / "profiles" / "slurm"), config=path)
    assert r.returncode == 0, r.stderr + r.stdout
    out = r.stdout + r.stderr
    blocks = [b for b in _jobs(out) if re.match(r"rule (masks|sfm|prepare|train|render|render_edit|fps|video|"
                                                r"metrics|report):", b)]
    assert len(blocks) == sum(EXPECTED.values()) - EXPECTED["all"]
    assert all("gpu=0" in b and "slurm_account=lab" in b for b in blocks)
    assert all("runtime=70," in b for b in _jobs_of(out, "train"))  # 10 + 20 x 3
    assert all("slurm_partition=big" in b and "runtime=99," in b for b in _jobs_of(out, "sfm"))
    assert all("slurm_partition=cpu," in b for b in _jobs_of(out, "render") + _jobs_of(out, "masks"))


def test_unknown_config_key_is_a_clear_error(dataset, tmp_path):
    cfg = tmp_path / "bad.yaml"
    bad = {"data": str(dataset / "data"), "defaults": {"prepare": {"downsmaple": 2}}}
    cfg.write_text(yaml.safe_dump(bad))
    r = snakemake(dataset, "-n", config=cfg)
    assert r.returncode != 0
    err = r.stdout + r.stderr
    assert "'defaults.prepare.downsmaple' does not exist" in err and "did you mean 'downsample'" in err


def test_masks_of_a_few_marked_views_make_the_masks_rule_wait_for_sfm(tmp_path):
    make_corner_scene(tmp_path / "data" / "marked", n_views=9, width=160, height=120, with_masks=True)
    for mask in sorted((tmp_path / "data" / "marked" / "transparent_masks").iterdir())[3:]:
        mask.unlink()  # three marked views: masks.source auto propagates them
    target = str(tmp_path / "results" / "marked" / "masks")
    r = snakemake(tmp_path, "-n", "-p", target, config=_config(tmp_path, overrides={}))
    assert r.returncode == 0, r.stderr + r.stdout
    out = r.stdout + r.stderr
    assert _job_counts(out)["sfm"] == 1
    masks = next(b for b in _jobs(out) if b.startswith("rule masks"))
    assert f"--sfm {tmp_path}/results/marked/sfm" in masks
    # sfm.use_masks would make sfm wait for the masks that wait for sfm: refused, naming the key
    config = _config(tmp_path, overrides={}, defaults={"sfm": {"use_masks": True}})
    r = snakemake(tmp_path, "-n", target, config=config)
    assert r.returncode != 0 and "sfm.use_masks" in r.stdout + r.stderr


def test_marks_in_the_config_make_the_masks_rule_wait_for_sfm(tmp_path):
    views = make_corner_scene(tmp_path / "data" / "drawn", n_views=9, width=160, height=120)
    marks = {v.name: {"box": [10, 10, 150, 110]} for v in views[:3]}  # no mask file: three boxes in the config
    target = str(tmp_path / "results" / "drawn" / "masks")
    config = _config(tmp_path, overrides={"drawn": {"masks": {"marks": marks}}})
    r = snakemake(tmp_path, "-n", "-p", target, config=config)
    assert r.returncode == 0, r.stderr + r.stdout
    masks = next(b for b in _jobs(r.stdout + r.stderr) if b.startswith("rule masks"))
    assert f"--sfm {tmp_path}/results/drawn/sfm" in masks
    assert views[0].name in masks and "[10, 10, 150, 110]" in masks  # the marks reach the stage's config


def test_real_run_to_prepared_scenes_and_resume(dataset):
    r = snakemake(dataset, "--cores", "2", "prepared_all")
    assert r.returncode == 0, r.stderr[-4000:]
    results = dataset / "results"
    glass = PreparedScene.load(results / "glass" / "prepared")
    plain = PreparedScene.load(results / "plain" / "prepared")
    assert glass.has_transparency and not plain.has_transparency
    assert (glass.cameras[0].width, glass.cameras[0].height) == (80, 60)
    # plain: SfM with SIMPLE_RADIAL -> undistorted images (their size may differ by a few pixels)
    sfm = json.loads((results / "plain" / "sfm" / "summary.json").read_text())
    und = read_header(next(Path(sfm["image_dir"]).iterdir()))
    assert sfm["undistorted"]
    assert (plain.cameras[0].width, plain.cameras[0].height) == (und.width // 4, und.height // 4)
    assert [c.name for c in glass.test_cameras] == ["view_000", "view_008"]
    assert read_mask(glass.mask_path("view_004")).any()
    assert glass.load_points()[0].shape[0] == 500  # the dataset's model was used
    assert len(plain.cameras) == 9 and plain.load_points()[0].shape[0] > 100  # real SfM
    for scene in ("glass", "plain"):
        for stage in ("masks", "sfm", "prepare"):
            assert (results / scene / "logs" / f"{stage}.log").stat().st_size > 0
            assert (results / scene / "benchmarks" / f"{stage}.tsv").is_file()
    assert "Mean reprojection" not in (results / "glass" / "logs" / "sfm.log").read_text()
    assert "images registered" in (results / "plain" / "logs" / "sfm.log").read_text()
    # a second run has nothing to do
    again = snakemake(dataset, "--cores", "2", "prepared_all")
    assert again.returncode == 0 and "Nothing to be done" in again.stdout + again.stderr
    # changing one scene's settings reruns only that scene's affected job
    changed = _config(dataset, overrides={"plain": {"prepare": {"downsample": 2}}})
    dry = snakemake(dataset, "-n", "prepared_all", config=changed)
    counts = _job_counts(dry.stdout + dry.stderr)
    assert counts.get("prepare") == 1 and "sfm" not in counts and "masks" not in counts
    assert "scene=plain" in dry.stdout + dry.stderr


def test_failed_scene_leaves_no_finished_output_and_resumes(tmp_path):
    make_corner_scene(tmp_path / "data" / "good", n_views=4, width=80, height=60, with_model=True)
    make_corner_scene(tmp_path / "data" / "bad", n_views=4, width=80, height=60, with_model=True)
    img = tmp_path / "data" / "bad" / "images" / "view_001.png"
    original = img.read_bytes()
    img.write_bytes(original[:200])
    cfg = _config(tmp_path, overrides={})
    r = snakemake(tmp_path, "--cores", "2", "--keep-going", "prepared_all", config=cfg)
    assert r.returncode != 0
    results = tmp_path / "results"
    assert (results / "good" / "prepared" / "scene.json").is_file()
    assert not (results / "bad" / "sfm").exists() and not (results / "bad" / "prepared").exists()
    log = (results / "bad" / "logs" / "sfm.log").read_text()
    assert "view_001.png: cannot read image" in log and "Fix:" in log
    img.write_bytes(original)
    r = snakemake(tmp_path, "--cores", "2", "prepared_all", config=cfg)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (results / "bad" / "prepared" / "scene.json").is_file()
    sfm_jobs = [b for b in _jobs(r.stdout + r.stderr) if re.match(r"(local)?rule sfm:", b)]
    assert len(sfm_jobs) == 1 and "scene=bad" in sfm_jobs[0]  # only the failed scene re-ran


def _rules_to_run(output: str) -> set[tuple[str, str]]:
    """(rule, scene) of each job of a dry run."""
    jobs = set()
    for block in _jobs(output):
        rule, scene = re.match(r"(?:local)?rule (\w+):", block), re.search(r"scene=(\w+)", block)
        if rule and scene:
            jobs.add((rule.group(1), scene.group(1)))
    return jobs


def test_an_image_edited_in_place_reruns_its_scene_and_an_untouched_dataset_nothing(tmp_path):
    import cv2

    for scene in ("glass", "other"):
        make_corner_scene(tmp_path / "data" / scene, n_views=4, width=80, height=60, with_model=True,
                          with_masks=True)
    cfg = _config(tmp_path, overrides={})
    results = tmp_path / "results"

    def finished_run():
        """The preprocessing outputs as a finished run leaves them: newer than every input."""
        old = time.time() - 100
        for scene in ("glass", "other"):
            os.utime(results / scene / "inputs.json", (old, old))
            for stage in ("masks", "sfm", "prepared"):
                (results / scene / stage).mkdir(exist_ok=True)
                os.utime(results / scene / stage)

    r = snakemake(tmp_path, "-n", "prepared_all", config=cfg)
    assert r.returncode == 0, r.stderr + r.stdout
    assert (results / "glass" / "inputs.json").is_file()
    finished_run()
    r = snakemake(tmp_path, "-n", "prepared_all", config=cfg)
    assert "Nothing to be done" in r.stdout + r.stderr

    image = tmp_path / "data" / "glass" / "images" / "view_001.png"
    folder_mtime = image.parent.stat().st_mtime_ns
    image.write_bytes(cv2.imencode(".png", cv2.imread(str(image)) // 2)[1].tobytes())  # same inode, new pixels
    assert image.parent.stat().st_mtime_ns == folder_mtime  # what the folder inputs alone cannot see
    edited = {("masks", "glass"), ("sfm", "glass"), ("prepare", "glass")}
    for _ in range(2):  # a dry run does not use up the change: the next run still reruns the scene
        r = snakemake(tmp_path, "-n", "prepared_all", config=cfg)
        assert r.returncode == 0, r.stderr + r.stdout
        assert _rules_to_run(r.stdout + r.stderr) == edited

    finished_run()
    os.utime(image, (1_000_000_000, 1_000_000_000))  # an older copy of the image put back (cp -p, rsync -t)
    r = snakemake(tmp_path, "-n", "prepared_all", config=cfg)
    assert _rules_to_run(r.stdout + r.stderr) == edited


@pytest.mark.slow
def test_whole_dag_to_the_report(tmp_path):
    """Train, render (plus an edit), metrics and the report for real, on a tiny two-method run."""
    make_corner_scene(tmp_path / "data" / "glass", n_views=9, width=80, height=60, with_model=True, with_masks=True)
    cfg = _config(
        tmp_path, overrides={},
        methods={"rtsplat": {"role": "main"}, "2dgs": {"effects": {"transmission": "off", "specular": "off"}}},
    )  # the main method is named: yaml.safe_dump sorts the keys, so "first listed" would be 2dgs
    data = yaml.safe_load(cfg.read_text())
    data["defaults"]["prepare"] = {"downsample": 2}
    data["defaults"]["train"] = {
        "iterations": 12,
        "options": {
            "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32},
            "schedule": {
                "volume_until": 2,
                "specular_from": 4,
                "densify_from": 1000,
                "reset_every": 0,
                "eval_every": 6,
                "log_every": 3,
                "checkpoint_every": 0,
            },
        },
    }
    data["defaults"]["render"] = {"edits": {"no-reflections": ["reflections=off"]}}
    data["defaults"]["video"] = {"frames": 6}
    cfg.write_text(yaml.safe_dump(data))
    # one thread per training and rendering job, as `make demo` runs them: two such jobs run at a time
    r = snakemake(tmp_path, "--cores", "2", "--set-threads", "train=1", "render=1", "render_edit=1", "video=1",
                  config=cfg)
    assert r.returncode == 0, r.stderr[-4000:]
    results = tmp_path / "results"
    for method in ("rtsplat", "2dgs"):
        summary = json.loads((results / "glass" / "runs" / method / "summary.json").read_text())
        assert summary["iterations"] == 12
        metrics = json.loads((results / "glass" / "metrics" / f"{method}.json").read_text())
        assert metrics["mean"]["psnr"] > 5 and "psnr_transparent" in metrics["mean"]
        assert (results / "glass" / "benchmarks" / f"train_{method}.tsv").is_file()
    assert json.loads((results / "glass" / "runs" / "2dgs" / "effects.json").read_text())["transmission"] is False
    assert (results / "glass" / "renders" / "rtsplat@no-reflections" / "render.json").is_file()
    # the FPS timing jobs ran with nothing beside them, and say so
    beside = _jobs_beside(r.stderr, "fps")
    assert len(beside) == 2 and all(not others for _, others in beside), beside
    assert any(others for _, others in _jobs_beside(r.stderr, "render_edit"))  # the others ran two at a time
    for method in ("rtsplat", "2dgs"):
        fps = json.loads((results / "glass" / "fps" / f"{method}.json").read_text())
        assert fps["fps"] > 0 and fps["timing"]["scheduled_alone"] is True and fps["timing"]["threads"] == 2
    md = (results / "report" / "index.md").read_text()
    assert "| rtsplat |" in md and "| 2dgs |" in md and "no-reflections" in md
    assert "FPS alone" in md and "training CPU s" in md
    # what trained the runs, through the CLIs: recorded by train, carried by render and metrics, on the first screen
    root = Path(__file__).resolve().parent.parent
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(root), "diff", "HEAD"], capture_output=True, text=True).stdout)
    for method in ("rtsplat", "2dgs"):
        trained = json.loads((results / "glass" / "runs" / method / "summary.json").read_text())["provenance"]
        assert trained["commit"] == (head or None)
        metrics = json.loads((results / "glass" / "metrics" / f"{method}.json").read_text())
        assert metrics["training_provenance"] == trained
    first_screen = md.split("\n## ", 1)[0]
    if head and not dirty:
        assert f"Every run was trained by commit {head[:12]} (no uncommitted changes)" in first_screen
    elif head:
        assert "2 of 2 runs were trained from a tree with uncommitted changes" in first_screen
    page = (results / "report" / "index.html").read_text()
    for method in ("rtsplat", "2dgs"):  # the same path for both, embedded with a poster and a download link
        assert (results / "glass" / "videos" / f"{method}.mp4").is_file()
        assert f"glass_video_{method}.mp4" in page and f"poster='glass_video_{method}.png'" in page
        assert (results / "report" / f"glass_video_{method}.mp4").is_file()


def test_train_and_render_jobs_get_the_configured_device_and_a_gpu_on_slurm(dataset, tmp_path):
    cfg = yaml.safe_load(_config(dataset).read_text())
    cfg["defaults"]["train"]["device"] = "cuda"
    cfg["defaults"]["render"] = {"device": "cuda:0"}
    cfg["defaults"]["video"] = {"device": "cuda:0"}
    cfg["overrides"]["plain"]["train"] = {"device": "cpu"}
    path = tmp_path / "device.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = snakemake(dataset, "-n", "--profile", str(ROOT / "profiles" / "slurm"), config=path)
    assert r.returncode == 0, r.stderr + r.stdout
    jobs = _jobs(r.stdout + r.stderr)

    def config_json(block: str, stage: str) -> dict:
        line = next(x for x in block.splitlines() if f" {stage} --data" in x)
        args = shlex.split(line.strip())
        return json.loads(args[args.index("--config-json") + 1])

    train = [b for b in jobs if b.startswith("rule train")]
    render = [b for b in jobs if b.startswith("rule render:")]
    assert len(train) == 2 and len(render) == 2
    devices = sorted(config_json(b, "train")["device"] for b in train)
    assert devices == ["cpu", "cuda"]
    assert all(config_json(b, "render")["device"] == "cuda:0" for b in render)
    video = [b for b in jobs if b.startswith("rule video:")]
    assert len(video) == 2 and all(config_json(b, "video")["device"] == "cuda:0" for b in video)
    assert all("gpu=1" in b for b in train + render + video)


def test_a_scene_folder_with_a_video_gets_its_frames_once(tmp_path):
    from rtsplat.io.video import Mp4Writer

    scene = tmp_path / "data" / "walk"
    scene.mkdir(parents=True)
    rng = np.random.default_rng(0)
    with Mp4Writer(scene / "walk.MOV", 64, 48, 10.0) as writer:
        for _ in range(20):
            writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    config = _config(tmp_path, overrides={"walk": {"frames": {"count": 4}}})
    r = snakemake(tmp_path, "-n", "-p", str(tmp_path / "results" / "walk" / "sfm"), config=config)
    assert r.returncode == 0, r.stderr + r.stdout
    names = sorted(p.name for p in (scene / "images").iterdir())
    assert len(names) == 4 and all(re.fullmatch(r"frame_\d{5}\.jpg", n) for n in names)
    assert "4 of 20 frames" in r.stderr
    sfm = next(b for b in _jobs(r.stdout + r.stderr) if b.startswith("rule sfm"))
    assert f"{scene}/images" in sfm
    again = snakemake(tmp_path, "-n", str(tmp_path / "results" / "walk" / "sfm"), config=config)
    assert again.returncode == 0 and "frames" not in again.stderr.split("Building DAG")[0]
    assert sorted(p.name for p in (scene / "images").iterdir()) == names
