"""``rtsplat report``: the benchmark report, ``index.html`` plus a Markdown twin ``index.md``, and its
tables as data in ``report.json`` with the code and the machines that trained the runs (from which
``python -m rtsplat.results_page`` writes ``docs/results.md``).

It reads what the other stages wrote under ``--results`` (the layout of ``docs/architecture.md``)::

    <scene>/runs/<method>/{summary.json, train_log.jsonl, config.json}    rtsplat train
    <scene>/renders/<method>/{render.json, color/, reflection/, ...}       rtsplat render
    <scene>/renders/<method>@<edit>/                                       rtsplat render --edit ...
    <scene>/fps/<method>.json                                              rtsplat fps (timed alone)
    <scene>/videos/<method>.{mp4,png}                                      rtsplat video (and its poster)
    <scene>/metrics/<method>.json                                          rtsplat metrics
    <scene>/sfm/summary.json                                               rtsplat sfm
    <scene>/masks/summary.json                                             rtsplat masks
    <scene>/prepared/scene.json                                            rtsplat prepare

Each method's role comes from the pipeline config (``methods.<name>.role``, see
:func:`rtsplat.config.method_roles`), handed over as ``--roles-json``; without it every method is a
baseline and there is no main method. The report opens with what trained the runs: the one commit and
machine, or, when the runs mix commits, trees with uncommitted changes or machines, sentences that say so
(:mod:`rtsplat.provenance`, from each run's ``summary.json``). Then a summary across scenes (the
:func:`comparison_pairs`: the main method minus the baseline ``2dgs``, and ``<main>_<suffix>`` minus
``2dgs_<suffix>``, PSNR on the transparent region and the entire image, beside the seed noise that
repeats with another seed measured), the scene family when there is one, the convergence of both methods over
the budgets that ran (:mod:`rtsplat.report_convergence`: the gap and the layers at the demo budget and at
convergence, with the time each took) when a scene has more than one, then the provenance of every run
(commit, machine, device, packages; and the code that computed the metrics). Per scene: the SfM
table (registered/total views, reprojection error and time of every attempt, and for scenes whose
dataset ships reference cameras the rotation and centre errors after a similarity fit), the transparent masks
(:func:`_masks_section`: where they came from, given, segmented, or propagated from how many marked views, the
polarity decision and its warning, the prepare stage's warning when it did not use the masks' region of interest,
and the masks of three photos tinted over them), the
quality table (entire
image / transparent region), the time table (FPS timed alone, training CPU and wall seconds and how busy the
other cores were meanwhile), the ablation table (the ablations against the main
method), decomposition scores when the scene has ground-truth layers, the accuracy-against-time
plots and table with the Pareto front (every run's final test PSNR against its training time, and
the test-PSNR curves logged during training; the time is :func:`time_measure`: the training steps' CPU
seconds where every run trained on the CPU and recorded them, which depend little on the jobs that ran
beside a run, else their wall seconds), one test view (the first with ground-truth layers, if
any): ground truth / main / the other methods except ablations, each method's per-pixel error map
(|render - ground truth| averaged over channels, viridis from 0 to :data:`ERROR_MAP_MAX`), the main
method's decomposition, its reflection and colour - reflection next to the ground-truth layers with
their error maps when the prepared scene has them, the editing images, and the camera-path videos
(HTML5 ``<video>`` with the first frame as poster and a download link). Images are nearest-neighbour
upscaled by an integer factor until their shorter side is at least :data:`REPORT_IMAGE_MIN_SIDE` px,
so every pixel stays visible and unblended. After the scenes, the noise: for every repeat (the same
config run again, with the same seed or another one, as its ``config.json`` says) the report prints
the measured differences to the method it repeats, or says that none were measured; last, the exact
commands and the config.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import html
import itertools
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from rtsplat.errors import PipelineError
from rtsplat.io.images import read_image, write_png
from rtsplat.io.outputs import check_output_dir, output_dir
from rtsplat.io.train_log import LOG_NAME, read_log
from rtsplat.layer_references import LAYERS_SUM, ceilings, read_views
from rtsplat.model.composite import transmission_with_scatter
from rtsplat.provenance import commit_label, group_runs, mixture_sentences
from rtsplat.scene import GT_LAYERS_DIR, REFLECTION_REACH_FILE, SCENE_FILE, PreparedScene

ROLES = ("main", "baseline", "ablation", "repeat")
REPORT_JSON = "report.json"  # the report's tables as data, with what trained the runs (rtsplat.results_page)
PLAIN_2DGS = "2dgs"  # the plain-2DGS baseline the summary compares the main method with


@dataclass(frozen=True)
class Roles:
    """Each method's role (``main``, ``baseline``, ``ablation``, ``repeat``), what a repeat reruns and whose
    run's training time a method trained for (``time_of``)."""

    role: dict[str, str] = field(default_factory=dict)
    of: dict[str, str] = field(default_factory=dict)
    time_of: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: dict, source: str = "--roles-json") -> Roles:
        """``{method: {"role": ..., "of": ..., "time_of": ...}}`` as :func:`rtsplat.config.roles_json` writes it."""
        if not isinstance(data, dict):
            raise PipelineError(f"{source} must be a JSON object {{method: {{role, of}}}}")
        role, of, time_of = {}, {}, {}
        for method, entry in data.items():
            entry = entry if isinstance(entry, dict) else {}
            if entry.get("role") not in ROLES:
                raise PipelineError(f"{source}: method {method!r} has role {entry.get('role')!r}",
                                    fix=f"use one of {list(ROLES)}")
            role[method] = entry["role"]
            if entry["role"] == "repeat":
                if not entry.get("of"):
                    raise PipelineError(f"{source}: repeat {method!r} does not say which method it reruns",
                                        fix="give it 'of': <method>")
                of[method] = entry["of"]
            if entry.get("time_of"):
                time_of[method] = entry["time_of"]
        if list(role.values()).count("main") > 1:
            raise PipelineError(f"{source}: more than one method has role main", fix="keep one")
        return cls(role, of, time_of)

    @property
    def main(self) -> str | None:
        return next((m for m, r in self.role.items() if r == "main"), None)

    def of_role(self, runs: dict, role: str) -> list[str]:
        """The methods of ``runs`` with ``role``, sorted by name (unlisted methods are baselines)."""
        return sorted(m for m in runs if self.role.get(m, "baseline") == role)


@dataclass
class Run:
    scene: str
    method: str
    summary: dict = field(default_factory=dict)
    log: list[dict] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    fps: dict = field(default_factory=dict)  # rtsplat fps: the FPS timed in a job of its own

    @property
    def mean(self) -> dict:
        return self.metrics.get("mean", {})

    def seconds(self, measure: TimeMeasure) -> float | None:
        value = self.summary.get(measure.key)
        return float(value) if isinstance(value, (int, float)) and value > 0 else None


@dataclass(frozen=True)
class TimeMeasure:
    """A training time of the runs: its key in summary.json, its key in train_log.jsonl, its label."""

    key: str
    log_key: str
    label: str
    caption: str


CPU_TIME = TimeMeasure(
    "train_cpu_seconds", "cpu_seconds", "training CPU s",
    "Training time: the CPU seconds of the training steps (user + system, all threads of the training "
    "process), which depend little on the jobs that ran beside it (rtsplat/usage.py).")
WALL_TIME = TimeMeasure(
    "train_seconds", "seconds", "training wall s",
    "Training time: the wall seconds of the training steps, which grow with the jobs that ran beside each "
    "run (see 'other cores busy'): not every run trained on the CPU and recorded its CPU seconds.")


def time_measure(runs: dict[str, Run]) -> TimeMeasure:
    """:data:`CPU_TIME` when every run of ``runs`` trained on the CPU and recorded its CPU seconds, else
    :data:`WALL_TIME` (a GPU run's CPU seconds count only the host's part of the work)."""
    on_cpu = all(r.summary.get("device", "cpu") == "cpu" and r.seconds(CPU_TIME) is not None for r in runs.values())
    return CPU_TIME if on_cpu else WALL_TIME


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PipelineError(f"cannot read ({exc})", path=path, fix="rerun the stage that writes it") from None


def _note(message: str) -> None:
    print(f"rtsplat report: {message}", file=sys.stderr)


def collect(results: Path, note: Callable[[str], None] = _note) -> dict[str, dict[str, Run]]:
    """{scene: {method: Run}} for every run that has a summary (finished training); what was dropped from a
    training log (:func:`rtsplat.io.train_log.read_log`) is said through ``note``."""
    scenes: dict[str, dict[str, Run]] = {}
    for summary in sorted(results.glob("*/runs/*/summary.json")):
        run_dir = summary.parent
        scene, method = run_dir.parent.parent.name, run_dir.name
        run = Run(scene, method, summary=_read_json(summary))
        log = run_dir / LOG_NAME
        if log.is_file():
            run.log = [record for record, _ in read_log(log, note)]
        metrics = results / scene / "metrics" / f"{method}.json"
        if metrics.is_file():
            run.metrics = _read_json(metrics)
        fps = results / scene / "fps" / f"{method}.json"
        if fps.is_file():
            run.fps = _read_json(fps)
        scenes.setdefault(scene, {})[method] = run
    if not scenes:
        raise PipelineError("no finished training runs found (no <scene>/runs/<method>/summary.json)", path=results,
                            fix="run the workflow (snakemake) or `rtsplat train` first")
    return scenes


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """For (time, quality) points: True where no other point is at least as fast AND at least as good
    with one of the two strictly better."""
    flags = []
    for i, (t, q) in enumerate(points):
        dominated = any((t2 <= t and q2 >= q and (t2 < t or q2 > q)) for j, (t2, q2) in enumerate(points) if j != i)
        flags.append(not dominated)
    return flags


def _signed(value: float | None) -> str:
    """A difference with its sign and two decimals; "-" for None."""
    return "-" if value is None else f"{value:+.2f}"


def _fmt(value, digits: int = 2) -> str:
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value)
    if isinstance(value, (int, float)):
        return f"{value:.{digits}f}"
    return str(value)


