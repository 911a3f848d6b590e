"""rtsplat.provenance: the commit and uncommitted changes of a checkout, and how runs' records group and mix."""

from __future__ import annotations

import subprocess
from pathlib import Path

from rtsplat.provenance import group_runs, mixture_sentences, parts_of, run_record, source_tree


def _git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True).stdout.strip()


def test_source_tree_names_the_commit_and_tells_uncommitted_changes_apart(tmp_path):
    root = tmp_path / "repo"
    root.mkdir()
    _git(root, "init", "-q")
    (root / "code.py").write_text("x = 1\n")
    _git(root, "add", "code.py")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    clean = source_tree(root)
    assert clean == {"commit": _git(root, "rev-parse", "HEAD"), "dirty": False, "diff_sha256": None}
    (root / "untracked.py").write_text("y = 2\n")  # untracked files are not counted
    assert source_tree(root) == clean
    (root / "code.py").write_text("x = 2\n")
    first = source_tree(root)
    assert first["commit"] == clean["commit"] and first["dirty"] is True and len(first["diff_sha256"]) == 16
    assert source_tree(root) == first  # the same changes, the same hash
    (root / "code.py").write_text("x = 3\n")
    assert source_tree(root)["diff_sha256"] != first["diff_sha256"]
    # edits to the documentation (docs/, Markdown anywhere), which no stage reads, are not uncommitted changes
    (root / "code.py").write_text("x = 1\n")
    documentation = [root / page for page in ("docs/page.md", "docs/figure.svg", "README.md", "pkg/notes.md")]
    for page in documentation:
        page.parent.mkdir(exist_ok=True)
        page.write_text("one\n")
    _git(root, "add", ".")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "pages")
    pages = source_tree(root)
    for page in documentation:
        page.write_text("two\n")
    assert source_tree(root) == pages and pages["dirty"] is False
    (root / "pkg" / "notes.py").write_text("z = 1\n")
    _git(root, "add", "pkg/notes.py")  # staged, not committed: a change to the code
    assert source_tree(root)["dirty"] is True
    # a folder inside a checkout is not the checkout of the code: nothing recorded rather than another commit
    (root / "sub").mkdir()
    assert source_tree(root / "sub") == {"commit": None, "dirty": None, "diff_sha256": None}
    assert source_tree(tmp_path) == {"commit": None, "dirty": None, "diff_sha256": None}


def _record(commit: str, host: str = "h1", dirty: bool = False) -> dict:
    return {"commit": commit * 40, "dirty": dirty, "diff_sha256": "d" * 16 if dirty else None, "device": "cpu",
            "machine": {"hostname": host, "processor": "CPU", "cpus": 2}, "versions": {"torch": "2.13.0"}}


def test_a_run_resumed_by_other_code_keeps_each_part_and_groups_apart():
    one = run_record([_record("a")])
    resumed = run_record([_record("a"), _record("b")])
    assert "earlier_parts" not in one and parts_of(one) == [_record("a")]
    assert parts_of(resumed) == [_record("a"), _record("b")] and run_record([]) is None
    groups = group_runs({"s/x": one, "s/y": dict(one), "s/z": resumed, "s/old": None})
    assert [(g["commit"], g["runs"]) for g in groups] == [
        ("aaaaaaaaaaaa", ["s/x", "s/y"]), ("aaaaaaaaaaaa then bbbbbbbbbbbb", ["s/z"]), ("not recorded", ["s/old"])]


def test_mixture_sentences_name_commits_dirty_trees_machines_and_missing_records():
    assert mixture_sentences({"s/x": _record("a"), "s/y": _record("a")}) == []
    mixed = mixture_sentences({"s/x": _record("a"), "s/y": _record("b", host="h2"), "s/z": _record("a", dirty=True),
                               "s/old": None})
    assert len(mixed) == 4
    assert mixed[0].startswith("These runs were trained by 3 different versions of the code")
    assert "1 of 4 runs were trained from a tree with uncommitted changes" in mixed[1] and "s/z" in mixed[1]
    assert "2 machines" in mixed[2] and "h2: CPU, 2 cores" in mixed[2]
    assert mixed[3] == "1 of 4 runs do not record the code that trained them: s/old."
