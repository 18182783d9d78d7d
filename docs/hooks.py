"""MkDocs hook: publish the committed benchmark reports and figures (``benchmarks/results``)
under ``results/`` in the site, so the performance page and the gallery link to them
without a copy in ``docs/``. Smoke-run outputs (``*_quick.*``, git-ignored) are skipped."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
PUBLISHED = (".md", ".png")


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
