"""Output folders a stage may replace: only ones it wrote itself, never its inputs or a dataset.

Every stage output folder holds a marker file, :data:`MARKER`, naming the stage that wrote it. Before a
stage touches anything, :func:`check_output_dir` refuses an ``--out`` that

- is, contains or lies inside one of the stage's inputs,
- is or lies inside a dataset folder (a folder with ``images/`` or ``sparse/`` that no stage wrote)
  or inside another stage's output,
- already exists with content but without this stage's marker (a folder of the user's, or another
  stage's output).

:func:`output_dir` is :func:`rtsplat.io.atomic.atomic_dir` with that check and the marker. A command whose
output is one file (metrics, fps, the video and its poster, a generated page) checks it with
:func:`check_output_file`: no folder, no input, and an existing file only when its content says that command
wrote it (the result's keys, the MP4's comment, the PNG's ``Software`` text, the page's "Written by" line),
never another file of the user's. :func:`write_page` is that check and an atomic write for the generated
Markdown pages. Every command-line option that names an output goes through one of these
(``tests/test_outputs.py`` lists them all).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from rtsplat.errors import PipelineError
from rtsplat.io.atomic import atomic_dir, write_json_atomic, write_text_atomic
from rtsplat.io.images import png_software

MARKER = ".rtsplat-output"
DATASET_PARTS = ("images", "sparse")


def output_stage(folder: str | Path) -> str | None:
    """The stage named by ``folder``'s marker, None when it has none (or an unreadable one)."""
    path = Path(folder) / MARKER
    if not path.is_file():
        return None
    try:
        stage = json.loads(path.read_text()).get("stage")
    except (OSError, ValueError, AttributeError):
        return None
    return stage if isinstance(stage, str) else None


def is_dataset_dir(folder: str | Path) -> bool:
    """Whether ``folder`` looks like a dataset scene (``images/`` or ``sparse/`` inside) no stage wrote."""
    folder = Path(folder)
    return output_stage(folder) is None and any((folder / part).is_dir() for part in DATASET_PARTS)


def _resolved(path: str | Path) -> Path:
    return Path(path).expanduser().resolve()


def check_output_dir(out: str | Path, stage: str, inputs: Iterable[str | Path | None] = (),
                     containers: Iterable[str | Path | None] = (), flag: str = "--out") -> None:
    """Raise :class:`PipelineError` unless ``stage`` may write (and replace) the folder ``out``.

    ``inputs``: folders or files the stage reads (None entries are skipped); ``out`` may be none of
    them, contain none and lie inside none. ``containers``: inputs inside which ``out`` may lie (the
    report's results tree), though it may still be neither one of them nor contain one. ``flag``: the
    option that named ``out``, for the messages.
    """
    target = _resolved(out)
    fix = f"pass {'an' if flag == '--out' else 'a'} {flag} of its own, e.g. a new folder under results/"
    folder_is = "the output folder" if flag == "--out" else f"the {flag} folder"
    for kind, paths in (("input", inputs), ("container", containers)):
        for given in paths:
            if given is None:
                continue
            inp = _resolved(given)
            if target == inp:
                raise PipelineError(f"{folder_is} is the {stage} input {given}; writing it would "
                                    "replace that input", path=out, fix=fix)
            if target in inp.parents:
                raise PipelineError(f"{folder_is} contains the {stage} input {given}; writing it would "
                                    "delete that input", path=out, fix=fix)
            if kind == "input" and inp in target.parents:
                raise PipelineError(f"{folder_is} lies inside the {stage} input {given}", path=out, fix=fix)
    for folder in target.parents:
        if is_dataset_dir(folder):
            raise PipelineError(f"{folder_is} lies inside the dataset folder {folder}", path=out,
                                fix=fix + "; dataset folders are never written")
    _check_outside_outputs(target, out, folder_is, fix)
    if not target.exists():
        return
    if not target.is_dir():
        raise PipelineError(f"{folder_is.replace('folder', 'path')} exists and is not a folder", path=out,
                            fix="pass the path of a folder (it is created), or remove that file yourself")
    found = output_stage(target)
    if found == stage:
        return
    if found is not None:
        raise PipelineError(f"{folder_is} was written by 'rtsplat {found}', not 'rtsplat {stage}'",
                            path=out, fix=fix)
    if is_dataset_dir(target):
        raise PipelineError(f"{folder_is} is a dataset folder (it has images/ or sparse/); "
                            f"'rtsplat {stage}' never replaces it", path=out, fix=fix)
    if any(target.iterdir()):
        raise PipelineError(f"{folder_is} exists, is not empty and was not written by 'rtsplat {stage}' "
                            f"(it has no {MARKER} file)", path=out,
                            fix=fix + ", or delete that folder yourself if you no longer need it")


