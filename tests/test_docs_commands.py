"""The commands that README.md and the guide show exist as shown.

Every ``rtsplat``, ``make``, ``snakemake`` and ``python -m`` command in a fenced shell block or an inline
code span of the user docs is checked against the code: the stage exists and takes every ``--flag``
(its own argparse parser); the make target and the variables set on its command line are in the Makefile;
the snakemake flags are snakemake's, ``--config key=value`` keys and ``--configfile`` files pass the
pipeline schema, ``--profile`` folders exist; ``python -m`` modules import. Every fenced YAML block is a
pipeline config fragment that passes the schema. The checker itself is tested on made-up commands.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from rtsplat import cli
from rtsplat.config import check_methods, load_config_dict, validate_config
from rtsplat.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
PROGRAMS = ("rtsplat", "make", "snakemake", "python", "python3")
SHELL_LANGUAGES = ("", "bash", "sh", "shell", "console")


def doc_files() -> list[Path]:
    docs = ROOT / "docs"
    return [ROOT / "README.md", *sorted(docs.glob("guide*.md")), *sorted((docs / "guide").glob("*.md"))]


@dataclass(frozen=True)
class Command:
    text: str
    where: str  # file:line


@dataclass(frozen=True)
class YamlBlock:
    text: str
    where: str


def _fenced_blocks(text: str):
    """(language, first line number, body) of every fenced code block."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^\s*```(\S*)", lines[i])
        if m:
            start, body = i + 1, []
            i += 1
            while i < len(lines) and not re.match(r"^\s*```\s*$", lines[i]):
                body.append(lines[i])
                i += 1
            yield m.group(1).lower(), start + 1, body
        i += 1


def _shell_lines(body: list[str], first: int):
    """(line number, logical line) with backslash continuations joined."""
    pending, start = "", first
    for n, line in enumerate(body, first):
        if not pending:
            start = n
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""
    if pending:
        yield start, pending


def extract(path: Path) -> tuple[list[Command], list[YamlBlock]]:
    """The commands and YAML blocks of one Markdown file."""
    text = path.read_text()
    name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    commands, blocks = [], []
    fenced_lines = set()
    for language, first, body in _fenced_blocks(text):
        fenced_lines.update(range(first - 1, first + len(body) + 1))
        if language == "yaml":
            blocks.append(YamlBlock("\n".join(body), f"{name}:{first}"))
        elif language in SHELL_LANGUAGES:
            for n, line in _shell_lines(body, first):
                commands.append(Command(line, f"{name}:{n}"))
    for n, line in enumerate(text.splitlines(), 1):
        if n in fenced_lines:
            continue
        for span in re.findall(r"`([^`\n]+)`", line):
            if span.split(" ", 1)[0].removeprefix(".venv/bin/") in PROGRAMS and " " in span:
                commands.append(Command(span, f"{name}:{n}"))
    return commands, blocks


# ----------------------------------------------------------------------------------------------------
# the checks


@functools.cache
def stage_options(stage_name: str) -> frozenset[str]:
    stage = next(s for s in cli.STAGES if s.name == stage_name)
    module = cli._load(stage)
    return frozenset(cli.stage_parser(stage, module)._option_string_actions)


@functools.cache
def snakemake_options() -> frozenset[str]:
    from snakemake.cli import get_argument_parser

    return frozenset(get_argument_parser()._option_string_actions)


@functools.cache
def makefile() -> tuple[frozenset[str], frozenset[str]]:
    """(targets, variables) of the Makefile."""
    text = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([A-Za-z][\w.-]*)\s*:(?!=)", text, re.M))
    variables = set(re.findall(r"^([A-Z_][A-Z0-9_]*)\s*[?:]?=", text, re.M))
    return frozenset(targets), frozenset(variables)


