"""Report stage: tables, accuracy-against-time plots with the Pareto front, images, atomic output."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest

from rtsplat.bench.toy_scene import write_scene
from rtsplat.errors import PipelineError
from rtsplat.fps import measure_fps
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.images import read_image, write_png
from rtsplat.metrics import compute_metrics
from rtsplat.render import Edits, render_run
from rtsplat.report import (
    CPU_TIME,
    TIME_HEADER,
    WALL_TIME,
    Roles,
    ablation_reference,
    build_report,
    comparison_pairs,
    pareto_front,
)
from rtsplat.train.trainer import Trainer
from rtsplat.train_config import TrainConfig
from rtsplat.video import render_video

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


def test_comparison_pairs_by_hand():
    roles = Roles.from_dict({"rt": {"role": "main"}, "2dgs": {"role": "baseline"}, "rt_x4": {"role": "baseline"},
                             "2dgs_x4": {"role": "baseline"}, "2dgs_half": {"role": "baseline"},
                             "2dgs_seed1": {"role": "repeat", "of": "2dgs"}, "rt_seed1": {"role": "repeat", "of": "rt"},
                             "2dgs_abl": {"role": "ablation"}, "rt_abl": {"role": "ablation"}})
    methods = ["2dgs_x4", "rt", "rt_x4", "2dgs", "2dgs_half", "2dgs_seed1", "rt_seed1", "2dgs_abl", "rt_abl",
               "refgs"]
    # rt_half does not exist; repeats and ablations are no pairs; unlisted methods (refgs) are baselines
    assert comparison_pairs(methods, roles) == [("rt", "2dgs"), ("rt_x4", "2dgs_x4")]
    assert comparison_pairs(["rt", "rt_x4", "2dgs_x4"], roles) == [("rt_x4", "2dgs_x4")]  # no plain 2dgs run
    assert comparison_pairs(methods, Roles()) == []  # no main method, nothing to compare with
    unlisted = Roles.from_dict({"rt": {"role": "main"}})
    assert comparison_pairs(["rt", "2dgs", "rt_x4", "2dgs_x4"], unlisted) == [("rt", "2dgs"), ("rt_x4", "2dgs_x4")]


def test_a_run_at_the_time_of_a_2dgs_run_is_compared_with_that_run():
    roles = Roles.from_dict({"rt": {"role": "main"}, "2dgs": {"role": "baseline"}, "2dgs_x4": {"role": "baseline"},
                             "rt_x4": {"role": "baseline"}, "rt_eq": {"role": "baseline", "time_of": "2dgs"},
                             "rt_eq4": {"role": "baseline", "time_of": "2dgs_x4"},
                             "rt_eqx": {"role": "baseline", "time_of": "refgs"},
                             "rt_abl": {"role": "ablation", "time_of": "2dgs"},
                             "other": {"role": "baseline", "time_of": "2dgs"}})
    assert roles.time_of["rt_eq"] == "2dgs" and "rt" not in roles.time_of
    methods = ["rt", "2dgs", "rt_x4", "2dgs_x4", "rt_eq", "rt_eq4", "rt_eqx", "rt_abl", "other", "refgs"]
    # only the main method's variants, against a 2DGS run of a pair; not ablations, not other methods
    assert comparison_pairs(methods, roles) == [("rt", "2dgs"), ("rt_x4", "2dgs_x4"), ("rt_eq", "2dgs"),
                                                ("rt_eq4", "2dgs_x4")]
    assert comparison_pairs(["rt", "rt_eq"], roles) == []  # the 2DGS run it matched did not run


def test_ablations_are_compared_with_the_full_model_of_their_budget():
    roles = Roles.from_dict({"rt": {"role": "main"}, "rt_x4": {"role": "baseline"}, "rt_x16": {"role": "baseline"},
                             "rt_seed1": {"role": "repeat", "of": "rt"}, "abl_gating": {"role": "ablation"},
                             "abl_gating_x4": {"role": "ablation"}, "abl_mask_x16": {"role": "ablation"},
                             "abl_mask_seed1": {"role": "ablation"}})
    methods = ["rt", "rt_x4", "rt_seed1", "abl_gating", "abl_gating_x4", "abl_mask_x16", "abl_mask_seed1"]
    assert ablation_reference("abl_gating", methods, roles) == "rt"
    assert ablation_reference("abl_gating_x4", methods, roles) == "rt_x4"
    assert ablation_reference("abl_mask_seed1", methods, roles) == "rt"  # a repeat is no full-model budget
    assert ablation_reference("abl_mask_x16", methods, roles) == "rt"  # rt_x16 did not run: the main method
    assert ablation_reference("abl_gating_x4", ["abl_gating_x4"], roles) is None
    assert ablation_reference("abl_gating", methods, Roles()) is None


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
    videos = root / "toy" / "videos"
    render_video(root / "toy" / "runs" / "rtsplat", scene.root, videos / "rtsplat.mp4", frames=4, panels=True,
                 poster=videos / "rtsplat.png", progress=False)
    return root


def test_report_has_tables_plots_and_images(results, tmp_path):
    (results / "toy" / "masks").mkdir(exist_ok=True)
    write_json_atomic(results / "toy" / "masks" / "summary.json",
                      {"has_masks": True, "source": "ingest", "num_images": 12, "mean_coverage": 0.25})
    index = build_report(results, tmp_path / "report", roles=Roles.from_dict(ROLES), commands=["make demo"])
    html, md = index.read_text(), (tmp_path / "report" / "index.md").read_text()
    assert "Transparent masks: given for the 12 photos, mean coverage 25.0%." in md
    assert json.loads((results / "toy" / "prepared" / "scene.json").read_text())["roi_warning"] == ""
    assert "Warning (region of interest" not in md  # prepare used the masks' region: nothing to warn of
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
    # the camera-path video: HTML5 video with its poster frame and a download link, copied into the report
    assert "<video " in html and "poster='toy_video_rtsplat.png'" in html
    assert "<a href='toy_video_rtsplat.mp4' download>" in html
    assert (tmp_path / "report" / "toy_video_rtsplat.png").is_file()
    assert (tmp_path / "report" / "toy_video_rtsplat.mp4").read_bytes() == \
        (results / "toy" / "videos" / "rtsplat.mp4").read_bytes()
    assert "rtsplat: orbit path, 4 frames at 24 fps, 40x30 per panel (image | reflection | transmission" in md
    assert "[![rtsplat: orbit path" in md and "](toy_video_rtsplat.mp4)" in md


def test_report_shows_the_masks_over_three_photos_with_the_polarity_decision(results, tmp_path):
    sys.path.insert(0, str(Path(__file__).parent))
    from fixtures_pipeline import make_corner_scene

    from rtsplat.io.images import read_mask, write_mask
    from rtsplat.masks import make_masks

    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    shutil.rmtree(copy / "toy" / "masks", ignore_errors=True)  # another test's hand-written summary
    data = tmp_path / "data" / "toy"
    make_corner_scene(data, n_views=5, width=48, height=36, with_masks=True)
    pane = np.ones((36, 48), bool)  # glass that fills the view: white but for a strip of wall above
    pane[:4] = False
    for stem in ("view_000", "view_002", "view_004"):
        write_mask(data / "transparent_masks" / f"{stem}.png", pane)
    summary = make_masks(data, copy / "toy" / "masks", progress=False)
    assert summary.polarity_warning  # white covers more than half of the photos on average

    index = build_report(copy, tmp_path / "report", roles=Roles.from_dict(ROLES))
    html, md = index.read_text(), index.with_suffix(".md").read_text()
    for text in (md, html):
        assert "Polarity: masks.polarity: auto: white = see-through, kept as given" in text
        assert "Warning: white covers" in text and "set masks.polarity: black" in text
    shown = 0
    for i in (0, 2, 4):  # five photos: the first, the middle and the last
        name = f"view_{i:03d}"
        file = f"images/toy_mask_{name}.png"
        assert f"src='{file}'" in html and f"![{name}.png: given, " in md
        photo = read_image(data / "images" / f"{name}.png")
        overlay = read_image(tmp_path / "report" / file)
        assert overlay.shape == photo.shape
        mask = read_mask(copy / "toy" / "masks" / f"{name}.png")
        changed = np.abs(overlay - photo).max(-1) > 0.5 / 255
        np.testing.assert_array_equal(changed, mask)  # tinted exactly where the mask is
        shown += 1
        assert f"{name}.png: given, {100 * summary.coverage[name]:.1f}% covered" in md
    assert shown == 3 and "toy_mask_view_001" not in html


def test_report_names_the_scene_whose_masks_region_of_interest_prepare_did_not_use(results, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    write_json_atomic(copy / "toy" / "masks" / "summary.json",
                      {"has_masks": True, "source": "ingest", "num_images": 8, "mean_coverage": 0.25})
    warning = ("the masks' visual hull lies away from the glass (its sphere meets 0% of the see-through pixels' "
               "rays in the median view, needs 50%): the region of interest is the estimated one instead; set "
               "prepare.roi to place it")
    scene_json = copy / "toy" / "prepared" / "scene.json"
    scene_json.write_text(json.dumps({**json.loads(scene_json.read_text()), "roi_warning": warning}))
    index = build_report(copy, tmp_path / "report", roles=Roles.from_dict(ROLES))
    html, md = index.read_text(), index.with_suffix(".md").read_text()
    assert f"Warning (region of interest, scene toy): {warning}." in md
    assert "Warning (region of interest, scene toy): the masks&#x27; visual hull lies away from the glass" in html
    # under the scene's masks, before its quality table
    assert md.index("### Transparent masks") < md.index("Warning (region of interest") < md.index("### Quality")


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


def _md_row(md: str, start: str) -> list[str]:
    line = next(line for line in md.splitlines() if line.startswith(start))
    return [cell.strip() for cell in line.strip("|").split("|")]


def _mean(results, method: str) -> dict:
    return json.loads((results / "toy" / "metrics" / f"{method}.json").read_text())["mean"]


def test_summary_rows_are_the_metric_gaps_with_the_seed_noise_beside_them(results, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    for src, dst, shift in (("rtsplat", "rtsplat_x4", 1.5), ("2dgs", "2dgs_x4", 0.25), ("2dgs", "2dgs_seed3", 0.3)):
        shutil.copytree(copy / "toy" / "runs" / src, copy / "toy" / "runs" / dst)
        metrics = json.loads((copy / "toy" / "metrics" / f"{src}.json").read_text())
        metrics["mean"]["psnr"] += shift
        metrics["mean"]["psnr_transparent"] -= shift / 2
        (copy / "toy" / "metrics" / f"{dst}.json").write_text(json.dumps(metrics))
    config = json.loads((copy / "toy" / "runs" / "2dgs_seed3" / "config.json").read_text())
    (copy / "toy" / "runs" / "2dgs_seed3" / "config.json").write_text(json.dumps({**config, "seed": 3}))
    roles = Roles.from_dict({**ROLES, "rtsplat_x4": {"role": "baseline"}, "2dgs_x4": {"role": "baseline"},
                             "2dgs_seed3": {"role": "repeat", "of": "2dgs"}})
    md = build_report(copy, tmp_path / "report", roles=roles).with_suffix(".md").read_text()
    assert md.index("Summary: RT-Splatting against plain 2DGS") < md.index("# Scene toy")
    assert "smaller than twice the seed noise is not significant" in md
    for ours, theirs in (("rtsplat", "2dgs"), ("rtsplat_x4", "2dgs_x4")):
        row = _md_row(md, f"| toy | {ours} - {theirs} |")
        a, b = _mean(copy, ours), _mean(copy, theirs)
        assert float(row[2]) == pytest.approx(a["psnr_transparent"] - b["psnr_transparent"], abs=0.005)
        assert float(row[3]) == pytest.approx(a["psnr"] - b["psnr"], abs=0.005)
        assert row[9].endswith("x") and float(row[9][:-1]) > 0  # the time ratio
        if ours == "rtsplat":  # 2dgs_seed3 reran 2dgs with another seed: 0.15 dB transparent, 0.3 dB entire
            assert (float(row[4]), float(row[5]), row[6]) == (pytest.approx(0.15, abs=5e-4),
                                                              pytest.approx(0.3, abs=5e-4), "2dgs_seed3")
        else:
            assert row[4:6] == ["not measured", "not measured"]
    # rtsplat_x4 - 2dgs_x4 was built as a gap of 1.25 dB more on the entire image than rtsplat - 2dgs
    gap = float(_md_row(md, "| toy | rtsplat_x4 - 2dgs_x4 |")[3]) - float(_md_row(md, "| toy | rtsplat - 2dgs |")[3])
    assert gap == pytest.approx(1.25, abs=0.011)
    plain = build_report(copy, tmp_path / "plain").with_suffix(".md").read_text()
    assert "so there is no summary" in plain  # without roles there is no main method


def test_the_equal_time_gap_reads_both_logs_at_the_shorter_runs_time():
    from rtsplat.report import Run, equal_time_gap, psnr_at_time

    def run(points, cpu_seconds):
        log = [{"iteration": 10 * i, "cpu_seconds": t, "test_psnr": v} for i, (t, v) in enumerate(points)]
        log.insert(1, {"iteration": 5, "cpu_seconds": 1.0, "loss": 0.1})  # a step without an evaluation
        return Run("s", "m", summary={"train_cpu_seconds": cpu_seconds}, log=log)

    slow = run([(0.0, 10.0), (40.0, 20.0), (100.0, 26.0)], 100.0)  # twice as long, better in the end
    fast = run([(0.0, 10.0), (25.0, 22.0), (50.0, 24.0)], 50.0)
    assert psnr_at_time(slow, 50.0, "test_psnr", CPU_TIME) == pytest.approx(21.0)  # 20 + 6 x 10 / 60
    assert psnr_at_time(fast, 80.0, "test_psnr", CPU_TIME) == 24.0  # past its last evaluation: its last value
    assert psnr_at_time(fast, 10.0, "test_psnr_transparent", CPU_TIME) is None  # no such evaluations
    # at the fast run's 50 s, the slow run is 3 dB behind, although its final PSNR is 2 dB ahead
    assert equal_time_gap(slow, fast, "test_psnr", CPU_TIME) == pytest.approx(-3.0)
    assert equal_time_gap(fast, slow, "test_psnr", CPU_TIME) == pytest.approx(3.0)
    assert equal_time_gap(slow, Run("s", "x", summary={}), "test_psnr", CPU_TIME) is None


def _zero_colour() -> np.ndarray:
    return np.round(np.array(matplotlib.colormaps["viridis"](0.0)[:3]) * 255) / 255


def test_images_are_nearest_upscaled_and_error_maps_show_zero_for_a_perfect_render(results, tmp_path):
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    view = sorted(json.loads((copy / "toy" / "metrics" / "rtsplat.json").read_text())["views"])[0]
    gt = copy / "toy" / "prepared" / "images" / f"{view}.png"
    shutil.copy(gt, copy / "toy" / "renders" / "2dgs" / "color" / f"{view}.png")  # a perfect 2dgs render
    # ground-truth layers equal to the main method's own layers: its layer error maps show zero too
    renders = copy / "toy" / "renders" / "rtsplat"
    color, reflection = (read_image(renders / layer / f"{view}.png") for layer in ("color", "reflection"))
    for layer, image in (("reflection", reflection), ("transmission", np.clip(color - reflection, 0, 1))):
        (copy / "toy" / "prepared" / "gt_layers" / layer).mkdir(parents=True)
        write_png(copy / "toy" / "prepared" / "gt_layers" / layer / f"{view}.png", image, bits=16)
    md = build_report(copy, tmp_path / "report", roles=Roles.from_dict(ROLES)).with_suffix(".md").read_text()
    images = tmp_path / "report" / "images"

    source = read_image(renders / "color" / f"{view}.png")
    assert source.shape == (30, 40, 3)
    copied = read_image(images / f"toy_{view}_rtsplat.png")
    factor = 10  # the smallest integer that brings the shorter side, 30 px, to 300 px
    assert copied.shape == (300, 400, 3)
    np.testing.assert_array_equal(copied[::factor, ::factor], source)  # downscaled back: the source
    blocks = copied.reshape(30, factor, 40, factor, 3)
    np.testing.assert_array_equal(blocks, np.broadcast_to(source[:, None, :, None], blocks.shape))  # no blending

    zero = _zero_colour()
    perfect = read_image(images / f"toy_{view}_2dgs_error.png")
    assert perfect.shape == (300, 400, 3)
    np.testing.assert_allclose(perfect, np.broadcast_to(zero, perfect.shape), atol=1e-6)
    main_error = read_image(images / f"toy_{view}_rtsplat_error.png")
    assert np.abs(main_error - zero).max() > 0.1  # a 20-iteration run is not perfect: its map is not flat
    assert "viridis, 0 to 0.25" in md

    assert f"Decomposition against the ground-truth layers (view {view})" in md
    for layer in ("reflection", "transmission"):
        layer_error = read_image(images / f"toy_{view}_rtsplat_{layer}_error.png")
        np.testing.assert_allclose(layer_error, np.broadcast_to(zero, layer_error.shape), atol=1e-6)
        assert read_image(images / f"toy_{view}_rtsplat_gt_{layer}.png").shape == (300, 400, 3)


def test_near_reflection_rows_list_the_runs_that_asked_for_them():
    from rtsplat.report import Run, near_reflection_rows

    fit = {"iteration": 201, "planes": 4, "planar_share": 0.92, "on": True, "reason": "auto: planar glass"}
    bent = dict(fit, bent_planes=3, coverage=0.4127)
    runs = {
        "rtsplat": Run("film", "rtsplat", summary={"effects": {"near_reflection": True}, "near_reflection": bent,
                                                   "seconds_per_iteration": 0.61, "iterations": 200,
                                                   "train_cpu_seconds": 100.0}),
        "2dgs": Run("film", "2dgs", summary={"effects": {"near_reflection": False}, "near_reflection": None,
                                             "seconds_per_iteration": 0.3}),
        "old": Run("film", "old", summary={"effects": {"transmission": True}}),  # written before the term
        "learnt": Run("film", "learnt", summary={"effects": {"near_reflection": True}, "near_reflection": fit,
                                                 "mirror_planes_moved": [{"degrees": 0.48, "shift": 0.0015},
                                                                         {"degrees": 1.67, "shift": -0.034}],
                                                 "seconds_per_iteration": 0.64, "iterations": 200,
                                                 "train_cpu_seconds": 110.0}),
    }
    rows = near_reflection_rows(runs)
    assert rows == [["learnt", "on", "4", "-", "0.92", "-", "auto: planar glass", "up to 1.7 deg, 0.034", "0.640",
                     "0.550"],
                    ["rtsplat", "on", "4", "3", "0.92", "0.41", "auto: planar glass", "-", "0.610", "0.500"]]


def _table_rows(md: str, header_start: str) -> dict[str, dict[str, str]]:
    """The Markdown table whose header row starts with ``header_start``: {first cell: {column: cell}}."""
    lines = md.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    header = [c.strip() for c in lines[at].strip("|").split("|")]
    rows = {}
    for line in lines[at + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = dict(zip(header, cells, strict=True))
    return rows


def test_time_columns_are_the_measures_that_do_not_depend_on_neighbours(results, tmp_path):
    """Training time against accuracy is the training CPU seconds (wall seconds beside them), FPS the one
    `rtsplat fps` timed in a job scheduled alone; a GPU run's CPU seconds are not used."""
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    prepared = copy / "toy" / "prepared"
    measure_fps(copy / "toy" / "runs" / "rtsplat", prepared, copy / "toy" / "fps" / "rtsplat.json", rounds=1,
                scheduled_alone=True)
    measure_fps(copy / "toy" / "runs" / "2dgs", prepared, copy / "toy" / "fps" / "2dgs.json", rounds=1)
    md = build_report(copy, tmp_path / "report", roles=Roles.from_dict(ROLES)).with_suffix(".md").read_text()
    assert "FPS alone: the test views' renders timed by `rtsplat fps`" in md
    times = _table_rows(md, "| " + " | ".join(TIME_HEADER[:2]))
    alone = json.loads((copy / "toy" / "fps" / "rtsplat.json").read_text())
    assert float(times["rtsplat"]["FPS alone"]) == pytest.approx(alone["fps"], abs=0.051)
    assert times["rtsplat"]["FPS threads"] == str(alone["timing"]["threads"])
    assert float(times["rtsplat"]["FPS: other cores busy"]) == pytest.approx(alone["timing"]["other_busy_cores"],
                                                                             abs=0.0051)
    assert times["2dgs"]["FPS alone"] == "-"  # timed, but not alone
    assert times["ablation_gating"]["FPS alone"] == "-"  # not timed by rtsplat fps at all
    for method in METHODS:
        summary = json.loads((copy / "toy" / "runs" / method / "summary.json").read_text())
        row = times[method]
        assert float(row["training CPU s"]) == pytest.approx(summary["train_cpu_seconds"], abs=0.051)
        assert float(row["training wall s"]) == pytest.approx(summary["train_seconds"], abs=0.051)
        assert float(row["training: other cores busy"]) == pytest.approx(summary["run_usage"]["other_busy_cores"],
                                                                         abs=0.0051)
        assert float(row["training CPU share"]) == pytest.approx(summary["cpu_share"], abs=0.0051)
    pareto = _table_rows(md, f"| method | {CPU_TIME.label} |")
    assert CPU_TIME.caption in md
    for method, row in pareto.items():
        summary = json.loads((copy / "toy" / "runs" / method / "summary.json").read_text())
        assert float(row[CPU_TIME.label]) == pytest.approx(summary["train_cpu_seconds"], abs=0.051)
    # one run trained on a GPU: its CPU seconds are the host's share only, so the scene's time is wall seconds
    path = copy / "toy" / "runs" / "2dgs" / "summary.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "device": "cuda:0"}))
    md = build_report(copy, tmp_path / "report_gpu", roles=Roles.from_dict(ROLES)).with_suffix(".md").read_text()
    assert WALL_TIME.caption in md and CPU_TIME.caption not in md
    pareto = _table_rows(md, f"| method | {WALL_TIME.label} |")
    summary = json.loads((copy / "toy" / "runs" / "rtsplat" / "summary.json").read_text())
    assert float(pareto["rtsplat"][WALL_TIME.label]) == pytest.approx(summary["train_seconds"], abs=0.051)


