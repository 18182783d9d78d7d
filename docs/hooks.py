"""MkDocs hooks.

* Publish the committed benchmark reports and figures (``benchmarks/results``) under
  ``results/`` in the site, so the performance page and the gallery link to them without a
  copy in ``docs/``. Smoke-run outputs (``*_quick.*``, git-ignored) are skipped.
* Keep ``--strict`` strict under ``--quiet``: mkdocs' ``--quiet`` raises its logger's level
  to ERROR, so warnings (a cross-reference that resolves to nothing, a broken link) never
  reach the handler that counts them and ``mkdocs build --strict --quiet`` passes with
  them. In strict mode the hook lowers the logger back to WARNING, so that they fail the
  build and are printed (strict makes them errors); INFO stays silent.
"""

from __future__ import annotations

import logging
from pathlib import Path

from mkdocs.structure.files import File
from mkdocs.utils import CountHandler

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
PUBLISHED = (".md", ".png")


def on_config(config):
    log = logging.getLogger("mkdocs")
    if config["strict"] and log.level > logging.WARNING:
        for handler in log.handlers:
            if not isinstance(handler, CountHandler):
                handler.setLevel(logging.WARNING)  # no INFO on the console
        log.setLevel(logging.WARNING)
    return config


def on_files(files, config):
    results = BENCHMARKS / "results"
    for path in sorted(results.rglob("*")):
        if path.is_file() and path.suffix in PUBLISHED and "_quick" not in path.stem:
            files.append(
                File(
                    path.relative_to(BENCHMARKS).as_posix(),
                    src_dir=str(BENCHMARKS),
                    dest_dir=config["site_dir"],
                    use_directory_urls=config["use_directory_urls"],
                )
            )
    return files
