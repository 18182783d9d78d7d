"""How ``jurs.fit`` chooses its basis: the capped uniform grid against the adaptive basis,
and what the automatic choice (``basis="auto"``) takes, on the quality suite's outlines.

For every case of ``benchmarks/_quality_cases.py`` at each noise level, the same cloud
(sampled and seeded as ``benchmarks/quality.py`` does) is fitted three ways in one process:
``jurs.fit(points, normals, basis=b)`` for ``b`` in ``uniform``, ``adaptive`` and ``auto``
(the default). Each is timed (a first call, then warm calls; the warm median) and its zero
set measured with ``jurs.levelset.analyze`` against dense samples of the clean outline
(Chamfer and Hausdorff distances over the bounding-box diagonal, components).

The table shows where the uniform grid was capped (its cells over those the data ask for,
``Settings.data_cell``), the capped grid's residual that ``basis="auto"`` reads (the 90th
percentile of the points' distances to its zero set, in spacings: ``uniform_residual``),
the basis it took, and the accuracy and time of each basis; ratios are against the uniform
fit of the same run.

    python -m benchmarks.basis_choice [--levels 0,0.002] [--cases a,b] [--markdown-only]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import jurs  # noqa: E402
import jurs.datasets  # noqa: E402
import jurs.levelset  # noqa: E402
import jurs.shapes  # noqa: E402
from jurs._fit.adaptive import (  # noqa: E402
    AUTO_REFINEMENT,
    UNIFORM_RESIDUAL_SPACINGS,
    wants_adaptive,
)

from ._common import (  # noqa: E402
    RESULTS,
    machine,
    md_table,
    rerender_beside,
    time_repeated,
    write_results,
)
from ._quality_cases import CASES, choose_m, clean_outline  # noqa: E402
from .quality import noise_seed  # noqa: E402

BASES = ("uniform", "adaptive", "auto")
#: Noise levels (over the outline's diagonal): the clean clouds, where the grid is capped
#: most, and the lowest noise of the quality suite; at 0.5 % and more the noise sets
#: cells of 4 sigma, under the cap on every case (no choice to make).
LEVELS = (0.0, 0.002)
#: A basis counts as more accurate than the uniform grid where its distance is this much
#: smaller.
BETTER = 0.9


def run_case(case: str, level: float) -> dict:
    shape, kwargs, _ = CASES[case]
    comps, reference, diag, length = clean_outline(shape)
    m = choose_m(length, diag)
    points, normals = jurs.shapes.get(shape, m, **kwargs)
    if level > 0:
        points, normals = jurs.datasets.add_noise(
            points, normals, sigma=level * diag, seed=noise_seed(case, level)
        )
    out: dict = {"case": case, "noise": level, "m": int(m), "true_components": len(comps)}
    for basis in BASES:

        def fit(basis=basis):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                sol = jurs.fit(points, normals, basis=basis, throw=False)
            jax.block_until_ready(sol.spline)
            return sol

        timing = time_repeated(fit, budget_s=1.0, max_repeats=5)
        sol = timing.pop("output")
        st = sol.settings
        report = jurs.levelset.analyze(sol.spline, points, offset=st.offset, reference=reference)
        out[basis] = {
            **timing,
            "chamfer": report.chamfer / diag,
            "hausdorff": report.hausdorff / diag,
            "components": report.num_components,
            "status": sol.status,
            "spline": "adaptive" if isinstance(sol.spline, jurs.AdaptiveSpline) else "uniform",
            "uniform_residual": sol.stats.get("uniform_residual"),
        }
        if basis == "uniform":
            out["grid"] = list(st.grid)
            out["refinement"] = st.cell_width / st.data_cell
            out["capped"] = bool(wants_adaptive(st))
    return out


def ratio(run, basis, key):
    return run[basis][key] / run["uniform"][key]


def findings(runs) -> list[str]:
    capped = [r for r in runs if r["capped"]]
    kept = [r for r in capped if r["auto"]["spline"] == "uniform"]
    taken = [r for r in capped if r["auto"]["spline"] == "adaptive"]

    def better(r):
        return min(ratio(r, "adaptive", "chamfer"), ratio(r, "adaptive", "hausdorff")) < BETTER

    missed = [r for r in kept if better(r)]
    gained = [r for r in taken if better(r)]
    names = ", ".join
    return [
        f"- **Capped grids:** {len(capped)} of {len(runs)} runs (cells at least "
        f"{AUTO_REFINEMENT}x wider than the data ask for); only these choose.",
        f"- **Kept the capped grid:** {len(kept)} (residual <= {UNIFORM_RESIDUAL_SPACINGS} "
        f"spacings). Of these, the adaptive basis was more accurate (Chamfer or Hausdorff "
        f"below {BETTER}x the grid's) on {len(missed)}"
        + (f": {names(map(_label, missed))}" if missed else "")
        + ".",
        f"- **Took the adaptive basis:** {len(taken)}; more accurate than the grid on "
        f"{len(gained)} of them" + (f" ({names(map(_label, gained))})" if gained else "") + ".",
        "- **Warm time of the automatic fit over the uniform grid's** (median): kept "
        f"{_median(kept, 'auto', 'warm_s')}, taken {_median(taken, 'auto', 'warm_s')}; the "
        f"adaptive basis alone on the kept runs {_median(kept, 'adaptive', 'warm_s')}.",
    ]


def _label(run) -> str:
    return f"{run['case']} ({run['noise']})"


def _median(runs, basis, key) -> str:
    if not runs:
        return "—"
    return f"{np.median([ratio(r, basis, key) for r in runs]):.2f}x"


def markdown(payload) -> str:
    runs = payload["runs"]
    header = [
        "case", "noise", "m", "grid", "cells / asked", "residual (spacings)", "auto takes",
        "Chamfer adaptive / uniform", "Hausdorff adaptive / uniform", "components u / a / true",
        "warm uniform", "warm adaptive", "warm auto", "auto / uniform time",
    ]  # fmt: skip
    rows = []
    for r in runs:
        u, a, auto = r["uniform"], r["adaptive"], r["auto"]
        residual = auto["uniform_residual"]
        rows.append([
            r["case"], r["noise"], r["m"], "x".join(map(str, r["grid"])),
            f"{r['refinement']:.2f}", "—" if residual is None else f"{residual:.3f}",
            auto["spline"] if r["capped"] else f"{auto['spline']} (not capped)",
            f"{ratio(r, 'adaptive', 'chamfer'):.2f}", f"{ratio(r, 'adaptive', 'hausdorff'):.2f}",
            f"{u['components']} / {a['components']} / {r['true_components']}",
            f"{u['warm_s'] * 1e3:.0f} ms", f"{a['warm_s'] * 1e3:.0f} ms",
            f"{auto['warm_s'] * 1e3:.0f} ms", f"{ratio(r, 'auto', 'warm_s'):.2f}",
        ])  # fmt: skip
    lines = [
        '# Choice of basis: the capped uniform grid, the adaptive basis and `basis="auto"`',
        "",
        f"Run {payload['date']} on {payload['machine']}. Command: `{payload['command']}` "
        f"({payload['elapsed_s'] / 60:.1f} min). 1-minute load average "
        f"{payload['load'][0]:.1f} at the start, {payload['load'][1]:.1f} at the end (a "
        "shared machine: times carry tens of percent of noise). Float64.",
        "",
        "Each cloud of the quality suite (`benchmarks/_quality_cases.py`, sampled and seeded "
        "as `benchmarks/quality.py` does) fitted by `jurs.fit(points, normals, basis=b)` in "
        "one process, `b` = uniform, adaptive, auto (the default). Distances over the clean "
        "outline's bounding-box diagonal; ratios against the uniform fit of the same run. "
        "*cells / asked*: the uniform grid's cells over the cell the data ask for "
        f"(`Settings.data_cell`); at {AUTO_REFINEMENT} and above the grid is capped and "
        "`auto` fits it first. *residual*: the 90th percentile of the points' distances to "
        "the capped grid's zero set, in spacings (`sol.stats['uniform_residual']`); above "
        f"{UNIFORM_RESIDUAL_SPACINGS} `auto` fits the adaptive basis instead.",
        "",
        *findings(runs),
        "",
        *md_table(header, rows),
        "",
    ]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--levels", default=",".join(map(str, LEVELS)))
    parser.add_argument("--cases", help=f"comma-separated subset of {', '.join(CASES)}")
    parser.add_argument("--markdown-only", action="store_true")
    args = parser.parse_args(argv)
    if args.markdown_only:
        print(rerender_beside(os.path.join(RESULTS, "basis_choice.json"), markdown))
        return
    cases = args.cases.split(",") if args.cases else list(CASES)
    levels = [float(v) for v in args.levels.split(",")]
    start, load = time.perf_counter(), [os.getloadavg()[0]]
    runs = []
    for case in cases:
        for level in levels:
            runs.append(run_case(case, level))
            r = runs[-1]
            chamfer, time_ratio = ratio(r, "adaptive", "chamfer"), ratio(r, "auto", "warm_s")
            print(
                f"{case} {level}: auto takes {r['auto']['spline']}, Chamfer a/u "
                f"{chamfer:.2f}, time auto/u {time_ratio:.2f}",
                flush=True,
            )
    load.append(os.getloadavg()[0])
    payload = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "command": "python -m benchmarks.basis_choice" + (" " + " ".join(argv) if argv else ""),
        "elapsed_s": time.perf_counter() - start,
        "load": load,
        "runs": runs,
    }
    text = markdown(payload)
    write_results("basis_choice", payload, text)
    print(text)


if __name__ == "__main__":
    main(sys.argv[1:])
