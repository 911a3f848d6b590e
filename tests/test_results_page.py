"""docs/results.md (and every docs page with a record kept beside it) is generated: it is what
`python -m rtsplat.results_page` writes from that record."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtsplat.results_page import kept_json, read_report, results_markdown

ROOT = Path(__file__).resolve().parent.parent
PAGE = "docs/results.md"
KEPT = sorted((ROOT / "docs").glob("*.report.json"))  # every generated page's record (docs/results.report.json, ...)


def test_docs_results_keeps_its_record():
    assert kept_json(ROOT / PAGE) == ROOT / "docs" / "results.report.json" and kept_json(ROOT / PAGE) in KEPT


@pytest.mark.parametrize("record", KEPT, ids=[path.name for path in KEPT])
def test_a_generated_page_is_what_its_kept_record_gives(record):
    """A hand edit of docs/results.md (or of any page with a record beside it, or of the record without writing
    the page again) fails here."""
    page = record.with_name(record.name.removesuffix(".report.json") + ".md")
    relative = page.relative_to(ROOT).as_posix()
    assert results_markdown(read_report(record), relative) == page.read_text(), (
        f"{relative} is not what its record gives: write it with `python -m rtsplat.results_page --report "
        f"{record.relative_to(ROOT).as_posix()} --out {relative}` (or its make target), never by hand")


def test_the_kept_record_is_written_beside_the_page_but_never_over_a_users_json(tmp_path, capsys):
    from rtsplat.results_page import main

    (tmp_path / "rep").mkdir()
    (tmp_path / "rep" / "report.json").write_text('{"tables": [], "scenes": ["s"], "written": "today"}')
    users = tmp_path / "mine.report.json"
    users.write_text('{"my": "numbers"}')
    before = users.read_bytes()
    assert main(["--report", str(tmp_path / "rep"), "--out", str(tmp_path / "mine.md")]) == 1
    assert "mine.report.json" in capsys.readouterr().err
    assert users.read_bytes() == before and not (tmp_path / "mine.md").exists()  # neither file written
    assert main(["--report", str(tmp_path / "rep"), "--out", str(tmp_path / "page.md")]) == 0
    kept = read_report(tmp_path / "page.report.json")
    assert kept["scenes"] == ["s"] and kept["source"] == str(tmp_path / "rep")
    # written again from its kept record, the page is the same and the record stays as it is
    page, record = (tmp_path / "page.md").read_text(), (tmp_path / "page.report.json").read_bytes()
    assert main(["--report", str(tmp_path / "page.report.json"), "--out", str(tmp_path / "page.md")]) == 0
    assert (tmp_path / "page.md").read_text() == page and (tmp_path / "page.report.json").read_bytes() == record
