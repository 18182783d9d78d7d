"""Turn Sphinx cross-reference roles into mkdocstrings (autorefs) cross-references.

The docstrings are rendered as Markdown by mkdocstrings, where a Sphinx role such as
``:func:`fit``` is plain text: it neither links nor fails the build when its target is
renamed. This script rewrites each role, in the docstrings and comments of ``.py`` files
and in ``.md`` files (outside fenced code blocks), into one of two forms:

* a cross-reference, ``[`fit`][jurs.fit]`` (or ``[`jurs.fit`][]`` when the text is the
  identifier), when the target is rendered in the documentation site. ``mkdocs build
  --strict`` then fails if the target later goes away (mkdocs-autorefs warns on a
  cross-reference it cannot resolve, and strict mode turns the warning into an error);
* plain inline code, ``fit`` between double backticks (single ones in ``.md`` files), when
  it is not (private helpers, other libraries): an autoref to an object the site does not
  render would fail the strict build.

Rendered or not is asked of mkdocstrings itself: the script builds the site into a
temporary folder (``mkdocs build``, a few seconds) and reads the inventory that
mkdocstrings writes, ``objects.inv``. That lists every object the ``:::`` directives of
docs/api.md render, under its public path (``jurs.fit``) and its canonical path
(``jurs._fit.fit.fit``), both pointing at the same anchor; the anchor (the public path) is
the identifier written. ``--inventory PATH`` reads an inventory already built instead.

A role's target is resolved as Sphinx would, relative to where it is written, with the
imports of the module followed (griffe, statically: nothing is imported): a name in a
method's docstring is looked up in its class, then its module, then as written. So
``:class:`LeastSquares``` in ``jurs/solvers/_held_out.py`` (which imports it) becomes
``[`LeastSquares`][jurs.LeastSquares]``, ``:data:`MAX_X``` names the module's ``MAX_X``,
and ``~`` keeps only the last component as the text. A target written as a private path
that mkdocstrings renders under a public one is written with the public path.

Only docstrings (string statements: a module's, class's, function's or attribute's) and
comments of ``.py`` files change, never code. A changed line longer than its paragraph's
lines were (at most ``[tool.ruff] line-length`` of pyproject.toml) is wrapped within the
paragraph, so ``ruff check`` still passes. Running it twice changes nothing the second time.

Usage::

    python docs/xrefs.py [PATH ...]          # rewrite (default: jurs docs README.md)
    python docs/xrefs.py --check [PATH ...]  # list the roles left; exit 1 if any

Folders are searched for ``*.py`` and ``*.md`` files. ``--check`` needs neither mkdocs nor
griffe. This file itself is skipped (its docstring shows the roles).
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import subprocess
import sys
import tempfile
import tokenize
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SELF = Path(__file__).resolve()
DEFAULT_PATHS = ("jurs", "docs", "README.md")

#: The Python-domain roles; ``:py:func:`` spellings and the ``!`` (no link) prefix too.
ROLE = re.compile(
    r"(?<![\w`]):(?:py:)?(?P<role>func|class|data|mod|meth|attr|obj|exc|const|any|type)"
    r":`(?P<body>[^`\n]+)`"
)
#: What ``--check`` looks for: any role opening, closed on its line or not.
ROLE_START = re.compile(
    r"(?<![\w`]):(?:py:)?(?:func|class|data|mod|meth|attr|obj|exc|const|any|type):`(?=[^`\s])"
)
TITLED = re.compile(r"^(?P<title>.*?)\s*<(?P<target>[^<>]+)>$")
FENCE = re.compile(r"^\s*(```|~~~)")
#: Line starts that would open a Markdown block (list, quote, heading, table) if a wrapped
#: line began with them.
BLOCK_START = re.compile(r"^(?:[-*+](?:\s|$)|>|#+(?:\s|$)|\||=+\s*$|\d+[.)](?:\s|$))")


def line_length() -> int:
    text = (ROOT / "pyproject.toml").read_text()
    match = re.search(r"^\[tool\.ruff\][^\[]*?^line-length\s*=\s*(\d+)", text, re.M | re.S)
    return int(match.group(1)) if match else 88


# --------------------------------------------------------------------------- rendered names


def read_inventory(path: Path) -> dict[str, str]:
    """Every name in a Sphinx inventory (``objects.inv``) -> the anchor it links to."""
    data = path.read_bytes()
    header = data.split(b"\n", 4)
    body = zlib.decompress(header[4]).decode()
    anchors = {}
    for line in body.splitlines():
        match = re.match(r"(\S+)\s+\S+\s+-?\d+\s+(\S+)", line)
        if match:
            name, uri = match.groups()
            anchor = uri.rpartition("#")[2].replace("$", name) if "#" in uri else name
            anchors[name] = anchor
    return anchors


def built_inventory() -> dict[str, str]:
    """Build the site (not strictly: the roles may be stale) and read its inventory."""
    with tempfile.TemporaryDirectory() as site:
        subprocess.run(
            [sys.executable, "-m", "mkdocs", "build", "--quiet", "--no-strict", "-d", site],
            cwd=ROOT,
            check=True,
        )
        return read_inventory(Path(site) / "objects.inv")


class Resolver:
    """Sphinx-like resolution of a role's target, then rendered or not: ``anchors`` maps
    every name in the site's inventory to the identifier to write. The modules are read by
    griffe from their source (``allow_inspection=False``: nothing is imported)."""

    def __init__(self, anchors: dict[str, str]):
        import griffe

        self.anchors = anchors
        self.loader = griffe.GriffeLoader(search_paths=[ROOT], allow_inspection=False)
        self.modules: dict[str, object] = {}

    def module(self, path: Path):
        """The griffe module of a file, or None."""
        path = path.resolve()
        parts = [path.stem] if path.stem != "__init__" else []
        folder = path.parent
        while (folder / "__init__.py").exists():
            parts.insert(0, folder.name)
            folder = folder.parent
        if not parts:
            return None
        name = ".".join(parts)
        if name not in self.modules:
            try:
                if folder not in self.loader.finder.search_paths:
                    self.loader.finder.search_paths.append(folder)
                top = self.top(parts[0])
                self.modules[name] = top[".".join(parts[1:])] if len(parts) > 1 else top
            except Exception:
                self.modules[name] = None
        return self.modules[name]

    def top(self, name: str):
        """The top-level module ``name``, loaded once."""
        collection = self.loader.modules_collection
        if name not in collection.members:
            self.loader.load(name)
        return collection[name]

    def lookup(self, dotted: str, module):
        """The griffe object named ``dotted`` (absolute, or in ``module``), or None."""
        for base in ([module] if module is not None else []) + [None]:
            try:
                if base is None:
                    top = dotted.partition(".")[0]
                    if not ((ROOT / top / "__init__.py").exists() or (ROOT / f"{top}.py").exists()):
                        continue  # not this project's: not rendered, and slow to load
                    self.top(top)
                    obj = self.loader.modules_collection[dotted]
                else:
                    obj = base[dotted]
                return obj
            except Exception:
                continue
        return None

    def anchor(self, obj) -> str | None:
        names = [obj.path]
        try:
            names.append(obj.canonical_path)
            if obj.is_alias:
                names.append(obj.final_target.path)
        except Exception:
            pass
        for name in names:
            if name in self.anchors:
                return self.anchors[name]
        return None

    def resolve(self, target: str, module, scopes: list[str]) -> str | None:
        """The identifier to link to, or None if the target is not rendered."""
        target = target.lstrip(".")
        candidates = [f"{scope}.{target}" for scope in scopes] + [target]
        for dotted in candidates:
            if dotted in self.anchors:
                return self.anchors[dotted]
            obj = self.lookup(dotted, None)
            if obj is not None:
                return self.anchor(obj)
        if module is not None:
            obj = self.lookup(target, module)
            if obj is not None:
                return self.anchor(obj)
        return None


# --------------------------------------------------------------------------- rewriting


#: A role broken over two lines: its start, the line break and indentation (and a comment's
#: ``#``), and the rest up to the closing backtick and the punctuation after it.
SPLIT_ROLE = re.compile(
    r"(?<![\w`])(?P<head>:(?:py:)?(?:func|class|data|mod|meth|attr|obj|exc|const|any|type)"
    r":`[^`\n]*)\n(?P<indent>[ \t]*(?:#:?[ \t]?)?)(?P<tail>[ \t]*[^`\n]*`[^\s`]*)[ \t]?"
)


def join_split_roles(text: str) -> str:
    """``text`` with each role broken over two lines put back on the first one, the line
    break moved after it (so the line count stays): ``(:func:`a.`` / ``b`) c`` becomes
    ``(:func:`a.b`)`` / ``c``. A dotted name is joined without a space, words with one."""

    def one(match: re.Match) -> str:
        head, tail = match["head"], match["tail"].strip()
        sep = "" if head.endswith((".", "`")) or tail.startswith(".") else " "
        return f"{head.rstrip()}{sep}{tail}\n{match['indent']}"

    return SPLIT_ROLE.sub(one, text)


def rewrite_roles(text: str, convert, *, markdown: bool) -> str:
    """``text`` with each role replaced by ``convert(role, target, title)``'s answer."""

    def one(match: re.Match) -> str:
        body = match["body"].strip()
        titled = TITLED.match(body)
        if titled:
            title, target = titled["title"], titled["target"]
        else:
            target = body.lstrip("!")
            title = target.lstrip("~.").rpartition(".")[2] if target.startswith("~") else None
            target = target.lstrip("~")
            title = title or target
        identifier = None if body.startswith("!") else convert(match["role"], target)
        if identifier is None:
            return f"`{title}`" if markdown else f"``{title}``"
        if title == target and target.partition(".")[0] == identifier.partition(".")[0]:
            title = identifier  # a full path is written as the public one
        if title == identifier:
            return f"[`{identifier}`][]"
        return f"[`{title}`][{identifier}]"

    return ROLE.sub(one, text)


