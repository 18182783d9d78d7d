"""Speed and memory of jurs against the paper's own algorithm in NumPy and against SciPy's RBF.

One command measures everything, prints the tables and writes the dated results
``benchmarks/results/speed.{json,md}`` (``--quick``: a few-minute smoke run on small sizes,
written to ``speed_quick.{json,md}``):

1. **Sweep** over Example 1 clouds of m points (3m samples) and square grids: per solver
   step of ``IURS(tau=1e-2, lam=1e-3)``, ``IPIA()`` and ``NormalIPIA()`` (whose one-off
   assembly of D^T D is its ``init``, timed on its own), the warm time, the compile time
   (first call minus warm) and the peak memory; and ``LeastSquares(lam=1e-4)`` end to end
   through ``jurs.fit`` (problem building + assembly + solve), first call and warm. At
   1e6 points / 128 x 128 the IURS step is also timed inside ``jurs.fit`` (fits of 1 and
   21 steps), and the step on its own again with huge pages and ``jurs.COMPILER_OPTIONS``.
2. **Baselines, measured in the same run**: ``_numpy_port.py``, the paper's Algorithm 1
   with a dense collocation matrix rebuilt every step (where that matrix fits in
   ``DENSE_LIMIT_BYTES``), against the jurs IURS step; and
   ``scipy.interpolate.RBFInterpolator`` (thin-plate) on the same offset samples against
   ``jurs.fit(points, normals)`` with its automatic settings: fit-time ratios, the refined
   Chamfer distance to the exact curve and zero-set component counts.

Every measurement runs in a fresh subprocess (the workers of ``_speed_workers.py``), so
its peak resident set size (VmHWM) belongs to that measurement alone; the report gives the
peak and the peak minus the RSS after imports, JAX start-up and data creation.

    python -m benchmarks.speed [--quick]
    python -m benchmarks.speed --from-json benchmarks/results/speed.json   # re-render only

Runs on whatever device JAX picks (CPU here; a GPU if JAX sees one), in float64, and
records the device.
"""

from __future__ import annotations

import argparse
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))

# The timer, the result files and the table helpers live in _common, the workers and the
# settings they share with gpu_speed.py in _speed_workers (next to this script; neither
# imports JAX: each worker starts JAX itself).
from ._common import (  # noqa: E402
    LONG_CALL_S,
    bytes_text,
    elapsed_log,
    error_text,
    find_row,
    grid_text,
    machine,
    md_table,
    measured_row,
    ms_text,
    range_text,
    ratio_text,
    rerender_beside,
    s_text,
    us_text,
    where_cells,
    write_results,
)
from ._speed_workers import (  # noqa: E402
    ANALYSIS_RESOLUTION,
    EXAMPLE4_MAX_STEPS,
    EXAMPLE4_TOL,
    GIVEN_RBF_POINTS,
    LARGE_GRID,
    LARGE_POINTS,
    LSQ_LAM,
    REFERENCE_POINTS,
    REFINED_REFERENCE_SAMPLES,
    REFINED_SAMPLES_PER_DIAGONAL,
    STEP_BUDGET_S,
    STEP_SOLVERS,
    device_name,
    passes_floor_s,
    run_example4,
    run_worker,
    step_passes_s,
)

# --------------------------------------------------------------------------- settings

#: Sweep: points m -> grids (N = M). Fine grids on few points are pruned (with 3m samples
#: far below N*M coefficients the fit is mostly undetermined and says nothing new about
#: speed), and so is part of the rest, to keep the whole run short on 2 cores (the report
#: gives its duration).
FULL_SWEEP = {
    100: (8, 16, 32),
    1_000: (8, 16, 32, 64),
    10_000: (16, 32, 64, 128),
    100_000: (16, 32, 64, 128, 256),
    1_000_000: (8, 32, 128, 256),  # 8: the only grid where the dense NumPy port fits at 1e6
}
QUICK_SWEEP = {1_000: (16,), 10_000: (128,)}


#: The dense port runs where one 3m x NM float64 matrix is at most this big (B and D, and
#: the temporaries of a step, are each this size).
DENSE_LIMIT_BYTES = 2 * 10**9

