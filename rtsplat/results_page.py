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

from rtsplat.errors import PipelineError
from rtsplat.io.atomic import print_or_write
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
COMMAND = "python -m rtsplat.results_page --report REPORT_DIR --out {page}"
DEFAULT_PAGE = "docs/results.md"


def read_report(report: Path) -> dict:
    path = report / REPORT_JSON
    if not path.is_file():
        raise PipelineError(f"no {REPORT_JSON} in this folder", path=report,
                            fix="pass the folder that `rtsplat report` wrote (e.g. demo/results/report); "
                                "a report written before report.json existed needs `rtsplat report` again")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PipelineError(f"not valid JSON ({exc})", path=path, fix="write the report again") from None


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
        f"Written by `{COMMAND.format(page=page)}` from the report in `{source}` "
        f"(written {record.get('written', '?')}): "
        "do not edit by hand. What the columns mean, the plots and every other table: the report itself "
        "(`index.html`); what was measured around these numbers and why: [benchmarks.md](benchmarks.md).",
        "",
        commit_line(record),
        f"- Machine: {machine.get('processor') or '?'} ({machine.get('cpus', '?')} CPUs), "
        f"{machine.get('platform', '?')}; rendering device: {record.get('render_device') or '?'}",
        f"- Packages: {versions or '?'}",
        f"- Scenes: {', '.join(record.get('scenes', [])) or '?'}",
        "",
    ]
    current_scene, current_headings = None, None
    for table in record.get("tables", []):
        headings = table.get("headings", [])
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
    try:
        text = results_markdown(read_report(args.report), str(args.report), str(args.out or DEFAULT_PAGE))
    except PipelineError as exc:
        print(f"rtsplat.results_page: error: {exc}", file=sys.stderr)
        return 1
    print_or_write(text, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