def code_spans(line: str) -> list[tuple[int, int]]:
    """The spans of ``line`` inside backticks or a cross-reference's brackets."""
    return [m.span() for m in re.finditer(r"(`+)[^`]*?\1|\[[^\]\s]*\]", line)]


def split_point(line: str, width: int, indent: int) -> int | None:
    """Where to break ``line`` to fit in ``width``: a space outside code, leaving no Markdown
    block start behind it; None if there is none."""
    spans = code_spans(line)
    for i in range(min(width, len(line) - 1), indent, -1):
        if line[i] != " " or any(a < i < b for a, b in spans):
            continue
        head, tail = line[:i].rstrip(), line[i:].lstrip()
        if len(head) > indent and tail and not BLOCK_START.match(tail):
            return i
    return None


def indent_of(line: str) -> int:
    return len(line) - len(line.lstrip())


def continues(line: str, indent: int) -> bool:
    """Whether ``line`` carries on a paragraph whose continuation lines start at ``indent``."""
    stripped = line.strip()
    return (
        bool(stripped)
        and indent_of(line) == indent
        and not BLOCK_START.match(stripped)
        and not FENCE.match(line)
        and not stripped.startswith(('"""', "'''"))
        and not re.fullmatch(r"[A-Z][\w ]*:", stripped)  # a docstring section
    )