#: RBF comparison: points -> a coarser jurs grid, shown for context beside the defaults
#: (which choose their own grid, at most 96 a side).
RBF_GRIDS = {100: 16, 300: 24, 1_000: 32, 2_000: 48, 5_000: 64}
QUICK_RBF_POINTS = (300,)
#: Skip the next RBF size when its fit is predicted (O(m^3) from the last one) to exceed this.
RBF_MAX_PREDICTED_S = 150.0


#: Side of the float64 matrix product that measures the machine's multiply-add rate.
CEILING_N = 2000

#: An environment in which glibc's malloc asks for transparent huge pages (glibc >= 2.35,
#: Linux THP in "madvise" or "always" mode). XLA's CPU buffers come from malloc; with 4 KB
#: pages every step of a large problem page-faults its fresh buffers in again. The large
#: problem's measurements are repeated in it (the library itself cannot set it: glibc
#: reads it at process start).
HUGEPAGE_ENV = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}

# --------------------------------------------------------------------------- orchestration


def run_sweep(sweep: dict, log) -> list[dict]:
    """Steps of each solver and the LeastSquares fit at every (m, grid) of the sweep."""
    rows = []
    for m, grids in sweep.items():
        for g in grids:
            row = {"m": m, "samples": 3 * m, "grid": g}
            for key in STEP_SOLVERS:
                row[key] = run_worker({"kind": "step", "m": m, "grid": g, "solver": key}, log)
            row["lstsq"] = run_worker({"kind": "lstsq", "m": m, "grid": g, "lam": LSQ_LAM}, log)
            rows.append(row)
    return rows


def run_port(sweep_rows: list[dict], log) -> list[dict]:
    """The dense NumPy port at every sweep configuration where its matrices fit."""
    from . import _numpy_port as port

    rows = []
    for r in sweep_rows:
        size = port.dense_bytes(r["m"], (r["grid"], r["grid"]))
        if size > DENSE_LIMIT_BYTES:
            continue
        res = run_worker({"kind": "port", "m": r["m"], "grid": r["grid"]}, log)
        ours = r["iurs"].get("step_warm_s")
        ratio = res["step_warm_s"] / ours if ours and "step_warm_s" in res else None
        rows.append(
            {
                "m": r["m"],
                "grid": r["grid"],
                "dense_b": size,
                "port": res,
                "jurs_iurs_step_s": ours,
                "ratio": ratio,
            }
        )
    return rows


def run_rbf(points_list, log) -> list[dict]:
    """RBF vs jurs at growing m, stopping before an RBF fit predicted to take too long."""
    rows, last = [], None
    for m in points_list:
        if last is not None and "rbf" in last[1]:
            predicted = last[1]["rbf"]["fit_s"] * (m / last[0]) ** 3
            if predicted > RBF_MAX_PREDICTED_S:
                log(f"skip RBF at m={m}: predicted {predicted:.0f} s")
                rows.append(
                    {
                        "m": m,
                        "grid": RBF_GRIDS[m],
                        "skipped": f"RBF fit predicted to take {predicted:.0f} s",
                    }
                )
                continue
        res = run_worker(
            {"kind": "rbf", "m": m, "grid": RBF_GRIDS[m], "given": m == GIVEN_RBF_POINTS}, log
        )
        rows.append({"m": m, "grid": RBF_GRIDS[m], **res})
        last = (m, res)
    return rows


def run_tuned(log) -> dict:
    """The IURS step and the exact solve at the target size again, in ``HUGEPAGE_ENV``; and
    the step compiled with ``jurs.COMPILER_OPTIONS`` (as ``jurs.fit`` compiles large
    problems), without and with it."""
    step = {"kind": "step", "m": LARGE_POINTS, "grid": LARGE_GRID, "solver": "iurs"}
    lstsq = {"kind": "lstsq", "m": LARGE_POINTS, "grid": LARGE_GRID, "lam": LSQ_LAM}
    return {
        "env": HUGEPAGE_ENV,
        "iurs": run_worker(step, log, HUGEPAGE_ENV),
        "lstsq": run_worker(lstsq, log, HUGEPAGE_ENV),
        "iurs_options": run_worker({**step, "compiler_options": True}, log),
        "iurs_both": run_worker({**step, "compiler_options": True}, log, HUGEPAGE_ENV),
    }


