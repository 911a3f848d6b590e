"""Layers point one way: every import of the package (including the ones inside functions), followed
transitively, must respect the layering rules below."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "rtsplat"
STAGES = ("rtsplat.sfm", "rtsplat.masks", "rtsplat.prepare", "rtsplat.train", "rtsplat.render", "rtsplat.video",
          "rtsplat.fps", "rtsplat.metrics", "rtsplat.report", "rtsplat.frames")

# (modules the rule applies to, modules they must not reach)
RULES = [
    (("rtsplat.model",), STAGES + ("rtsplat.cli", "rtsplat.config", "rtsplat.synth", "rtsplat.bench", "rtsplat.demo")),
    (("rtsplat.render", "rtsplat.video", "rtsplat.fps", "rtsplat.metrics", "rtsplat.viewer"), ("rtsplat.train",)),
    (("rtsplat.quality",), ("rtsplat.model", "rtsplat.raster", "rtsplat.train", "rtsplat.config", *STAGES)),
    (("rtsplat.schema", "rtsplat.errors", "rtsplat.io", "rtsplat.provenance"),
     ("rtsplat.model", "rtsplat.train", "rtsplat.config", *STAGES)),
]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def direct_imports(name: str) -> set[str]:
    """rtsplat modules that ``name`` imports anywhere in its source (with their parent packages)."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base for alias in node.names]
        for target in targets:
            parts = target.split(".")
            for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__ and a/b/__init__ too
                candidate = ".".join(parts[:i])
                if candidate in MODULES and candidate != name:
                    found.add(candidate)
    return found


def reachable(name: str) -> dict[str, str]:
    """Every rtsplat module ``name`` imports, directly or through others: module -> the importer."""
    seen, todo = {}, [name]
    while todo:
        current = todo.pop()
        for target in direct_imports(current):
            if target not in seen and target != name:
                seen[target] = current
                todo.append(target)
    return seen


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _chain(name: str, target: str, via: dict[str, str]) -> str:
    chain = [target]
    while chain[-1] != name and chain[-1] in via:
        chain.append(via[chain[-1]])
    return " <- ".join(chain)


def test_the_import_walk_sees_imports_inside_functions():
    # render imports the checkpoint reader inside render_run, metrics imports LPIPS inside compute_metrics
    assert "rtsplat.model.checkpoint" in direct_imports("rtsplat.render")
    assert "rtsplat.quality.lpips" in direct_imports("rtsplat.metrics")
    assert "rtsplat.train.trainer" in reachable("rtsplat.train.cli")


@pytest.mark.parametrize("sources, forbidden", RULES, ids=[",".join(r[0]) for r in RULES])
def test_layering(sources, forbidden):
    checked = [name for name in MODULES if _within(name, sources)]
    assert checked, sources
    violations = []
    for name in checked:
        via = reachable(name)
        violations += [f"{name} reaches {t}: {_chain(name, t, via)}" for t in sorted(via) if _within(t, forbidden)]
    assert not violations, "\n".join(violations)


# the parts of the sfm stage, lowest first: each imports only parts before it (the orchestrator last)
SFM_PARTS = ("rtsplat.sfm.stats", "rtsplat.sfm.matching", "rtsplat.sfm.attempts", "rtsplat.sfm.refine",
             "rtsplat.sfm.stage")


def test_sfm_parts_import_downward():
    assert set(SFM_PARTS) == {name for name in MODULES if name.startswith("rtsplat.sfm.")}
    violations = []
    for k, name in enumerate(SFM_PARTS):
        for target in sorted(direct_imports(name) & set(SFM_PARTS)):
            if target not in SFM_PARTS[:k]:
                violations.append(f"{name} imports {target}")
    assert not violations, "\n".join(violations)
    # one orchestrator: only the stage runs the attempts and the refinement
    assert {"rtsplat.sfm.attempts", "rtsplat.sfm.refine"} <= direct_imports("rtsplat.sfm.stage")
    assert direct_imports("rtsplat.sfm") & set(SFM_PARTS) == {"rtsplat.sfm.stage"}
