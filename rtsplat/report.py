"""``rtsplat report``: the benchmark report, ``index.html`` plus a Markdown twin ``index.md``.

It reads what the other stages wrote under ``--results`` (the layout of ``docs/architecture.md``)::

    <scene>/runs/<method>/{summary.json, train_log.jsonl, config.json}    rtsplat train
    <scene>/renders/<method>/{render.json, color/, reflection/, ...}       rtsplat render
    <scene>/renders/<method>@<edit>/                                       rtsplat render --edit ...
    <scene>/metrics/<method>.json                                          rtsplat metrics
    <scene>/sfm/summary.json                                               rtsplat sfm

Each method's role comes from the pipeline config (``methods.<name>.role``, see
:func:`rtsplat.config.method_roles`), handed over as ``--roles-json``; without it every method is a
baseline and there is no main method. The report writes, per scene: the SfM table (registered/total views,
reprojection error and time of every attempt, and for scenes whose dataset ships reference cameras
the rotation and centre errors after a similarity fit), the quality table (entire
image / transparent region, FPS, training time), the ablation table (the ablations against the main
method), decomposition scores when the scene has ground-truth layers, the accuracy-against-time
plots and table with the Pareto front (every run's final test PSNR against its training time, and
the test-PSNR curves logged during training), test-view comparisons (ground truth / main / the
other methods except ablations), the main method's decomposition and editing images; then the
machine, the package versions, the exact commands and the config. Noise: for every repeat (the
same config run again, with the same seed or another one, as its ``config.json`` says) the report
prints the measured differences to the method it repeats; otherwise it says that none were measured.
"""

from __future__ import annotations

import argparse
import html
import json
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from rtsplat.errors import PipelineError
from rtsplat.io.outputs import check_output_dir, output_dir

ROLES = ("main", "baseline", "ablation", "repeat")


@dataclass(frozen=True)
class Roles:
    """Each method's role (``main``, ``baseline``, ``ablation``, ``repeat``) and what a repeat reruns."""

    role: dict[str, str] = field(default_factory=dict)
    of: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: dict, source: str = "--roles-json") -> Roles:
        """``{method: {"role": ..., "of": ...}}`` as :func:`rtsplat.config.roles_json` writes it."""
        if not isinstance(data, dict):
            raise PipelineError(f"{source} must be a JSON object {{method: {{role, of}}}}")
        role, of = {}, {}
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
        if list(role.values()).count("main") > 1:
            raise PipelineError(f"{source}: more than one method has role main", fix="keep one")
        return cls(role, of)

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

    @property
    def mean(self) -> dict:
        return self.metrics.get("mean", {})

    @property
    def seconds(self) -> float | None:
        return self.summary.get("train_seconds")


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PipelineError(f"cannot read ({exc})", path=path, fix="rerun the stage that writes it") from None


def collect(results: Path) -> dict[str, dict[str, Run]]:
    """{scene: {method: Run}} for every run that has a summary (finished training)."""
    scenes: dict[str, dict[str, Run]] = {}
    for summary in sorted(results.glob("*/runs/*/summary.json")):
        run_dir = summary.parent
        scene, method = run_dir.parent.parent.name, run_dir.name
        run = Run(scene, method, summary=_read_json(summary))
        log = run_dir / "train_log.jsonl"
        if log.is_file():
            run.log = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        metrics = results / scene / "metrics" / f"{method}.json"
        if metrics.is_file():
            run.metrics = _read_json(metrics)
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


def _fmt(value, digits: int = 2) -> str:
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value)
    if isinstance(value, (int, float)):
        return f"{value:.{digits}f}"
    return str(value)


class Document:
    """Builds the HTML and the Markdown twin side by side."""

    def __init__(self, title: str):
        self.html = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
                     "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:"
                     "collapse}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
                     "td:first-child{text-align:left}img{max-width:100%}.pareto{font-weight:bold}</style>"
                     "</head><body>", f"<h1>{html.escape(title)}</h1>"]
        self.md = [f"# {title}", ""]

    def heading(self, text: str, level: int = 2) -> None:
        self.html.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.md += ["#" * level + " " + text, ""]

    def paragraph(self, text: str) -> None:
        self.html.append(f"<p>{html.escape(text)}</p>")
        self.md += [text, ""]

    def code(self, text: str) -> None:
        self.html.append(f"<pre>{html.escape(text)}</pre>")
        self.md += ["```", text, "```", ""]

    def table(self, header: list[str], rows: list[list[str]]) -> None:
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

    def finish(self) -> tuple[str, str]:
        return "\n".join(self.html + ["</body></html>"]) + "\n", "\n".join(self.md) + "\n"