def run_fit_steps(log) -> dict:
    """The IURS step inside ``jurs.fit`` at the target size, as it is and in ``HUGEPAGE_ENV``."""
    spec = {"kind": "fit_steps", "m": LARGE_POINTS, "grid": LARGE_GRID}
    return {
        "env": HUGEPAGE_ENV,
        "default": run_worker(spec, log),
        "hugepages": run_worker(spec, log, HUGEPAGE_ENV),
    }


# --------------------------------------------------------------------------- report


def _env_text(env: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in env.items())


def _given_label(options: dict, code: bool = False) -> str:
    q = "`" if code else ""
    return ", ".join(f"{q}{k}={v:g}{q}" for k, v in options.items())


def report(data: dict) -> str:
    """The markdown report (also printed)."""
    lines = [
        f"# Speed{' (QUICK run: small sizes only)' if data['quick'] else ''}",
        "",
        f"Date: {data.get('date', 'not recorded')}. Machine: {data['machine']}. "
        f"Device of the measurements: {data['device']}. "
        f"float64. Whole run: {data['runtime_s'] / 60:.1f} min."
        + _probe_text(data.get("ceiling"), data.get("ceiling_start")),
        "",
        "Load average when the run began (other work on the machine, before this "
        "run added its own): "
        + (f"{data['load_average']:.1f}" if "load_average" in data else "not recorded")
        + ". Timings taken beside other work are indicative.",
        "",
    ]
    lines += [f"Note: {n}" for n in data.get("notes", [])] + [""] * bool(data.get("notes"))
    loop_note = (
        "* **In a loop**: the same step run `k` times in one jitted `fori_loop` that "
        "carries the state, as the driver's loop in `jurs.fit` does (median and fastest "
        "loop, divided by `k`; `k` gives a loop of about 50 ms, 5 to 200 steps). A step "
        "called on its own returns its whole state in fresh buffers; a loop updates its "
        "carry in place. NormalIPIA's state holds the assembled stencil (6.4 MB at "
        "128 x 128), which a step called on its own copies every call."
    )
    lines += [
        "## What is measured",
        "",
        "* Data: the paper's Example 1 curve, `jurs.datasets.example1(m)`; 3m samples "
        "(points and both offsets, d = 0.1, eps = 0.01), box = bounding box + 10 %.",
        "* **Warm step**: median time of a jitted `solver.step(problem, state)` on a state "
        "one step in (weights already moved), as in `benchmarks/step_speed.py`; "
        "**compile** = first call minus warm (the jit cache is cleared first). Repeats: "
        f"until about {STEP_BUDGET_S:g} s are spent, at least 3 (2 after a first call "
        f"above that, 1 after one above {LONG_CALL_S:g} s), at most 20; the minimum is "
        "shown in brackets "
        "(closest to an unshared machine).",
        loop_note,
        "* **NormalIPIA assembly**: its `init` (D^T D as a 49-point stencil and D^T b), "
        "warm, and its first call (with compilation), apart from its step.",
        f"* **LeastSquares**: `jurs.fit(points, normals, grid, solver=LeastSquares("
        f"lam={LSQ_LAM:g}))` from NumPy arrays to the solved spline: problem building "
        "(host-side sample layout), assembly and linear solve; first call (compiles) "
        "and warm (median).",
        "* **Peak memory**: every measurement runs in a fresh subprocess; *peak* is its "
        "peak resident set size (VmHWM), *over base* is the peak minus the RSS after "
        "imports, JAX start-up and data creation, i.e. the memory the problem build, "
        "the init, XLA compilation and the timed calls took at their worst (at small "
        "sizes compilation dominates it). Host memory only"
        + (
            "; the device's own peak is in the JSON."
            if data["device"].split(":")[0] != "cpu"
            else "."
        ),
        "* Grid sweep: "
        + "; ".join(
            f"m = {int(m):.0e}: {', '.join(map(str, g))}" for m, g in data["sweep_config"].items()
        )
        + " (pruned: fine grids on few points, and part of the rest to keep the run "
        "short; the 1e6 x 8 x 8 point is there for the NumPy baseline).",
        "",
    ]
    lines += _sweep_tables(data["sweep"])
    lines += _port_table(data["port"])
    lines += _rbf_table(data["rbf"])
    lines += _example4_table(data["example4"])
    lines += _tuned_table(data.get("tuned"), data["sweep"], data.get("fit_steps"))
    return "\n".join(lines) + "\n"