def _tokens(command: str) -> list[str]:
    """The words of a command, placeholders' brackets and alternatives removed."""
    command = command.replace("\\|", "|")
    try:
        words = shlex.split(command, comments=True)
    except ValueError:
        words = command.split()
    out = []
    for word in words:
        word = word.strip("[]")
        if word and word != "..." and word != "|":
            out.append(word)
    return out


def _segments(words: list[str]) -> list[list[str]]:
    """A command line split at ``&&``, ``||``, ``;`` and pipes."""
    out, current = [], []
    for word in words:
        if word in ("&&", "||", ";", "|"):
            out.append(current)
            current = []
        else:
            current.append(word)
    out.append(current)
    return [s for s in out if s]


def _flag(word: str) -> str | None:
    if word.startswith("--") and len(word) > 2:
        return word.split("=", 1)[0]
    if re.fullmatch(r"-[A-Za-z]", word):
        return word
    return None


def check_rtsplat(words: list[str]) -> list[str]:
    if not words:
        return ["'rtsplat' without a stage"]
    stage = words[0]
    names = {s.name for s in cli.STAGES}
    if re.fullmatch(r"<\w+>", stage):  # rtsplat <stage> --help
        return [f"rtsplat has no option {f}" for f in map(_flag, words[1:]) if f not in (None, "--help", "-h")]
    if stage.startswith("-"):
        return [] if stage in ("--help", "-h", "--version") else [f"rtsplat has no option {stage}"]
    if stage not in names:
        return [f"rtsplat has no stage '{stage}' (stages: {', '.join(sorted(names))})"]
    options = stage_options(stage)
    return [f"rtsplat {stage} has no option {flag}" for flag in map(_flag, words[1:])
            if flag is not None and flag not in options]


def check_make(words: list[str]) -> list[str]:
    targets, variables = makefile()
    problems = []
    for word in words:
        if "=" in word and not word.startswith("-"):
            name = word.split("=", 1)[0]
            if name not in variables:
                problems.append(f"the Makefile has no variable {name}")
        elif not word.startswith("-") and word not in targets:
            problems.append(f"the Makefile has no target '{word}'")
    return problems


def _config_problem(data: dict, source: str) -> str | None:
    """What the workflow would refuse in a config (fragment): the schema, and each method's trainer tree."""
    try:
        validate_config(data, source=source)
        check_methods(load_config_dict(data, source))
    except ConfigError as exc:
        return str(exc)
    return None


def check_snakemake(words: list[str]) -> list[str]:
    options = snakemake_options()
    problems, i = [], 0
    while i < len(words):
        word = words[i]
        flag = _flag(word)
        if flag is not None and flag not in options:
            problems.append(f"snakemake has no option {flag}")
        if flag == "--config":
            i += 1
            while i < len(words) and not words[i].startswith("-"):
                key, _, value = words[i].partition("=")
                problem = _config_problem({key: yaml.safe_load(value)}, f"--config {words[i]}")
                if problem:
                    problems.append(problem)
                i += 1
            continue
        if flag == "--configfile":
            i += 1
            layered: dict = {}
            while i < len(words) and not words[i].startswith("-"):
                path = ROOT / words[i]
                if not path.is_file():
                    problems.append(f"--configfile {words[i]} does not exist")
                else:
                    from rtsplat.config import deep_merge

                    layered = deep_merge(layered, yaml.safe_load(path.read_text()) or {})
                i += 1
            problem = _config_problem(layered, "--configfile")
            if problem:
                problems.append(problem)
            continue
        if flag == "--profile" and i + 1 < len(words):
            if not (ROOT / words[i + 1]).is_dir():
                problems.append(f"--profile {words[i + 1]}: no such folder")
        i += 1
    if not problems:
        problems += [f"the workflow has no rule '{t}'" for t in snakemake_targets(words)
                     if re.fullmatch(r"\w+", t) and t not in workflow_rules()]
    return problems