def test_appearance_rows_show_the_spread_and_the_corrections_size():
    from rtsplat.report import Run, appearance_rows

    on = {"on": True, "spread": 0.047, "reason": "auto: the photos' exposure spread is 0.047 (>= 0.03)",
          "confidence": "high", "train_mean_abs_log_gain": 0.052, "test_mean_abs_log_gain": 0.071}
    runs = {"rtsplat": Run("glass", "rtsplat", summary={"appearance": on}),
            "2dgs": Run("glass", "2dgs", summary={"appearance": {"on": False, "spread": 0.01, "reason": "auto"}}),
            "old": Run("glass", "old", summary={})}
    rows = appearance_rows(runs)
    assert rows == [["2dgs", "off", "0.010", "-", "auto", "-", "-"],  # written before the confidence
                    ["rtsplat", "on", "0.047", "high", on["reason"], "0.052", "0.071"]]


def test_the_near_reflection_section_says_what_share_of_the_true_reflection_is_near(tmp_path):
    from rtsplat.report import scene_reflection_reach

    prepared = tmp_path / "prepared"
    assert scene_reflection_reach(prepared) == ""  # a real capture: no ground truth, nothing said
    (prepared / "gt_layers").mkdir(parents=True)
    (prepared / "gt_layers" / "reflection_reach.json").write_text(json.dumps(
        {"glass_pixels": 100, "near_pixels": 59, "near_weight": 0.514, "median_distance": 3.32, "near_share": 0.59}))
    text = scene_reflection_reach(prepared)
    assert "0.59" in text and "0.51" in text and "3.32" in text
    (prepared / "gt_layers" / "reflection_reach.json").write_text(json.dumps(
        {"glass_pixels": 10, "near_pixels": 0, "near_weight": 0.0, "median_distance": None, "near_share": 0.0}))
    assert "median distance" not in scene_reflection_reach(prepared)
    (prepared / "gt_layers" / "reflection_reach.json").write_text("{not json")
    assert scene_reflection_reach(prepared) == ""