def _probe_text(ceiling, ceiling_start) -> str:
    """The machine's speed in this run, by which runs compare (it moves between runs): the
    probe at its start and at its end (the end alone where the first probe failed)."""
    if not ceiling or "macs_per_s" not in ceiling:
        return ""

    def rate(probe):
        return f"{probe['macs_per_s'] / 1e9:.3g} G multiply-adds/s"

    text = f" Machine speed in this run: a float64 matrix product of side {ceiling['n']} reached "
    if ceiling_start and "macs_per_s" in ceiling_start:
        return text + (
            f"{rate(ceiling_start)} at the start of the run and {rate(ceiling)} at "
            "its end (compare runs by it)."
        )
    return text + f"{rate(ceiling)} (measured at the end of the run; compare runs by it)."


def _sweep_tables(sweep) -> list[str]:
    lines = []
    for key, (label, _, _) in STEP_SOLVERS.items():
        extra = ["assembly (init) warm", "assembly first call"] if key == "normal_ipia" else []
        rows = []
        for r in sweep:
            res = r[key]
            rows.append(
                measured_row(
                    where_cells(r),
                    res,
                    7 + len(extra),
                    lambda: (
                        [
                            f"{ms_text(res['step_warm_s'])} ({ms_text(res['step_min_s'])})",
                            f"{ms_text(res['loop_step_warm_s'])} "
                            f"({ms_text(res['loop_step_min_s'])})",
                            res["loop_steps"],
                            s_text(res["step_compile_s"]),
                            bytes_text(res["peak_over_base_b"]),
                            bytes_text(res["peak_b"]),
                            s_text(res["build_s"]),
                        ]
                        + (
                            [ms_text(res["init_warm_s"]), s_text(res["init_first_s"])]
                            if extra
                            else []
                        )
                    ),
                )
            )
        lines += [f"## {label}: one step", ""]
        lines += md_table(
            [
                "m",
                "grid",
                "warm step (min)",
                "in a loop: step (min)",
                "loop steps",
                "compile",
                "peak over base",
                "peak RSS",
                "problem build",
            ]
            + extra,
            rows,
        )
        lines.append("")
    rows = []
    for r in sweep:
        res = r["lstsq"]
        rows.append(
            measured_row(
                where_cells(r),
                res,
                6,
                lambda: [
                    f"{s_text(res['fit_warm_s'])} ({s_text(res['fit_min_s'])})",
                    s_text(res["fit_first_s"]),
                    bytes_text(res["peak_over_base_b"]),
                    bytes_text(res["peak_b"]),
                    res.get("result", "—"),
                    f"{res['E_ave']:.2e}",
                ],
            )
        )
    lines += [f"## LeastSquares(lam={LSQ_LAM:g}) end to end through jurs.fit", ""]
    lines += md_table(
        ["m", "grid", "warm (min)", "first call", "peak over base", "peak RSS", "result", "E_ave"],
        rows,
    )
    return lines + [""]


