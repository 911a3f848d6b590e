"""``docs/results.md`` from a report: the current numbers on one page, with the commit and the machine.

``rtsplat report`` writes its tables as data (``report.json``: every table with the headings above it,
the commit of the code that computed the metrics, the machine, the package versions). This module keeps
the tables a reader of the project asks for first (RT-Splatting against 2DGS, the scene family, quality, speed and
training time, accuracy against time, ablations, the decomposition) and writes them as one Markdown
page that says where they come from::

    python -m rtsplat.results_page --report demo/results/report --out docs/results.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rtsplat.errors import PipelineError, run_command
from rtsplat.io.outputs import write_page
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
)
PROGRAM = "python -m rtsplat.results_page"
COMMAND = PROGRAM + " --report REPORT_DIR --out {page}"
MARKER = f"Written by `{PROGRAM} "  # the page's first line: how --out knows a page of its own
DEFAULT_PAGE = "docs/results.md"


def read_report(report: Path) -> dict:
    path = report / REPORT_JSON
    if not path.is_file():
        raise PipelineError(f"no {REPORT_JSON} in this folder", path=report,
                            fix="pass the folder that `rtsplat report` wrote (e.g. demo/results/report); "
                                "a report written before report.json existed needs `rtsplat report` again")
    try:
        record = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PipelineError(f"not valid JSON ({exc})", path=path, fix="write the report again") from None
    problem = report_shape_problem(record)
    if problem:
        raise PipelineError(f"not a report of `rtsplat report`: {problem}", path=path,
                            fix="pass the folder that `rtsplat report` wrote, or write the report again")
    return record


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


def commit_line(record: dict) -> str:
    """The page's commit line: the report's commit, or each commit with how many runs it measured when the
    report's runs came from different code (``commits``)."""
    commits = record.get("commits") or {}
    if len(commits) > 1:
        return "- Commits: " + ", ".join(f"`{commit}` ({len(runs)} run{'' if len(runs) == 1 else 's'})"
                                         for commit, runs in commits.items())
    return f"- Commit: `{record.get('commit') or 'not recorded'}`"


def results_markdown(record: dict, source: str, page: str = DEFAULT_PAGE) -> str:
    """The page of one report's ``record`` (its report.json); ``source``: the report folder, as named on the
    page; ``page``: the path the page is written to, as its command to write it again names it."""
    machine = record.get("machine") or {}
    versions = ", ".join(f"{k} {v}" for k, v in (record.get("versions") or {}).items())
    lines = [
        "# Results",
        "",
        f"{MARKER}{COMMAND.format(page=page).removeprefix(PROGRAM + ' ')}` from the report in `{source}` "
        f"(written {record.get('written', '?')}): "
        "do not edit by hand. What the columns mean, the plots and every other table: the report itself "
        "(`index.html`); what was measured around these numbers and why: [benchmarks.md](benchmarks.md).",
        "",
        commit_line(record),
        f"- Machine: {machine.get('processor') or '?'} ({machine.get('cpus', '?')} CPUs), "
        f"{machine.get('platform', '?')}; rendering device: {record.get('render_device') or '?'}",
        f"- Packages: {versions or '?'}",
        f"- Scenes: {', '.join(map(str, record.get('scenes') or [])) or '?'}",
        "",
    ]
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
    parser.add_argument("--report", type=Path, required=True, help="a folder written by rtsplat report")
    parser.add_argument("--out", type=Path, help="the page to write (default: print it)")
    args = parser.parse_args(argv)

    def work() -> None:
        text = results_markdown(read_report(args.report), str(args.report), str(args.out or DEFAULT_PAGE))
        write_page(text, args.out, PROGRAM, MARKER, inputs=[args.report])

    return run_command("rtsplat.results_page", work)


if __name__ == "__main__":
    sys.exit(main())