class Document:
    """Builds the HTML and the Markdown twin side by side."""

    def __init__(self, title: str):
        self.title = title
        self.headings: list[str] = []  # the headings above the current point, one per level from 2
        self.tables: list[dict] = []  # every table with the headings it is under (report.json)
        self.html = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
                     "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:"
                     "collapse}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
                     "td:first-child{text-align:left}img,video{max-width:100%}.pareto{font-weight:bold}</style>"
                     "</head><body>", f"<h1>{html.escape(title)}</h1>"]
        self.md = [f"# {title}", ""]

    def heading(self, text: str, level: int = 2) -> None:
        self.headings = self.headings[:max(level - 2, 0)] + [text]
        self.html.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.md += ["#" * level + " " + text, ""]

    def paragraph(self, text: str) -> None:
        self.html.append(f"<p>{html.escape(text)}</p>")
        self.md += [text, ""]

    def code(self, text: str) -> None:
        self.html.append(f"<pre>{html.escape(text)}</pre>")
        self.md += ["```", text, "```", ""]

    def table(self, header: list[str], rows: list[list[str]]) -> None:
        self.tables.append({"headings": list(self.headings), "header": list(header), "rows": [list(r) for r in rows]})
        self.html.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
        for row in rows:
            self.html.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>")
        self.html.append("</table>")
        self.md += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        self.md += ["| " + " | ".join(row) + " |" for row in rows]
        self.md.append("")

    def images(self, items: list[tuple[str, str]]) -> None:
        """(relative path, caption) shown in one row."""
        cells = "".join(f"<figure style='display:inline-block;margin:4px'><img src='{html.escape(p)}'>"
                        f"<figcaption>{html.escape(c)}</figcaption></figure>" for p, c in items)
        self.html.append(f"<div>{cells}</div>")
        self.md += [" ".join(f"![{c}]({p})" for p, c in items), ""]

    def video(self, video: str, poster: str | None, caption: str) -> None:
        """An HTML5 video (relative path) with its poster frame, a caption and a download link; in Markdown the
        poster linking to the video."""
        poster_attr = f" poster='{html.escape(poster)}'" if poster else ""
        self.html.append(f"<figure style='margin:4px'><video controls loop muted playsinline preload='metadata'"
                         f"{poster_attr}><source src='{html.escape(video)}' type='video/mp4'></video>"
                         f"<figcaption>{html.escape(caption)} (<a href='{html.escape(video)}' download>download "
                         "MP4</a>)</figcaption></figure>")
        self.md += [f"[![{caption}]({poster})]({video})" if poster else f"[{caption}]({video})", ""]

    def finish(self) -> tuple[str, str]:
        return "\n".join(self.html + ["</body></html>"]) + "\n", "\n".join(self.md) + "\n"


QUALITY_HEADER = ["method", "PSNR", "SSIM", "LPIPS", "PSNR (transp.)", "SSIM (transp.)", "LPIPS (transp.)",
                  "surfels"]
TIME_HEADER = ["method", "FPS alone", "FPS threads", "FPS: other cores busy", "training CPU s", "training wall s",
               "training: other cores busy", "training CPU share"]
TIME_CAPTION = (
    "FPS alone: the test views' renders timed by `rtsplat fps` in a job that the workflow ran with nothing beside "
    "it (it holds all of the run's cores and renders on as many threads), frames per wall second; '-' where no "
    "such timing exists or it did not run alone. Training CPU s: the CPU seconds of the training steps (all "
    "threads), which depend little on what ran beside the run; training wall s: the same steps' wall seconds, "
    "which do. Other cores busy: the mean number of cores that other processes (of this workflow or not) kept "
    "busy while the FPS was timed or the run trained (0: nothing beside it, 1: about one single-threaded job "
    "beside it all the time). CPU share: CPU seconds / (wall seconds x threads) of the training steps, below 1 "
    "where the run waited for a core.")


def fps_alone(run: Run) -> tuple[float | None, dict]:
    """The run's FPS from ``rtsplat fps`` and its timing record when that job was scheduled alone, else
    (None, {})."""
    timing = run.fps.get("timing", {})
    if not timing.get("scheduled_alone") or not isinstance(run.fps.get("fps"), (int, float)):
        return None, {}
    return float(run.fps["fps"]), timing


def _methods_in_order(runs: dict[str, Run], main: str | None) -> list[str]:
    return sorted(runs, key=lambda m: (m != main, m))


def quality_rows(runs: dict[str, Run], main: str | None = None) -> list[list[str]]:
    rows = []
    for method in _methods_in_order(runs, main):
        r = runs[method]
        m = r.mean
        split = r.metrics.get("split", "test")
        label = method if split == "test" else f"{method} [{split} views]"
        rows.append([label] + [_fmt(m.get(k), d) for k, d in (
            ("psnr", 2), ("ssim", 3), ("lpips", 3), ("psnr_transparent", 2), ("ssim_transparent", 3),
            ("lpips_transparent", 3))] + [_fmt(r.summary.get("surfels"), 0)])
    return rows


def time_rows(runs: dict[str, Run], main: str | None = None) -> list[list[str]]:
    """One row of :data:`TIME_HEADER` per run."""
    rows = []
    for method in _methods_in_order(runs, main):
        r = runs[method]
        fps, timing = fps_alone(r)
        training = r.summary.get("run_usage") or {}
        rows.append([method, _fmt(fps, 1), _fmt(timing.get("threads"), 0), _fmt(timing.get("other_busy_cores"), 2),
                     _fmt(r.seconds(CPU_TIME), 1), _fmt(r.seconds(WALL_TIME), 1),
                     _fmt(training.get("other_busy_cores"), 2), _fmt(r.summary.get("cpu_share"), 2)])
    return rows


def time_points(runs: dict[str, Run], key: str, measure: TimeMeasure) -> list[tuple[str, float, float]]:
    """(method, training seconds by ``measure``, test metric) of every run with both."""
    points = []
    for method, r in runs.items():
        value = r.mean.get(key, r.summary.get("test_" + key))
        seconds = r.seconds(measure)
        if isinstance(value, float) and seconds:
            points.append((method, seconds, value))
    return points