def _port_table(port_rows) -> list[str]:
    lines = [
        "## Baseline: the paper's Algorithm 1 in NumPy (dense D rebuilt every step)",
        "",
        "`benchmarks/_numpy_port.py`: dense B (3m x NM) from "
        "`scipy.interpolate.BSpline.design_matrix` once; per step W = B w, "
        "D = B * w / W, mu = 2 / max column sum of D, eq. 33 and the weight gradient "
        "(its iterates equal jurs.IURS's: `benchmarks/tests/test_numpy_port.py`). Same tau = 1e-2, "
        f"lam = 1e-3. Run where one dense matrix is <= {DENSE_LIMIT_BYTES / 1e9:g} GB.",
        "",
    ]
    rows = []
    for r in port_rows:
        p = r["port"]
        rows.append(
            measured_row(
                where_cells(r) + [bytes_text(r["dense_b"])],
                p,
                5,
                lambda: [
                    s_text(p["build_s"]),
                    ms_text(p["step_warm_s"]),
                    ms_text(r["jurs_iurs_step_s"]),
                    ratio_text(r["ratio"]),
                    bytes_text(p["peak_over_base_b"]),
                ],
            )
        )
    lines += md_table(
        [
            "m",
            "grid",
            "one dense matrix",
            "build B",
            "NumPy step",
            "jurs IURS step",
            "NumPy / jurs",
            "NumPy peak over base",
        ],
        rows,
    )
    return lines + [""]


def _unconverged(rbf_rows) -> int:
    """Points of the refined distances whose projection onto a zero set did not converge,
    over every fit and RBF of the comparison."""
    fits = [
        r[k]
        for r in rbf_rows
        if not error_text(r) and "skipped" not in r
        for k in ("jurs_main", "jurs_coarse", "rbf")
    ]
    fits += [g for r in rbf_rows for g in r.get("jurs_given") or []]
    return sum(f.get("unconverged", 0) for f in fits)


def _rbf_table(rbf_rows) -> list[str]:
    lines = [
        "## Baseline: scipy RBFInterpolator (thin-plate) vs jurs defaults",
        "",
        "Example 1 with m points. jurs: `jurs.fit(points, normals)`, every setting "
        "automatic (grid, d, eps, lambda; `LeastSquares`), timed with the automatic "
        "settings included. RBF: `benchmarks/_baselines.rbf_fit` on the same 3m offset "
        "samples and targets (the d and eps the defaults chose; fit time = the dense "
        "solve; evaluation not timed). Both zero sets are sampled on the default fit's "
        f"box at resolution {ANALYSIS_RESOLUTION} and measured with "
        "`jurs.levelset.analyze_grid` (as `rbf_report` does): components, all / "
        "supplementary (more than half the length farther than 2 d from the data), and "
        "the *analysis* Chamfer, which resamples the contour at half a grid cell: a floor "
        "of about 1.5e-3 under any fit. **Refined** Chamfer and Hausdorff (the target's "
        "measure): `jurs.levelset.refined_chamfer_hausdorff`, no sampling floor. The "
        f"contour, resampled at {REFINED_SAMPLES_PER_DIAGONAL} points per box diagonal, is "
        "moved onto the zero set by Newton steps (jurs: the spline's gradient; RBF: "
        "central differences) and measured to the segments of "
        f"{REFERENCE_POINTS} samples of the exact curve, and "
        f"{REFINED_REFERENCE_SAMPLES} of those are projected onto the zero set. Contour "
        "points measured without the projection, however densely resampled, carry "
        "marching squares' own error, about 1e-5 here, under which accurate fits tie. "
        "Last column, for context: jurs with the same settings on the coarser grid G. "
        f"Projections that did not converge (then measured where they ended): "
        f"{_unconverged(rbf_rows)} in this table.",
        "",
    ]
    rows = []
    for r in rbf_rows:
        if error_text(r) or "skipped" in r:
            rows.append([r["m"], error_text(r) or f"skipped: {r['skipped']}"] + [""] * 10)
            continue
        j, b, c = r["jurs_main"], r["rbf"], r["jurs_coarse"]
        rows.append(
            [
                r["m"],
                grid_text(j["grid"]),
                f"{j['offset']:.3g}",
                s_text(b["fit_s"]),
                ms_text(j["warm_s"]),
                s_text(j["first_s"]),
                f"{ratio_text(b['fit_s'] / j['warm_s'])} / {ratio_text(b['fit_s'] / j['first_s'])}",
                f"{j['refined_chamfer']:.2e} / {b['refined_chamfer']:.2e}",
                f"{j['refined_hausdorff']:.2e} / {b['refined_hausdorff']:.2e}",
                f"{j['chamfer']:.2e} / {b['chamfer']:.2e}",
                f"{j['num_components']}/{j['num_supplementary']} vs "
                f"{b['num_components']}/{b['num_supplementary']}",
                f"{grid_text(c['grid'])}: {c['refined_chamfer']:.2e}, "
                f"{c['num_components']}/{c['num_supplementary']}, {ms_text(c['warm_s'])} "
                f"({ratio_text(b['fit_s'] / c['warm_s'])})",
            ]
        )
    lines += md_table(
        [
            "m",
            "jurs grid",
            "d",
            "RBF fit",
            "jurs warm",
            "jurs first call",
            "RBF / jurs (warm / first)",
            "refined Chamfer jurs / RBF",
            "refined Hausdorff jurs / RBF",
            "analysis Chamfer jurs / RBF",
            "components jurs vs RBF",
            "coarser grid G: refined Chamfer, components, warm (RBF / it)",
        ],
        rows,
    )
    for r in rbf_rows:
        if not r.get("jurs_given") or error_text(r):
            continue
        b = r["rbf"]
        lines += [
            "",
            f"At m = {r['m']}, jurs with settings given (the rest automatic, timed "
            "too): finer grids and smoothings far below the default. Such smoothings "
            "grow supplementary components on glyphs and traced outlines "
            "(`benchmarks/results/smoothing.md`), so the defaults do not use them. "
            f"The RBF: refined Chamfer {b['refined_chamfer']:.2e}, Hausdorff "
            f"{b['refined_hausdorff']:.2e}, fit {s_text(b['fit_s'])}.",
            "",
        ]
        rows = [
            [
                _given_label(e["given"], code=True),
                grid_text(e["grid"]),
                f"{e['lam']:.3g}",
                ms_text(e["warm_s"]),
                ratio_text(b["fit_s"] / e["warm_s"]),
                f"{e['refined_chamfer']:.2e} "
                f"({ratio_text(e['refined_chamfer'] / b['refined_chamfer'])})",
                f"{e['refined_hausdorff']:.2e}",
                f"{e['num_components']}/{e['num_supplementary']}",
            ]
            for e in r["jurs_given"]
        ]
        lines += md_table(
            [
                "given",
                "grid",
                "lambda",
                "jurs warm",
                "RBF / jurs",
                "refined Chamfer (x the RBF's)",
                "refined Hausdorff",
                "components",
            ],
            rows,
        )
    return lines + [""]


