"""The report's convergence section, from runs at 1x to 8x the demo budget built on disk as `rtsplat train` and
`rtsplat metrics` write them (summary.json, train_log.jsonl, metrics/<method>.json), with test PSNR curves that
flatten at known budgets, read through the `rtsplat report` CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rtsplat.config import load_config, roles_json
from rtsplat.io.images import write_png
from rtsplat.report import Roles, build_report
from rtsplat.report_convergence import series_at

ROOT = Path(__file__).resolve().parent.parent
VIEWS = ("test_000", "test_001")
DEMO_ITERATIONS, EVAL_EVERY = 600, 100
CPU_SECONDS = {"rtsplat": 200.0, "2dgs": 100.0}  # training CPU seconds per 1x of the budget

# scene -> method -> budget -> (test PSNR entire, transparent, reflection layer, transmission layer)
CURVES = {
    "shop_window-0": {  # rtsplat converges at 4x (2x -> 4x still +0.30 transparent), 2dgs at 2x
        "rtsplat": {1: (30.00, 29.00, 20.0, 24.0), 2: (30.60, 29.80, 21.0, 24.5), 4: (30.65, 30.10, 22.0, 25.0),
                    8: (30.70, 30.15, 22.5, 25.2)},
        "2dgs": {1: (29.50, 28.00, 17.0, 21.0), 2: (29.80, 28.20, 17.1, 21.2), 4: (29.85, 28.25, 17.1, 21.3),
                 8: (29.83, 28.27, 17.2, 21.3)},
    },
    "car-0": {  # rtsplat still gains 0.30 dB per doubling at 8x; 2dgs flat from 1x on
        "rtsplat": {1: (25.00, 24.00, 19.0, 22.0), 2: (25.30, 24.30, 19.5, 22.5), 4: (25.60, 24.60, 20.0, 23.0),
                    8: (25.90, 24.90, 20.5, 23.5)},
        "2dgs": {1: (25.00, 23.50, 16.0, 20.0), 2: (25.05, 23.52, 16.0, 20.0), 4: (25.07, 23.53, 16.0, 20.0),
                 8: (25.08, 23.55, 16.0, 20.0)},
    },
}


def _name(method: str, budget: int) -> str:
    return method if budget == 1 else f"{method}_x{budget}"


def write_run(results: Path, scene: str, run: str, budget: float, values: tuple, cpu_seconds: float) -> None:
    """A finished run: its summary, a training log with an evaluation every EVAL_EVERY x budget iterations
    (climbing to the final values), and its metrics over VIEWS."""
    psnr, transparent, reflection, transmission = values
    folder = results / scene / "runs" / run
    folder.mkdir(parents=True)
    iterations = round(DEMO_ITERATIONS * budget)
    (folder / "summary.json").write_text(json.dumps({
        "iterations": iterations, "train_seconds": 1.2 * cpu_seconds, "train_cpu_seconds": cpu_seconds,
        "threads": 1, "device": "cpu", "surfels": 20000, "test_psnr": psnr, "test_psnr_transparent": transparent}))
    steps = range(0, iterations + 1, round(EVAL_EVERY * budget))
    (folder / "train_log.jsonl").write_text("".join(json.dumps({
        "iteration": i, "seconds": 1.2 * cpu_seconds * i / iterations, "cpu_seconds": cpu_seconds * i / iterations,
        "test_psnr": psnr - 5 * (1 - i / iterations), "test_psnr_transparent": transparent - 5 * (1 - i / iterations),
    }) + "\n" for i in steps))
    (folder / "config.json").write_text(json.dumps({"seed": 0, "schedule": {"iterations": iterations}}))
    mean = {"psnr": psnr, "psnr_transparent": transparent, "psnr_reflection_layer": reflection,
            "psnr_transmission_layer": transmission}
    metrics = results / scene / "metrics"
    metrics.mkdir(parents=True, exist_ok=True)
    (metrics / f"{run}.json").write_text(json.dumps({"split": "test", "mean": mean,
                                                     "views": {v: mean for v in VIEWS}, "lpips": "not computed"}))


LOW, HIGH = 51 / 255, 153 / 255  # the true reflection: two flat halves, its mean colour 102/255 between them


def write_true_layers(prepared: Path) -> None:
    """Ground-truth layers of the test views: a reflection of two halves LOW and HIGH inside a full mask, which
    the flat reference (its mean colour) misses by 51/255 everywhere: -10 log10((51/255)^2) = 13.98 dB."""
    for view in VIEWS:
        reflection = np.full((16, 20, 3), LOW, np.float32)
        reflection[:, 10:] = HIGH
        write_png(prepared / "gt_layers" / "reflection" / f"{view}.png", reflection)
        write_png(prepared / "gt_layers" / "transmission" / f"{view}.png", np.zeros_like(reflection))
        write_png(prepared / "images" / f"{view}.png", reflection)
        write_png(prepared / "masks" / f"{view}.png", np.ones((16, 20), np.float32))


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("convergence")
    for scene, curves in CURVES.items():
        for method, curve in curves.items():
            for budget, values in curve.items():
                write_run(root, scene, _name(method, budget), budget, values, CPU_SECONDS[method] * budget)
    # a pair of another kind (the half-size start at the demo's budget): no point of the budget curve
    for method in ("rtsplat", "2dgs"):
        write_run(root, "shop_window-0", f"{method}_halfstart", 1, (1.0, 1.0, 1.0, 1.0), 50.0)
    write_run(root, "case-0", "rtsplat", 1, (26.0, 24.0, 22.0, 23.0), 200.0)  # one budget only: no curve
    write_run(root, "case-0", "2dgs", 1, (25.0, 23.0, 18.0, 21.0), 100.0)
    write_true_layers(root / "shop_window-0" / "prepared")
    return root


def _table(md: str, header_start: str) -> list[dict[str, str]]:
    """The rows of the Markdown table whose header starts with ``header_start``, as {column: cell}."""
    lines = md.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith(header_start))
    header = [c.strip() for c in lines[at].strip("|").split("|")]
    rows = []
    for line in lines[at + 2:]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, [c.strip() for c in line.strip("|").split("|")], strict=True)))
    return rows


def _convergence_roles() -> str:
    """The roles benchmarks/convergence.yaml gives its methods, as the workflow hands them to the report."""
    return roles_json(load_config(ROOT / "benchmarks" / "convergence.yaml"), quote=False)


@pytest.fixture(scope="module")
def report(results, tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("report") / "report"
    done = subprocess.run([sys.executable, "-m", "rtsplat.cli", "report", "--results", str(results), "--out",
                           str(out), "--roles-json", _convergence_roles()], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return (out / "index.md").read_text()


def test_the_gap_is_read_at_the_larger_converged_budget_beside_the_demo_budgets(report):
    section = report.split("## Convergence")[1].split("\n## ")[0]
    assert "less than 0.1 dB of test PSNR per doubling" in section
    rows = {(r["scene"], r["budget"]): r for r in _table(section, "| scene | budget |")}
    assert set(rows) == {("shop_window-0", "1x (demo)"), ("shop_window-0", "4x (converged)"),
                         ("car-0", "1x (demo)"), ("car-0", "8x (largest; not converged)")}  # case-0: one budget
    demo, converged = rows[("shop_window-0", "1x (demo)")], rows[("shop_window-0", "4x (converged)")]
    # rtsplat: 2x -> 4x gained 0.05 entire but 0.30 transparent, 4x -> 8x 0.05 in both; 2dgs: 2x -> 4x 0.05 in both
    assert demo["converged at (rtsplat / 2dgs)"] == converged["converged at (rtsplat / 2dgs)"] == "4x / 2x"
    assert (demo["dPSNR transp."], demo["dPSNR"]) == ("+1.00", "+0.50")
    assert (converged["dPSNR transp."], converged["dPSNR"]) == ("+1.85", "+0.80")  # both runs at 4x
    assert (converged["rtsplat reflection"], converged["rtsplat transmission"]) == ("22.00", "25.00")
    assert (demo["rtsplat training CPU s"], demo["2dgs training CPU s"]) == ("200", "100")
    assert (converged["rtsplat training CPU s"], converged["2dgs training CPU s"]) == ("800", "400")
    assert float(converged["flat reference"]) == pytest.approx(-10 * np.log10((51 / 255) ** 2), abs=0.01)
    # the true reflection blurred by 2 px keeps the two halves apart away from their edge: above the flat colour
    assert float(converged["blurred 2 px reference"]) > float(converged["flat reference"]) + 3
    car = rows[("car-0", "8x (largest; not converged)")]
    assert car["converged at (rtsplat / 2dgs)"] == "not converged by 8x / 1x"
    assert (car["dPSNR transp."], car["dPSNR"]) == ("+1.35", "+0.82")
    assert car["flat reference"] == "-"  # the scene has no ground-truth layers


def test_every_budget_shows_its_psnr_gain_per_doubling_layers_and_time(report):
    section = report.split("## Convergence")[1].split("\n## ")[0]
    rows = {(r["scene"], r["run"]): r for r in _table(section, "| scene | run | budget |")}
    assert "shop_window-0" in {scene for scene, _ in rows} and not {run for _, run in rows} & {
        "rtsplat_halfstart", "2dgs_halfstart"}
    for scene, curves in CURVES.items():
        for method, curve in curves.items():
            for budget, (psnr, transparent, reflection, transmission) in curve.items():
                row = rows[(scene, _name(method, budget))]
                assert row["budget"] == f"{budget}x" and row["iterations"] == str(DEMO_ITERATIONS * budget)
                assert (float(row["PSNR"]), float(row["PSNR transp."])) == (psnr, transparent)
                assert (float(row["reflection"]), float(row["transmission"])) == (reflection, transmission)
                assert float(row["training CPU s"]) == CPU_SECONDS[method] * budget
                if budget > 1:
                    before = curve[budget // 2]
                    assert float(row["gain / doubling"]) == pytest.approx(psnr - before[0], abs=0.006)
                    assert float(row["gain / doubling transp."]) == pytest.approx(transparent - before[1], abs=0.006)
                else:
                    assert row["gain / doubling"] == row["gain / doubling transp."] == "-"
    flat = -10 * np.log10((51 / 255) ** 2)
    assert float(rows[("shop_window-0", "rtsplat_x8")]["reflection - flat"]) == pytest.approx(22.5 - flat, abs=0.01)
    assert rows[("car-0", "rtsplat_x8")]["reflection - flat"] == "-"


def test_a_gain_spread_over_a_skipped_budget_counts_per_doubling(tmp_path):
    """Without the 2x runs, 1x -> 4x is two doublings: shop_window-0's rtsplat gained 1.10 transparent there
    (0.55 per doubling), 4x -> 8x 0.05: converged at 4x; 2dgs's 0.25 over two doublings (0.125) is not enough."""
    copy = tmp_path / "results"
    for method in ("rtsplat", "2dgs"):
        for budget in (1, 4, 8):
            values = CURVES["shop_window-0"][method][budget]
            write_run(copy, "shop_window-0", _name(method, budget), budget, values, CPU_SECONDS[method] * budget)
    md = build_report(copy, tmp_path / "report", roles=Roles.from_dict(json.loads(_convergence_roles())))
    rows = _table(md.with_suffix(".md").read_text(), "| scene | budget |")
    assert [r["converged at (rtsplat / 2dgs)"] for r in rows] == ["4x / 4x", "4x / 4x"]
    assert [r["budget"] for r in rows] == ["1x (demo)", "4x (converged)"]