def quality_rows(runs: dict[str, Run], main: str | None = None) -> list[list[str]]:
    rows = []
    for method in sorted(runs, key=lambda m: (m != main, m)):
        r = runs[method]
        m = r.mean
        fps = r.metrics.get("fps")
        rows.append([method] + [_fmt(m.get(k), d) for k, d in (
            ("psnr", 2), ("ssim", 3), ("lpips", 3), ("psnr_transparent", 2), ("ssim_transparent", 3),
            ("lpips_transparent", 3))] + [_fmt(fps, 1), _fmt(r.seconds, 1), _fmt(r.summary.get("surfels"), 0)])
    return rows


def time_points(runs: dict[str, Run], key: str) -> list[tuple[str, float, float]]:
    """(method, training seconds, test metric) of every run with both."""
    points = []
    for method, r in runs.items():
        value = r.mean.get(key, r.summary.get("test_" + key))
        if isinstance(value, float) and r.seconds:
            points.append((method, float(r.seconds), value))
    return points


def plot_accuracy_time(scene: str, runs: dict[str, Run], out: Path) -> list[str]:
    """One PNG per quality key; returns the file names written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for key, label in (("psnr", "PSNR entire image (dB)"), ("psnr_transparent", "PSNR transparent region (dB)")):
        points = time_points(runs, key)
        if not points:
            continue
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for method, r in sorted(runs.items()):
            curve = [(e["seconds"], e[f"test_{key}"]) for e in r.log if f"test_{key}" in e]
            if len(curve) > 1:
                ax.plot(*zip(*curve, strict=True), "-", alpha=0.5, label=f"{method} (during training)")
        flags = pareto_front([(t, q) for _, t, q in points])
        front = sorted((t, q) for (_, t, q), f in zip(points, flags, strict=True) if f)
        for (method, t, q), on_front in zip(points, flags, strict=True):
            ax.plot(t, q, "o" if on_front else "x", color="k")
            ax.annotate(method, (t, q), fontsize=7, xytext=(3, 3), textcoords="offset points")
        if front:
            ax.step(*zip(*front, strict=True), where="post", color="r", lw=1, label="Pareto front (final runs)")
        ax.set_xlabel("training time (s)")
        ax.set_ylabel(label)
        ax.set_title(f"{scene}: accuracy against training time")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
        name = f"{scene}_{key}_vs_time.png"
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(name)
    return written


def _copy_image(src: Path, out: Path, name: str) -> str | None:
    if not src.is_file():
        return None
    (out / "images").mkdir(exist_ok=True)
    shutil.copyfile(src, out / "images" / name)
    return f"images/{name}"


def _noise_rows(scene: str, runs: dict[str, Run], roles: Roles, results: Path) -> list[list[str]]:
    """|difference| of each repeat to the method it reruns; the seeds come from the runs' config.json."""
    rows = []
    for method in roles.of_role(runs, "repeat"):
        r, base_name = runs[method], roles.of[method]
        if base_name not in runs:
            continue
        base = runs[base_name]
        seed, base_seed = (_run_seed(results / scene / "runs" / m) for m in (method, base_name))
        kind = "same seed" if seed == base_seed else f"seed {seed}"
        row = [scene, base_name, kind]
        for key in ("psnr", "psnr_transparent"):
            a, b = base.mean.get(key), r.mean.get(key)
            row.append(_fmt(abs(a - b), 3) if isinstance(a, float) and isinstance(b, float) else "-")
        ta, tb = base.seconds, r.seconds
        row.append(_fmt(100 * abs(ta - tb) / max(ta, 1e-9), 1) if ta and tb else "-")
        rows.append(row)
    return rows


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