def _example4_table(rows_in) -> list[str]:
    lines = [
        "## Full regularised IURS fits of Example-4 size",
        "",
        f"`jurs.fit(points, normals, grid=15, solver=IURS(tau, lam, tol={EXAMPLE4_TOL:g}, "
        f"max_steps={EXAMPLE4_MAX_STEPS}))` on `jurs.shapes.get(shape, points)`. Cold: "
        "the first call in a fresh process, compilation included (imports timed apart); "
        "warm: median of later calls. Each fit runs in several fresh processes: cold and "
        "warm are the medians over them, with the range of the cold times and the fastest "
        "warm call. *Cold, cache filled*: the same first call where JAX's persistent "
        "compilation cache (`JAX_COMPILATION_CACHE_DIR`, with "
        "`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0`) holds the fit, compiled by one "
        "process before these: the process loads it instead of compiling it (median and "
        "range over as many processes).",
        "",
    ]
    rows = []
    for r in rows_in:
        cells = [r["label"], grid_text(r["grid"]), f"{r['tau']:g}", f"{r['lam']:g}"]
        runs = r.get("cold_runs_s") or []
        cached_runs = r.get("cold_cached_runs_s") or []
        cached = f"{s_text(r['cold_cached_s'])} ({range_text(cached_runs)})" if cached_runs else "—"
        rows.append(
            measured_row(
                cells,
                r,
                8,
                lambda: [
                    r["num_steps"],
                    r["result"],
                    f"{ms_text(r['warm_s'])} ({ms_text(r['min_s'])})",
                    s_text(r["cold_s"]),
                    range_text(runs) if runs else "—",
                    cached,
                    s_text(r["import_s"]),
                    f"{r['E_ave']:.2e}",
                ],
            )
        )
    lines += md_table(
        [
            "fit",
            "grid",
            "tau",
            "lam",
            "steps",
            "result",
            "warm (fastest)",
            "cold",
            "cold range",
            "cold, cache filled (range)",
            "imports",
            "E_ave",
        ],
        rows,
    )
    timed = [r for r in rows_in if r.get("passes") and "num_steps" in r]
    if not timed:
        return lines + [""]
    lines += [
        "",
        "Where the warm time goes: the passes over the samples that every IURS step "
        "makes, each timed alone in a jitted loop of "
        f"{timed[0]['passes']['repeats']} passes (fastest run), as jurs's kernels run "
        "them. F2: W and F(wC) at the new weights (eq. 14); F1: F(wC) at the new C "
        "(eq. 35); T2: D^T r with D's column sums (eqs. 33, 25), and the two sums of "
        "the weight gradient (eq. 19). Times the fit's steps they are a floor for "
        "these kernels, with no bookkeeping, dispatch or metrics.",
        "",
    ]
    rows = [
        [
            r["label"],
            us_text(r["passes"]["F2_s"]),
            us_text(r["passes"]["F1_s"]),
            us_text(r["passes"]["T2_s"]),
            us_text(step_passes_s(r)),
            us_text(r["warm_s"] / r["num_steps"]),
            ms_text(passes_floor_s(r)),
            ms_text(r["warm_s"]),
        ]
        for r in timed
    ]
    lines += md_table(
        [
            "fit",
            "F2",
            "F1",
            "T2",
            "a step's passes (F2 + F1 + 2 T2)",
            "warm fit / steps",
            "passes x steps",
            "warm fit",
        ],
        rows,
    )
    return lines + [""]


