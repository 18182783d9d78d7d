"""The package's import structure (docs/design.md section 0), read from the source with
``ast``: no two modules of ``jurs`` import each other, and no module imports another
module's private (underscored) name. Every import counts, also those inside functions and
under ``TYPE_CHECKING``: a lazy import still ties the two modules together.

A helper that other modules use is a public name of its (private) module; a piece two
modules share lives in the module of its idea, below both."""

from __future__ import annotations

import ast
import collections
import pathlib

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "jurs"

#: Private names a module may import from another, each with its reason:
#: ``(importing module, imported module, name): reason``. Keep it short.
ALLOWED_PRIVATE: dict[tuple[str, str, str], str] = {}


def _modules() -> dict[str, tuple[pathlib.Path, bool]]:
    """``{dotted name: (file, is a package)}`` of every module of jurs."""
    mods = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        mods[".".join(parts)] = (path, is_package)
    return mods


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str | None:
    """The absolute module a ``from ... import`` names."""
    if node.level == 0:
        return node.module
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports():
    """``(edges, private)``: the modules each module imports, and every import of another
    module's private name as ``(importing module, imported module, name)``."""
    mods = _modules()
    edges = collections.defaultdict(set)
    private = []
    for module, (path, is_package) in mods.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                target = _resolve(module, is_package, node)
                if not target or not target.startswith("jurs"):
                    continue
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    if full in mods:  # a submodule: the package's own business
                        edges[module].add(full)
                        continue
                    if target in mods:
                        edges[module].add(target)
                    underscored = alias.name.startswith("_") and not alias.name.startswith("__")
                    if underscored and target != module:
                        private.append((module, target, alias.name))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in mods:
                        edges[module].add(alias.name)
    return edges, private


def test_the_reader_sees_the_package():
    edges, _ = _imports()
    assert "jurs._fit.fit" in edges["jurs"]
    assert "jurs._fit.progress" in edges["jurs._fit.fit"]


def test_no_two_modules_import_each_other():
    edges, _ = _imports()
    pairs = sorted((a, b) for a in list(edges) for b in edges[a] if a < b and a in edges.get(b, ()))
    assert not pairs, f"modules that import each other: {pairs}"


def test_no_module_imports_another_modules_private_names():
    _, private = _imports()
    unexplained = [p for p in private if p not in ALLOWED_PRIVATE]
    assert not unexplained, f"private names imported from another module: {unexplained}"
    stale = [p for p in ALLOWED_PRIVATE if p not in private]
    assert not stale, f"allowed private imports no longer made: {stale}"