def wrap(
    lines: list[str], changed: list[bool], limit: int, first_offset: int = 0, target: int = 0
) -> list[str]:
    """Break the changed lines longer than ``target`` columns (the paragraph's own width,
    at most ``limit``; ``limit`` if 0), carrying the rest into the paragraph's next line, or
    a new one. ``lines[0]`` starts at column ``first_offset``, which is also the
    indentation of the lines after it (a docstring's)."""
    lines, changed = list(lines), list(changed)
    target = min(target or limit, limit)
    i, fenced = 0, False
    while i < len(lines):
        line = lines[i]
        if FENCE.match(line):
            fenced = not fenced
        offset = first_offset if i == 0 else 0
        if fenced or not changed[i] or len(line) + offset <= target:
            i += 1
            continue
        indent = indent_of(line) if i else 0
        cut = split_point(line, target - offset, indent + 1) or split_point(
            line, limit - offset, indent + 1
        )
        if cut is None:
            i += 1
            continue
        head, tail = line[:cut].rstrip(), line[cut:].lstrip()
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if i == 0:
            cont = first_offset
        elif i + 1 < len(lines) and nxt.strip() and indent_of(nxt) > indent:
            cont = indent_of(nxt)  # an item's continuation lines
        elif re.match(r"\s*[-*+] ", line):
            cont = indent + 2
        elif re.match(r"\s*[\w*]+( \([^)]*\))?: ", line) and indent > first_offset:
            cont = indent + 4  # the first line of an Args-style item
        else:
            cont = indent
        lines[i] = head
        if i + 1 < len(lines) and continues(nxt, cont) and not tail.endswith(('"""', "'''")):
            lines[i + 1] = " " * cont + tail + " " + nxt.strip()
            changed[i + 1] = True
        else:
            lines.insert(i + 1, " " * cont + tail)
            changed.insert(i + 1, True)
        i += 1
    return lines


