"""How low the default smoothing can go: clean shapes, two densities, a ladder of smoothing.

``jurs.auto_settings`` picks ``CLEAN_SMOOTHING = 1e-6`` on clean clouds. Lower values fit a
smooth curve more closely (the membrane term R pulls less on the slope of g), and they are
what an exact interpolant such as the thin-plate RBF would need to be matched on a smooth
curve; this script measures what they cost on the project's other shapes, so that the
default rests on a measurement anyone can repeat:

* **Cases.** The clean outlines of ``benchmarks/quality.py`` (analytic curves, glyphs,
  traced silhouettes), each at the number of points ``quality.py`` gives it and at
  ``DENSE_POINTS``, where the default grid is at its cap and every cell holds many points.
* **Fits.** ``jurs.fit`` with the automatic grid, offset and eps, and ``LeastSquares`` with
  the scale-free lambda of each smoothing in ``LADDER``.
* **Measures.** ``jurs.levelset.analyze`` against dense samples of the clean outline, as
  ``quality.py``: Chamfer and Hausdorff distance (1e-3 of the bounding-box diagonal),
  components against the true number, supplementary components and tiny loops.

Writes ``benchmarks/results/smoothing.{json,md}`` (about 2 minutes on 2 cores;
``--markdown-only`` rewrites the markdown from the JSON).

    python -m benchmarks.smoothing [--markdown-only]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jurs  # noqa: E402
import jurs.levelset  # noqa: E402
import jurs.shapes  # noqa: E402

from ._common import RESULTS, machine, write_results  # noqa: E402
from ._quality_cases import CASES, RESOLUTION, choose_m, clean_outline  # noqa: E402

SHAPES = (
    "example1",
    "ellipse",
    "rose",
    "lobes",
    "annulus",
    "glyph_B",
    "glyph_a",
    "glyph_8",
    "horse",
    "coins",
)
#: Dense clouds: at this many points every shape's default grid is at its cap.
DENSE_POINTS = 5000
LADDER = (1e-6, 1e-7, 1e-8, 1e-10)


def measure(case: str, m: int, ref, diag: float, true_components: int) -> dict:
    shape, kwargs, _ = CASES[case]
    points, normals = jurs.shapes.get(shape, m, **kwargs)
    auto = jurs.auto_settings(points, normals)
    row = {
        "case": case,
        "m": m,
        "grid": list(auto.grid),
        "default_smoothing": auto.smoothing,
        "cell_over_spacing": (auto.domain[1][0] - auto.domain[0][0])
        / (auto.grid[0] - 3)
        / auto.spacing,
        "fits": {},
    }
    for smoothing in LADDER:
        st = jurs.auto_settings(points, normals, smoothing=smoothing)
        sol = jurs.fit(
            points,
            normals,
            grid=st.grid,
            offset=st.offset,
            eps=st.eps,
            domain=st.domain,
            solver=jurs.LeastSquares(lam=st.lam),
        )
        rep = jurs.levelset.analyze(
            sol.spline, points, offset=st.offset, reference=ref, resolution=RESOLUTION
        )
        row["fits"][f"{smoothing:g}"] = {
            "chamfer": rep.chamfer / diag,
            "hausdorff": rep.hausdorff / diag,
            "num_components": rep.num_components,
            "true_components": true_components,
            "num_supplementary": rep.num_supplementary,
            "num_tiny_loops": rep.num_tiny_loops,
        }
    return row


def clean(fit: dict) -> bool:
    """The zero set has the true number of components, none supplementary, no tiny loop."""
    return (
        fit["num_components"] == fit["true_components"]
        and fit["num_supplementary"] == 0
        and fit["num_tiny_loops"] == 0
    )


def markdown(rows: list[dict], meta: dict) -> str:
    keys = [f"{s:g}" for s in LADDER]
    lines = [
        "# Smoothing below the default on clean shapes",
        "",
        f"Machine: {meta['machine']}. float64. Whole run: {meta['runtime_s'] / 60:.1f} min.",
        "",
        "`jurs.fit` with the automatic grid, offset and eps and `LeastSquares` at the "
        "scale-free lambda of each smoothing (column *default*: what "
        "`jurs.auto_settings` picks; more than 1e-6 on the traced outlines, whose pixel "
        "steps measure as a little noise). Each cell: Chamfer / Hausdorff distance to the clean "
        "outline in 1e-3 of its diagonal, then the zero set's components / true "
        "components, and `+k supp` for k supplementary components, `+k tiny` for tiny "
        "loops. h / s: the grid's cell width over the point spacing (above 1.5 the grid "
        "is at its cap of 96).",
        "",
    ]
    lines += [
        "| shape | m | grid | h / s | default | "
        + " | ".join(f"smoothing {k}" for k in keys)
        + " |",
        "|" + "---|" * (5 + len(keys)),
    ]
    for r in rows:
        cells = []
        for k in keys:
            f = r["fits"][k]
            extra = "".join(
                f" +{f[n]} {w}"
                for n, w in (("num_supplementary", "supp"), ("num_tiny_loops", "tiny"))
                if f[n]
            )
            cells.append(
                f"{f['chamfer'] * 1e3:.3f} / {f['hausdorff'] * 1e3:.2f}, "
                f"{f['num_components']}/{f['true_components']}{extra}"
            )
        lines.append(
            f"| {r['case']} | {r['m']} | {r['grid'][0]}x{r['grid'][1]} | "
            f"{r['cell_over_spacing']:.1f} | {r['default_smoothing']:.2g} | "
            + " | ".join(cells)
            + " |"
        )
    lines += ["", "## Summary", ""]
    ref = keys[0]
    for k in keys[1:]:
        bad = [f"{r['case']} ({r['m']})" for r in rows if not clean(r["fits"][k])]
        worst = max(rows, key=lambda r: r["fits"][k]["hausdorff"] / r["fits"][ref]["hausdorff"])
        growth = worst["fits"][k]["hausdorff"] / worst["fits"][ref]["hausdorff"]
        lines.append(
            f"* smoothing {k}: zero set clean in {len(rows) - len(bad)}/{len(rows)} "
            "runs"
            + (f" (not in: {', '.join(bad)})" if bad else "")
            + f"; Hausdorff distance at most {growth:.2g}x that at smoothing {ref} "
            f"({worst['case']}, m = {worst['m']})"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--markdown-only",
        action="store_true",
        help="rewrite the markdown from the last run's JSON (no measuring)",
    )
    if parser.parse_args(argv).markdown_only:
        with open(os.path.join(RESULTS, "smoothing.json")) as fh:
            data = json.load(fh)
        text = markdown(data["rows"], data)
        print(text)
        write_results("smoothing", data, text)
        return
    start = time.perf_counter()
    rows = []
    for case in SHAPES:
        comps, ref, diag, length = clean_outline(CASES[case][0])
        for m in (choose_m(length, diag), DENSE_POINTS):
            rows.append(measure(case, m, ref, diag, len(comps)))
            print(
                f"[{time.perf_counter() - start:6.1f} s] {case} m={m}", file=sys.stderr, flush=True
            )
    meta = {
        "machine": machine(),
        "runtime_s": time.perf_counter() - start,
        "ladder": list(LADDER),
        "dense_points": DENSE_POINTS,
    }
    text = markdown(rows, meta)
    print(text)
    write_results("smoothing", {**meta, "rows": rows}, text)


if __name__ == "__main__":
    main()