def _tuned_table(tuned, sweep, fit_steps=None) -> list[str]:
    big = find_row(sweep, m=LARGE_POINTS, grid=LARGE_GRID)
    if not tuned or not big:
        return []
    env = _env_text(tuned["env"])
    lines = [
        "## Large problems: huge pages and compiler options",
        "",
        f"The same workers at {LARGE_POINTS:.0e} points, {grid_text(LARGE_GRID)}. "
        f"*Huge pages*: `{env}` in the environment, so glibc's malloc, from which "
        "XLA's CPU buffers come, asks for transparent huge pages (glibc >= 2.35; Linux "
        "THP in `madvise` or `always` mode); with 4 KB pages every call page-faults its "
        "fresh buffers in again. glibc reads it at start-up: a setting of the process, "
        "not of the library. *Options*: the step jitted with `jurs.COMPILER_OPTIONS` "
        "(as `jurs.fit` compiles large problems: floating-point reassociation, so LLVM "
        "vectorises the per-bucket sums; "
        "NaN, Inf, division and functions keep IEEE semantics). *Page faults*: minor "
        "faults of one warm step.",
        "",
    ]
    variants = [
        ("IURS step", big["iurs"]),
        ("IURS step, huge pages", tuned["iurs"]),
        ("IURS step, options", tuned.get("iurs_options", {})),
        ("IURS step, huge pages and options", tuned.get("iurs_both", {})),
    ]
    rows = [
        measured_row(
            [name],
            r,
            3,
            lambda r=r: [
                f"{ms_text(r['step_warm_s'])} ({ms_text(r['step_min_s'])})",
                r.get("step_page_faults", "—"),
                bytes_text(r["peak_over_base_b"]),
            ],
        )
        for name, r in variants
        if r
    ]
    for name, r in (
        (f"LeastSquares(lam={LSQ_LAM:g}) fit", big["lstsq"]),
        (f"LeastSquares(lam={LSQ_LAM:g}) fit, huge pages", tuned["lstsq"]),
    ):
        rows.append(
            measured_row(
                [name],
                r,
                3,
                lambda r=r: [
                    f"{s_text(r['fit_warm_s'])} ({s_text(r['fit_min_s'])})",
                    "—",
                    bytes_text(r["peak_over_base_b"]),
                ],
            )
        )
    lines += md_table(["measurement", "warm (min)", "page faults", "peak over base"], rows)
    lines += _fit_steps_table(fit_steps)
    return lines + [""]