def _git(*args: str) -> str | None:
    done = subprocess.run(["git", "-C", str(Path(__file__).resolve().parent.parent), *args], capture_output=True,
                          text=True)
    return done.stdout.strip() if done.returncode == 0 else None


def test_every_run_records_the_code_machine_and_device_that_trained_it_and_render_and_metrics_carry_it(results):
    import os
    import socket

    import torch

    head = _git("rev-parse", "HEAD")
    changed = bool(_git("diff", "HEAD", "--name-only"))
    for method in METHODS:
        record = json.loads((results / "toy" / "runs" / method / "summary.json").read_text())["provenance"]
        assert record["commit"] == head and record["dirty"] is (changed if head else None)
        assert (record["diff_sha256"] is not None) is (changed and head is not None)
        assert record["machine"]["hostname"] == socket.gethostname() and record["machine"]["cpus"] == os.cpu_count()
        assert record["device"] == "cpu" and record["versions"]["torch"] == torch.__version__
        assert record["versions"]["numpy"] == np.__version__ and "earlier_parts" not in record
        render = json.loads((results / "toy" / "renders" / method / "render.json").read_text())
        metrics = json.loads((results / "toy" / "metrics" / f"{method}.json").read_text())
        assert render["training_provenance"] == record and metrics["training_provenance"] == record