def snakemake_targets(words: list[str]) -> list[str]:
    """The targets snakemake reads from its arguments (its own parser: ``--config`` and ``--set-threads``
    take every word after them)."""
    from snakemake.cli import get_argument_parser

    args, _ = get_argument_parser().parse_known_args(words)
    return list(args.targets or [])


@functools.cache
def workflow_rules() -> frozenset[str]:
    files = [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]
    return frozenset(name for f in files for name in re.findall(r"^rule (\w+)\s*:", f.read_text(), re.M))


@functools.cache
def module_help(module: str) -> str:
    """What ``python -m module --help`` prints (its options)."""
    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    return done.stdout + done.stderr


def check_python(words: list[str]) -> list[str]:
    if len(words) < 2 or words[0] != "-m":
        return []
    module = words[1]
    if not module.startswith("rtsplat"):
        return []
    if importlib.util.find_spec(module) is None:
        return [f"no module {module}"]
    flags = [f for f in map(_flag, words[2:]) if f is not None]
    if not flags:
        return []
    text = module_help(module)
    return [f"python -m {module} has no option {f}" for f in flags if not re.search(rf"{re.escape(f)}\b", text)]


def check_command(command: str) -> list[str]:
    """What is wrong with one documented command line (empty: nothing)."""
    problems = []
    for words in _segments(_tokens(command)):
        while words and re.fullmatch(r"[A-Z_][A-Z0-9_]*=.*", words[0]):  # VAR=value before the program
            words = words[1:]
        if not words:
            continue
        program = Path(words[0]).name if words[0].startswith((".venv/bin/", "$")) else words[0]
        if program == "rtsplat":
            problems += check_rtsplat(words[1:])
        elif program == "make":
            problems += check_make(words[1:])
        elif program == "snakemake":
            problems += check_snakemake(words[1:])
        elif program in ("python", "python3"):
            problems += check_python(words[1:])
    return problems


def check_yaml(text: str, source: str) -> list[str]:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        return [f"{source}: not YAML ({exc})"]
    if not isinstance(data, dict):
        return [f"{source}: not a config mapping"]
    problem = _config_problem(data, source)
    return [problem] if problem else []


# ----------------------------------------------------------------------------------------------------
# the docs


def _all():
    commands, blocks = [], []
    for path in doc_files():
        c, b = extract(path)
        commands += c
        blocks += b
    return commands, blocks


def test_the_docs_show_commands_of_every_kind():
    commands, blocks = _all()
    programs = {_segments(_tokens(c.text))[0][0].removeprefix(".venv/bin/") for c in commands if _tokens(c.text)}
    assert {"rtsplat", "make", "snakemake", "python"} <= programs
    stages = {w[1] for c in commands for w in _segments(_tokens(c.text)) if len(w) > 1 and w[0] == "rtsplat"}
    assert stages >= {s.name for s in cli.STAGES} - {"demo"}, "every stage is shown at least once"
    assert blocks, "the docs show config fragments"


def test_every_documented_command_exists_as_shown():
    commands, _ = _all()
    problems = [f"{c.where}: `{c.text.strip()}`: {p}" for c in commands for p in check_command(c.text)]
    assert not problems, "\n".join(problems)


def test_every_documented_config_fragment_passes_the_schema():
    _, blocks = _all()
    problems = [p for b in blocks for p in check_yaml(b.text, b.where)]
    assert not problems, "\n".join(problems)


def test_readme_keeps_the_commands_that_ci_runs():
    readme, _ = extract(ROOT / "README.md")
    shown = {" ".join(_tokens(c.text)) for c in readme}
    ci = (ROOT / ".ci" / "run").read_text()
    for target in ("make test", "make test-slurm"):
        assert target in ci and any(s.startswith(target) for s in shown), target


# ----------------------------------------------------------------------------------------------------
# the checker on made-up commands


