"""The package's shape, checked on its source: imports run one way between packages (cli -> studies ->
evaluation/training -> policies, subskills, data -> envs), and an import inside a function is there for a reason
written beside it (a heavy or optional dependency), not to hide a cycle."""

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


def _modules(root: Path):
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        package = rel.parts[0] if len(rel.parts) > 1 else ("cotpc" if rel.stem == "__init__" else rel.stem)
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
            parts = name.split(".")
            target = parts[1] if len(parts) > 1 else "cotpc"
            if target != package and RANK.get(target, 99) >= RANK[package]:
                wrong.append(f"{path.relative_to(root)}:{node.lineno} ({package}) imports {name} ({target})")
    return wrong


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
    wrong = upward_imports(tmp_path)
    assert len(wrong) == 2 and "envs/bad.py:1 (envs) imports cotpc.studies.runs" in wrong[0]
    assert "newpkg" in wrong[1]
    assert silent_function_imports(tmp_path) == ["studies/silent.py:2: import json"]
