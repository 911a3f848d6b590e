"""Every command-line option that names a file or folder, of every ``rtsplat <stage>`` and every
``python -m rtsplat.*`` command, is either an input (only read) or an output that goes through the
output rule of :mod:`rtsplat.io.outputs` (written only where nothing is or where its own earlier output
is, never onto an input, atomically), with a test that shows it refusing a user's file and leaving it
as it was. A new option of type Path fails here until it is listed below with such a test."""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import test_bad_inputs  # noqa: E402

from rtsplat.cli import STAGES, stage_parser  # noqa: E402

PACKAGE = Path(__file__).resolve().parent.parent / "rtsplat"
TESTS = Path(__file__).resolve().parent

# (command, option) -> the tests that show the option refusing what is not its own output: a case of
# test_bad_inputs.CASES, or "<test file>::<test function>"
OUTPUTS = {
    ("rtsplat sfm", "--out"): ["output: sfm out is a user folder", "output: sfm out is the scene"],
    ("rtsplat masks", "--out"): ["output: masks out is a user folder", "output: masks out is the scene"],
    ("rtsplat prepare", "--out"): ["output: prepare out is the scene", "output: prepare out is the run"],
    ("rtsplat train", "--out"): ["output: train out is a user folder", "output: train out is the prepared scene"],
    ("rtsplat train", "--checkpoint-dir"): ["write: train --checkpoint-dir is a user folder"],
    ("rtsplat render", "--out"): ["output: render out is the run", "output: render out inside the dataset"],
    ("rtsplat video", "--out"): ["test_video.py::test_bad_video_settings_are_clear_errors"],
    ("rtsplat video", "--poster"): ["entry: video --poster onto a user's PNG", "entry: video --poster inside the run",
                                    "test_bad_inputs.py::test_a_command_replaces_its_own_file_and_its_committed_page"],
    ("rtsplat video", "--keep-frames"): ["entry: video --keep-frames a user folder"],
    ("rtsplat fps", "--out"): ["write: fps onto the metrics JSON", "write: fps onto a folder"],
    ("rtsplat metrics", "--out"): ["write: metrics onto a user's file", "write: metrics onto the renders"],
    ("rtsplat report", "--out"): ["output: report out is the results", "output: report out is the masks output"],
    ("rtsplat synth", "--out"): ["test_outputs.py::test_synth_replaces_only_with_overwrite"],
    ("rtsplat demo", "--out"): ["entry: demo --out a user folder", "entry: rtsplat demo --out a dataset"],
    ("python -m rtsplat.demo", "--out"): ["entry: demo --out a user folder"],
    ("python -m rtsplat.results_page", "--out"): [
        "entry: results_page --out a user's notes", "entry: results_page --out its own report.json",
        "test_bad_inputs.py::test_a_command_replaces_its_own_file_and_its_committed_page"],
    ("python -m rtsplat.config_reference", "--out"): ["entry: config_reference --out a user's notes"],
    ("python -m rtsplat.bench.layer_strip", "--out"): ["entry: bench.layer_strip --out a user's PNG"],
    ("python -m rtsplat.bench.mask_propagation", "--figure"): ["entry: bench.mask_propagation --figure a user's PNG"],
    ("python -m rtsplat.bench.iteration", "--state-dir"): ["entry: bench.iteration --state-dir a user folder"],
    ("python -m rtsplat.bench.paired_cost", "--out"): [
        "test_paired_cost.py::test_the_out_folder_is_never_a_folder_of_the_users"],
    ("python -m rtsplat.bench.sfm_steps", "--out"): ["output: sfm out is a user folder"],  # each run is run_sfm's
    ("python -m rtsplat.synth.sfm_check", "work"): ["output: sfm out is a user folder"],  # run_sfm's --out
}
INPUTS = {
    "--scene-dir", "--masks", "--sfm", "--data", "--run", "--renders", "--gt-layers", "--results", "--config",
    "--report", "--check", "--dataset", "--prepared", "--scene", "--checkout", "--model", "scene_dir", "scenes",
    "dataset", "--seconds-of", "--baseline",
}


class _Parsed(Exception):
    """Raised in place of parsing: the parser of a ``main`` is caught without running the command."""


def _parser_of(module) -> argparse.ArgumentParser:
    """The argument parser a module's ``main`` builds, caught as it is about to parse."""
    caught = {}

    def catch(self, *args, **kwargs):
        caught["parser"] = self
        raise _Parsed

    original = argparse.ArgumentParser.parse_args
    argparse.ArgumentParser.parse_args = catch
    try:
        module.main([])
    except _Parsed:
        pass
    finally:
        argparse.ArgumentParser.parse_args = original
    return caught["parser"]


def commands() -> dict[str, argparse.ArgumentParser]:
    """Every command a user runs, by name, with its parser."""
    found = {f"rtsplat {stage.name}": stage_parser(stage, importlib.import_module(stage.module)) for stage in STAGES}
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        if 'if __name__ == "__main__"' not in text or "def main(" not in text or path.name == "cli.py":
            continue
        name = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        found[f"python -m {name}"] = _parser_of(importlib.import_module(name))
    return found


def path_options() -> set[tuple[str, str]]:
    """(command, option) for every option or argument of type Path (its flag, or its name if positional)."""
    options = set()
    for command, parser in commands().items():
        for action in parser._actions:
            if action.type is Path and action.help != argparse.SUPPRESS:
                options.add((command, action.option_strings[0] if action.option_strings else action.dest))
    return options


def test_every_option_naming_a_path_is_an_input_or_a_checked_output():
    options = path_options()
    assert ("rtsplat video", "--poster") in options and ("python -m rtsplat.results_page", "--out") in options
    unlisted = sorted(o for o in options if o not in OUTPUTS and o[1] not in INPUTS)
    assert not unlisted, (f"options that name a path but are neither listed inputs nor outputs with a test: "
                          f"{unlisted}; an output goes through rtsplat.io.outputs (see its docstring)")
    stale = sorted(o for o in OUTPUTS if o not in options)
    assert not stale, f"listed outputs that no command has any more: {stale}"


@pytest.mark.parametrize("option", sorted(OUTPUTS))
def test_every_output_option_has_a_test_that_refuses_a_users_file(option):
    for test in OUTPUTS[option]:
        if "::" in test:
            file, function = test.split("::")
            assert re.search(rf"^def {function}\(", (TESTS / file).read_text(), re.M), f"{test} does not exist"
        else:
            assert test in test_bad_inputs.CASES, f"no case {test!r} in test_bad_inputs.CASES"


def test_synth_replaces_only_with_overwrite(tmp_path, capsys):
    """``rtsplat synth --out`` writes a dataset (images/, sparse/): an existing folder is replaced only when
    the user says so with --overwrite, and then only one that synth wrote."""
    from rtsplat.cli import main

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine/notes.txt").write_text("the user's own file")
    argv = ["synth", "--scene", "dome", "--views", "40", "--width", "16", "--height", "16", "--spp", "1",
            "--out", str(tmp_path / "mine")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 'mine'}: the output exists" in err and "--overwrite" in err
    assert main([*argv, "--overwrite"]) == 1
    assert "was not written by 'rtsplat synth'" in capsys.readouterr().err
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]
    assert (tmp_path / "mine/notes.txt").read_text() == "the user's own file"