def _with_provenance(results: Path, copy: Path, change: dict[str, dict]) -> None:
    """``results`` copied to ``copy`` with every run's training provenance set to one clean commit on one
    machine, then ``change[method]`` merged into that method's."""
    shutil.copytree(results, copy)
    clean = {"commit": "a" * 40, "dirty": False, "diff_sha256": None, "device": "cpu", "versions": {"torch": "2.13.0"},
             "machine": {"hostname": "bench-1", "processor": "Test CPU", "cpus": 2}}
    for method in METHODS:
        path = copy / "toy" / "runs" / method / "summary.json"
        summary = json.loads(path.read_text())
        path.write_text(json.dumps({**summary, "provenance": {**clean, **change.get(method, {})}}))


def _first_screen(md: str) -> str:
    """What the report shows before its first section: the lines between the title and the first heading."""
    return md.split("\n## ", 1)[0]


def test_a_report_over_runs_of_one_clean_commit_names_it_on_its_first_screen(results, tmp_path):
    from rtsplat.results_page import main as results_page

    _with_provenance(results, tmp_path / "results", {})
    build_report(tmp_path / "results", tmp_path / "report", roles=Roles.from_dict(ROLES))
    md = (tmp_path / "report" / "index.md").read_text()
    first = _first_screen(md)
    assert ("Every run was trained by commit aaaaaaaaaaaa (no uncommitted changes) on bench-1: Test CPU, 2 cores"
            in first)
    assert "Mixed provenance" not in md
    html = (tmp_path / "report" / "index.html").read_text()
    assert html.index("Every run was trained by commit aaaaaaaaaaaa") < html.index("<h2>")
    record = json.loads((tmp_path / "report" / "report.json").read_text())
    assert record["commit"] == "aaaaaaaaaaaa" and record["mixed"] == []
    assert sorted(record["provenance"][0]["runs"]) == sorted(f"toy/{m}" for m in METHODS)

    assert results_page(["--report", str(tmp_path / "report"), "--out", str(tmp_path / "results.md")]) == 0
    page = (tmp_path / "results.md").read_text()
    assert f"--out {tmp_path / 'results.md'}`" in page  # the command that writes this page again
    assert "- Commit: `aaaaaaaaaaaa` (trained every run)" in page and "bench-1: Test CPU, 2 cores" in page
    # the kept tables are the report's own rows, under the scene's heading
    for header_start in ("| method | PSNR | SSIM |", "| method | FPS alone |"):
        assert _table_rows(page, header_start) == _table_rows(md, header_start)
        assert _table_rows(page, header_start)
    assert "## Scene toy" in page and "### Ablations (transparent-region PSNR)" in page
    assert "Summary: RT-Splatting against plain 2DGS" in page
    assert "Noise" not in page.split("## Scene toy", 1)[1]  # the noise section is left to the report
    # the record kept beside the page gives the same page again
    kept = tmp_path / "results.report.json"
    assert json.loads(kept.read_text())["source"] == str(tmp_path / "report")
    assert results_page(["--report", str(kept), "--out", str(tmp_path / "again.md")]) == 0
    again = (tmp_path / "again.md").read_text()
    assert again == page.replace(f"--out {tmp_path / 'results.md'}`", f"--out {tmp_path / 'again.md'}`").replace(
        "kept beside this page as `results.report.json`", "kept beside this page as `again.report.json`")