def test_no_convergence_section_without_a_second_budget(tmp_path):
    copy = tmp_path / "results"
    for method, values in (("rtsplat", (26.0, 24.0, 22.0, 23.0)), ("2dgs", (25.0, 23.0, 18.0, 21.0))):
        write_run(copy, "case-0", method, 1, values, CPU_SECONDS[method])
    md = build_report(copy, tmp_path / "report", roles=Roles.from_dict(json.loads(_convergence_roles())))
    assert "Convergence" not in md.with_suffix(".md").read_text()


def test_equal_time_compares_each_budget_with_the_2dgs_budget_of_the_same_time(report):
    """rtsplat costs twice 2dgs per budget (CPU_SECONDS): its Nx run took as long as 2dgs's 2Nx run, so each gap is
    read at a 2dgs run, and the 8x run, dearer than 2dgs's largest budget, has none."""
    section = report.split("## Convergence")[1].split("\n## ")[0]
    rows = {(r["scene"], r["rtsplat budget"]): r for r in _table(section, "| scene | rtsplat budget |")}
    for scene, curves in CURVES.items():
        for budget in (1, 2, 4):
            row, ours, theirs = rows[(scene, f"{budget}x")], curves["rtsplat"][budget], curves["2dgs"][2 * budget]
            assert row["2dgs budget in that time"] == f"{2 * budget}x"
            assert float(row["dPSNR transp. at equal time"]) == pytest.approx(ours[1] - theirs[1], abs=0.006)
            assert float(row["dPSNR at equal time"]) == pytest.approx(ours[0] - theirs[0], abs=0.006)
        beyond = rows[(scene, "8x")]
        assert beyond["2dgs budget in that time"] == beyond["dPSNR transp. at equal time"] == "-"
    assert not {scene for scene, _ in rows} - set(CURVES)  # case-0 (one budget) and the half-size pair: no rows


