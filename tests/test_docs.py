"""The reference site (mkdocs.yml, docs/) builds with `mkdocs build --strict` from the checkout, and
it shows every public name of `jaxrender`, `fitting` and `sims` with the shapes of its signature,
every subcommand and option of the three command lines, the notebooks and the formats page.

The public names are read here from the sources with `ast` (re-exports `from ._x import Y as Y`,
`__all__`, top-level definitions), independently of the griffe walk in docs/_hooks/reference.py
that writes the pages, so a name the hook misses fails here."""

from __future__ import annotations

import ast
import html
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from jaxrender.app.cli.driver import command_parser
from jaxrender.app.cli.programs import COMMAND_TABLES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jaxrender", "fitting", "sims")
UNDOCUMENTED = ("jaxrender.app.cli",)  # the command lines have their own pages
BUILD_TIMEOUT_S = 300  # the build takes ~10 s; a hang must not eat the suite's budget


def _source(module: str) -> Path:
    path = ROOT.joinpath(*module.split("."))
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def _is_public(name: str) -> bool:
    return not name.startswith("_")


def _definitions(module: str) -> dict[str, ast.AST | None]:
    """Public names of a module: `__all__` if it has one, else its re-exports and top-level
    definitions; each with its defining node (a re-export followed to its module), None for an
    assignment."""
    tree = ast.parse(_source(module).read_text())
    package = module if _source(module).name == "__init__.py" else module.rsplit(".", 1)[0]
    found: dict[str, ast.AST | None] = {}
    exported: list[str] | None = None
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            found[node.name] = node
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                if isinstance(target, ast.Name) and target.id == "__all__":
                    exported = list(ast.literal_eval(node.value))
                elif isinstance(target, ast.Name):
                    found[target.id] = None
        elif isinstance(node, ast.ImportFrom):
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            source = (f"{base}.{node.module}" if node.module else base) if node.level else node.module
            for alias in node.names:
                if alias.asname == alias.name or (exported and alias.name in exported):
                    found[alias.name] = _definitions(source).get(alias.name) if source.startswith(PACKAGES) else None
    names = exported if exported is not None else [n for n in found if _is_public(n)]
    return {n: found.get(n) for n in names if not (n.startswith("__") and n.endswith("__"))}


def _submodules(module: str) -> list[str]:
    path = _source(module).parent
    if _source(module).name != "__init__.py":
        return []
    subs = [p.stem for p in path.glob("*.py") if p.stem != "__init__"]
    subs += [p.name for p in path.iterdir() if (p / "__init__.py").is_file()]
    return sorted(f"{module}.{s}" for s in subs if _is_public(s))


def _documented(module: str) -> dict[str, dict[str, ast.AST | None]]:
    """{module: its public names} for every module that has a page: a package that re-exports names
    has one, and so do its subpackages; below a package that re-exports nothing, every public module."""
    names = _definitions(module)
    found = {module: names} if names else {}
    for sub in _submodules(module):
        if sub not in UNDOCUMENTED and (not names or _source(sub).name == "__init__.py"):
            found.update(_documented(sub))
    return found


DOCUMENTED = {m: names for package in PACKAGES for m, names in _documented(package).items()}


def _shapes(node: ast.AST | None) -> set[str]:
    """The jaxtyping shape strings in a function's annotations (`Float[Array, "H W 3"]` -> "H W 3")."""
    if not isinstance(node, ast.FunctionDef):
        return set()
    args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
    annotations = [a.annotation for a in args if a.annotation is not None] + [node.returns]
    return {" ".join(c.value.split()) for a in annotations if isinstance(a, ast.Subscript)
            for c in ast.walk(a) if isinstance(c, ast.Constant) and isinstance(c.value, str) and c.value.strip()}


def _text(page: str) -> str:
    return " ".join(html.unescape(re.sub(r"<[^>]+>", "", page)).split())


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("docs") / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                            str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    assert build.returncode == 0, f"mkdocs build --strict failed:\n{build.stdout}\n{build.stderr}"
    return out


def test_the_public_names_are_read_from_the_sources():
    # guards the reader above: it must find the packages' re-exports and modules, not an empty list
    assert {"jaxrender.shafts", "jaxrender.io", "jaxrender.app.scenes", "fitting", "sims"} <= set(DOCUMENTED)
    assert "render" in DOCUMENTED["jaxrender.shafts"] and "InputError" in DOCUMENTED["jaxrender.io"]
    assert isinstance(DOCUMENTED["jaxrender.shafts"]["render"], ast.FunctionDef)
    assert not any(m.startswith(UNDOCUMENTED) for m in DOCUMENTED)


@pytest.mark.parametrize("module", sorted(DOCUMENTED))
def test_every_public_name_has_an_entry_with_its_shapes(site, module):
    page = (site / "api" / module / "index.html").read_text()
    anchors = set(re.findall(r'id="([^"]+)"', page))
    missing = [n for n in DOCUMENTED[module] if f"{module}.{n}" not in anchors]
    assert not missing, f"{module}: no entry for {missing}"
    text = _text(page)
    shapes = set().union(*(_shapes(node) for node in DOCUMENTED[module].values()))
    assert not [s for s in shapes if s not in text], f"{module}: shapes missing from the signatures"


@pytest.mark.parametrize("program", sorted(COMMAND_TABLES))
def test_every_subcommand_and_option_is_on_its_cli_page(site, program):
    page = (site / "cli" / program / "index.html").read_text()
    text = _text(page)
    _, commands = COMMAND_TABLES[program]
    for name in commands:
        assert f'id="{program}-{name}"' in page, f"{program} {name}: no section"
        _, parser = command_parser(program, name, commands)
        options = [s for action in parser._actions for s in action.option_strings]  # argparse has no public list
        assert not [s for s in options if s not in text], f"{program} {name}: options missing"


def test_the_notebooks_and_the_formats_page_are_rendered(site):
    notebooks = sorted((ROOT / "examples").glob("*.ipynb"))
    assert notebooks
    for notebook in notebooks:
        page = site / "examples" / notebook.stem / "index.html"
        assert page.is_file(), f"{notebook.name}: no page"
        assert 'class="jp-Notebook' in page.read_text() or "jp-Cell" in page.read_text(), notebook.name
    formats = _text((site / "formats" / "index.html").read_text())
    assert "Capture directory" in formats


def test_no_docstring_renders_as_italics(site):
    # `rho*kappa ... rho*K` or `__init__` outside backticks pair up as Markdown emphasis: the asterisks
    # or underscores vanish and the text between them turns italic. Formulas go in backticks.
    found = {page.parent.name: re.findall(r"<(em|strong)>(.*?)</\1>", page.read_text(), flags=re.S)
             for page in (site / "api").glob("*/index.html")}
    assert not {m: hits for m, hits in found.items() if hits}
