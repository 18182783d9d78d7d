"""Every jurs solver on Example 1 (9 x 9, 15 x 15) and Example 10: energy, time, compile.

    .venv/bin/python -m benchmarks.solvers [--quick]

Writes ``benchmarks/results/solvers.{md,json}``. Each row is one ``jurs.fit`` call (input
checks, jit dispatch, problem assembly and the solve): ``compile`` is the first call minus
the warm median. The exact solve ([`jurs.LeastSquares`][]) is the reference line of every
block; ``E / E_exact`` and ``E_ave / E_ave(exact)`` are measured against it in the same run.

Two objectives per case:
* ``lam = 1e-4`` (objective lambda): the fixed-weight minimiser is unique and well
  conditioned, so every B-spline solver should reach the exact energy;
* ``lam = 0`` for the rational (joint) solvers: the paper's setting for E_ave (Table 1).
A second table compares LeastSquares' linear solvers (dense Cholesky vs CG on the stencil)
across grid sizes: it sets ``DENSE_MAX_COEFFICIENTS``. A third compiles every solver with
and without ``jurs.COMPILER_OPTIONS`` on the bucketed layout of large problems, where
``jurs.fit`` uses them for solvers that declare ``reassociation_safe``: how far each result
moves.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import equinox as eqx
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import lineax as lx  # noqa: E402
import optax  # noqa: E402
import optimistix as optx  # noqa: E402

import jurs  # noqa: E402

from ._common import machine, write_results  # noqa: E402

warnings.filterwarnings("ignore", category=UserWarning, module="jaxopt")
LAM = 1e-4


def fixed_weight_solvers(lam):
    tol = dict(rtol=1e-10, atol=1e-12)
    solvers = {
        "LeastSquares (exact)": jurs.LeastSquares(lam=lam),
        "optx.LevenbergMarquardt": jurs.OptimistixLeastSquares(
            optx.LevenbergMarquardt(**tol), lam=lam
        ),
        "optx.GaussNewton": jurs.OptimistixLeastSquares(optx.GaussNewton(**tol), lam=lam),
        "optx.Dogleg": jurs.OptimistixLeastSquares(optx.Dogleg(**tol), lam=lam),
        "optx.BFGS": jurs.OptimistixMinimiser(
            optx.BFGS(rtol=1e-9, atol=1e-12), lam=lam, max_steps=2000
        ),
        "optx.NonlinearCG": jurs.OptimistixMinimiser(
            optx.NonlinearCG(rtol=1e-9, atol=1e-12), lam=lam, max_steps=2000
        ),
        "optx.OptaxMinimiser(adam 1e-2)": jurs.OptimistixMinimiser(
            optx.OptaxMinimiser(optax.adam(1e-2), rtol=1e-9, atol=1e-12), lam=lam, max_steps=5000
        ),
    }
    try:
        import jaxopt  # noqa: F401

        solvers.update(
            {
                "jaxopt.LBFGS": jurs.JaxoptLBFGS(lam=lam, max_steps=3000, tol=1e-9),
                "jaxopt.GaussNewton": jurs.JaxoptGaussNewton(lam=lam, max_steps=20, tol=1e-10),
                "jaxopt.LevenbergMarquardt": jurs.JaxoptLevenbergMarquardt(
                    lam=lam, max_steps=50, tol=1e-10
                ),
            }
        )
    except ImportError:
        pass
    return solvers


def joint_solvers(lam):
    solvers = {
        "LeastSquares (exact B-spline)": jurs.LeastSquares(lam=lam),
        "JointLevenbergMarquardt 30 steps": jurs.JointLevenbergMarquardt(lam=lam, max_steps=30),
        "JointLevenbergMarquardt 100 steps": jurs.JointLevenbergMarquardt(lam=lam, max_steps=100),
        "optx.LevenbergMarquardt joint (QR) 100": jurs.OptimistixLeastSquares(
            optx.LevenbergMarquardt(rtol=1e-8, atol=1e-12), lam=lam, joint=True, max_steps=100
        ),
        "optx.LevenbergMarquardt joint (Normal CG) 100": jurs.OptimistixLeastSquares(
            optx.LevenbergMarquardt(
                rtol=1e-8,
                atol=1e-12,
                linear_solver=lx.Normal(lx.CG(rtol=1e-8, atol=1e-12, max_steps=500)),
            ),
            lam=lam,
            joint=True,
            max_steps=100,
        ),
        "optx.BFGS joint 1000": jurs.OptimistixMinimiser(
            optx.BFGS(rtol=1e-8, atol=1e-12), lam=lam, joint=True, max_steps=1000
        ),
        "IURS (paper, tau 1e-2, 200 steps)": jurs.IURS(tau=1e-2, lam=0.0, max_steps=200),
        "IPIA (paper, 200 steps)": jurs.IPIA(max_steps=200),
    }
    try:
        import jaxopt  # noqa: F401

        solvers["jaxopt.LevenbergMarquardt joint 100"] = jurs.JaxoptLevenbergMarquardt(
            lam=lam,
            joint=True,
            max_steps=100,
            tol=1e-12,
            options=(("solver", "cholesky"), ("materialize_jac", True)),
        )
    except ImportError:
        pass
    return solvers


def timed_fit(points, normals, grid, solver):
    def call():
        sol = jurs.fit(points, normals, grid=grid, solver=solver, throw=False)
        jax.block_until_ready(sol.spline.control)
        return sol

    t0 = time.perf_counter()
    sol = call()
    first = time.perf_counter() - t0
    times = []
    while len(times) < 3 or (sum(times) < 1.0 and len(times) < 20):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    warm = float(np.median(times))
    return sol, warm, max(first - warm, 0.0)


def short_result(sol) -> str:
    names = [
        (jurs.RESULTS.successful, "converged"),
        (jurs.RESULTS.max_steps_reached, "max_steps"),
        (jurs.RESULTS.failed, "failed"),
        (jurs.RESULTS.nonfinite, "non-finite"),
    ]
    return next(name for item, name in names if sol.result == item)


def inner_steps(sol):
    return int(getattr(sol.state, "num_steps", sol.stats["num_steps"]))


def run_block(title, points, normals, grid, solvers):
    rows = []
    reference = None
    for name, solver in solvers.items():
        sol, warm, compile_s = timed_fit(points, normals, grid, solver)
        m = {k: float(v) for k, v in sol.metrics.items()}
        if reference is None:
            reference = m
        rows.append(
            {
                "case": title,
                "solver": name,
                "E": m["E"],
                "E_d": m["E_d"],
                "E_ave": m["E_ave"],
                "E_max": m["E_max"],
                "lam": m["lam"],
                "E_over_exact": m["E"] / reference["E"],
                "E_ave_over_exact": m["E_ave"] / reference["E_ave"],
                "steps": inner_steps(sol),
                "result": short_result(sol),
                "warm_s": warm,
                "compile_s": compile_s,
            }
        )
        r = rows[-1]
        print(
            f"{title:28s} {name:46s} E={r['E']:.4e} E/E*={r['E_over_exact']:.6f} "
            f"E_ave={r['E_ave']:.3e} ({r['E_ave_over_exact']:.3f}) steps={r['steps']:5d} "
            f"warm={warm * 1e3:9.2f} ms compile={compile_s:6.2f} s",
            flush=True,
        )
    return rows


def linear_solver_table(grids):
    """LeastSquares with dense Cholesky vs Jacobi-CG, Example 10 (500 points), lam = 1e-4."""
    points, normals = jurs.datasets.example10(0)
    rows = []
    for grid in grids:
        for name, ls in (
            ("Cholesky (dense)", lx.Cholesky()),
            ("CG (stencil, Jacobi)", lx.CG(rtol=1e-10, atol=1e-12, max_steps=20 * grid * grid)),
        ):
            if name.startswith("Cholesky") and grid > 64:
                continue
            sol, warm, compile_s = timed_fit(
                points, normals, grid, jurs.LeastSquares(lam=LAM, linear_solver=ls)
            )
            rows.append(
                {
                    "grid": grid,
                    "linear_solver": name,
                    "E": float(sol.metrics["E"]),
                    "warm_s": warm,
                    "compile_s": compile_s,
                }
            )
            print(
                f"grid {grid:3d} {name:22s} E={rows[-1]['E']:.10e} warm={warm * 1e3:8.2f} ms "
                f"compile={compile_s:5.2f} s",
                flush=True,
            )
    return rows


def compiler_options_table():
    """Every fixed-weight solver, and the paper's iterations, compiled with and without
    ``jurs.COMPILER_OPTIONS`` on Example 1 (1000 points, 15 x 15) in the bucketed power
    form (``bucket_size=8``: the layout of large problems, on which ``jurs.fit`` uses the
    options): energies against the exact solve without options, and how far the
    coefficients move."""
    points, normals = jurs.datasets.example1(1000)
    problem = jurs.make_problem(points, normals, grid=15, offset=0.1, eps=0.01, bucket_size=8)
    solvers = {
        **fixed_weight_solvers(LAM),
        "IURS (tau 1e-2, lam 1e-3, 200 steps)": jurs.IURS(tau=1e-2, lam=1e-3),
        "IPIA (200 steps)": jurs.IPIA(),
        "NormalIPIA (200 steps)": jurs.NormalIPIA(),
    }

    def run(problem, solver):
        return jurs.solve(solver, problem, throw=False)

    exact = None
    rows = []
    for name, solver in solvers.items():
        plain, tuned = (
            eqx.filter_jit(run, compiler_options=options)(problem, solver)
            for options in (None, jurs.COMPILER_OPTIONS)
        )
        e_plain, e_tuned = float(plain.metrics["E"]), float(tuned.metrics["E"])
        exact = e_plain if exact is None else exact  # the first row: LeastSquares
        c_plain, c_tuned = np.asarray(plain.spline.control), np.asarray(tuned.spline.control)
        rows.append(
            {
                "solver": name,
                "reassociation_safe": type(solver).reassociation_safe,
                "E_plain": e_plain,
                "E_options": e_tuned,
                "E_plain_over_exact": e_plain / exact,
                "E_options_over_exact": e_tuned / exact,
                "rel_E_change": abs(e_tuned - e_plain) / abs(e_plain),
                "rel_C_change": float(np.max(np.abs(c_tuned - c_plain)) / np.max(np.abs(c_plain))),
                "steps_plain": inner_steps(plain),
                "steps_options": inner_steps(tuned),
            }
        )
        r = rows[-1]
        print(
            f"options {name:46s} safe={r['reassociation_safe']!s:5s} "
            f"E/E*-1 {r['E_plain_over_exact'] - 1:.2e} -> {r['E_options_over_exact'] - 1:.2e} "
            f"dC {r['rel_C_change']:.1e} steps {r['steps_plain']} -> {r['steps_options']}",
            flush=True,
        )
    return rows


def markdown(rows, linear_rows, option_rows=()):
    lines = [
        "# Solvers on Example 1 and Example 10",
        "",
        f"Machine: {machine()}. Generated by `benchmarks/solvers.py`; each time is one "
        "`jurs.fit` call (warm median; compile = first call minus warm). `E/E*` and "
        "`E_ave/exact` are relative to the exact LeastSquares solve (first row of each block), "
        "measured in the same run. `steps` counts the inner solver's steps. Single warm "
        "times on this 2-core machine vary from run to run (up to 2x between runs of this "
        "script): compare rows within a block.",
        "",
        "| case | solver | E | E/E* | E_ave | E_ave/exact | steps | result | warm | compile |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['solver']} | {r['E']:.4e} | {r['E_over_exact']:.6f} | "
            f"{r['E_ave']:.3e} | {r['E_ave_over_exact']:.3f} | {r['steps']} | {r['result']} | "
            f"{r['warm_s'] * 1e3:.1f} ms | {r['compile_s']:.1f} s |"
        )
    lines += ["", "## Which solver (derived from the rows above)", ""]
    for case in dict.fromkeys(r["case"] for r in rows):
        block = [r for r in rows if r["case"] == case]
        exact = [
            r for r in block if r["E_over_exact"] <= 1 + 1e-6 and r["E_ave_over_exact"] >= 0.999
        ]
        fastest = min(exact, key=lambda r: r["warm_s"])
        line = (
            f"- {case}: fastest to the exact B-spline energy: **{fastest['solver']}** "
            f"({fastest['warm_s'] * 1e3:.1f} ms)"
        )
        # Lower E_ave only counts when the objective E is lower too (a solver stopped early
        # can trade E_d at the offsets for E_ave at the points).
        better = [r for r in block if r["E_over_exact"] < 1 - 1e-6]
        if better:
            best = min(better, key=lambda r: r["E_ave"])
            line += (
                f"; lowest E_ave at a lower E: **{best['solver']}** "
                f"({best['E_ave_over_exact']:.3f} x the exact B-spline's, "
                f"{best['warm_s'] * 1e3:.0f} ms)"
            )
        lines.append(line + ".")
    lines += [
        "",
        "## LeastSquares: dense Cholesky vs CG on the stencil (Example 10, lam = 1e-4)",
        "",
        "| grid | linear solver | E | warm | compile |",
        "|---|---|---|---|---|",
    ]
    for r in linear_rows:
        lines.append(
            f"| {r['grid']} x {r['grid']} | {r['linear_solver']} | {r['E']:.10e} | "
            f"{r['warm_s'] * 1e3:.1f} ms | {r['compile_s']:.1f} s |"
        )
    if option_rows:
        lines += [
            "",
            "## With and without jurs.COMPILER_OPTIONS (Example 1, 1000 points, "
            f"15 x 15, bucket_size=8, lam = {LAM:g})",
            "",
            "Each solver through `jurs.solve`, jitted without and with the options "
            "(floating-point reassociation). `E/E* - 1`: energy above the exact solve's "
            "(first row, without options); the paper's iterations minimise other "
            "objectives (IURS its own lambda, I-PIA none), so only their change counts. "
            "*Safe*: the solver's `reassociation_safe`, which lets `jurs.fit` use the "
            "options on large problems.",
            "",
            "| solver | safe | E/E* - 1 without | E/E* - 1 with | relative change of E | "
            "relative change of C | steps without / with |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in option_rows:
            lines.append(
                f"| {r['solver']} | {'yes' if r['reassociation_safe'] else 'no'} | "
                f"{r['E_plain_over_exact'] - 1:.2e} | {r['E_options_over_exact'] - 1:.2e} | "
                f"{r['rel_E_change']:.1e} | {r['rel_C_change']:.1e} | "
                f"{r['steps_plain']} / {r['steps_options']} |"
            )
    return "\n".join(lines) + "\n"


def rewrite_markdown():
    """Re-render solvers.md from solvers.json (no fits)."""
    with open(
        os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "solvers.json")
    ) as fh:
        data = json.load(fh)
    write_results(
        "solvers",
        data,
        markdown(data["rows"], data["linear_solvers"], data.get("compiler_options", ())),
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="Example 1, 9 x 9 only")
    parser.add_argument(
        "--markdown-only", action="store_true", help="re-render the markdown from the existing JSON"
    )
    args = parser.parse_args()
    if args.markdown_only:
        return rewrite_markdown()
    cases = [("Example 1, 9x9", jurs.datasets.example1(120), 9)]
    if not args.quick:
        cases += [
            ("Example 1, 15x15", jurs.datasets.example1(120), 15),
            ("Example 10, 15x15", jurs.datasets.example10(0), 15),
        ]
    rows = []
    for title, (points, normals), grid in cases:
        rows += run_block(f"{title}, lam={LAM:g}", points, normals, grid, fixed_weight_solvers(LAM))
        rows += run_block(f"{title}, lam=0", points, normals, grid, joint_solvers(0.0))
    linear_rows = linear_solver_table([9, 16, 32] if args.quick else [9, 16, 32, 48, 64, 128])
    option_rows = [] if args.quick else compiler_options_table()
    write_results(
        "solvers",
        {
            "machine": machine(),
            "rows": rows,
            "linear_solvers": linear_rows,
            "compiler_options": option_rows,
        },
        markdown(rows, linear_rows, option_rows),
    )


if __name__ == "__main__":
    main()
