"""The documentation's references stay live: no Sphinx roles (which mkdocstrings renders as
plain text, so a stale one goes unnoticed) and no dotted ``jurs`` names in the pages that
no longer exist. Cross-references themselves are checked by ``mkdocs build --strict``."""

import importlib
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_no_sphinx_roles():
    """``docs/xrefs.py`` turns them into cross-references or inline code."""
    check = subprocess.run(
        [sys.executable, "docs/xrefs.py", "--check", "jurs", "docs", "README.md"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert check.returncode == 0, check.stdout + check.stderr


def _exists(name: str) -> bool:
    """Whether ``jurs.a.b.c`` names a module, or an attribute of its longest module prefix."""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        try:
            for attr in parts[split:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return False
        return True
    return False


def test_named_objects_exist():
    """Every ``jurs.x.y`` in backticks in docs/ and the README names something."""
    pages = sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]
    stale = [
        f"{page.relative_to(ROOT)}:{number}: {match[1]}"
        for page in pages
        for number, line in enumerate(page.read_text().splitlines(), 1)
        for match in re.finditer(r"`(jurs(?:\.\w+)+)(?:\(\))?`", line)
        if not _exists(match[1])
    ]
    assert not stale, "\n".join(stale)