def own_width(lines: list[str], first_offset: int = 0) -> int:
    """The width a block of lines was wrapped to: its longest line."""
    return max(len(line) + (first_offset if i == 0 else 0) for i, line in enumerate(lines))


def docstring_tokens(source: str) -> set[tuple[int, int]]:
    """Start positions (line, column) of the string tokens that are string statements."""
    starts = set()
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Expr)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            starts.add((node.lineno, node.col_offset))
    return starts


def scopes_at(source: str, module_name: str | None) -> dict[int, list[str]]:
    """For each line, the enclosing classes' dotted paths (innermost first), then the
    module's."""
    scopes: dict[int, list[str]] = {}
    if module_name is None:
        return scopes

    def visit(node, path: list[str]):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                inner = [f"{path[0]}.{child.name}", *path]
                for line in range(child.lineno, (child.end_lineno or child.lineno) + 1):
                    scopes[line] = inner
                visit(child, inner)
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, path)

    visit(ast.parse(source), [module_name])
    return scopes


def comment_blocks(tokens: list[tokenize.TokenInfo], lines: list[str]):
    """The comments in runs: consecutive whole-line comments at one column with one prefix
    (``#`` or ``#:``) form a block; a comment after code is a block of its own."""
    blocks: list[list[tokenize.TokenInfo]] = []
    for tok in tokens:
        whole = not lines[tok.start[0] - 1][: tok.start[1]].strip()
        if blocks:
            last = blocks[-1][-1]
            if (
                whole
                and not lines[last.start[0] - 1][: last.start[1]].strip()
                and last.start[0] == tok.start[0] - 1
                and last.start[1] == tok.start[1]
                and comment_prefix(last.string).rstrip() == comment_prefix(tok.string).rstrip()
            ):
                blocks[-1].append(tok)
                continue
        blocks.append([tok])
    return blocks


def comment_prefix(comment: str) -> str:
    return re.match(r"#+:?\s?", comment).group(0)  # type: ignore[union-attr]