def test_the_results_page_keeps_the_convergence_tables(results, tmp_path):
    """`python -m rtsplat.results_page` writes a report's convergence section onto its page, all three tables."""
    from rtsplat.results_page import read_report, results_markdown

    out = tmp_path / "report"
    build_report(results, out, roles=Roles.from_dict(json.loads(_convergence_roles())))
    page = results_markdown(read_report(out), "docs/results_convergence.md")
    section = page.split("## Convergence: RT-Splatting and plain 2DGS at several budgets")[1]
    for header in ("| scene | budget |", "| scene | run | budget |", "| scene | rtsplat budget |"):
        assert _table(section, header), header
    assert {r["run"] for r in _table(section, "| scene | run | budget |")} >= {"rtsplat_x8", "2dgs_x8"}


def test_no_equal_time_gap_where_a_larger_2dgs_budget_took_no_longer(tmp_path):
    """2dgs's 2x run timed at its 1x run's seconds (a run beside heavy load): its series has no time axis."""
    copy = tmp_path / "results"
    for method in ("rtsplat", "2dgs"):
        for budget in (1, 2):
            seconds = 100.0 if method == "2dgs" else CPU_SECONDS[method] * budget / 2
            write_run(copy, "car-0", _name(method, budget), budget, CURVES["car-0"][method][budget], seconds)
    md = build_report(copy, tmp_path / "report", roles=Roles.from_dict(json.loads(_convergence_roles())))
    rows = _table(md.with_suffix(".md").read_text(), "| scene | rtsplat budget |")
    assert [r["rtsplat budget"] for r in rows] == ["1x", "2x"]
    assert {r["dPSNR transp. at equal time"] for r in rows} == {r["2dgs budget in that time"] for r in rows} == {"-"}


def test_a_series_is_read_linearly_in_log_time_and_never_beyond_its_runs():
    series = [(100.0, 20.0), (400.0, 22.0), (800.0, 22.5)]
    assert series_at(series, 200.0) == pytest.approx(21.0)  # one of two doublings from 100 s to 400 s
    assert series_at(series, 400.0) == pytest.approx(22.0)
    assert series_at(series, 800.0 / 2 ** 0.5) == pytest.approx(22.25)
    assert series_at(series, 99.0) is None and series_at(series, 801.0) is None and series_at(series, None) is None
    assert series_at([(100.0, 20.0), (400.0, None)], 200.0) is None
