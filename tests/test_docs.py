"""The reference site (mkdocs.yml, docs/) builds with `mkdocs build --strict` from the checkout, and
it shows every public name of `jaxrender`, `fitting` and `sims` with the shapes of its signature,
every subcommand and option of the three command lines, the notebooks and the formats page.

The public names are read here from the sources with `ast` (re-exports `from ._x import Y as Y`,
`__all__`, top-level definitions), independently of the griffe walk in docs/_hooks/reference.py
that writes the pages, so a name the hook misses fails here."""

from __future__ import annotations

import ast
import html
import json
import os
import re
import subprocess
import sys
from pathlib import Path

from jaxrender.app.cli.driver import command_parser
from jaxrender.app.cli.programs import COMMAND_TABLES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jaxrender", "fitting", "sims")
UNDOCUMENTED = ("jaxrender.app.cli",)  # the command lines have their own pages
GALLERY_IMAGES = ("stage.jpg", "desert.jpg", "fitting.jpg", "noh.jpg")  # docs/images/, from `jaxrender gallery`
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


def _build(out: Path) -> None:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                            str(ROOT / "mkdocs.yml"), "--site-dir", str(out)],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    assert build.returncode == 0, f"mkdocs build --strict failed:\n{build.stdout}\n{build.stderr}"


def _api_problems(site: Path) -> list[str]:
    """Public names without an entry on their module's page, shapes missing from the signatures, and
    text that renders as italics (`rho*kappa ... rho*K` or `__init__` outside backticks pair up as
    Markdown emphasis: the asterisks or underscores vanish; formulas go in backticks)."""
    problems = []
    for module, names in DOCUMENTED.items():
        path = site / "api" / module / "index.html"
        if not path.is_file():
            problems.append(f"{module}: no page")
            continue
        page = path.read_text()
        anchors = set(re.findall(r'id="([^"]+)"', page))
        if missing := [n for n in names if f"{module}.{n}" not in anchors]:
            problems.append(f"{module}: no entry for {missing}")
        text = _text(page)
        shapes = set().union(*(_shapes(node) for node in names.values()))
        if missing := sorted(s for s in shapes if s not in text):
            problems.append(f"{module}: shapes missing from the signatures: {missing}")
        if italics := re.findall(r"<(?:em|strong)>(.*?)</(?:em|strong)>", page, flags=re.S):
            problems.append(f"{module}: renders as italics (put formulas in backticks): {italics}")
    return problems


def _cli_problems(site: Path) -> list[str]:
    problems = []
    for program, (_, commands) in COMMAND_TABLES.items():
        page = (site / "cli" / program / "index.html").read_text()
        text = _text(page)
        for name in commands:
            _, parser = command_parser(program, name, commands)
            options = [s for action in parser._actions for s in action.option_strings]  # argparse: no public list
            if f'id="{program}-{name}"' not in page or [s for s in options if s not in text]:
                problems.append(f"{program} {name}: no section, or options missing from it")
    return problems


def _page_problems(site: Path) -> list[str]:
    """Notebooks without a page or whose code is not on it; the formats page."""
    notebooks = sorted((ROOT / "examples").glob("*.ipynb"))
    problems = [] if notebooks else ["no notebooks found in examples/"]
    for notebook in notebooks:
        page = site / "examples" / notebook.stem / "index.html"
        text = _text(page.read_text()) if page.is_file() else ""
        cells = [c for c in json.loads(notebook.read_text())["cells"] if c["cell_type"] == "code"]
        firsts = [" ".join(line.split()) for c in cells for line in ["".join(c["source"]).strip().split("\n")[0]]]
        if not text or [line for line in firsts if line not in text]:
            problems.append(f"{notebook.name}: no page, or its code is not on it")
        # stored with its outputs, the page shows its figures (embedded PNGs)
        figures = sum("image/png" in out.get("data", {}) for c in cells for out in c.get("outputs", []))
        shown = page.read_text().count("data:image/png;base64") if page.is_file() else 0
        if figures == 0 or shown < figures:
            problems.append(f"{notebook.name}: {figures} figures stored, {shown} on its page")
    front = (site / "index.html").read_text()
    for name in GALLERY_IMAGES:  # one picture per showcase, with the command that made it
        if f'src="images/{name}"' not in front or not (site / "images" / name).is_file():
            problems.append(f"index.md: gallery image images/{name} not shown")
    if "jaxrender gallery --out" not in _text(front):
        problems.append("index.md: the gallery command is not on the front page")
    if "Capture directory" not in _text((site / "formats" / "index.html").read_text()):
        problems.append("formats.md: not rendered")
    return problems


def test_the_public_names_are_read_from_the_sources():
    # guards the reader above: it must find the packages' re-exports and modules, not an empty list
    assert {"jaxrender.shafts", "jaxrender.io", "jaxrender.app.scenes", "fitting", "sims"} <= set(DOCUMENTED)
    assert "render" in DOCUMENTED["jaxrender.shafts"] and "InputError" in DOCUMENTED["jaxrender.io"]
    assert isinstance(DOCUMENTED["jaxrender.shafts"]["render"], ast.FunctionDef)
    assert not any(m.startswith(UNDOCUMENTED) for m in DOCUMENTED)


def test_the_reference_builds_strictly_and_shows_every_public_name(tmp_path):
    # one test, one build: under `pytest -n 2` a fixture shared by several tests could build twice
    site = tmp_path / "site"
    _build(site)
    problems = _api_problems(site) + _cli_problems(site) + _page_problems(site)
    assert not problems, "\n".join(problems)