@pytest.mark.parametrize("command, problem", [
    ("rtsplat train --data P --out R --iteratons 10", "rtsplat train has no option --iteratons"),
    ("rtsplat trian --data P", "rtsplat has no stage 'trian'"),
    ("rtsplat view --run R --prot 8080", "rtsplat view has no option --prot"),
    ("make tests", "the Makefile has no target 'tests'"),
    ("make test PYTEST_ARG=-x", "the Makefile has no variable PYTEST_ARG"),
    (".venv/bin/snakemake --cores all --dry", "snakemake has no option --dry"),
    ("snakemake --cores 2 --config datta=/scenes", "config key 'datta' does not exist"),
    ("snakemake --configfile benchmarks/nothing.yaml", "--configfile benchmarks/nothing.yaml does not exist"),
    ("snakemake --profile profiles/pbs", "--profile profiles/pbs: no such folder"),
    ("python -m rtsplat.bench.rastr", "no module rtsplat.bench.rastr"),
    (".venv/bin/snakemake --cores all prepare_all", "the workflow has no rule 'prepare_all'"),
    ("python -m rtsplat.config --chek config.yaml", "python -m rtsplat.config has no option --chek"),
    ("cd x && rtsplat render --run R --edits roughness=2", "rtsplat render has no option --edits"),
])
def test_the_checker_finds_made_up_commands(command, problem):
    problems = check_command(command)
    assert any(problem in p for p in problems), problems


@pytest.mark.parametrize("command", [
    "rtsplat train --data P --out R --iterations 10",
    "rtsplat render --run RUN --data PREPARED --out DIR [--edit roughness=2 ...]",
    "rtsplat video --run R --data P --out V.mp4 [--path orbit\\|spiral\\|interpolate] [--panels]",
    "make test PYTEST_ARGS=\"-k raster\"",
    ".venv/bin/snakemake --cores all --config data=/path/to/scenes   # every <scene>/images/",
    ".venv/bin/snakemake --cores all prepared_all",
    "snakemake -s Snakefile -d real --configfile benchmarks/real.yaml --cores 2",
    "python -m rtsplat.bench.raster",
    "python -m rtsplat.config --check config.yaml",
])
def test_the_checker_passes_real_commands(command):
    assert check_command(command) == []


def test_the_checker_finds_a_bad_config_fragment():
    assert check_yaml("defaults:\n  prepare:\n    downsampel: 4\n", "x") != []
    assert check_yaml("methods:\n  fast: {model: {mlp_widht: 64}}\n", "x") != []  # a trainer key
    assert check_yaml("defaults:\n  prepare:\n    downsample: 4\n", "x") == []


