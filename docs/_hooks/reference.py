"""mkdocs hook: writes the generated pages of the reference at build time, so they never drift.

- API pages: one per documented module of `jaxrender`, `fitting` and `sims`, found by walking the
  packages with griffe (`public_modules`): its docstring, a table of its public names (what its
  `__init__` re-exports, `from ._x import Y as Y` (see `reexports.py`), its `__all__`, or else its
  own top-level definitions) and one mkdocstrings entry (signature, docstring) per name.
- CLI pages: one per program, from the argparse parsers of `jaxrender.app.cli` (`command_parser`).
- Notebook pages: `examples/*.ipynb` (at `examples/NAME/`), rendered by mkdocs-jupyter without executing them.

The navigation is built here too; mkdocs.yml lists only the hand-written pages.
"""

from __future__ import annotations

import argparse
import html
import sys
from pathlib import Path

import griffe
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(Path(__file__).parent)]  # this checkout's packages, then reexports.py

from reexports import RedundantAliasExports  # noqa: E402

from jaxrender.app.cli.driver import command_parser  # noqa: E402
from jaxrender.app.cli.programs import COMMAND_TABLES  # noqa: E402

PACKAGES = ("jaxrender", "fitting", "sims")
UNDOCUMENTED = ("jaxrender.app.cli",)  # the command lines have their own pages
API_DIR, CLI_DIR = "api", "cli"


def public_names(module: griffe.Module) -> list[str]:
    """The module's public objects other than submodules: `__all__`, re-exports and its own definitions."""
    return [name for name, member in module.members.items()
            if member.is_public and not member.is_module and not (name.startswith("__") and name.endswith("__"))]


def public_modules(module: griffe.Module) -> list[griffe.Module]:
    """Modules with a page: those with public names. Below a package that re-exports names only its
    subpackages get pages of their own (its modules are implementation); below one that re-exports
    nothing (`jaxrender`, `jaxrender.app`) every public module does."""
    reexports = bool(public_names(module))
    found = [module] if reexports else []
    for sub in module.modules.values():
        if sub.is_alias or not sub.is_public or sub.path in UNDOCUMENTED:
            continue
        if sub.is_init_module or not reexports:
            found += public_modules(sub)
    return found


def _load_packages() -> list[griffe.Module]:
    extensions = griffe.load_extensions(RedundantAliasExports())
    return [griffe.load(name, search_paths=[str(ROOT)], extensions=extensions) for name in PACKAGES]


def _first_sentence(docstring: str) -> str:
    """The docstring's first sentence (its first paragraph up to a full stop before a capital letter,
    outside code and brackets): mkdocstrings' own summary tables cut at the first line break."""
    text = " ".join(docstring.strip().split("\n\n")[0].split())
    depth, code = 0, False
    for i, char in enumerate(text):
        code ^= char == "`"
        depth += (char in "([{") - (char in ")]}")
        if char == "." and not code and depth <= 0 and text[i + 1:i + 3].strip()[:1].isupper():
            return text[:i + 1]
    return text


def _api_page(module: griffe.Module) -> str:
    """The module's docstring, a table of its public names, then one entry per name."""
    lines = [f"# `{module.path}`", "", f"::: {module.path}", "    options:", "      members: false",
             "      show_root_heading: false", "      show_root_toc_entry: false", "",
             "| name | kind | summary |", "|---|---|---|"]
    entries = []
    for name in public_names(module):
        member = module[name]
        summary = _first_sentence(member.docstring.value) if member.docstring else ""
        lines.append(f"| [`{name}`](#{module.path}.{name}) | {member.kind.value} | {_markdown_cell(summary)} |")
        entries += ["", f"::: {module.path}.{name}"]
    return "\n".join(lines + entries) + "\n"


def _cell(text: str) -> str:
    """Plain text for a table cell: one line, HTML-escaped, pipes escaped."""
    return html.escape(" ".join(text.split())).replace("|", "\\|")


