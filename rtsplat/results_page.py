"""``docs/results.md`` from a report: the current numbers on one page, with the code and the machine that made them.

``rtsplat report`` writes its tables as data (``report.json``: every table with the headings above it, what
trained each run: commit, uncommitted changes, machine, device, packages, and whether they mix). This module
keeps the tables a reader of the project asks for first (RT-Splatting against 2DGS, the scene family, quality,
speed and training time, accuracy against time, ablations, the decomposition, the convergence section) and
writes them as one Markdown page that says where they come from, with the report's record kept beside it
(``docs/results.report.json`` beside ``docs/results.md``: the page is what that JSON gives, which a test checks)::

    python -m rtsplat.results_page --report demo/results/report --out docs/results.md
    python -m rtsplat.results_page --report docs/results.report.json --out docs/results.md   # the same page again

``make results-page`` runs the benchmark behind ``docs/results.md`` on a clean tree and writes both.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rtsplat.errors import PipelineError, run_command
from rtsplat.io.atomic import write_json_atomic
from rtsplat.io.outputs import check_output_file, json_with_keys, write_page
from rtsplat.provenance import NOT_RECORDED
from rtsplat.report import REPORT_JSON

# the report's headings whose tables the page keeps, in the report's order
KEPT_HEADINGS = (
    "Summary: RT-Splatting against plain 2DGS",
    "Scene family: RT-Splatting minus plain 2DGS per scene",
    "Quality",
    "Speed and training time",
    "Accuracy against training time",
    "Ablations (transparent-region PSNR)",
    "Decomposition against the ground-truth layers (PSNR in the transparent region, test views)",
    "Convergence: RT-Splatting and plain 2DGS at several budgets",
)
PROGRAM = "python -m rtsplat.results_page"
COMMAND = PROGRAM + " --report REPORT_DIR --out {page}"
MARKER = f"Written by `{PROGRAM} "  # the page's first line: how --out knows a page of its own
DEFAULT_PAGE = "docs/results.md"
KEPT_SUFFIX = ".report.json"
REPORT_RECORD_KEYS = ("tables", "source")  # what tells a kept record written here from another JSON file


def kept_json(page: Path) -> Path:
    """The report record kept beside ``page``: ``docs/results.md`` -> ``docs/results.report.json``."""
    return page.with_name(page.stem + KEPT_SUFFIX)


def read_report(report: Path) -> dict:
    """The record of a report folder (its ``report.json``) or of a kept record (a ``.json`` file), with the
    report it came from as ``source`` (the folder as named here, unless the record already names one)."""
    path = report if report.suffix == ".json" else report / REPORT_JSON
    if not path.is_file():
        raise PipelineError(f"no {REPORT_JSON} in this folder" if path != report else "no such file", path=report,
                            fix="pass the folder that `rtsplat report` wrote (e.g. demo/results/report) or a "
                                "kept record (docs/results.report.json); a report written before report.json "
                                "existed needs `rtsplat report` again")
    try:
        record = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PipelineError(f"not valid JSON ({exc})", path=path, fix="write the report again") from None
    problem = report_shape_problem(record)
    if problem:
        raise PipelineError(f"not a report of `rtsplat report`: {problem}", path=path,
                            fix="pass the folder that `rtsplat report` wrote, or write the report again")
    return {**record, "source": record.get("source") or str(report)}


# the keys of report.json the page reads, with the JSON type each must have when present
REPORT_KEYS = {"tables": list, "machine": dict, "versions": dict, "commits": dict, "scenes": list}
TABLE_KEYS = {"headings": list, "header": list, "rows": list}


def report_shape_problem(record) -> str | None:
    """What in ``record`` (a parsed report.json) is not of the shape the page reads, None when all is."""
    if not isinstance(record, dict):
        return f"it holds a JSON {type(record).__name__}, not an object"
    for key, kind in REPORT_KEYS.items():
        if record.get(key) is not None and not isinstance(record[key], kind):
            return f"its {key!r} is a JSON {type(record[key]).__name__}, not a {kind.__name__}"
    for number, table in enumerate(record.get("tables") or [], 1):
        if not isinstance(table, dict) or not all(isinstance(table.get(k), t) for k, t in TABLE_KEYS.items()):
            return f"its table {number} is not an object with the lists {', '.join(TABLE_KEYS)}"
    return None


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines + [""]


def provenance_lines(record: dict) -> list[str]:
    """What trained the page's runs: what they mix (the report's ``mixed`` sentences) first, then the one
    commit and machine, or each group of runs with its commit, machine and device."""
    groups = record.get("provenance")
    if not groups:
        return ["- Commit: not recorded (this report.json records no provenance of its runs)"]
    lines = ["**Mixed provenance:** " + " ".join(record["mixed"]), ""] if record.get("mixed") else []
    if len(groups) == 1:
        only = groups[0]
        commit = ("not recorded by the runs' training" if only["commit"] == NOT_RECORDED
                  else f"`{only['commit']}` (trained every run)")
        return lines + [f"- Commit: {commit}",
                        f"- Machine: {only['machine']}; training device: {only['device']}; rendering device: "
                        f"{record.get('render_device') or '?'}",
                        f"- Packages: {only['packages']}"]
    lines.append(f"- Trained by {len(groups)} combinations of commit, machine and device "
                 f"(rendering device: {record.get('render_device') or '?'}):")
    for group in groups:
        runs = len(group["runs"])
        lines.append(f"  - `{group['commit']}` on {group['machine']}, device {group['device']}, "
                     f"{group['packages']}: {runs} run{'' if runs == 1 else 's'} ({', '.join(group['runs'])})")
    return lines


def results_markdown(record: dict, page: str = DEFAULT_PAGE) -> str:
    """The page of one report's ``record`` (:func:`read_report`); ``page``: the path the page is written to,
    as its command to write it again names it."""
    kept = kept_json(Path(page)).name
    lines = [
        "# Results",
        "",
        f"{MARKER}{COMMAND.format(page=page).removeprefix(PROGRAM + ' ')}` from the report in "
        f"`{record.get('source', '?')}` (written {record.get('written', '?')}), whose record is kept beside this "
        f"page as `{kept}`: do not edit by hand (a test checks that this page is what that record gives). What the "
        "columns mean, the plots and every other table: the report itself (`index.html`); what was measured around "
        "these numbers and why: [benchmarks.md](benchmarks.md).",
        "",
    ]
    if record.get("note"):
        lines += [record["note"], ""]
    lines += [*provenance_lines(record), f"- Scenes: {', '.join(record.get('scenes', [])) or '?'}", ""]
    current_scene, current_headings = None, None
    for table in record.get("tables") or []:
        headings = table["headings"]
        if not headings or headings[-1] not in KEPT_HEADINGS:
            continue
        scene = headings[0] if len(headings) > 1 else None
        if scene != current_scene and scene is not None:
            lines += [f"## {scene}", ""]
            current_scene = scene
        if headings != current_headings:  # a section's second table follows its first without a heading
            lines += [f"{'###' if scene else '##'} {headings[-1]}", ""]
            current_headings = headings
        lines += _table(table["header"], table["rows"])
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.results_page", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--report", type=Path, required=True,
                        help="a folder written by rtsplat report, or a kept record (docs/results.report.json)")
    parser.add_argument("--out", type=Path, help="the page to write, with the record beside it "
                        "(<page stem>.report.json; default: print the page)")
    args = parser.parse_args(argv)

    def work() -> None:
        record = read_report(args.report)
        text = results_markdown(record, str(args.out or DEFAULT_PAGE))
        kept = None if args.out is None else kept_json(args.out)
        if kept is not None and kept.resolve() == args.report.resolve():
            kept = None  # written again from its own kept record: the record stays as it is
        if kept is not None:  # checked before the page is written, so a refusal writes neither
            check_output_file(kept, "results_page", lambda path: json_with_keys(path, REPORT_RECORD_KEYS),
                              example="another --out, whose record goes beside it", command=PROGRAM)
        write_page(text, args.out, PROGRAM, MARKER, inputs=[args.report])
        if kept is not None:
            write_json_atomic(kept, record)

    return run_command("rtsplat.results_page", work)


if __name__ == "__main__":
    sys.exit(main())
