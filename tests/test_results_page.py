"""docs/results.md is generated: it is what `python -m rtsplat.results_page` writes from the record kept beside it."""

from __future__ import annotations

from pathlib import Path

from rtsplat.results_page import kept_json, read_report, results_markdown

ROOT = Path(__file__).resolve().parent.parent
PAGE = "docs/results.md"


def test_docs_results_is_what_its_kept_record_gives():
    """A hand edit of docs/results.md (or of its record without writing the page again) fails here."""
    record = read_report(kept_json(ROOT / PAGE))
    assert kept_json(ROOT / PAGE) == ROOT / "docs" / "results.report.json"
    assert results_markdown(record, PAGE) == (ROOT / PAGE).read_text(), (
        "docs/results.md is not what its record gives: write it with `python -m rtsplat.results_page --report "
        "docs/results.report.json --out docs/results.md` (or `make results-page`), never by hand")