def _check_outside_outputs(target: Path, out: str | Path, what: str, fix: str) -> None:
    """Refuse ``target`` (``out`` resolved) inside a folder a stage wrote: that stage replaces the whole
    folder when it runs again, and ``what`` (the output, for the message) would go with it."""
    for folder in target.parents:
        other = output_stage(folder)
        if other is not None:
            raise PipelineError(f"{what} lies inside the output of 'rtsplat {other}' ({folder}), "
                                "which would delete it when it runs again", path=out, fix=fix)


def mark_output(folder: str | Path, stage: str) -> None:
    """Write the marker that says ``stage`` wrote ``folder`` (and may replace it)."""
    write_json_atomic(Path(folder) / MARKER, {"stage": stage})


@contextmanager
def output_dir(out: str | Path, stage: str, inputs: Iterable[str | Path | None] = (),
               containers: Iterable[str | Path | None] = ()) -> Iterator[Path]:
    """:func:`rtsplat.io.atomic.atomic_dir` for the output of ``stage``: checked with
    :func:`check_output_dir` before anything is written, marked as ``stage``'s output."""
    inputs, containers = list(inputs), list(containers)
    check_output_dir(out, stage, inputs, containers)
    with atomic_dir(out) as tmp:
        mark_output(tmp, stage)
        yield tmp


def check_output_file(out: str | Path, stage: str, is_own: Callable[[Path], bool],
                      inputs: Iterable[str | Path | None] = (), example: str | None = None, flag: str = "--out",
                      command: str | None = None) -> None:
    """Raise :class:`PipelineError` unless ``stage`` may write (and replace) the file ``out``: it is no
    folder, none of ``inputs`` nor inside one of them nor inside a folder a stage wrote (which that stage
    replaces whole), and a file already there is one ``stage`` wrote
    (``is_own`` says so from its content), never another file of the user's or of a stage. ``example``: the
    kind of path to suggest instead (default: a new JSON file); ``flag``: the option that named ``out``;
    ``command``: the command as the messages name it (default ``rtsplat <stage>``)."""
    target = _resolved(out)
    command = command or f"rtsplat {stage}"
    fix = f"pass another {flag}, e.g. {example or f'a new <name>.json beside the other {stage} files'}"
    for given in inputs:
        if given is None:
            continue
        inp = _resolved(given)
        if target == inp or inp in target.parents:
            raise PipelineError(f"the {flag} file is or lies inside the {stage} input {given}; writing it would "
                                "change that input", path=out, fix=fix)
    _check_outside_outputs(target, out, f"the {flag} file", fix)
    if target.is_dir():
        raise PipelineError(f"the {flag} path is a folder; '{command}' writes one file there", path=out,
                            fix=f"pass the path of a file, e.g. {example or Path(out) / (stage + '.json')}")
    if target.exists() and not is_own(target):
        raise PipelineError(f"the {flag} file exists and is not a result of '{command}'; it is left as it is",
                            path=out, fix=fix + ", or delete that file yourself if you no longer need it")


def check_png_output(out: str | Path, command: str, inputs: Iterable[str | Path | None] = (),
                     flag: str = "--out") -> None:
    """:func:`check_output_file` for a PNG that ``command`` writes with :func:`rtsplat.io.images.write_png`
    (``software=command``): the path ends in .png, and a file there is replaced only when its ``Software``
    text names ``command``."""
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise PipelineError(f"{flag} is written as PNG, but ends in {out.suffix or 'no extension'!r}", path=out,
                            fix=f"pass a file name ending in .png, e.g. {out.with_suffix('.png')}")
    check_output_file(out, command, lambda path: png_software(path) == command, inputs=inputs,
                      example="a new <name>.png", flag=flag, command=command)


def text_holds(path: Path, marker: str) -> bool:
    """Whether the text file ``path`` holds ``marker`` (False when it is unreadable or not text)."""
    try:
        return marker in path.read_text(encoding="utf-8")
    except (OSError, ValueError):
        return False


def write_page(text: str, out: Path | None, command: str, marker: str,
               inputs: Iterable[str | Path | None] = ()) -> None:
    """A generated page: printed when ``out`` is None, else written to ``out`` in one step, where nothing is
    or where the file there holds ``marker`` (the page's own "Written by" line); ``command``: the command
    that writes it, for the messages; ``inputs``: what it was made from, never written."""
    if out is None:
        sys.stdout.write(text)
        return
    check_output_file(out, command, lambda path: text_holds(path, marker), inputs=inputs,
                      example="a new <name>.md", command=command)
    write_text_atomic(out, text)
    print(f"wrote {out}")


def json_with_keys(path: Path, keys: Iterable[str]) -> bool:
    """Whether ``path`` holds a JSON object with all of ``keys`` (False when it is unreadable)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and all(key in data for key in keys)
