"""Griffe extension: `from ._x import Y as Y` in a module marks `Y` public (the project's re-export
convention, README "Layout"), as `__all__` would; plain imports stay private."""

from __future__ import annotations

import ast

import griffe


class RedundantAliasExports(griffe.Extension):
    def on_alias_instance(self, *, node, alias, agent, **kwargs) -> None:
        if isinstance(node, ast.ImportFrom) and alias.parent is not None and alias.parent.is_module:
            if any(a.asname == a.name == alias.name for a in node.names):
                alias.public = True