def convert_python(path: Path, source: str, resolver: Resolver, limit: int) -> str:
    module = resolver.module(path)
    module_name = module.path if module is not None else None
    scopes = scopes_at(source, module_name)
    starts = docstring_tokens(source)
    lines = source.splitlines(keepends=True)
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    edits = []  # (start line, start col, end line, end col, new text), 1-based lines

    def rewrite(text: str, row: int) -> str:
        where = scopes.get(row, [module_name] if module_name else [])
        return rewrite_roles(
            text, lambda role, target: resolver.resolve(target, module, where), markdown=False
        )

    for tok in tokens:
        if tok.type == tokenize.STRING and tok.start in starts and ROLE.search(tok.string):
            old = tok.string.split("\n")
            new = rewrite(join_split_roles(tok.string), tok.start[0]).split("\n")
            changed = [a != b for a, b in zip(old, new)]
            width = own_width(old, tok.start[1])
            text = "\n".join(wrap(new, changed, limit, tok.start[1], width))
            edits.append((*tok.start, *tok.end, text))
    comments = [tok for tok in tokens if tok.type == tokenize.COMMENT]
    for block in comment_blocks(comments, lines):
        if not any(ROLE.search(tok.string) for tok in block):
            continue
        first, last = block[0], block[-1]
        row, col = first.start
        prefix = comment_prefix(first.string)
        old = [tok.string[len(comment_prefix(tok.string)) :] for tok in block]
        joined = join_split_roles("\n".join(old)).split("\n")
        new = [rewrite(text, tok.start[0]) for text, tok in zip(joined, block)]
        changed = [a != b for a, b in zip(old, new)]
        room = limit - col - len(prefix)
        code_line = lines[row - 1]
        if code_line[:col].strip():  # after code: go on below, at the code's indentation
            indent, room = indent_of(code_line), limit - indent_of(code_line) - len(prefix)
            wrapped = wrap(new, changed, limit - col - len(prefix))
            wrapped = [wrapped[0], *(w.strip() for w in wrapped[1:])]
        else:
            indent = col
            wrapped = wrap(new, changed, room, 0, own_width(old))
        text = ("\n" + " " * indent).join(prefix + w if w else prefix.rstrip() for w in wrapped)
        edits.append((row, col, *last.end, text))
    for srow, scol, erow, ecol, new in sorted(edits, reverse=True):
        head = lines[srow - 1][:scol]
        tail = lines[erow - 1][ecol:]
        lines[srow - 1 : erow] = [head + new + tail]
    return "".join(lines)


def convert_markdown(source: str, resolver: Resolver) -> str:
    out, fenced = [], False
    for line in join_split_roles(source).splitlines(keepends=True):
        if FENCE.match(line):
            fenced = not fenced
        if not fenced:
            line = rewrite_roles(line, lambda role, target: resolver.resolve(target, None, []),
                                 markdown=True)  # fmt: skip
        out.append(line)
    return "".join(out)


# --------------------------------------------------------------------------- check


def roles_left(path: Path, source: str) -> list[tuple[int, str]]:
    """(line, text) of each role left in ``path``'s docstrings and comments (or Markdown)."""
    found = []
    if path.suffix == ".md":
        fenced = False
        for number, line in enumerate(source.splitlines(), 1):
            if FENCE.match(line):
                fenced = not fenced
            elif not fenced and ROLE_START.search(line):
                found.append((number, line.strip()))
        return found
    starts = docstring_tokens(source)
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT or (tok.type == tokenize.STRING and tok.start in starts):
            for offset, line in enumerate(tok.string.split("\n")):
                if ROLE_START.search(line):
                    found.append((tok.start[0] + offset, line.strip()))
    return found


def files(paths: list[str]) -> list[Path]:
    out = []
    for name in paths:
        path = Path(name)
        if path.is_dir():
            out += sorted(p for p in path.rglob("*") if p.suffix in (".py", ".md"))
        elif path.suffix in (".py", ".md"):
            out.append(path)
    skip = ("site", ".venv", "node_modules", ".git")
    return [p for p in out if p.resolve() != SELF and not set(p.parts) & set(skip)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="*", default=list(DEFAULT_PATHS))
    parser.add_argument("--check", action="store_true", help="list the roles left; rewrite nothing")
    parser.add_argument("--inventory", type=Path, help="an objects.inv built already")
    args = parser.parse_args(argv)
    paths = files(args.paths)
    if args.check:
        left = [(p, n, t) for p in paths for n, t in roles_left(p, p.read_text())]
        for path, number, text in left:
            print(f"{path}:{number}: {text}")
        if left:
            print(
                f"{len(left)} line(s) with Sphinx roles: run python docs/xrefs.py", file=sys.stderr
            )
        return 1 if left else 0
    anchors = read_inventory(args.inventory) if args.inventory else built_inventory()
    resolver, width = Resolver(anchors), line_length()
    for path in paths:
        source = path.read_text()
        if not ROLE.search(source):
            continue
        if path.suffix == ".md":
            new = convert_markdown(source, resolver)
        else:
            new = convert_python(path, source, resolver, width)
        if new != source:
            path.write_text(new)
            print(f"rewrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
