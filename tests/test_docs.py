"""The documentation's references stay live: no Sphinx roles (which mkdocstrings renders as
plain text, so a stale one goes unnoticed) and no dotted ``jurs`` names in the pages that
no longer exist. Cross-references themselves are checked by ``mkdocs build --strict``."""

import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

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


# --- every ```python snippet runs as written ----------------------------------------------

PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
SNIPPET = re.compile(r"^```python\n(.*?)^```", re.S | re.M)

#: Snippets not run, by page and number (1-based, in the page's order), and why.
SKIP = {
    ("docs/design.md", 1): "the public contract: a summary with placeholders (xy, ...)",
    ("docs/design.md", 2): "reserved names: a summary with placeholders (P, N, ...)",
    ("docs/sharding.md", 1): "a million points; tests/test_sharding.py fits small clouds so",
    ("docs/sharding.md", 2): "a script started once per process (python -m jurs.distributed); "
    "tests/test_distributed.py runs one so",
    ("docs/sharding.md", 3): "the same script's lines for scans of a surface (files not here)",
}
#: Pages whose snippets run with the fast tests: they fit nothing. The others compile and
#: run fits (the home page's alone, a default 2D fit, takes a few seconds on an idle 2-core
#: machine; the README's and surfaces page's fit and mesh 3D clouds) and run with the slow
#: tests.
FAST_PAGES = {"docs/normals.md"}


def _snippets():
    """One case per page, its snippets in order: they continue one another (names defined
    in one are used in the next), so they run in one namespace, as a reader would type them
    in one session. Each skipped snippet is a case of its own, skipped with its reason
    (``pytest -rs`` lists them)."""
    cases = []
    for page in PAGES:
        name = page.relative_to(ROOT).as_posix()
        found = [(k, m[1]) for k, m in enumerate(SNIPPET.finditer(page.read_text()), 1)]
        for k, _ in found:
            if (name, k) in SKIP:
                skip = pytest.mark.skip(reason=SKIP[name, k])
                cases.append(pytest.param(name, [], id=f"{name}-{k}", marks=[skip]))
        run = [(k, code) for k, code in found if (name, k) not in SKIP]
        if run:
            marks = [] if name in FAST_PAGES else [pytest.mark.slow]
            cases.append(pytest.param(name, run, id=name, marks=marks))
    return cases


def test_snippet_lists_name_real_snippets():
    counts = {
        page.relative_to(ROOT).as_posix(): len(SNIPPET.findall(page.read_text())) for page in PAGES
    }
    for name, k in SKIP:
        assert 1 <= k <= counts.get(name, 0), (name, k)
    assert all(counts.get(name) for name in FAST_PAGES)


@pytest.mark.parametrize("page, snippets", _snippets())
def test_snippets_run(page, snippets, tmp_path, monkeypatch):
    """Each page's ```python blocks, extracted and run in order (in a scratch folder: they
    write figures and meshes). A snippet that fails names its page and number."""
    import warnings

    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    for k, code in snippets:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a snippet's notes are the reader's to see
            try:
                exec(compile(code, f"{page} snippet {k}", "exec"), namespace)
            except Exception as exc:
                raise AssertionError(f"{page}, snippet {k}: {type(exc).__name__}: {exc}") from exc


def test_settings_page_states_the_noise_measured():
    """The noise figures on the settings page are what auto_settings measures (to the two
    digits given)."""
    import jurs

    text = (ROOT / "docs/guide/settings.md").read_text()
    paragraph = text[text.index("the **noise** sigma") :].split("\n\n")[0]
    stated = {float(t) for t in re.findall(r"\d+(?:\.\d+)?(?:e-?\d+)?", paragraph)}
    clouds = [jurs.datasets.example1(m) for m in (120, 500, 2000)] + [jurs.datasets.example10()]
    for cloud in clouds:
        # smoothing given: no held-out fits to choose it, only the measurements
        noise = jurs.auto_settings(*cloud, smoothing=1e-6).noise
        assert float(f"{noise:.2g}") in stated, (len(cloud[0]), noise, sorted(stated))