def _markdown_cell(text: str) -> str:
    """Markdown for a table cell: pipes escaped outside code spans (the table reads those as one cell)."""
    parts = text.split("`")
    return "`".join(p.replace("|", "\\|") if i % 2 == 0 else p for i, p in enumerate(parts))


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    """One table row per argument, written as `--help` writes it (argparse keeps no public list of
    its arguments nor a public formatter for one: `_actions` and `_format_action_invocation`)."""
    formatter = parser._get_formatter()
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        if not action.option_strings or action.required:
            default = "required"
        elif action.nargs == 0 or action.default in (None, argparse.SUPPRESS):
            default = ""
        else:
            default = f"`{action.default}`"
        rows.append(f"| `{formatter._format_action_invocation(action)}` | {default} | "
                    f"{_cell(action.help or '')} |")
    return rows


def _cli_page(program: str, description: str, commands: dict[str, tuple[str, str]]) -> str:
    lines = [f"# `{program}`", "", description, "",
             "Generated from the argparse parsers at build time; "
             f"`{program} COMMAND --help` prints the same.", "",
             "| command | what it does |", "|---|---|"]
    lines += [f"| [`{program} {name}`](#{program}-{name}) | {_cell(help_)} |" for name, (_, help_) in commands.items()]
    for name in commands:
        _, parser = command_parser(program, name, commands)
        lines += ["", f"## `{program} {name}` {{ #{program}-{name} }}", "", parser.description or "", "",
                  "```text", parser.format_usage().strip(), "```", "",
                  "| argument | default | meaning |", "|---|---|---|", *_option_rows(parser)]
    return "\n".join(lines) + "\n"


_state: dict = {}


def on_config(config):
    packages = _load_packages()
    modules = [m for package in packages for m in public_modules(package)]
    notebooks = sorted((ROOT / "examples").glob("*.ipynb"))
    _state.update(modules=modules, notebooks=notebooks, programs=COMMAND_TABLES)
    kernels = {name: [] for name in PACKAGES}
    layer = []  # the orchestration layer jaxrender.app, apart from the kernels
    for module in sorted(modules, key=lambda m: m.path):
        page = {module.path: f"{API_DIR}/{module.path}.md"}
        (layer if module.path.startswith("jaxrender.app") else kernels[module.path.split(".")[0]]).append(page)
    api_nav = [pages[0] if len(pages) == 1 else {name: pages}
               for name, pages in [*kernels.items(), ("jaxrender.app", layer)]]
    listed = {next(iter(entry.values())) if isinstance(entry, dict) else entry for entry in config.nav}
    written = sorted(p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").glob("*.md"))
    more = [page for page in written if page not in listed]  # hand-written pages mkdocs.yml does not list yet
    config.nav = [*config.nav, *([{"How it works": more}] if more else []),
                  {"API reference": api_nav},
                  {"Command lines": [{p: f"{CLI_DIR}/{p}.md"} for p in COMMAND_TABLES]},
                  {"Notebooks": [nb.relative_to(ROOT).as_posix() for nb in notebooks]}]
    return config


@event_priority(50)  # before mkdocs-jupyter's on_files, which turns the .ipynb files into pages
def on_files(files: Files, config) -> Files:
    for module in _state["modules"]:
        files.append(File.generated(config, f"{API_DIR}/{module.path}.md", content=_api_page(module)))
    for program, (description, commands) in _state["programs"].items():
        page = _cli_page(program, description, commands)
        files.append(File.generated(config, f"{CLI_DIR}/{program}.md", content=page))
    for notebook in _state["notebooks"]:
        # a File read from the checkout, not File.generated: mkdocs-jupyter's wrapper loses a generated
        # file's source path; the page keeps the notebook's path in the repository (examples/NAME/)
        files.append(File(notebook.relative_to(ROOT).as_posix(), src_dir=str(ROOT), dest_dir=config.site_dir,
                          use_directory_urls=config.use_directory_urls))
    return files