def plot_accuracy_time(scene: str, runs: dict[str, Run], out: Path) -> list[str]:
    """One PNG per quality key; returns the file names written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    measure = time_measure(runs)
    for key, label in (("psnr", "PSNR entire image (dB)"), ("psnr_transparent", "PSNR transparent region (dB)")):
        points = time_points(runs, key, measure)
        if not points:
            continue
        fig, ax = plt.subplots(figsize=(8, 5))
        # 20 colours x 3 line styles: the curves of a report with every budget and ablation stay distinct
        styles = [(colour, line) for line in ("-", "--", ":") for colour in plt.get_cmap("tab20").colors]
        for i, (method, r) in enumerate(sorted(runs.items())):
            # the evaluation before the first step (0 s) has no place on the log time axis
            curve = [(e[measure.log_key], e[f"test_{key}"]) for e in r.log
                     if f"test_{key}" in e and (e.get(measure.log_key) or 0) > 0]
            if len(curve) > 1:
                colour, line = styles[i % len(styles)]
                ax.plot(*zip(*curve, strict=True), linestyle=line, color=colour, alpha=0.7,
                        label=f"{method} (during training)")
        flags = pareto_front([(t, q) for _, t, q in points])
        front = sorted((t, q) for (_, t, q), f in zip(points, flags, strict=True) if f)
        for (method, t, q), on_front in zip(points, flags, strict=True):
            ax.plot(t, q, "o" if on_front else "x", color="k")
            ax.annotate(method, (t, q), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if front:
            ax.step(*zip(*front, strict=True), where="post", color="r", lw=1, label="Pareto front (final runs)")
        ax.set_xscale("log")  # budgets of 1x to 16x the demo's: equal steps per doubling
        ax.margins(x=0.15)  # room on the right for the names of the longest runs
        ax.set_xlabel(f"{measure.label} (log scale)")
        ax.set_ylabel(label)
        ax.set_title(f"{scene}: accuracy against {measure.label}")
        ax.grid(alpha=0.3)
        # beside the axes, not on them: the curves end in the top right, where a legend inside would sit
        ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
        name = f"{scene}_{key}_vs_time.png"
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(fig)
        written.append(name)
    return written


REPORT_IMAGE_MIN_SIDE = 300  # px: images in the report are upscaled until their shorter side reaches this
ERROR_MAP_MAX = 0.25  # |render - ground truth| (mean over channels) at the top of the error maps' colour map
ERROR_COLOUR_MAP = "viridis"


def upscale_factor(height: int, width: int, min_side: int = REPORT_IMAGE_MIN_SIDE) -> int:
    """The smallest integer factor that makes the shorter side at least ``min_side`` (1 when it already is)."""
    return max(1, -(-min_side // max(1, min(height, width))))


def nearest_upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Every pixel repeated ``factor`` x ``factor`` times (nearest neighbour: no pixel value is invented)."""
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def error_map(render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``|render - target|`` averaged over channels, through the fixed colour map (0 to
    :data:`ERROR_MAP_MAX`, larger errors clipped): RGB float32 ``[H, W, 3]`` in [0, 1]."""
    import matplotlib

    error = np.abs(render.astype(np.float32) - target.astype(np.float32)).mean(axis=2)
    colours = matplotlib.colormaps[ERROR_COLOUR_MAP](np.clip(error / ERROR_MAP_MAX, 0.0, 1.0))
    return colours[..., :3].astype(np.float32)


def _write_image(image: np.ndarray, out: Path, name: str) -> str:
    """Write ``image`` (float [0, 1]) into the report's images/ as an 8-bit PNG, nearest-upscaled by
    :func:`upscale_factor`; returns its path relative to the report."""
    (out / "images").mkdir(exist_ok=True)
    write_png(out / "images" / name, nearest_upscale(image, upscale_factor(*image.shape[:2])))
    return f"images/{name}"


def _copy_image(src: Path, out: Path, name: str) -> str | None:
    """A copy of the image ``src`` in the report (see :func:`_write_image`), None when there is no such file."""
    if not src.is_file():
        return None
    return _write_image(read_image(src), out, name)


def _same_size(image: np.ndarray, reference: np.ndarray, path: Path) -> None:
    if image.shape != reference.shape:
        raise PipelineError(f"image is {image.shape[1]}x{image.shape[0]}, its ground truth "
                            f"{reference.shape[1]}x{reference.shape[0]}", path=path,
                            fix="render from the prepared scene the metrics and the report read")


def _error_image(render_path: Path, target: np.ndarray, out: Path, name: str) -> str | None:
    """The error map of the image ``render_path`` against ``target`` in the report, None without the file."""
    if not render_path.is_file():
        return None
    render = read_image(render_path)
    _same_size(render, target, render_path)
    return _write_image(error_map(render, target), out, name)


def comparison_pairs(methods, roles: Roles) -> list[tuple[str, str]]:
    """(RT-Splatting run, plain 2DGS run) pairs with the same budget among ``methods``: the main method
    against the baseline ``2dgs``, for every baseline ``2dgs_<suffix>`` the method ``<main>_<suffix>``
    against it (e.g. ``rtsplat_x4`` against ``2dgs_x4``), where both exist, and every baseline ``<main>_...``
    that trained for the time of one of those 2DGS runs (``time_of``) against that run: the comparison at
    equal time between finished runs."""
    main, methods = roles.main, set(methods)
    if main is None:
        return []

    def baseline(m: str) -> bool:
        return m in methods and roles.role.get(m, "baseline") == "baseline"

    pairs = [(main, PLAIN_2DGS)] if main in methods and baseline(PLAIN_2DGS) else []
    for other in sorted(methods):
        suffix = other[len(PLAIN_2DGS) + 1:]
        if other.startswith(PLAIN_2DGS + "_") and suffix and baseline(other) and baseline(f"{main}_{suffix}"):
            pairs.append((f"{main}_{suffix}", other))
    paired, twodgs = {ours for ours, _ in pairs}, {theirs for _, theirs in pairs}
    for ours in sorted(methods - paired):
        if ours.startswith(main + "_") and baseline(ours) and roles.time_of.get(ours) in twodgs:
            pairs.append((ours, roles.time_of[ours]))
    return pairs


def ablation_reference(ablation: str, methods, roles: Roles) -> str | None:
    """The full-model run an ablation is compared with: the baseline ``<main>_<suffix>`` for an ablation
    whose name ends with ``_<suffix>`` (``ablation_gating_x4`` against ``rtsplat_x4``, the same budget), else
    the main method; None when that run is not among ``methods``."""
    main, methods = roles.main, set(methods)
    if main is None:
        return None
    for other in sorted(methods, key=len, reverse=True):  # the longest suffix that fits
        suffix = other[len(main):]
        if (other.startswith(main + "_") and roles.role.get(other, "baseline") == "baseline"
                and ablation.endswith(suffix)):
            return other
    return main if main in methods else None


def _difference(a, b) -> float | None:
    return a - b if isinstance(a, float) and isinstance(b, float) else None


REPEAT_KEYS = ("psnr", "psnr_transparent", "psnr_reflection_layer", "psnr_transmission_layer")


def _repeat_differences(scene: str, runs: dict[str, Run], roles: Roles, results: Path) -> list[dict]:
    """For every repeat of the scene whose method ran: what it reruns, whether with the same seed, and
    |difference| of PSNR (:data:`REPEAT_KEYS`: entire, transparent, each layer against the ground truth) and
    relative training time to that method."""
    found = []
    for method in roles.of_role(runs, "repeat"):
        r, base_name = runs[method], roles.of[method]
        if base_name not in runs:
            continue
        base = runs[base_name]
        seed, base_seed = (_run_seed(results / scene / "runs" / m) for m in (method, base_name))
        diffs = {key: _difference(base.mean.get(key), r.mean.get(key)) for key in REPEAT_KEYS}
        measure = time_measure({base_name: base, method: r})
        ta, tb = base.seconds(measure), r.seconds(measure)
        found.append({"method": method, "of": base_name, "seed": seed, "same_seed": seed == base_seed,
                      **{key: None if d is None else abs(d) for key, d in diffs.items()},
                      "time_percent": 100 * abs(ta - tb) / max(ta, 1e-9) if ta and tb else None})
    return found


def interpolate_between(points: list[tuple[float, float | None]], x: float, log_axis: bool = False) -> float | None:
    """The value at ``x`` of ``points`` (``(position, value)`` by increasing position), linear between the two
    points around it (in log2 of the position with ``log_axis``); None outside the points (no extrapolation)
    or where a point around it has no value."""
    for (t0, v0), (t1, v1) in itertools.pairwise(points):
        if t0 <= x <= t1 and v0 is not None and v1 is not None:
            if t1 == t0:
                return v0
            share = math.log2(x / t0) / math.log2(t1 / t0) if log_axis else (x - t0) / (t1 - t0)
            return v0 + share * (v1 - v0)
    return None


def psnr_at_time(run: Run, seconds: float, key: str, measure: TimeMeasure) -> float | None:
    """The run's test PSNR ``key`` (``test_psnr``, ``test_psnr_transparent``) after ``seconds`` of training by
    ``measure``, read from its log's evaluations (iteration 0: the initialisation), linearly between the two
    around it; the last one from its time on. None without evaluations up to that time."""
    points = sorted((float(r[measure.log_key]), float(r[key])) for r in run.log
                    if isinstance(r.get(key), (int, float)) and isinstance(r.get(measure.log_key), (int, float)))
    if not points or points[0][0] > seconds:
        return None
    if seconds >= points[-1][0]:
        return points[-1][1]
    return interpolate_between(points, seconds)


def equal_time_gap(ours: Run, theirs: Run, key: str, measure: TimeMeasure) -> float | None:
    """Test PSNR ``key`` of ``ours`` minus that of ``theirs``, both read from their logs
    (:func:`psnr_at_time`) at the training time of the shorter run: the gap a user with that much time sees."""
    times = [ours.seconds(measure), theirs.seconds(measure)]
    if None in times:
        return None
    at = min(times)
    return _difference(psnr_at_time(ours, at, key, measure), psnr_at_time(theirs, at, key, measure))


def summary_rows(scene: str, runs: dict[str, Run], roles: Roles, results: Path) -> list[list[str]]:
    """One row per :func:`comparison_pairs` pair of the scene: the PSNR gaps (transparent region, entire
    image), beside them the largest |dPSNR| of a repeat of either method with another seed, then the gaps
    at equal training time (:func:`equal_time_gap`) and the ratio of the two runs' training times."""
    repeats = [d for d in _repeat_differences(scene, runs, roles, results) if not d["same_seed"]]
    measure = time_measure(runs)
    rows = []
    for ours, theirs in comparison_pairs(runs, roles):
        noise = [d for d in repeats if d["of"] in (ours, theirs)]
        row = [scene, f"{ours} - {theirs}"]
        for key in ("psnr_transparent", "psnr"):
            gap = _difference(runs[ours].mean.get(key), runs[theirs].mean.get(key))
            row.append(_signed(gap))
        for key in ("psnr_transparent", "psnr"):
            measured = [d[key] for d in noise if d[key] is not None]
            row.append(_fmt(max(measured), 3) if measured else "not measured")
        row.append(", ".join(d["method"] for d in noise) or "-")
        for key in ("test_psnr_transparent", "test_psnr"):
            gap = equal_time_gap(runs[ours], runs[theirs], key, measure)
            row.append(_signed(gap))
        a, b = runs[ours].seconds(measure), runs[theirs].seconds(measure)
        row.append(f"{a / b:.2f}x" if a and b else "-")
        rows.append(row)
    return rows


EQUAL_TIME_KEY = "psnr_transparent_equal_time"  # the transparent gap of the run at 2DGS's time (equal_time_run)
FAMILY_KEYS = (("psnr_transparent", "transparent"), ("psnr", "entire"),
               ("psnr_reflection_layer", "reflection layer"), ("psnr_transmission_layer", "transmission layer"),
               (EQUAL_TIME_KEY, "transparent, finished run at 2DGS's time"))
FAMILY_SIGNIFICANCE = 2.0  # a gap is significant beyond this many times its seed noise
def _family_splits() -> tuple[tuple[str, str], ...]:
    """Each split of the family (:attr:`rtsplat.synth.family.Member.split`) with its label."""
    from rtsplat.synth.family import HELD_OUT_SEEDS, SEEN_SEEDS

    seeds = ", ".join(map(str, SEEN_SEEDS))
    return (("tuning", "tuning"), ("seen", f"seen (former held-out seeds {seeds})"),
            ("held_out", f"held out (seeds {HELD_OUT_SEEDS[0]}-{HELD_OUT_SEEDS[-1]})"))


@dataclass
class FamilyScene:
    """The main method minus plain 2DGS on one scene of the generated family, with the seed noise."""

    scene: str
    kind: str
    seed: int
    split: str  # tuning, seen or held_out (rtsplat.synth.family.Member.split)
    gap: dict  # FAMILY_KEYS key -> dPSNR (None where a run lacks it)
    noise: dict  # key -> largest |dPSNR| of a repeat of either run with another seed (None: not measured)
    no_reflection_psnr: float | None = None  # how little the glass reflects (see family_scenes)

    def verdict(self, key: str) -> str:
        """``better``, ``worse`` (beyond :data:`FAMILY_SIGNIFICANCE` x the seed noise), ``within noise``,
        ``noise not measured`` or ``-`` (no gap)."""
        gap, noise = self.gap.get(key), self.noise.get(key)
        if gap is None:
            return "-"
        if noise is None:
            return "noise not measured"
        if abs(gap) > FAMILY_SIGNIFICANCE * noise:
            return "better" if gap > 0 else "worse"
        return "within noise"


def family_scenes(scenes: dict[str, dict[str, Run]], roles: Roles, results: Path,
                  references: dict[str, dict[str, float] | None]) -> list[FamilyScene]:
    """The scenes of the generated family (:mod:`rtsplat.synth.family`; dataset folders named
    ``<kind>-<seed>``) on which the main method and plain 2DGS both ran, in name order. ``references``: each
    scene's :func:`scene_layer_references`, whose ``zero`` row tells how strongly its glass reflects (the PSNR of no
    reflection at all against the true reflection inside the mask; the lower, the more of the glass's light is
    reflection)."""
    from rtsplat.synth.family import parse_name

    main, found = roles.main, []
    for scene in sorted(scenes):
        runs = scenes[scene]
        try:
            member = parse_name(scene)
        except ValueError:
            continue
        if main not in runs or PLAIN_2DGS not in runs:
            continue
        repeats = [d for d in _repeat_differences(scene, runs, roles, results)
                   if not d["same_seed"] and d["of"] in (main, PLAIN_2DGS)]
        gap, noise = {}, {}
        equal_time = equal_time_run(runs, roles)
        for key, _ in FAMILY_KEYS:
            ours, metric = (equal_time, "psnr_transparent") if key == EQUAL_TIME_KEY else (main, key)
            gap[key] = _difference(runs[ours].mean.get(metric), runs[PLAIN_2DGS].mean.get(metric)) if ours else None
            measured = [d[metric] for d in repeats if d.get(metric) is not None]
            noise[key] = max(measured) if measured else None
        reference = references.get(scene)
        found.append(FamilyScene(scene, member.kind, member.seed, member.split, gap, noise,
                                 reference["zero"] if reference else None))
    return found


def equal_time_run(runs: dict[str, Run], roles: Roles) -> str | None:
    """The main method's run that trained for the time of the plain 2DGS run (``time_of``; the first by name),
    or None: the comparison of finished runs at equal time."""
    return next((ours for ours, theirs in comparison_pairs(runs, roles)
                 if theirs == PLAIN_2DGS and roles.time_of.get(ours) == PLAIN_2DGS), None)


def family_reflection_correlation(family: list[FamilyScene]) -> tuple[int, float, float] | None:
    """(scenes, Spearman's rho, its p-value) between the scenes' no-reflection PSNR and their gap on the
    transparent region; None with fewer than three scenes that have both."""
    pairs = [(f.no_reflection_psnr, f.gap["psnr_transparent"]) for f in family
             if f.no_reflection_psnr is not None and f.gap.get("psnr_transparent") is not None]
    if len(pairs) < 3:
        return None
    from scipy.stats import spearmanr

    psnrs, gaps = zip(*pairs, strict=True)
    rho, p = spearmanr(psnrs, gaps)
    return (len(pairs), float(rho), float(p)) if np.isfinite(rho) else None


def family_scene_rows(family: list[FamilyScene]) -> list[list[str]]:
    """One row per scene: kind, seed, split, then per key the gap, its seed noise and the verdict, then the
    scene's no-reflection PSNR."""
    rows = []
    for f in family:
        row = [f.scene, f.kind, str(f.seed), f.split.replace("_", " ")]
        for key, _ in FAMILY_KEYS:
            gap = f.gap.get(key)
            row += [_signed(gap), _fmt(f.noise.get(key), 3), f.verdict(key)]
        rows.append(row + [_fmt(f.no_reflection_psnr)])
    return rows


def family_split_rows(family: list[FamilyScene]) -> list[list[str]]:
    """Per split and key: how many scenes, the median and the worst gap, and how many are significantly
    better or worse, within noise, or without measured noise."""
    rows = []
    for split, label in _family_splits():
        mine = [f for f in family if f.split == split]
        for key, name in FAMILY_KEYS:
            scored = [f for f in mine if f.gap.get(key) is not None]
            if not scored:
                continue
            gaps = [f.gap[key] for f in scored]
            worst = min(scored, key=lambda f: f.gap[key])
            verdicts = collections.Counter(f.verdict(key) for f in scored)
            rows.append([label, name, str(len(scored)), f"{float(np.median(gaps)):+.2f}",
                         f"{worst.gap[key]:+.2f} ({worst.scene})", str(verdicts["better"]), str(verdicts["worse"]),
                         str(verdicts["within noise"]), str(verdicts["noise not measured"])])
    return rows


def plot_family(family: list[FamilyScene], out: Path, key: str = "psnr_transparent") -> str | None:
    """The distribution of the per-scene gaps on ``key``: one column of points per split (colour = kind), each
    with a bar of +-:data:`FAMILY_SIGNIFICANCE` x its seed noise, and the splits' medians. Returns the PNG's name."""
    scored = [f for f in family if f.gap.get(key) is not None]
    if not scored:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rtsplat.synth.family import KINDS

    fig, ax = plt.subplots(figsize=(7, 4.5))
    colours = dict(zip(KINDS, plt.get_cmap("tab10").colors, strict=False))
    offsets = np.linspace(-0.25, 0.25, len(KINDS))
    splits = _family_splits()
    for x, (split, _) in enumerate(splits):
        mine = [f for f in scored if f.split == split]
        for f in mine:
            xi = x + offsets[KINDS.index(f.kind)] + 0.02 * (f.seed % 5)
            bar = None if f.noise.get(key) is None else FAMILY_SIGNIFICANCE * f.noise[key]
            ax.errorbar(xi, f.gap[key], yerr=bar, fmt="o", color=colours.get(f.kind, "k"), ms=5, capsize=2)
        if mine:
            ax.hlines(float(np.median([f.gap[key] for f in mine])), x - 0.35, x + 0.35, color="k", lw=1.5)
    for kind in KINDS:
        ax.plot([], [], "o", color=colours[kind], label=kind)
    ax.plot([], [], "-", color="k", label="median of the split")
    ax.axhline(0.0, color="grey", lw=0.8, ls="--")
    ax.set_xticks(range(len(splits)), [label for _, label in splits], fontsize=7)
    ax.set_xlim(-0.6, len(splits) - 0.4)
    ax.set_ylabel(f"dPSNR {dict(FAMILY_KEYS)[key]} (dB), RT-Splatting - 2DGS")
    ax.set_title(f"Scene family: per-scene gap (bars: +-{FAMILY_SIGNIFICANCE:g} x seed noise)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    name = f"family_{key}.png"
    fig.savefig(out / name, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return name


def _family_section(doc: Document, family: list[FamilyScene], out: Path) -> None:
    from rtsplat.synth.family import HELD_OUT_SEEDS, SEEN_DECISIONS, SEEN_SEEDS

    held, seen = ", ".join(map(str, HELD_OUT_SEEDS)), " and ".join(map(str, SEEN_SEEDS))
    doc.heading("Scene family: RT-Splatting minus plain 2DGS per scene")
    doc.paragraph(
        "The generated glass scenes (`rtsplat synth --scene family/<kind>-<seed>`, docs/synth.md): a scene "
        "whose dataset folder is named `<kind>-<seed>`, labelled by its split (rtsplat/synth/family.py): "
        f"'held out' are the seeds {held} of every kind (benchmarks/heldout.yaml), fixed once and reported only "
        "when an issue's work is done: no default, threshold or rule is chosen from them. 'seen' are the seeds "
        f"{seen}, which were held out once, but decisions used them: {'; '.join(SEEN_DECISIONS)}; their gaps are "
        "no unbiased estimate. 'tuning' are the other seeds, on which defaults and rules are chosen. The splits "
        "are summarised apart. Per scene, PSNR of the main "
        f"method minus PSNR of `{PLAIN_2DGS}` on the test views: the transparent region, the entire image, and "
        "each layer against the ground-truth layers (transparent region), and, where it ran, the transparent "
        "region's gap of the main method's finished run that trained for as long as the 2DGS run took (a method "
        f"with `time_of: {PLAIN_2DGS}`): the comparison at equal time. Beside each gap its seed noise: the "
        "largest |dPSNR| between either run and its repeat with another seed (for the run at 2DGS's time: the "
        "main method's and 2DGS's repeats). A gap is significant when it is "
        f"larger than {FAMILY_SIGNIFICANCE:g} x that noise: 'better' or 'worse'; otherwise 'within noise'.")
    doc.table(["split", "metric", "scenes", "median gap", "worst gap (scene)", "better", "worse", "within noise",
               "noise not measured"], family_split_rows(family))
    name = plot_family(family, out)
    if name:
        doc.images([(name, "per-scene dPSNR on the transparent region, by split")])
    header = ["scene", "kind", "seed", "split"]
    for _, label in FAMILY_KEYS:
        header += [f"d {label}", "noise", "verdict"]
    doc.table(header + ["no-reflection PSNR"], family_scene_rows(family))
    if any(f.no_reflection_psnr is not None for f in family):
        doc.paragraph(
            "How strongly each scene's glass reflects: 'no-reflection PSNR' is the PSNR of no reflection at all "
            "against the true reflection inside the mask (test views); the lower, the more of the glass's light is "
            "reflection, which plain 2DGS can only bake into view-dependent colour. Below (from three such scenes "
            "on), the rank correlation (Spearman) between it and the transparent region's gap over the scenes with "
            "ground-truth layers: a negative rho means that the scenes whose glass reflects more gain more.")
    correlation = family_reflection_correlation(family)
    if correlation:
        scenes, rho, p = correlation
        doc.table(["scenes", "rho (no-reflection PSNR, d transparent)", "p"], [[str(scenes), f"{rho:+.2f}",
                                                                                f"{p:.3f}"]])


def _noise_rows(scene: str, runs: dict[str, Run], roles: Roles, results: Path) -> list[list[str]]:
    """|difference| of each repeat to the method it reruns; the seeds come from the runs' config.json."""
    return [[scene, d["of"], "same seed" if d["same_seed"] else f"seed {d['seed']}", _fmt(d["psnr"], 3),
             _fmt(d["psnr_transparent"], 3), _fmt(d["time_percent"], 1)]
            for d in _repeat_differences(scene, runs, roles, results)]


def near_reflection_rows(runs: dict[str, Run]) -> list[list[str]]:
    """One row per run whose model asked for near reflections: on/off, planes, how many of them are bent,
    planar share, the mirrored render's coverage of the glass, why, how far the image loss moved the planes
    (``mirror_planes_moved``), s/it. Summaries written before the bend and the coverage show "-" there."""
    rows = []
    for m, r in sorted(runs.items()):
        fit = r.summary.get("near_reflection")
        if not r.summary.get("effects", {}).get("near_reflection") or not isinstance(fit, dict):
            continue
        rows.append([m, "on" if fit.get("on") else "off", _fmt(fit.get("planes"), 0), _fmt(fit.get("bent_planes"), 0),
                     _fmt(fit.get("planar_share")), _fmt(fit.get("coverage")),
                     str(fit.get("reason", "")), _planes_moved(r.summary.get("mirror_planes_moved")),
                     _fmt(r.summary.get("seconds_per_iteration"), 3),
                     _fmt(_per_iteration(r.summary.get("train_cpu_seconds"), r.summary.get("iterations")), 3)])
    return rows


def _planes_moved(moved) -> str:
    """The largest turn (degrees) and shift (scene units) of the learnt mirror planes; "-" when they were
    kept as fitted."""
    if not isinstance(moved, list) or not moved:
        return "-"
    turn = max(float(m.get("degrees", 0.0)) for m in moved)
    shift = max(abs(float(m.get("shift", 0.0))) for m in moved)
    return f"up to {turn:.1f} deg, {shift:.3g}"


def scene_test_views(runs: dict[str, Run]) -> set[str] | None:
    """The test views a scene's runs were scored on (the first run whose metrics name them); None: unknown."""
    return next((set(r.metrics["views"]) for r in runs.values() if r.metrics.get("views")), None)


def scene_layer_references(prepared: Path, names: set[str] | None) -> dict[str, float] | None:
    """The references made from a synthetic scene's ground truth itself (:func:`rtsplat.layer_references.ceilings`
    with the truth blurred 2 px) over the test views ``names``; None without ground-truth layers."""
    try:
        views = read_views(prepared, names)
    except PipelineError:
        return None
    return ceilings(views, sigmas=(2.0,))


FLAT_REFERENCE = "truth's mean"  # the keys of scene_layer_references: the true reflection painted flat,
BLURRED_REFERENCE = "truth blurred 2 px"  # and blurred by 2 px (rtsplat.layer_references.ceilings)


def layer_reference_rows(ref: dict[str, float] | None) -> tuple[list[list[str]], str]:
    """Rows of a scene's :func:`scene_layer_references` for the decomposition table, and a sentence on what
    they mean; none without layers."""
    if ref is None:
        return [], ""
    rows = [["(reference) the true reflection's mean colour, flat", _fmt(ref[FLAT_REFERENCE]), "-"],
            ["(reference) the true reflection blurred 2 px", _fmt(ref[BLURRED_REFERENCE]), "-"]]
    text = ("The reference rows are made from the ground truth itself: its reflection painted flat in its mean "
            "colour (what a reflection without any structure scores) and blurred by 2 pixels (what one right "
            "down to that scale scores). The ground truth's reflection plus transmission scores "
            f"{_fmt(ref[LAYERS_SUM])} dB against the image inside the mask: no layer score can be trusted "
            "beyond about that.")
    return rows, text


def scene_reflection_reach(prepared: Path) -> str:
    """What share of the glass's true reflection is of something near the glass, in words, for a synthetic
    scene (the ``reflection_reach`` that ``rtsplat prepare`` carries from the dataset); "" for other scenes."""
    path = prepared / GT_LAYERS_DIR / REFLECTION_REACH_FILE
    try:
        reach = json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError):
        return ""
    if not isinstance(reach, dict):
        return ""
    distance = reach.get("median_distance")
    return (f"What the scene calls for (ground truth, `rtsplat.synth.reach`): of the glass pixels of the views with "
            f"true layers, {_fmt(reach.get('near_share'))} reflect something at a finite distance, carrying "
            f"{_fmt(reach.get('near_weight'))} of the true reflection's luminance"
            + (f" (median distance {_fmt(distance)})" if isinstance(distance, (int, float)) else "")
            + "; the rest reflects the environment at infinity, which the environment lookup alone can show.")


def appearance_rows(runs: dict[str, Run]) -> list[list[str]]:
    """One row per run that measured its photos' exposure spread: on/off, spread, how confident the decision
    is (high, low, unknown; '-' for runs that did not record it), why, and the mean absolute log gain its
    training and test views' corrections took."""
    rows = []
    for m, r in sorted(runs.items()):
        a = r.summary.get("appearance")
        if not isinstance(a, dict):
            continue
        rows.append([m, "on" if a.get("on") else "off", _fmt(a.get("spread"), 3), str(a.get("confidence") or "-"),
                     str(a.get("reason", "")),
                     _fmt(a.get("train_mean_abs_log_gain"), 3), _fmt(a.get("test_mean_abs_log_gain"), 3)])
    return rows


def _per_iteration(seconds, iterations) -> float | None:
    return seconds / iterations if isinstance(seconds, (int, float)) and iterations else None


MARK_KINDS = {"file": ("mask file", "mask files"), "polygon": ("polygon", "polygons"), "box": ("box", "boxes"),
              "filled box": ("filled box", "filled boxes")}  # how a view was marked: singular, plural


def masks_paragraph(summary: dict) -> str:
    """Where a scene's transparent masks came from, from the masks stage's summary.json: given, segmented,
    none, or propagated from marked views (how each was marked, how many were propagated and through what
    (:func:`carried_text`), refined, left empty or had no pose)."""
    source, total = summary.get("source"), summary.get("num_images", "?")
    if not summary.get("has_masks"):
        return f"Transparent masks: none for the {total} photos (trained without the transmission's masks)."
    coverage = f"mean coverage {100 * float(summary.get('mean_coverage', 0.0)):.1f}%."
    if source != "propagate":
        how = {"ingest": "given", "onnx": f"segmented by the ONNX model {summary.get('model_kind') or ''}".strip()}
        return f"Transparent masks: {how.get(source, source)} for the {total} photos, {coverage}"
    kinds = collections.Counter((summary.get("mark_sources") or {}).values())
    sources = collections.Counter((summary.get("mask_sources") or {}).values())
    marked = summary.get("marked") or []
    refined = summary.get("refined") or []
    how = ", ".join(f"{n} {MARK_KINDS.get(kind, (kind, kind))[n != 1]}" for kind, n in sorted(kinds.items()))
    text = (f"Transparent masks: propagated from {len(marked)} marked views ({how}: {', '.join(marked)}) to "
            f"{sources.get('propagated', 0)} of the {total} photos{carried_text(summary)}")
    if refined:
        text += f", {len(refined)} of them refined ({summary.get('refinement') or '?'})"
    for key, what in (("empty", "left empty (the marked region is not in view)"),
                      ("unregistered", "without an SfM pose (empty)")):
        if sources.get(key):
            text += f"; {sources[key]} {what}"
    return f"{text}; {coverage}"


def carried_text(summary: dict) -> str:
    """How propagated marks reached the other photos (the masks summary's ``propagation_method``): through the
    marked views' visual hull, or through the glass's plane with its fit; empty in summaries without it."""
    method = summary.get("propagation_method")
    if method == "hull":
        return " through the marked views' visual hull"
    if method != "plane":
        return ""
    plane = summary.get("glass_plane") or {}
    text = (f" through the glass's plane ({plane.get('inliers', '?')} of {plane.get('outline_points', '?')} SfM "
            f"points on the marks' outlines lie on it, RMS residual "
            f"{100 * float(plane.get('relative_residual', 0.0)):.2f}% of their depth; the marked views agree through "
            f"it at IoU {float(plane.get('agreement', 0.0)):.2f})")
    panes = summary.get("glass_panes") or []
    own = [p for p in panes if p.get("own_plane")]
    if own:
        residuals = ", ".join(f"{100 * float(p.get('relative_residual', 0.0)):.2f}%" for p in own)
        text += (f", the marks being {len(panes)} panes, {len(own)} of them through a plane of its own (RMS "
                 f"residual{'s' if len(own) > 1 else ''} {residuals})")
    return text


def polarity_text(summary: dict) -> str:
    """The masks stage's polarity decision and why (:func:`rtsplat.masks.polarity.decide_polarity`), for masks read from
    mask files; empty for segmented masks, marks drawn in the config only, and summaries without it."""
    reason = summary.get("polarity_reason") or ""
    if not reason or summary.get("source") not in ("ingest", "propagate") or not summary.get("has_masks"):
        return ""
    return f"Polarity: {reason}."


def roi_warning_text(scene: str, prepared: Path) -> str:
    """The prepare stage's warning when it did not use the region of interest around the masks' visual hull
    (``scene.json``'s ``roi_warning``, :func:`rtsplat.prepare.checked_mask_roi`), as a sentence naming the scene;
    empty when it used it and where there is no prepared scene."""
    if not (prepared / SCENE_FILE).is_file():
        return ""
    warning = PreparedScene.load(prepared, check_files=False).roi_warning
    return f"Warning (region of interest, scene {scene}): {warning}." if warning else ""


MASK_OVERLAYS = 3  # photos per scene shown with their mask tinted over them
OVERLAY_MAX_SIDE = 960  # px: larger photos are area-downsampled by an integer factor for the overlays
OVERLAY_TINT = np.array([1.0, 0.0, 1.0], np.float32)  # magenta over the see-through surface
OVERLAY_TINT_NEAR = np.array([0.0, 1.0, 0.0], np.float32)  # green where the photo is near magenta itself
OVERLAY_ALPHA = 0.5


def overlay_photos(summary: dict, count: int = MASK_OVERLAYS) -> list[str]:
    """The photos (names) whose masks the report shows: spread evenly over the photos by name; for propagated
    masks one marked view first, the others spread over the propagated ones."""
    names = sorted(summary.get("photos") or {})
    sources = summary.get("mask_sources") or {}
    marked = [n for n in names if sources.get(n) == "given"]
    pool = [n for n in names if sources.get(n) == "propagated"] if marked else names
    chosen = marked[:1]
    wanted = min(count - len(chosen), len(pool))
    if wanted > 0:
        chosen += [pool[int(i)] for i in np.unique(np.round(np.linspace(0, len(pool) - 1, wanted)).astype(int))]
    return chosen


def mask_source(summary: dict, name: str) -> str:
    """Where the mask of photo ``name`` came from, for a caption: given, given empty (no mask file), marked
    (how), propagated, empty, no SfM pose, segmented (model kind)."""
    source = summary.get("source")
    if source == "ingest":
        return "no mask file: empty" if name in (summary.get("without_mask") or []) else "given"
    if source == "onnx":
        return f"segmented ({summary.get('model_kind') or 'ONNX'})"
    kind = (summary.get("mask_sources") or {}).get(name, "?")
    if kind == "given":
        return f"marked ({(summary.get('mark_sources') or {}).get(name, 'file')})"
    return {"unregistered": "no SfM pose: empty", "empty": "empty (the marked region is not in view)"}.get(kind, kind)


def mask_overlay(photo: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``photo`` (float RGB [H, W, 3]) with ``mask`` (bool or the covered fraction of each pixel, [H, W]) tinted
    over it: :data:`OVERLAY_TINT` at :data:`OVERLAY_ALPHA`, :data:`OVERLAY_TINT_NEAR` where the photo is close to
    that colour itself, so that every covered pixel changes and every other pixel stays as it is."""
    near = np.abs(photo - OVERLAY_TINT).max(-1, keepdims=True) < 0.25
    tint = np.where(near, OVERLAY_TINT_NEAR, OVERLAY_TINT)
    weight = OVERLAY_ALPHA * np.asarray(mask, np.float32)[..., None]
    return (photo * (1 - weight) + tint * weight).astype(np.float32)


def _mask_overlay_image(photo_path: Path, mask_path: Path) -> np.ndarray:
    """The overlay of one photo and its mask at the photo's size, or area-downsampled by the smallest integer
    factor that brings its longer side to :data:`OVERLAY_MAX_SIDE` at most."""
    from rtsplat.io.images import area_downsample, read_mask

    photo, mask = read_image(photo_path), read_mask(mask_path)
    if mask.shape != photo.shape[:2]:
        raise PipelineError(f"mask is {mask.shape[1]}x{mask.shape[0]}, its photo {photo.shape[1]}x{photo.shape[0]}",
                            path=mask_path, fix="rerun 'rtsplat masks' on the scene's photos")
    factor = -(-max(photo.shape[:2]) // OVERLAY_MAX_SIDE)
    return mask_overlay(area_downsample(photo, factor), area_downsample(mask.astype(np.float32), factor))


def _masks_section(doc: Document, scene_dir: Path, out: Path) -> None:
    """The scene's transparent masks: where they came from, the polarity decision and its warning, the warning of
    :func:`roi_warning_text`, and the masks of :func:`overlay_photos` tinted over the photos (the photos from the
    dataset scene the masks stage recorded, the masks from its output), written into the report's images/."""
    masks_dir = scene_dir / "masks"
    summary = _read_json(masks_dir / "summary.json")
    doc.heading("Transparent masks", 3)
    doc.paragraph(" ".join(t for t in (masks_paragraph(summary), polarity_text(summary)) if t))
    for key in ("polarity_warning", "coverage_warning"):
        if summary.get(key):
            doc.paragraph(f"Warning: {summary[key]}.")
    roi_warning = roi_warning_text(scene_dir.name, scene_dir / "prepared")
    if roi_warning:
        doc.paragraph(roi_warning)
    if not summary.get("has_masks"):
        return
    images = Path(summary.get("scene_dir") or "") / "images"
    coverage = summary.get("coverage") or {}
    items, missing = [], []
    for name in overlay_photos(summary):
        stem = Path(name).stem
        if not (images / name).is_file() or not (masks_dir / f"{stem}.png").is_file():
            missing.append(name)
            continue
        overlay = _mask_overlay_image(images / name, masks_dir / f"{stem}.png")
        (out / "images").mkdir(exist_ok=True)
        file = f"images/{scene_dir.name}_mask_{stem}.png"
        write_png(out / file, overlay)
        cover = coverage.get(stem)
        items.append((file, f"{name}: {mask_source(summary, name)}"
                      + (f", {100 * float(cover):.1f}% covered" if cover is not None else "")))
    if items:
        doc.paragraph("The masks tinted magenta (green over magenta-like pixels) on the photos: the tint should lie "
                      "on the see-through surface and nowhere else. If it lies on everything but the glass, the "
                      "mask files are inverted: set masks.polarity: black.")
        doc.images(items)
    if missing:
        doc.paragraph(f"No overlay for {', '.join(missing)}: the photo is not in {images} or its mask not in "
                      f"{masks_dir}.")


def sfm_section(summary: dict) -> tuple[str, list[str], list[list[str]]]:
    """(paragraph, header, rows) of a scene's SfM table from the sfm stage's summary.json."""
    total = summary.get("total", "?")
    if summary.get("source") == "dataset":
        text = (f"Cameras from the dataset's own model (sparse/0, no SfM): {summary.get('registered')}/{total} views, "
                f"mean reprojection error {_fmt(summary.get('mean_reprojection_error'), 3)} px.")
        return text, [], []
    header = ["attempt", "settings", "registered", "reproj. px", "time s", "rot. err. deg", "rot. err. deg (orient.)",
              "centre err. %", "chosen"]
    rows = []
    for i, a in enumerate(summary.get("attempts", [])):
        st = a.get("settings", {})
        knobs = f"{st.get('mapper')}, {st.get('matcher')}" + (", guided" if st.get("guided_matching") else "")
        if st.get("mapper") == "incremental":
            knobs += f", init {st.get('init_min_num_inliers')}, abs pose {st.get('abs_pose_min_num_inliers')}"
        pose = a.get("pose_errors") or {}
        centre = pose.get("center_error_relative")
        chosen = "yes" if i == summary.get("chosen_attempt") else ("" if a.get("acceptable") else "not acceptable")
        rows.append([f"{i + 1}. {a.get('name')}", knobs, f"{a.get('registered')}/{total}",
                     _fmt(a.get("mean_reprojection_error"), 3), _fmt(a.get("seconds"), 1),
                     _fmt(pose.get("rotation_error_deg_mean"), 3),
                     _fmt(pose.get("orientation_aligned_rotation_error_deg_mean"), 3),
                     _fmt(None if centre is None else 100 * centre, 2),
                     chosen])
    text = (f"SfM from the images: {summary.get('registered')}/{total} views registered, mean reprojection error "
            f"{_fmt(summary.get('mean_reprojection_error'), 3)} px, {len(rows)} attempt(s), "
            f"{_fmt(summary.get('seconds'), 0)} s. Choice: {summary.get('choice') or '?'}.")
    if summary.get("unregistered"):
        text += " Not registered: " + ", ".join(summary["unregistered"]) + "."
    if summary.get("pose_errors"):
        text += (" Rotation and centre errors (means): against the dataset's reference cameras after a similarity "
                 "fit to the camera centres; 'orient.': the rotation fitted to the camera orientations instead, "
                 "which an arc of cameras constrains better than its centres. Centre error in % of the cameras' "
                 "mean distance to their centroid.")
    return text, header, rows


def _run_seed(run_dir: Path):
    """The seed of a run's trainer config (``config.json``), None when it has none."""
    path = run_dir / "config.json"
    return _read_json(path).get("seed") if path.is_file() else None


def training_records(scenes: dict[str, dict[str, Run]]) -> dict[str, dict | None]:
    """Each run ("scene/method") with the provenance its training recorded (None: not recorded)."""
    return {f"{scene}/{method}": run.summary.get("provenance") for scene, runs in scenes.items()
            for method, run in runs.items()}


def metrics_commits(scenes: dict[str, dict[str, Run]]) -> dict[str, list[str]]:
    """The code that computed the runs' metrics: its commit label -> the runs, the label of most runs first
    (runs without metrics left out; metrics written without a provenance under "not recorded")."""
    runs_of: dict[str, list[str]] = {}
    for scene, runs in scenes.items():
        for method, run in runs.items():
            if run.metrics:
                runs_of.setdefault(commit_label(run.metrics.get("provenance")), []).append(f"{scene}/{method}")
    return dict(sorted(runs_of.items(), key=lambda item: -len(item[1])))


PROVENANCE_HEADING = "Provenance: the code and the machine that trained each run"


def _provenance_first_screen(doc: Document, mixture: list[str], groups: list[dict]) -> None:
    """The report's opening lines: what mixes in these runs (:func:`rtsplat.provenance.mixture_sentences`),
    or the one commit and machine that trained them all."""
    if mixture:
        doc.paragraph("Mixed provenance, read before comparing numbers: " + " ".join(mixture)
                      + f" The section '{PROVENANCE_HEADING}' lists every run.")
    else:
        only = groups[0]
        doc.paragraph(f"Every run was trained by commit {only['commit']} (no uncommitted changes) on "
                      f"{only['machine']}, device {only['device']}.")


def _provenance_section(doc: Document, groups: list[dict], scenes: dict[str, dict[str, Run]],
                        any_metrics: dict) -> None:
    doc.heading(PROVENANCE_HEADING)
    doc.paragraph("What each run's training recorded (rtsplat.provenance): the commit, with '+changes' and a hash "
                  "of the differences when the tree had uncommitted changes (edits to docs/ and Markdown files, "
                  "which no stage reads, do not count), the machine (host name, CPU model, cores), the device and "
                  "the package versions; a run resumed by other code lists each part.")
    doc.table(["commit", "machine", "device", "packages", "runs"],
              [[g["commit"], g["machine"], g["device"], g["packages"], ", ".join(g["runs"])] for g in groups])
    computed = "; ".join(f"{label} ({len(runs)} run{'' if len(runs) == 1 else 's'})"
                         for label, runs in metrics_commits(scenes).items())
    doc.paragraph(f"Metrics computed by: {computed or 'no metrics'}; rendering device: "
                  f"{any_metrics.get('render_device', '?')}.")


def build_report(results: str | Path, out: str | Path, *, roles: Roles | None = None,
                 config_file: str | Path | list | None = None, commands: list[str] | None = None) -> Path:
    """Write the report of ``results`` into ``out`` (atomically). ``roles``: the methods' roles (none:
    every method is a baseline). ``config_file``: one path or a list of the config files of the run
    (printed in the Reproduce section, later ones layered over earlier)."""
    results, out = Path(results), Path(out)
    check_output_dir(out, "report", containers=[results])
    scenes = collect(results)
    with output_dir(out, "report", containers=[results]) as tmp:
        _write(results, scenes, tmp, roles or Roles(), config_file, commands)
    return out / "index.html"


ERROR_CAPTION = f"|error| ({ERROR_COLOUR_MAP}, 0 to {ERROR_MAP_MAX})"


def _test_view_section(doc: Document, results: Path, scene: str, view: str, compared: list[str], out: Path) -> None:
    """Ground truth and each compared method's render of ``view``, then their per-pixel error maps."""
    prepared = results / scene / "prepared" / "images" / f"{view}.png"
    items, errors = [], []
    gt = _copy_image(prepared, out, f"{scene}_{view}_gt.png")
    if gt:
        items.append((gt, "ground truth"))
    target = read_image(prepared) if prepared.is_file() else None
    for method in compared:
        render = results / scene / "renders" / method / "color" / f"{view}.png"
        img = _copy_image(render, out, f"{scene}_{view}_{method}.png")
        if img:
            items.append((img, method))
        err = _error_image(render, target, out, f"{scene}_{view}_{method}_error.png") if target is not None else None
        if err:
            errors.append((err, f"{method} {ERROR_CAPTION}"))
    if items:
        doc.heading(f"Test view {view}", 3)
        doc.images(items)
    if errors:
        doc.paragraph(f"Per-pixel error against the ground truth: |render - ground truth| averaged over the colour "
                      f"channels, colour map {ERROR_COLOUR_MAP} from 0 (dark) to {ERROR_MAP_MAX} (bright; larger "
                      f"errors are clipped), the same range for every method.")
        doc.images(errors)


def _layer_comparison_section(doc: Document, scene_dir: Path, view: str, main: str, out: Path) -> None:
    """The ground-truth reflection and transmission of ``view`` next to the main method's reflection layer
    and colour - reflection (the transmission as ``rtsplat metrics`` scores it), with their error maps."""
    renders = scene_dir / "renders" / main
    color_path, reflection_path = (renders / layer / f"{view}.png" for layer in ("color", "reflection"))
    if not (color_path.is_file() and reflection_path.is_file()):
        return
    color, reflection = read_image(color_path), read_image(reflection_path)
    ours = {"reflection": reflection,
            "transmission": transmission_with_scatter(torch.from_numpy(color), torch.from_numpy(reflection))
            .clamp(0, 1).numpy()}
    name = f"{scene_dir.name}_{view}_{main}"
    doc.heading(f"Decomposition against the ground-truth layers (view {view})", 3)
    for layer, ours_image in ours.items():
        truth_path = scene_dir / "prepared" / GT_LAYERS_DIR / layer / f"{view}.png"
        truth = read_image(truth_path)
        _same_size(ours_image, truth, reflection_path if layer == "reflection" else color_path)
        label = layer if layer == "reflection" else "transmission (colour - reflection)"
        doc.images([(_write_image(truth, out, f"{name}_gt_{layer}.png"), f"ground-truth {layer}"),
                    (_write_image(ours_image, out, f"{name}_{layer}.png"), f"{main} {label}"),
                    (_write_image(error_map(ours_image, truth), out, f"{name}_{layer}_error.png"),
                     f"{main} {layer} {ERROR_CAPTION}")])


VIDEO_PANEL_NAMES = {"color": "image", "reflection": "reflection", "transmission": "transmission",
                     "normal": "normal", "depth": "depth"}


def video_caption(method: str, comment: str | None) -> str:
    """What a video shows, from the settings ``rtsplat video`` recorded in its metadata comment."""
    from rtsplat.io.video import RTSPLAT_COMMENT

    comment = comment or ""
    try:
        info = json.loads(comment[len(RTSPLAT_COMMENT):]) if comment.startswith(RTSPLAT_COMMENT) else {}
    except ValueError:
        info = {}
    if not isinstance(info, dict) or not info:
        return method
    panels = " | ".join(VIDEO_PANEL_NAMES.get(p, str(p)) for p in info.get("panels", []))
    size = f"{info.get('width', '?')}x{info.get('height', '?')}" + (f" per panel ({panels})" if "|" in panels else "")
    fps = _fmt(info.get("fps"), 0)
    return f"{method}: {info.get('path', '?')} path, {info.get('frames', '?')} frames at {fps} fps, {size}"


def _video_section(doc: Document, scene_dir: Path, main: str | None, out: Path) -> None:
    """The scene's camera-path videos (``<scene>/videos/<method>.mp4`` with its poster ``<method>.png``), the main
    method first, copied into the report."""
    import shutil

    from rtsplat.io.video import mp4_comment

    found = sorted(scene_dir.glob("videos/*.mp4"), key=lambda p: (p.stem != main, p.stem))
    if not found:
        return
    doc.heading("Camera-path videos", 3)
    doc.paragraph("Each method rendered along the same camera path from its training cameras (rtsplat video); the "
                  "panels are the image and the layers of `rtsplat render`.")
    for path in found:
        name = f"{scene_dir.name}_video_{path.stem}"
        shutil.copyfile(path, out / f"{name}.mp4")
        poster = path.with_suffix(".png")
        if poster.is_file():
            shutil.copyfile(poster, out / f"{name}.png")
        doc.video(f"{name}.mp4", f"{name}.png" if poster.is_file() else None,
                  video_caption(path.stem, mp4_comment(path)))


def _write(results: Path, scenes: dict[str, dict[str, Run]], out: Path, roles: Roles, config_file,
           commands) -> None:
    doc = Document("rtsplat benchmark report")
    trained_by = training_records(scenes)
    groups, mixture = group_runs(trained_by), mixture_sentences(trained_by)
    _provenance_first_screen(doc, mixture, groups)
    _summary_section(doc, scenes, roles, results)
    references = {scene: scene_layer_references(results / scene / "prepared", scene_test_views(runs))
                  for scene, runs in scenes.items()}
    family = family_scenes(scenes, roles, results, references)
    if family:
        _family_section(doc, family, out)
    from rtsplat.report_convergence import convergence_section

    convergence_section(doc, scenes, roles, references)
    any_metrics = next((r.metrics for runs in scenes.values() for r in runs.values() if r.metrics), {})
    _provenance_section(doc, groups, scenes, any_metrics)
    doc.paragraph("LPIPS: " + str(any_metrics.get("lpips", "not computed")))
    for scene, runs in scenes.items():
        _scene_section(doc, results, scene, runs, roles, references[scene], out)
    _noise_section(doc, scenes, roles, results)
    _reproduce_section(doc, commands, config_file)
    _write_pages(doc, out, groups, mixture, scenes, any_metrics)


def _summary_section(doc: Document, scenes: dict[str, dict[str, Run]], roles: Roles, results: Path) -> None:
    """The first table: every RT-Splatting run against its plain-2DGS run, final and at equal time."""
    doc.heading("Summary: RT-Splatting against plain 2DGS")
    summary = [row for scene, runs in scenes.items() for row in summary_rows(scene, runs, roles, results)]
    if not summary:
        doc.paragraph(f"No scene has both the main method and the baseline {PLAIN_2DGS!r}, so there is no summary.")
        return
    doc.paragraph("PSNR of the RT-Splatting run minus PSNR of the plain-2DGS run with the same budget, on the "
                  "test views' transparent region and on the entire image (positive: RT-Splatting is better). "
                  "Beside each gap, the seed noise: the largest |dPSNR| between either run of the pair and "
                  "its repeat with another seed (Noise section; 'noise from' names the repeats). A gap "
                  "smaller than twice the seed noise is not significant; where the noise was not measured, "
                  "no gap can be called significant. At equal time: the same gaps read from the two runs' "
                  "test evaluations during training (train_log.jsonl, linearly between evaluations) at the "
                  "training time of the shorter run, what a user with that much time gets; time ratio: the "
                  "first run's training time over the second's (both by the measure of the scene's speed "
                  "table). A pair whose first run trained for the time of the second (a method with "
                  "`time_of`) compares finished runs at equal time: each run completed its own schedule, where "
                  "the equal-time columns read the longer run mid-schedule.")
    doc.table(["scene", "pair", "dPSNR transp.", "dPSNR", "seed noise transp.", "seed noise",
               "noise from", "dPSNR transp. at equal time", "dPSNR at equal time", "time ratio"], summary)


def _scene_section(doc: Document, results: Path, scene: str, runs: dict[str, Run], roles: Roles,
                   references, out: Path) -> None:
    """One scene's part of the report: its stages' summaries, every run's quality and time, and its images."""
    main = roles.main
    doc.heading(f"Scene {scene}")
    sfm_summary = results / scene / "sfm" / "summary.json"
    if sfm_summary.is_file():
        text, sfm_header, sfm_rows = sfm_section(_read_json(sfm_summary))
        doc.heading("Structure from motion", 3)
        doc.paragraph(text)
        if sfm_rows:
            doc.table(sfm_header, sfm_rows)
    if (results / scene / "masks" / "summary.json").is_file():
        _masks_section(doc, results / scene, out)
    doc.heading("Quality", 3)
    other_splits = {m: r.metrics.get("split") for m, r in runs.items() if r.metrics.get("split", "test") != "test"}
    if other_splits:
        doc.paragraph("Not held-out scores: " + ", ".join(
            f"{m} was scored on its {split} views" + (" (training views included)" if split in ("all", "train")
                                                       else "") for m, split in sorted(other_splits.items()))
            + "; the other runs on the test views.")
    doc.table(QUALITY_HEADER, quality_rows(runs, main))
    doc.heading("Speed and training time", 3)
    doc.paragraph(TIME_CAPTION)
    doc.table(TIME_HEADER, time_rows(runs, main))
    _ablation_section(doc, runs, roles)
    _layer_scores_section(doc, runs, references)
    _near_reflection_section(doc, results / scene / "prepared", runs)
    _appearance_section(doc, runs)
    _accuracy_time_section(doc, scene, runs, out)
    _scene_images_section(doc, results, scene, runs, roles, out)
    _video_section(doc, results / scene, main, out)


def _ablation_section(doc: Document, runs: dict[str, Run], roles: Roles) -> None:
    ablations = [(m, ablation_reference(m, runs, roles)) for m in roles.of_role(runs, "ablation")]
    ablations = [(m, full) for m, full in ablations if full is not None]
    if not ablations:
        return
    doc.heading("Ablations (transparent-region PSNR)", 3)
    doc.paragraph("Each ablation against the full model with the same budget (an ablation named "
                  "`..._<suffix>` against the baseline `<main>_<suffix>`, e.g. `_x4`; otherwise the main "
                  "method); a positive difference means the ablated term did not help here.")
    rows = []
    for m, full in ablations:
        v, ref = runs[m].mean.get("psnr_transparent"), runs[full].mean.get("psnr_transparent")
        rows.append([m, full, _fmt(v), _fmt(ref), _fmt(_difference(v, ref))])
    doc.table(["ablation", "full model", "PSNR (transp.)", "full model PSNR (transp.)", "difference"], rows)


def _layer_scores_section(doc: Document, runs: dict[str, Run], references) -> None:
    layer_rows = [[m, _fmt(r.mean.get("psnr_reflection_layer")), _fmt(r.mean.get("psnr_transmission_layer"))]
                  for m, r in sorted(runs.items()) if "psnr_transmission_layer" in r.mean]
    if not layer_rows:
        return
    doc.heading("Decomposition against the ground-truth layers (PSNR in the transparent region, test views)", 3)
    reference_rows, text = layer_reference_rows(references)
    if text:
        doc.paragraph(text)
    doc.table(["method", "reflection", "transmission"], layer_rows + reference_rows)


def _near_reflection_section(doc: Document, prepared: Path, runs: dict[str, Run]) -> None:
    near_rows = near_reflection_rows(runs)
    reach = scene_reflection_reach(prepared)
    if not (near_rows or reach):
        return
    doc.heading("Near reflections (mirror planes of the glass)", 3)
    if reach:
        doc.paragraph(reach)
    if near_rows:
        doc.paragraph("Whether each run reflected its own surfels in planes fitted to the see-through "
                      "surface (effects.near_reflection; auto keeps them where planes explain enough of it "
                      "and their mirrored render covers enough of it), how many planes carry a bend "
                      "(curved glass, model.near_reflection_bend), "
                      "how far the image loss moved the planes where they are learnt "
                      "(lr.mirror_plane_rotation, lr.mirror_plane_shift), and the seconds per training "
                      "iteration it paid (wall seconds, and CPU seconds, which depend less on what ran "
                      "beside it).")
        doc.table(["method", "near reflection", "planes", "bent", "planar share", "coverage", "why",
                   "planes learnt",
                   "wall s / iteration", "CPU s / iteration"], near_rows)


def _appearance_section(doc: Document, runs: dict[str, Run]) -> None:
    exposure_rows = appearance_rows(runs)
    if not any(row[1] == "on" for row in exposure_rows):
        return
    doc.heading("Per-view appearance (exposure and white balance)", 3)
    doc.paragraph("Whether each run learnt a colour correction per photo (effects.appearance; auto turns it "
                  "on where the photos' colours of the SfM points spread by exposure beyond what the "
                  "measurement's own noise explains, and keeps it off where too few observations lie off "
                  "the see-through surface to tell), how confident that decision is, and how far the "
                  "corrections moved (mean |log gain|; 0.1 is a 10% exposure change).")
    doc.table(["method", "appearance", "exposure spread", "confidence", "why", "train |log gain|",
               "test |log gain|"], exposure_rows)


def _accuracy_time_section(doc: Document, scene: str, runs: dict[str, Run], out: Path) -> None:
    doc.heading("Accuracy against training time", 3)
    measure = time_measure(runs)
    doc.paragraph(measure.caption + " The Pareto front: the runs that no other run beats in both time and PSNR.")
    for name in plot_accuracy_time(scene, runs, out):
        doc.images([(name, name)])
    key = "psnr_transparent" if time_points(runs, "psnr_transparent", measure) else "psnr"
    points = time_points(runs, key, measure)
    flags = pareto_front([(t, q) for _, t, q in points])
    beside = [WALL_TIME] if measure is not WALL_TIME else []  # the wall seconds, for reference
    doc.table(["method", measure.label, *(b.label for b in beside), key, "Pareto front"],
              [[m, _fmt(t, 1), *(_fmt(runs[m].seconds(b), 1) for b in beside), _fmt(q), "yes" if f else ""]
               for (m, t, q), f in sorted(zip(points, flags, strict=True), key=lambda x: x[0][1])])


def _scene_images_section(doc: Document, results: Path, scene: str, runs: dict[str, Run], roles: Roles,
                          out: Path) -> None:
    """One test view of the scene: every run's render, the main method's layers and edits."""
    main = roles.main
    test_names = next((r.metrics.get("views") for r in runs.values() if r.metrics.get("views")), {})
    if not test_names:
        return
    gt_layers = results / scene / "prepared" / GT_LAYERS_DIR
    with_layers = [v for v in sorted(test_names) if all((gt_layers / layer / f"{v}.png").is_file()
                                                        for layer in ("reflection", "transmission"))]
    view = (with_layers or sorted(test_names))[0]
    compared = [main] if main in runs else []
    compared += [m for m in sorted(runs) if m != main and roles.role.get(m, "baseline") != "ablation"]
    _test_view_section(doc, results, scene, view, compared, out)
    if main is None:
        return
    layers = []
    for layer in ("reflection", "transmission", "scatter", "normal", "depth"):
        img = _copy_image(results / scene / "renders" / main / layer / f"{view}.png", out,
                          f"{scene}_{view}_{layer}.png")
        if img:
            layers.append((img, layer))
    if layers:
        doc.heading(f"Decomposition ({main})", 3)
        doc.images(layers)
    if with_layers and main in runs:
        _layer_comparison_section(doc, results / scene, view, main, out)
    edits = []
    for edit_dir in sorted((results / scene / "renders").glob(f"{main}@*")):
        img = _copy_image(edit_dir / "color" / f"{view}.png", out, f"{scene}_{view}_{edit_dir.name}.png")
        if img:
            edits.append((img, edit_dir.name.split("@", 1)[1]))
    if edits:
        doc.heading("Scene editing", 3)
        doc.images(edits)


def _noise_section(doc: Document, scenes: dict[str, dict[str, Run]], roles: Roles, results: Path) -> None:
    doc.heading("Noise")
    noise = [row for scene, runs in scenes.items() for row in _noise_rows(scene, runs, roles, results)]
    if not noise:
        doc.paragraph("No repeated runs in these results, so run-to-run noise was not measured here.")
        return
    doc.paragraph("Differences between runs of the same config on this machine. Same seed: quality differences "
                  "come from non-deterministic floating-point reductions, time differences from machine load; "
                  "expect a rerun to reproduce the numbers within these. Another seed: the spread to expect "
                  "between methods that are in truth equally good, so smaller gaps between methods are not "
                  "significant. Time diff: of the training CPU seconds where both runs trained on the CPU and "
                  "recorded them, else of the wall seconds.")
    doc.table(["scene", "method", "rerun", "|dPSNR|", "|dPSNR transp.|", "time diff %"], noise)


def _reproduce_section(doc: Document, commands, config_file) -> None:
    doc.heading("Reproduce")
    doc.code("\n".join(commands or ["make demo"]))
    files = config_file if isinstance(config_file, (list, tuple)) else [config_file] if config_file else []
    for path in files:
        if Path(path).is_file():
            doc.paragraph(f"{Path(path).name}:")
            doc.code(Path(path).read_text())


def _write_pages(doc: Document, out: Path, groups, mixture, scenes, any_metrics) -> None:
    """index.html, index.md and the report's record (report.json: provenance and every table)."""
    page, markdown = doc.finish()
    (out / "index.html").write_text(page)
    (out / "index.md").write_text(markdown)
    commits: dict[str, list[str]] = {}
    for group in groups:
        commits.setdefault(group["commit"], []).extend(group["runs"])
    record = {"title": doc.title, "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "commit": groups[0]["commit"] if len(commits) == 1 else None, "commits": commits,
              "provenance": groups, "mixed": mixture, "render_device": any_metrics.get("render_device"),
              "scenes": list(scenes), "tables": doc.tables}
    (out / REPORT_JSON).write_text(json.dumps(record, indent=1) + "\n")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--results", type=Path, required=True, help="results directory of the workflow")
    parser.add_argument("--out", type=Path, required=True, help="report directory (replaced atomically)")
    parser.add_argument("--config", type=Path, action="append", default=[],
                        help="a config file to print in the Reproduce section (repeat for layered configs)")
    parser.add_argument("--command", action="append", default=[], help="a command to print in Reproduce")
    parser.add_argument("--roles-json", help="the methods' roles as JSON {method: {role, of, time_of}} "
                        "(rtsplat.config.roles_json; the workflow passes them); none: every method is a baseline")


def run(args: argparse.Namespace) -> int:
    roles = Roles()
    if args.roles_json:
        try:
            roles = Roles.from_dict(json.loads(args.roles_json))
        except json.JSONDecodeError as exc:
            raise PipelineError(f"--roles-json is not valid JSON ({exc})", fix="pass a JSON object") from None
    index = build_report(args.results, args.out, roles=roles, config_file=args.config, commands=args.command or None)
    print(f"report: {index}")
    return 0
