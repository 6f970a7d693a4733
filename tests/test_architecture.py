"""The import graph of the three packages (README, Layout): kernels import downward only, at
module top level; `jaxrender.app` (the orchestration layer) is the only place that composes the
packages; no cycles; nothing private is imported across subpackages.

Read from the source with `ast`, so it covers modules no test imports, and it reads the module
names the command and gallery tables load with `importlib` (string constants naming a project
module) as imports too."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jaxrender", "fitting", "sims")
LAYER = "jaxrender.app"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


MODULES = _modules()


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for _ in range(node.level - 1):
        package = package.rsplit(".", 1)[0]
    return f"{package}.{node.module}" if node.module else package


def _targets(module: str, path: Path, node: ast.AST) -> list[str]:
    """Project modules an import statement (or an importlib string) names."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = _resolve(module, path, node)
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
    elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in MODULES:
        names = [node.value]
    else:
        return []
    return [n for n in names if n.split(".")[0] in PACKAGES]


def _imports(module: str, path: Path) -> tuple[set[str], list[tuple[int, str]]]:
    """(modules imported at top level or named by strings, [(line, module)] imported inside functions)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    in_function: set[int] = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            in_function.update(id(n) for n in ast.walk(fn) if n is not fn)
    top, nested = set(), []
    for node in ast.walk(tree):
        targets = _targets(module, path, node)
        if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) in in_function:
            nested += [(node.lineno, t) for t in targets]
        else:
            top.update(targets)
    return top, nested


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def _is_layer(module: str) -> bool:
    return module == LAYER or module.startswith(LAYER + ".")


def test_the_graph_is_read_from_the_source():
    # guards the test itself: the tables' importlib strings and the layer's imports are seen
    assert "jaxrender.app.cli.gallery" in GRAPH["jaxrender.app.cli.programs"][0]
    assert "jaxrender.app.gallery.noh" in GRAPH["jaxrender.app.gallery"][0]
    assert {"fitting", "sims"} & {t.split(".")[0] for t in GRAPH["jaxrender.app.scenes.noh.scene"][0]}
    assert len([m for m in MODULES if _is_layer(m)]) > 20 and len([m for m in MODULES if not _is_layer(m)]) > 50


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_project_import_inside_a_function(module):
    assert GRAPH[module][1] == [], f"{module} imports inside functions: {GRAPH[module][1]}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if not _is_layer(m)))
def test_kernels_import_downward_only(module):
    top = GRAPH[module][0]
    assert not [t for t in top if _is_layer(t)], f"kernel {module} imports the orchestration layer"
    if module.startswith("jaxrender"):  # the renderer's kernels are the bottom: no sims, no fitting
        assert not [t for t in top if t.split(".")[0] in ("sims", "fitting")], f"{module} imports {top}"
    if module.split(".")[0] in ("sims", "fitting"):  # the two kernel packages built on jaxrender stay apart
        other = "fitting" if module.startswith("sims") else "sims"
        assert not [t for t in top if t.split(".")[0] == other], f"{module} imports {other}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_nothing_private_is_imported_across_subpackages(module):
    for target in GRAPH[module][0]:
        parts = target.split(".")
        private = [i for i, p in enumerate(parts) if p.startswith("_")]
        if private:
            owner = ".".join(parts[:private[0]])   # the package the private module belongs to
            assert module == owner or module.startswith(owner + "."), f"{module} imports private {target}"


def test_no_import_cycles():
    edges = {m: {t for t in GRAPH[m][0] if t in MODULES and t != m} for m in MODULES}
    state: dict[str, int] = {}   # 1 on the stack, 2 done

    def visit(m, stack):
        state[m] = 1
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                pytest.fail("import cycle: " + " -> ".join(stack[stack.index(t):] + [t]))
            if t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in sorted(MODULES):
        if m not in state:
            visit(m, [m])


@pytest.mark.parametrize("program", ["jaxrender", "fitting", "sims"])
def test_help_answers_without_importing_jax(program):
    code = (f"import sys; from jaxrender.app.cli.programs import PROGRAMS; PROGRAMS[{program!r}](['--help']); "
            "print('jax' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False" and "commands:" in out