def test_a_report_over_runs_of_two_commits_says_so_on_its_first_screen(results, tmp_path):
    """One run trained by another commit, one from a tree with uncommitted changes on another machine: the
    report's first screen (before any section) says all three, and so does the results page."""
    from rtsplat.results_page import main as results_page

    _with_provenance(results, tmp_path / "results", {
        "2dgs": {"commit": "b" * 40},
        "ablation_gating": {"dirty": True, "diff_sha256": "0123456789abcdef",
                            "machine": {"hostname": "bench-2", "processor": "Other CPU", "cpus": 16}}})
    build_report(tmp_path / "results", tmp_path / "report", roles=Roles.from_dict(ROLES))
    md = (tmp_path / "report" / "index.md").read_text()
    first = _first_screen(md)
    assert "Mixed provenance" in first and "3 different versions of the code" in first
    for label in ("aaaaaaaaaaaa", "bbbbbbbbbbbb", "aaaaaaaaaaaa+changes (diff 0123456789abcdef)"):
        assert label in first
    assert "1 of 3 runs were trained from a tree with uncommitted changes" in first and "toy/ablation_gating" in first
    assert "trained on 2 machines" in first and "bench-2: Other CPU, 16 cores" in first
    html = (tmp_path / "report" / "index.html").read_text()
    assert html.index("Mixed provenance") < html.index("<h2>")
    # the provenance section lists each group with its runs
    rows = {row[-1]: row for row in (line.strip("| ").split(" | ") for line in
                                     md.split("| commit | machine | device | packages | runs |")[1].split("\n\n")[0]
                                     .splitlines()[2:])}
    assert rows["toy/2dgs"][0] == "bbbbbbbbbbbb" and rows["toy/rtsplat"][1] == "bench-1: Test CPU, 2 cores"
    record = json.loads((tmp_path / "report" / "report.json").read_text())
    assert record["commit"] is None and record["commits"]["bbbbbbbbbbbb"] == ["toy/2dgs"]
    assert results_page(["--report", str(tmp_path / "report"), "--out", str(tmp_path / "results.md")]) == 0
    page = (tmp_path / "results.md").read_text()
    assert page.split("\n## ", 1)[0].count("**Mixed provenance:**") == 1
    assert "- Trained by 3 combinations of commit, machine and device" in page
    assert "  - `bbbbbbbbbbbb` on bench-1: Test CPU, 2 cores, device cpu, torch 2.13.0: 1 run (toy/2dgs)" in page