def _write(results: Path, scenes: dict[str, dict[str, Run]], out: Path, roles: Roles, config_file,
           commands) -> None:
    main = roles.main
    doc = Document("rtsplat benchmark report")
    any_metrics = next((r.metrics for runs in scenes.values() for r in runs.values() if r.metrics), {})
    machine = any_metrics.get("machine", {})
    doc.paragraph(f"Machine: {machine.get('processor') or '?'} ({machine.get('cpus', '?')} CPUs), "
                  f"{machine.get('platform', '?')}; rendering device: {any_metrics.get('render_device', '?')}. "
                  f"Packages: {', '.join(f'{k} {v}' for k, v in any_metrics.get('versions', {}).items())}.")
    doc.paragraph("LPIPS: " + str(any_metrics.get("lpips", "not computed")))
    header = ["method", "PSNR", "SSIM", "LPIPS", "PSNR (transp.)", "SSIM (transp.)", "LPIPS (transp.)", "FPS",
              "train s", "surfels"]
    for scene, runs in scenes.items():
        doc.heading(f"Scene {scene}")
        sfm_summary = results / scene / "sfm" / "summary.json"
        if sfm_summary.is_file():
            text, sfm_header, sfm_rows = sfm_section(_read_json(sfm_summary))
            doc.heading("Structure from motion", 3)
            doc.paragraph(text)
            if sfm_rows:
                doc.table(sfm_header, sfm_rows)
        doc.heading("Quality, speed and training time", 3)
        doc.table(header, quality_rows(runs, main))

        ablations = roles.of_role(runs, "ablation")
        if ablations and main in runs:
            doc.heading("Ablations (transparent-region PSNR)", 3)
            full = runs[main].mean.get("psnr_transparent")
            rows = [[main, _fmt(full), "0.00"]]
            for m in ablations:
                v = runs[m].mean.get("psnr_transparent")
                delta = v - full if isinstance(v, float) and isinstance(full, float) else None
                rows.append([m, _fmt(v), _fmt(delta)])
            doc.table(["method", "PSNR (transp.)", f"vs {main}"], rows)

        layer_rows = [[m, _fmt(r.mean.get("psnr_reflection_layer")), _fmt(r.mean.get("psnr_transmission_layer"))]
                      for m, r in sorted(runs.items()) if "psnr_transmission_layer" in r.mean]
        if layer_rows:
            doc.heading("Decomposition against the ground-truth layers (PSNR in the transparent region, test views)", 3)
            doc.table(["method", "reflection", "transmission"], layer_rows)

        doc.heading("Accuracy against training time", 3)
        for name in plot_accuracy_time(scene, runs, out):
            doc.images([(name, name)])
        points = time_points(runs, "psnr_transparent") or time_points(runs, "psnr")
        key = "psnr_transparent" if time_points(runs, "psnr_transparent") else "psnr"
        flags = pareto_front([(t, q) for _, t, q in points])
        doc.table(["method", "train s", key, "Pareto front"],
                  [[m, _fmt(t, 1), _fmt(q), "yes" if f else ""] for (m, t, q), f in
                   sorted(zip(points, flags, strict=True), key=lambda x: x[0][1])])

        test_names = next((r.metrics.get("views") for r in runs.values() if r.metrics.get("views")), {})
        if test_names:
            view = sorted(test_names)[0]
            items = []
            prepared = results / scene / "prepared" / "images" / f"{view}.png"
            gt = _copy_image(prepared, out, f"{scene}_{view}_gt.png")
            if gt:
                items.append((gt, "ground truth"))
            compared = [main] if main in runs else []
            compared += [m for m in sorted(runs) if m != main and roles.role.get(m, "baseline") != "ablation"]
            for method in compared:
                img = _copy_image(results / scene / "renders" / method / "color" / f"{view}.png", out,
                                  f"{scene}_{view}_{method}.png")
                if img:
                    items.append((img, method))
            if items:
                doc.heading(f"Test view {view}", 3)
                doc.images(items)
            layers = []
            for layer in ("reflection", "transmission", "scatter", "normal", "depth"):
                if main is None:
                    break
                img = _copy_image(results / scene / "renders" / main / layer / f"{view}.png", out,
                                  f"{scene}_{view}_{layer}.png")
                if img:
                    layers.append((img, layer))
            if layers:
                doc.heading(f"Decomposition ({main})", 3)
                doc.images(layers)
            edits = []
            for edit_dir in sorted((results / scene / "renders").glob(f"{main}@*") if main else []):
                img = _copy_image(edit_dir / "color" / f"{view}.png", out, f"{scene}_{view}_{edit_dir.name}.png")
                if img:
                    edits.append((img, edit_dir.name.split("@", 1)[1]))
            if edits:
                doc.heading("Scene editing", 3)
                doc.images(edits)

    doc.heading("Noise")
    noise = [row for scene, runs in scenes.items() for row in _noise_rows(scene, runs, roles, results)]
    if noise:
        doc.paragraph("Differences between runs of the same config on this machine. Same seed: quality differences "
                      "come from non-deterministic floating-point reductions, time differences from machine load; "
                      "expect a rerun to reproduce the numbers within these. Another seed: the spread to expect "
                      "between methods that are in truth equally good, so smaller gaps between methods are not "
                      "significant.")
        doc.table(["scene", "method", "rerun", "|dPSNR|", "|dPSNR transp.|", "time diff %"], noise)
    else:
        doc.paragraph("No repeated runs in these results, so run-to-run noise was not measured here.")
    doc.heading("Reproduce")
    doc.code("\n".join(commands or ["make demo"]))
    files = config_file if isinstance(config_file, (list, tuple)) else [config_file] if config_file else []
    for path in files:
        if Path(path).is_file():
            doc.paragraph(f"{Path(path).name}:")
            doc.code(Path(path).read_text())
    page, markdown = doc.finish()
    (out / "index.html").write_text(page)
    (out / "index.md").write_text(markdown)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--results", type=Path, required=True, help="results directory of the workflow")
    parser.add_argument("--out", type=Path, required=True, help="report directory (replaced atomically)")
    parser.add_argument("--config", type=Path, action="append", default=[],
                        help="a config file to print in the Reproduce section (repeat for layered configs)")
    parser.add_argument("--command", action="append", default=[], help="a command to print in Reproduce")
    parser.add_argument("--roles-json", help="the methods' roles as JSON {method: {role, of}} "
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
