"""Report stage: tables, accuracy-against-time plots with the Pareto front, images, atomic output."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from rtsplat.bench.toy_scene import write_scene
from rtsplat.errors import PipelineError
from rtsplat.io.atomic import write_json_atomic
from rtsplat.metrics import compute_metrics
from rtsplat.render import Edits, render_run
from rtsplat.report import Roles, build_report, pareto_front
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig

METHODS = {
    "rtsplat": {},
    "2dgs": {"effects": {"transmission": "off", "specular": "off"}},
    "ablation_gating": {"ablations": {"gating": False}},
}
ROLES = {"rtsplat": {"role": "main"}, "2dgs": {"role": "baseline"}, "ablation_gating": {"role": "ablation"}}


def test_pareto_front_by_hand():
    #            fast+bad  mid+best  slow+mid  mid+worst  = same as first
    points = [(1.0, 10.0), (2.0, 12.0), (3.0, 11.0), (2.0, 9.0), (1.0, 10.0)]
    assert pareto_front(points) == [True, True, False, False, True]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    root = tmp_path_factory.mktemp("results")
    scene = write_scene(root / "toy" / "prepared", views=8, width=40, height=30)
    for method, overrides in METHODS.items():
        cfg = TrainConfig.from_dict({
            "schedule": {"iterations": 20, "volume_until": 4, "specular_from": 8, "densify_from": 1000,
                         "reset_every": 0, "checkpoint_every": 0, "log_every": 5, "eval_every": 10},
            "model": {"env_height": 16, "env_width": 32, "env_levels": 3, "mlp_width": 32}, **overrides,
        })
        Trainer(scene, cfg, root / "toy" / "runs" / method, progress=False, log=lambda m: None).train()
        render_run(root / "toy" / "runs" / method, scene.root, root / "toy" / "renders" / method, progress=False)
        write_json_atomic(root / "toy" / "metrics" / f"{method}.json",
                          compute_metrics(root / "toy" / "renders" / method, scene.root, lpips_weights="/nonexistent"))
    render_run(root / "toy" / "runs" / "rtsplat", scene.root, root / "toy" / "renders" / "rtsplat@no-reflections",
               progress=False, edits=Edits(reflections=False))
    return root


def test_report_has_tables_plots_and_images(results, tmp_path):
    index = build_report(results, tmp_path / "report", roles=Roles.from_dict(ROLES), commands=["make demo"])
    html, md = index.read_text(), (tmp_path / "report" / "index.md").read_text()
    for method in METHODS:
        assert f"<td>{method}</td>" in html and f"| {method} |" in md
    assert "Ablations (transparent-region PSNR)" in md and "Pareto front" in md
    assert "no-reflections" in md and "Scene editing" in md
    for plot in ("toy_psnr_vs_time.png", "toy_psnr_transparent_vs_time.png"):
        data = (tmp_path / "report" / plot).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and plot in html
    # every image the pages reference exists
    import re

    for ref in re.findall(r"src='([^']+)'", html):
        assert (tmp_path / "report" / ref).is_file(), ref
    assert "run-to-run noise was not measured" in md
    assert "n/a (weights not found)" in md


def test_report_measures_noise_from_repeated_runs(results, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    shutil.copytree(copy / "toy" / "runs" / "2dgs", copy / "toy" / "runs" / "2dgs_repeat")
    shutil.copy(copy / "toy" / "metrics" / "2dgs.json", copy / "toy" / "metrics" / "2dgs_repeat.json")
    shutil.copytree(copy / "toy" / "runs" / "2dgs", copy / "toy" / "runs" / "2dgs_seed3")
    config = json.loads((copy / "toy" / "runs" / "2dgs_seed3" / "config.json").read_text())
    (copy / "toy" / "runs" / "2dgs_seed3" / "config.json").write_text(json.dumps({**config, "seed": 3}))
    metrics = json.loads((copy / "toy" / "metrics" / "2dgs.json").read_text())
    metrics["mean"]["psnr"] += 0.25  # another seed scored a quarter dB higher on the entire image
    (copy / "toy" / "metrics" / "2dgs_seed3.json").write_text(json.dumps(metrics))
    # the roles say which runs are repeats (their names do not matter: "again" reruns 2dgs too)
    shutil.copytree(copy / "toy" / "runs" / "2dgs", copy / "toy" / "runs" / "again")
    roles = Roles.from_dict({**ROLES, **{m: {"role": "repeat", "of": "2dgs"} for m in ("2dgs_repeat", "2dgs_seed3")},
                             "again": {"role": "baseline"}})
    md = build_report(copy, tmp_path / "report", roles=roles).with_suffix(".md").read_text()
    assert "| toy | 2dgs | same seed | 0.000 | 0.000 | " in md  # identical copies: zero difference
    assert "| toy | 2dgs | seed 3 | 0.250 | 0.000 | " in md
    assert md.count("| toy | 2dgs | ") == 2  # a baseline is no repeat, whatever its name or config
    assert "run-to-run noise was not measured" not in md
    # without roles nothing is a repeat, an ablation or the main method: the report does not guess from names
    plain = build_report(copy, tmp_path / "plain").with_suffix(".md").read_text()
    assert "run-to-run noise was not measured" in plain and "Ablations" not in plain
    assert "Decomposition (" not in plain and "Scene editing" not in plain


def test_bad_roles_are_clear_errors(results, tmp_path):
    for roles, text in (({"rtsplat": {"role": "star"}}, "role 'star'"),
                        ({"a": {"role": "repeat"}}, "which method it reruns"),
                        ({"a": {"role": "main"}, "b": {"role": "main"}}, "more than one")):
        with pytest.raises(PipelineError, match=text):
            Roles.from_dict(roles)
    result = subprocess.run([sys.executable, "-m", "rtsplat.cli", "report", "--results", str(results),
                             "--out", str(tmp_path / "r"), "--roles-json", "{"], capture_output=True, text=True)
    assert result.returncode == 1 and "--roles-json is not valid JSON" in result.stderr
    assert not (tmp_path / "r").exists()


def test_no_results_is_a_clear_error_and_leaves_nothing(tmp_path):
    with pytest.raises(PipelineError, match="no finished training runs"):
        build_report(tmp_path / "empty", tmp_path / "report")
    assert not (tmp_path / "report").exists()
    result = subprocess.run([sys.executable, "-m", "rtsplat.cli", "report", "--results", str(tmp_path),
                             "--out", str(tmp_path / "r")], capture_output=True, text=True)
    assert result.returncode == 1 and "rtsplat train" in result.stderr  # bad input: status 1, as every stage