def test_extract_reads_fenced_and_inline_commands(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("Run `rtsplat train --data P --bogus 1` first.\n\n```bash\nmake demo   # the demo\n"
                    "rtsplat render --run R \\\n    --nope\n```\n\n```yaml\ndata: x\n```\n\n"
                    "```python\nrtsplat x\n```\n")
    commands, blocks = extract(page)
    texts = [c.text for c in commands]
    assert any("--bogus" in t for t in texts) and any(t.startswith("make demo") for t in texts)
    joined = next(c for c in commands if "--nope" in c.text)
    assert check_command(joined.text) == ["rtsplat render has no option --nope"]
    assert [b.text for b in blocks] == ["data: x"]
    assert not any(t.startswith("rtsplat x") for t in texts)  # python blocks are not shell


def test_troubleshooting_names_every_error_class():
    import rtsplat.io.atomic  # noqa: F401  (the modules that define the subclasses)
    import rtsplat.model.checkpoint  # noqa: F401
    import rtsplat.train.divergence  # noqa: F401
    from rtsplat.errors import PipelineError

    def subclasses(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from subclasses(sub)

    page = (ROOT / "docs" / "guide" / "troubleshooting.md").read_text()
    names = {"PipelineError", *(c.__name__ for c in subclasses(PipelineError) if c.__module__.startswith("rtsplat"))}
    assert {"ConfigError", "CheckpointError", "TrainingDiverged", "WriteFailed"} <= names
    assert not [n for n in names if f"`{n}`" not in page], "docs/guide/troubleshooting.md misses an error class"


def _slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_links_between_the_docs_reach_their_files_and_headings():
    problems = []
    for page in [*doc_files(), ROOT / "docs" / "results.md", ROOT / "docs" / "configuration.md"]:
        for n, line in enumerate(page.read_text().splitlines(), 1):
            for target in re.findall(r"\]\(([^)\s]+)\)", line):
                if re.match(r"\w+://", target):
                    continue
                path, _, anchor = target.partition("#")
                file = (page.parent / path).resolve() if path else page
                if not file.exists():
                    problems.append(f"{page.relative_to(ROOT)}:{n}: {target}: no such file")
                elif anchor and file.suffix == ".md":
                    slugs = {_slug(h) for h in re.findall(r"^#+ (.+)$", file.read_text(), re.M)}
                    if anchor not in slugs:
                        problems.append(f"{page.relative_to(ROOT)}:{n}: {target}: no such heading")
    assert not problems, "\n".join(problems)


def test_the_link_checker_knows_githubs_anchors():
    assert _slug("The tests: `make test`, `make test-fast`") == "the-tests-make-test-make-test-fast"
    assert _slug("`defaults.train.options`") == "defaultstrainoptions"


SECTIONS = ("sfm", "masks", "prepare", "train", "render", "video", "metrics", "slurm", "schedule", "lr", "losses",
            "densify", "model", "ablations", "effects", "gating", "cameras", "appearance", "raster", "defaults",
            "overrides", "methods")
FILE_SUFFIXES = ("pt", "json", "jsonl", "yaml", "md", "png", "ply", "mp4", "py", "html", "txt", "npz")


@functools.cache
def config_keys() -> frozenset[str]:
    """Every dotted key of the pipeline schema, from the top, from ``defaults`` and from the trainer's tree."""
    from rtsplat.config import json_schema

    keys = set()

    def walk(schema, path):
        obj = schema if "properties" in schema else next(
            (o for o in schema.get("anyOf", []) if "properties" in o), None)
        if obj is None:
            return
        for key, prop in obj["properties"].items():
            child = f"{path}.{key}" if path else key
            keys.add(child)
            walk(prop, child)

    walk(json_schema(), "")
    out = set(keys)
    for prefix in ("defaults.", "defaults.train.options."):
        out |= {k[len(prefix):] for k in keys if k.startswith(prefix)}
    out |= {"train." + k[len("defaults.train.options."):] for k in keys if k.startswith("defaults.train.options.")}
    return frozenset(out)


def check_config_key(span: str) -> list[str]:
    """A dotted config key named in prose (``sfm.matcher``, ``model.mlp_width``) exists in the schema."""
    if not re.fullmatch(r"[a-z_]+(\.[a-z_0-9]+)+", span) or span.split(".")[0] not in SECTIONS:
        return []
    if span.rsplit(".", 1)[1] in FILE_SUFFIXES:  # model.pt, render.json: files, not keys
        return []
    return [] if span in config_keys() else [f"config key {span} is not in the schema"]


def test_every_config_key_named_in_the_docs_exists():
    problems = []
    for page in doc_files():
        for n, line in enumerate(page.read_text().splitlines(), 1):
            for span in re.findall(r"`([^`\n]+)`", line):
                problems += [f"{page.relative_to(ROOT)}:{n}: {p}" for p in check_config_key(span)]
    assert not problems, "\n".join(problems)


def test_the_key_checker_finds_a_made_up_key():
    assert check_config_key("sfm.matcher") == [] and check_config_key("model.mlp_width") == []
    assert check_config_key("train.device") == [] and check_config_key("defaults.train.device") == []
    assert check_config_key("sfm.matchr") == ["config key sfm.matchr is not in the schema"]
    assert check_config_key("rtsplat.bench.raster") == [] and check_config_key("model.pt") == []  # not keys
