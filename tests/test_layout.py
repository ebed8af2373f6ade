"""The package's shape, checked on its source: imports run one way between layers (cli -> studies ->
evaluation/training -> policies, subskills, data -> envs), no import cycle between packages, and an import inside a
function is there for a reason written beside it (a heavy or optional dependency), not to hide a cycle.

An environment is one folder, ``envs/<name>/``, whose modules sit at the layer of their role: ``env.py`` at the
bottom (envs), ``demos.py`` (and the maze's ``figure.py``) with the demo writers, ``rollout.py`` with evaluation."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "src" / "cotpc"

# A package may import only packages of a lower rank (never one of its own rank or above).
RANK = {
    "envs": 0,
    "data": 1,
    "policies": 1,
    "subskills": 2,
    "demos": 2,
    "evaluation": 2,
    "training": 2,
    "cotpc": 2,  # the top-level package (__init__: load_policy, __version__)
    "studies": 3,
    "bench": 3,
    "cli": 4,
}
ENTRY_POINTS = {"__main__", "train"}  # `python -m cotpc`, `torchrun -m cotpc.train`: above everything
# The layer of a module of an environment's folder (envs/<name>/<module>.py), by its role; other modules: envs.
ENV_FOLDER_ROLES = {"demos": "demos", "figure": "demos", "rollout": "evaluation"}


def layer_of(parts: list[str]) -> str:
    """The layer of the module ``cotpc.<parts>`` (a package name of RANK)."""
    if not parts:
        return "cotpc"
    if parts[0] == "envs" and len(parts) >= 3:  # envs/<name>/<module>
        return ENV_FOLDER_ROLES.get(parts[2], "envs")
    return parts[0]


def _modules(root: Path):
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        parts = [*rel.parts[:-1], rel.stem] if rel.stem != "__init__" else list(rel.parts[:-1])
        package = layer_of(parts) if len(rel.parts) > 1 or rel.stem == "__init__" else rel.stem
        yield path, package, ast.parse(path.read_text())


def _cotpc_imports(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "cotpc":
            yield node, node.module
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "cotpc":
                    yield node, alias.name


def upward_imports(root: Path) -> list[str]:
    """Imports from a package to one of its own rank or above (or to a package with no rank)."""
    wrong = []
    for path, package, tree in _modules(root):
        if package in ENTRY_POINTS:
            continue
        if package not in RANK:
            wrong.append(f"{path.relative_to(root)}: package {package!r} has no rank in tests/test_layout.py")
            continue
        for node, name in _cotpc_imports(tree):
            target = layer_of(name.split(".")[1:])
            if target != package and RANK.get(target, 99) >= RANK[package]:
                wrong.append(f"{path.relative_to(root)}:{node.lineno} ({package}) imports {name} ({target})")
    return wrong


def package_cycles(root: Path) -> list[list[str]]:
    """Import cycles between top-level packages (envs, data, policies, ...), each as the packages on it."""
    graph: dict[str, set[str]] = {}
    for path, _, tree in _modules(root):
        rel = path.relative_to(root)
        if len(rel.parts) == 1:
            continue
        for _, name in _cotpc_imports(tree):
            parts = name.split(".")
            if len(parts) > 1 and parts[1] != rel.parts[0] and (root / parts[1]).is_dir():
                graph.setdefault(rel.parts[0], set()).add(parts[1])
    cycles, done = [], set()

    def visit(node: str, stack: list[str]) -> None:
        if node in stack:
            cycles.append(stack[stack.index(node):] + [node])
            return
        if node in done:
            return
        for nxt in sorted(graph.get(node, ())):
            visit(nxt, stack + [node])
        done.add(node)

    for node in sorted(graph):
        visit(node, [])
    return cycles


def silent_function_imports(root: Path) -> list[str]:
    """Imports inside functions with no comment on their line, within their block of imports, or just above."""
    silent = []
    for path, _, tree in _modules(root):
        lines = path.read_text().splitlines()
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if not isinstance(node, (ast.Import, ast.ImportFrom)):
                    continue
                first = node.lineno - 1  # walk up over the imports just above it (one block)
                while first > 0 and lines[first - 1].strip().startswith(("import ", "from ")):
                    first -= 1
                block = lines[max(first - 1, 0): node.end_lineno]
                if not any("#" in line for line in block):
                    silent.append(f"{path.relative_to(root)}:{node.lineno}: {lines[node.lineno - 1].strip()}")
    return silent


def test_imports_run_one_way_between_packages():
    wrong = upward_imports(ROOT)
    assert not wrong, "imports that run up or sideways between packages:\n" + "\n".join(wrong)


def test_no_import_cycle_between_packages():
    cycles = package_cycles(ROOT)
    assert not cycles, "import cycles between packages:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_function_level_imports_say_why():
    silent = silent_function_imports(ROOT)
    assert not silent, "function-level imports without a reason beside them:\n" + "\n".join(silent)


def test_the_checks_find_what_they_are_for(tmp_path):
    """On a sample tree: an environment module importing a study, a silent function-level import and a package
    with no rank are reported; a commented function-level import and a downward import are not."""
    (tmp_path / "envs").mkdir()
    (tmp_path / "envs" / "bad.py").write_text("from cotpc.studies.runs import stats\n")
    (tmp_path / "studies").mkdir()
    (tmp_path / "studies" / "ok.py").write_text(
        "from cotpc.envs.spec import env_spec\n\ndef f():\n    import numpy  # heavy\n    return numpy\n")
    (tmp_path / "studies" / "silent.py").write_text("def g():\n    import json\n    return json\n")
    (tmp_path / "newpkg").mkdir()
    (tmp_path / "newpkg" / "m.py").write_text("x = 1\n")
    # An environment's folder: its env module may not import its rollout; the rollout may import evaluation.
    (tmp_path / "envs" / "toy").mkdir()
    (tmp_path / "envs" / "toy" / "env.py").write_text("from cotpc.envs.toy.rollout import run\n")
    (tmp_path / "envs" / "toy" / "rollout.py").write_text(
        "from cotpc.envs.toy.env import ToyEnv\nfrom cotpc.evaluation.stats import wilson_interval\n")
    (tmp_path / "evaluation").mkdir()
    (tmp_path / "evaluation" / "stats.py").write_text("from cotpc.envs.spec import SPECS\n")
    wrong = upward_imports(tmp_path)
    assert len(wrong) == 3, wrong
    assert "envs/bad.py:1 (envs) imports cotpc.studies.runs" in wrong[0]
    assert "envs/toy/env.py:1 (envs) imports cotpc.envs.toy.rollout (evaluation)" in wrong[1]
    assert "newpkg" in wrong[2]
    assert silent_function_imports(tmp_path) == ["studies/silent.py:2: import json"]
    # envs -> evaluation (the rollout) and evaluation -> envs: a cycle between packages, and envs -> studies closes
    # another through studies -> envs.
    assert sorted(package_cycles(tmp_path)) == [["envs", "evaluation", "envs"], ["envs", "studies", "envs"]]