def _fit_steps_table(fit_steps) -> list[str]:
    if not fit_steps:
        return []
    env = _env_text(fit_steps["env"])
    lines = [
        "",
        "**The step inside a fit.** `jurs.fit(points, normals, grid, solver=IURS("
        "tau=1e-2, lam=1e-3, tol=0, max_steps=n), offset, eps)` end to end for n = 1 and "
        "n = 1 + k; a step costs the difference of the warm medians over k. The fit's "
        "steps run in one compiled loop, whose buffers are allocated and page-faulted "
        "once per call, not per step; at this size `jurs.fit` compiles its own solvers "
        "with `jurs.COMPILER_OPTIONS` (column *options*). *Page faults*: minor faults "
        "of one warm fit call.",
        "",
    ]
    rows = []
    for name, r in (("as it is", fit_steps["default"]), (f"with {env}", fit_steps["hugepages"])):
        rows.append(
            measured_row(
                [name],
                r,
                7,
                lambda r=r: [
                    "yes" if r["compiler_options"] else "no",
                    r["steps"],
                    f"{ms_text(r['step_s'])} ({ms_text(r['step_min_s'])})",
                    ms_text(r["fits"]["1"]["warm_s"]),
                    ms_text(r["fits"][str(1 + r["steps"])]["warm_s"]),
                    f"{r['fits']['1']['page_faults']} / "
                    f"{r['fits'][str(1 + r['steps'])]['page_faults']}",
                    bytes_text(r["peak_over_base_b"]),
                ],
            )
        )
    lines += md_table(
        [
            "environment",
            "options",
            "k",
            "step (from fastest fits)",
            "fit, 1 step",
            "fit, 1 + k steps",
            "page faults (1 / 1 + k steps)",
            "peak over base",
        ],
        rows,
    )
    return lines


# --------------------------------------------------------------------------- main


def rerender(path: str) -> None:
    """The markdown again from saved measurements (no measuring), rewritten beside ``path``
    (``_common.rerender_beside``). Verdicts an older run saved (``targets``,
    ``bounds``) are dropped: the report shows measurements and their ratios only."""

    def render(data):
        data.pop("targets", None)
        data.pop("bounds", None)
        return report(data)

    print(rerender_beside(path, render))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="small sizes only (a few minutes); writes speed_quick.*",
    )
    parser.add_argument(
        "--from-json",
        metavar="PATH",
        help="re-render the report from a results JSON (no measuring)",
    )
    args = parser.parse_args(argv)
    if args.from_json:
        return rerender(args.from_json)

    import jax

    jax.config.update("jax_enable_x64", True)

    start = time.perf_counter()
    load_average = os.getloadavg()[0]
    log = elapsed_log()

    # The machine's speed moves between runs, and sometimes within one: probed at both ends.
    ceiling_start = run_worker({"kind": "ceiling", "n": CEILING_N}, log)
    sweep_config = QUICK_SWEEP if args.quick else FULL_SWEEP
    sweep = run_sweep(sweep_config, log)
    port = run_port(sweep, log)
    tuned = None if args.quick else run_tuned(log)
    fit_steps = None if args.quick else run_fit_steps(log)
    example4 = run_example4(log)
    rbf = run_rbf(QUICK_RBF_POINTS if args.quick else tuple(RBF_GRIDS), log)
    ceiling = run_worker({"kind": "ceiling", "n": CEILING_N}, log)
    data = {
        "date": time.strftime("%Y-%m-%d"),
        "quick": args.quick,
        "machine": machine(),
        "device": device_name(jax),
        "sweep_config": {str(m): list(g) for m, g in sweep_config.items()},  # JSON keys
        "sweep": sweep,
        "port": port,
        "rbf": rbf,
        "example4": example4,
        "tuned": tuned,
        "fit_steps": fit_steps,
        "ceiling": ceiling,
        "ceiling_start": ceiling_start,
        "load_average": load_average,
        "runtime_s": time.perf_counter() - start,
    }
    text = report(data)
    print(text)
    write_results("speed_quick" if args.quick else "speed", data, text)


if __name__ == "__main__":
    main()