def test_a_report_over_runs_that_record_no_provenance_says_so(results, tmp_path):
    shutil.copytree(results, tmp_path / "results")
    path = tmp_path / "results" / "toy" / "runs" / "2dgs" / "summary.json"
    path.write_text(json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k != "provenance"}))
    md = build_report(tmp_path / "results", tmp_path / "report").with_suffix(".md").read_text()
    assert "1 of 3 runs do not record the code that trained them: toy/2dgs." in _first_screen(md)


def test_results_page_of_a_folder_without_report_json_is_a_clear_error(tmp_path, capsys):
    from rtsplat.results_page import main as results_page

    assert results_page(["--report", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no report.json" in err and str(tmp_path) in err and "rtsplat report" in err
    assert results_page(["--report", str(tmp_path / "missing.json")]) == 1
    err = capsys.readouterr().err
    assert "no such file" in err and "missing.json" in err


def test_family_section_gives_each_scene_its_gap_noise_and_verdict_and_each_split_its_summary(results, tmp_path):
    """Copies of the toy run named as family scenes, with the main method's transparent PSNR set to a known
    gap over 2dgs and a repeat of rtsplat with another seed at a known distance (the seed noise). Seeds 0 and 2
    are tuning scenes, 1 and 3 seen (the former held-out half, which decisions used), 101 held out."""
    copy = tmp_path / "results"
    # scene: (gap on the transparent region, seed noise or None for no repeat)
    built = {"shop_window-0": (2.0, 0.3), "curved-2": (-1.0, 0.2), "shop_window-1": (0.1, 0.3), "car-3": (0.5, None),
             "grazing-101": (0.3, 0.2)}
    # the true reflection's 8-bit value on three scenes: the larger the gap, the stronger the reflection
    reflected = {"shop_window-0": 204, "shop_window-1": 102, "curved-2": 51}
    shutil.copytree(results / "toy", copy / "toy")  # not a family name: not in the section
    for scene, (gap, noise) in built.items():
        shutil.copytree(results / "toy", copy / scene)
        base = json.loads((copy / scene / "metrics" / "2dgs.json").read_text())
        ours = json.loads((copy / scene / "metrics" / "rtsplat.json").read_text())
        ours["mean"]["psnr_transparent"] = base["mean"]["psnr_transparent"] + gap
        ours["mean"]["psnr_reflection_layer"] = 20.0 + gap
        base["mean"]["psnr_reflection_layer"] = 20.0
        (copy / scene / "metrics" / "rtsplat.json").write_text(json.dumps(ours))
        (copy / scene / "metrics" / "2dgs.json").write_text(json.dumps(base))
        if noise is not None:
            shutil.copytree(copy / scene / "runs" / "rtsplat", copy / scene / "runs" / "rtsplat_seed1")
            config = json.loads((copy / scene / "runs" / "rtsplat_seed1" / "config.json").read_text())
            (copy / scene / "runs" / "rtsplat_seed1" / "config.json").write_text(json.dumps({**config, "seed": 1}))
            ours["mean"]["psnr_transparent"] += noise
            (copy / scene / "metrics" / "rtsplat_seed1.json").write_text(json.dumps(ours))
        if scene in reflected:  # true layers: a flat reflection of a known strength over the test views
            for view in ours["views"]:
                image = read_image(copy / scene / "prepared" / "images" / f"{view}.png")[..., :3]
                layers = copy / scene / "prepared" / "gt_layers"
                write_png(layers / "reflection" / f"{view}.png", np.full_like(image, reflected[scene] / 255))
                write_png(layers / "transmission" / f"{view}.png", np.zeros_like(image))
    # on one scene a run of the main method at the 2DGS run's time (time_of), 0.7 dB ahead of 2DGS there
    equal_time = copy / "shop_window-0"
    shutil.copytree(equal_time / "runs" / "rtsplat", equal_time / "runs" / "rtsplat_eq")
    eq = json.loads((equal_time / "metrics" / "2dgs.json").read_text())
    eq["mean"]["psnr_transparent"] += 0.7
    (equal_time / "metrics" / "rtsplat_eq.json").write_text(json.dumps(eq))
    roles = Roles.from_dict({**ROLES, "rtsplat_seed1": {"role": "repeat", "of": "rtsplat"},
                             "rtsplat_eq": {"role": "baseline", "time_of": "2dgs"}})
    report = build_report(copy, tmp_path / "report", roles=roles)
    md = report.with_suffix(".md").read_text()
    assert "Scene family: RT-Splatting minus plain 2DGS per scene" in md and "larger than 2 x that noise" in md
    assert _md_row(md, "| shop_window-0 | rtsplat_eq - 2dgs |")[2] == "+0.70"  # a summary pair of its own
    section = md.split("Scene family")[1].split("## Provenance")[0]
    assert "| toy |" not in section
    verdicts = {"shop_window-0": "better", "curved-2": "worse", "shop_window-1": "within noise",
                "car-3": "noise not measured", "grazing-101": "within noise"}
    splits = {"shop_window-0": "tuning", "curved-2": "tuning", "shop_window-1": "seen", "car-3": "seen",
              "grazing-101": "held out"}
    for scene, (gap, noise) in built.items():
        row = _md_row(section, f"| {scene} | ")
        kind, seed = scene.rsplit("-", 1)
        assert row[1:4] == [kind, seed, splits[scene]]
        assert float(row[4]) == pytest.approx(gap, abs=0.005)
        assert row[5] == ("-" if noise is None else f"{noise:.3f}") and row[6] == verdicts[scene]
        assert float(row[10]) == pytest.approx(gap, abs=0.005)  # the reflection layer's gap
        if scene == "shop_window-0":  # the finished run at 2DGS's time, with the main method's seed noise
            assert float(row[-4]) == pytest.approx(0.7, abs=0.005) and row[-3:-1] == [f"{noise:.3f}", "better"]
        else:
            assert row[-4:-1] == ["-", "-" if noise is None else f"{noise:.3f}", "-"]
        strength = row[-1]  # PSNR of no reflection against the true (flat) one: -20 log10(value)
        if scene in reflected:
            assert float(strength) == pytest.approx(-20 * np.log10(reflected[scene] / 255), abs=0.01)
        else:
            assert strength == "-"
    assert _md_row(section, "| 3 | ") == ["3", "-1.00", "0.000"]  # stronger reflection, larger gap, in rank
    tuning = _md_row(section, "| tuning | transparent |")
    assert tuning[2:] == ["2", "+0.50", "-1.00 (curved-2)", "1", "1", "0", "0"]
    seen = _md_row(section, "| seen (former held-out seeds 1, 3) | transparent |")
    assert seen[2:] == ["2", "+0.30", "+0.10 (shop_window-1)", "0", "0", "1", "1"]
    at_equal_time = _md_row(section, "| tuning | transparent, finished run at 2DGS's time |")
    assert at_equal_time[2:] == ["1", "+0.70", "+0.70 (shop_window-0)", "1", "0", "0", "0"]
    held = _md_row(section, "| held out (seeds 100-103) | transparent |")
    assert held[2:] == ["1", "+0.30", "+0.30 (grazing-101)", "0", "0", "1", "0"]
    # the section says which decisions used the seen scenes, and that no decision uses the held-out ones
    assert "model.shade_coverage came from diagnosing curved-3, car-3 and grazing-1" in section
    assert "losses.mask_coverage_weight" in section and "checked_mask_roi" in section
    assert "no default, threshold or rule is chosen from them" in section
    assert (report.parent / "family_psnr_transparent.png").is_file()
    plain = build_report(copy, tmp_path / "plain").with_suffix(".md").read_text()
    assert "Scene family" not in plain  # no main method: nothing to compare
