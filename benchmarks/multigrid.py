"""Multigrid (jurs._linalg.multigrid.Multigrid) against direct solves of the same normal equations.

2D: Example 1 sampled with ``m`` points on an ``n x n`` grid; 3D: the torus
(``jurs.datasets.torus``) on ``n^3``. For each lam the system ``(D^T D + 2 lam L) C = D^T b``
(unseen coefficients pinned, as LeastSquares does) is solved, in one process, by:

* the multigrid-preconditioned CG: ``setup`` is ``Multigrid.init`` (coarse operators, patch
  inverses), ``solve`` the iteration with that hierarchy reused (``linear_solve(...,
  state=)``), both warm (best of a few calls; ``compile`` is the first calls' excess).
  Stopping: ``rtol = 1e-4`` relative to the objective (``options["target_norm2"]``), i.e.
  an estimated gap of 1e-8 of the objective;
* SciPy's sparse direct solve (SuperLU via ``spsolve``; scikit-sparse's CHOLMOD does not
  build against this machine's SuiteSparse 5.12), in 2D and at 32^3;
* jurs' block Cholesky of grid lines where LeastSquares would use it (2D, ``n^3 <=
  DIRECT_MAX_ENTRIES``).

Reported: times and ratios, CG steps, the objective's relative gap to SuperLU's optimum
measured as ``(x - x*) A (x - x*) - 2 (x - x*) r*`` over ``E*`` (no cancellation against
``b . b``), and XLA's memory plan of the whole multigrid solve (setup + iteration).

``--memory N ...`` adds XLA's memory plans of 2D ``N x N`` solves, compiled but not run
(abstract arguments: no system is built), with float64 and with float32 patch inverses.

    python -m benchmarks.multigrid --quick   # 2D 128, 256 at three lam; 3D 32^3
    python -m benchmarks.multigrid           # 2D 128..1024, 3D 32^3..64^3
    python -m benchmarks.multigrid --quick --memory 512 1024
    python -m benchmarks.multigrid --no-solves --memory 512   # memory plans only
    python -m benchmarks.multigrid --append --no-solves --case 512 1e-4   # add a row
    python -m benchmarks.multigrid --rerender   # multigrid.md from the JSON

Results are rewritten after every case, so an interrupted run keeps what it measured;
``--append`` keeps the rows already there and adds a run (each row's ratios still come
from one process).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time

import numpy as np

from ._common import RESULTS, machine, rerender_beside, write_results

#: Square root of the objective gap asked of the multigrid solve, relative to the objective.
RTOL = 1e-4
MAX_STEPS = 200
#: 3D systems up to this side get a SuperLU reference (32^3: 30 s, 4 GB; 48^3 would take
#: many minutes).
SUPERLU_MAX_3D = 32


def system(n: int, m: int, lam: float, ndim: int):
    """``(stencil, rhs, b . b)``: Example 1 (2D) or the torus (3D), unseen coefficients
    pinned to 0 as LeastSquares does."""
    import jax.numpy as jnp

    import jurs
    import jurs.internal
    from jurs._linalg import stencil as _stencil

    data = jurs.datasets.example1 if ndim == 2 else jurs.datasets.torus
    points, normals = data(m)
    problem = jurs.make_problem(points, normals, grid=n)
    normal = jurs.internal.normal_equations(problem)
    stencil = normal.regularised(lam).stencil
    diag = _stencil.stencil_diagonal(stencil)
    centre = (Ellipsis,) + (_stencil.HALF,) * ndim
    stencil = stencil.at[centre].set(jnp.where(diag <= 0, 1.0, diag))
    return stencil, jnp.where(diag <= 0, 0.0, normal.rhs), float(normal.target_norm2)


def multigrid_solver(patch_dtype=None):
    """Jitted ``(setup, solve, memory)`` of the lineax Multigrid solve."""
    import jax
    import lineax as lx

    from jurs._linalg import multigrid as _multigrid
    from jurs._linalg import stencil as _stencil

    solver = _multigrid.Multigrid(rtol=RTOL, max_steps=MAX_STEPS, patch_dtype=patch_dtype)
    operator = _stencil.StencilOperator

    @jax.jit
    def setup(stencil, rhs):
        return solver.init(operator(stencil), {})

    @jax.jit
    def solve(stencil, rhs, state, b2):
        sol = lx.linear_solve(
            operator(stencil),
            rhs,
            solver,
            state=state,
            options={"target_norm2": b2},
            throw=False,
        )
        return sol.value, sol.stats["num_steps"], sol.result == lx.RESULTS.successful

    def whole(stencil, rhs, b2):
        return lx.linear_solve(
            operator(stencil), rhs, solver, options={"target_norm2": b2}, throw=False
        ).value

    plans = {}

    def memory(shape: tuple, ndim: int) -> dict:
        """XLA's plan (bytes: arguments, outputs, temporaries, total) for setup and solve in
        one call on a float64 grid of ``shape``, compiled from abstract arguments, and the
        compile's seconds; once per shape."""
        if shape not in plans:
            f64 = jax.numpy.float64
            args = (
                jax.ShapeDtypeStruct(shape + (_stencil.SIDE,) * ndim, f64),
                jax.ShapeDtypeStruct(shape, f64),
                jax.ShapeDtypeStruct((), f64),
            )
            t0 = time.perf_counter()
            plan = jax.jit(whole).lower(*args).compile().memory_analysis()
            parts = {
                "argument_bytes": float(plan.argument_size_in_bytes),
                "output_bytes": float(plan.output_size_in_bytes),
                "temp_bytes": float(plan.temp_size_in_bytes),
            }
            plans[shape] = dict(
                parts, total_bytes=sum(parts.values()), compile_s=time.perf_counter() - t0
            )
        return plans[shape]

    return setup, solve, memory


def timed(fn, *args, repeats=2):
    """``(output, best warm seconds, first-call seconds)``."""
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return out, best, first


def run_case(n, m, lam, ndim, mg):
    import jax
    import scipy.sparse.linalg as spl

    from jurs._linalg import cholesky as _cholesky
    from jurs._linalg import stencil as _stencil

    setup, solve, memory = mg
    stencil, rhs, b2 = system(n, m, lam, ndim)
    repeats = 2 if n**ndim <= 2**17 else 1
    state, setup_s, setup_first = timed(setup, stencil, rhs, repeats=repeats)
    (x, steps, ok), solve_s, solve_first = timed(solve, stencil, rhs, state, b2, repeats=repeats)
    row = dict(
        n=n,
        ndim=ndim,
        m=m,
        lam=lam,
        steps=int(steps),
        converged=bool(ok),
        setup_s=setup_s,
        solve_s=solve_s,
        mg_s=setup_s + solve_s,
        compile_s=setup_first + solve_first - setup_s - solve_s,
        mg_bytes=memory(rhs.shape, ndim)["total_bytes"],
    )
    if ndim == 2 or n <= SUPERLU_MAX_3D:
        a = _stencil.stencil_to_scipy(stencil).tocsc()
        b = np.asarray(rhs).ravel()
        t0 = time.perf_counter()
        exact = spl.spsolve(a, b)
        row["superlu_s"] = time.perf_counter() - t0
        d = np.asarray(x).ravel() - exact
        optimum = b2 - exact @ b  # E* = b.b - x*.rhs
        row["optimum"] = optimum
        row["gap"] = float(d @ (a @ d) - 2 * d @ (b - a @ exact)) / optimum
        row["superlu_over_mg"] = row["superlu_s"] / row["mg_s"]
    if ndim == 2 and n**3 <= _cholesky.DIRECT_MAX_ENTRIES:
        _, row["block_cholesky_s"], _ = timed(
            jax.jit(_cholesky.stencil_cholesky_solve), stencil, rhs, repeats=repeats
        )
    return row


def markdown(rows, plans, note) -> str:
    def cell(row, key, fmt):
        return fmt.format(row[key]) if key in row else "-"

    lines = [
        "# Multigrid vs direct solves of the normal equations",
        "",
        f"{note}",
        "",
        "2D: Example 1 (`m` points, offsets at 0.1) on `n x n`; 3D: the torus on `n^3`. "
        "System `(D^T D + 2 lam L) C = D^T b`, unseen coefficients pinned. `setup` is "
        "`Multigrid.init` (Galerkin levels, patch inverses), `solve` the CG iteration "
        f"(full-multigrid start, one V-cycle a step) with `rtol={RTOL}` relative to the "
        "objective (an estimated gap of 1e-8 of it), `MG` their sum; `SuperLU` SciPy's "
        "`spsolve`; `block Chol.` jurs' block Cholesky of grid lines (where LeastSquares uses "
        "it). `gap` is the objective's gap to SuperLU's optimum relative to that optimum "
        "`E*` (`(cap)`: the step cap was reached first); `memory` XLA's plan for "
        "setup and solve in one call. Design, the issue's targets and what stops each: "
        "`docs/multigrid.md`.",
        "",
        "| grid | m | lam | steps | setup | solve | MG | SuperLU | SuperLU/MG | block Chol. "
        "| gap | E* | memory | compile |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        grid = f"{r['n']}^{r['ndim']}" if r["ndim"] == 3 else f"{r['n']} x {r['n']}"
        steps = f"{r['steps']}" + ("" if r["converged"] else " (cap)")
        lines.append(
            f"| {grid} | {r['m']:.0e} | {r['lam']:.0e} | {steps} | {r['setup_s']:.2f} s | "
            f"{r['solve_s']:.2f} s | {r['mg_s']:.2f} s | {cell(r, 'superlu_s', '{:.2f} s')} | "
            f"{cell(r, 'superlu_over_mg', '{:.2f}')} | "
            f"{cell(r, 'block_cholesky_s', '{:.2f} s')} | {cell(r, 'gap', '{:.1e}')} | "
            f"{cell(r, 'optimum', '{:.1e}')} | {r['mg_bytes'] / 2**20:.0f} MiB | "
            f"{max(r['compile_s'], 0.0):.0f} s |"
        )
    if plans:
        lines += [
            "",
            "## Memory plans (compiled, not run)",
            "",
            "XLA's `memory_analysis` of one jitted call that builds the hierarchy and solves "
            "(float64 system; arguments: the stencil, `n^2 x 49` floats, and the right-hand "
            "side), compiled from abstract arguments on this CPU backend; the solve was not "
            "run. `patches` is the storage of the patch inverses (`patch_dtype`).",
            "",
            "| grid | patches | arguments | temporaries | outputs | total | compile |",
            "|---|---|---|---|---|---|---|",
        ]
        for p in plans:
            lines.append(
                f"| {p['n']} x {p['n']} | {p['patch_dtype']} | "
                f"{p['argument_bytes'] / 2**20:.0f} MiB | {p['temp_bytes'] / 2**20:.0f} MiB | "
                f"{p['output_bytes'] / 2**20:.0f} MiB | {p['total_bytes'] / 2**30:.2f} GiB | "
                f"{p['compile_s']:.0f} s |"
            )
    return "\n".join(lines) + "\n"


def load_results(folder: str) -> tuple[list, list, list]:
    """``(rows, memory plans, runs)`` of ``folder/multigrid.json``."""
    with open(os.path.join(folder, "multigrid.json")) as fh:
        old = json.load(fh)
    rows, plans, runs = old["rows"], old.get("memory_plans", []), old.get("runs", [])
    if not runs:  # results written before runs were recorded: one earlier run
        runs = [
            dict(started=old["date"], machine=old["machine"], solves=len(rows), plans=len(plans))
        ]
    return rows, plans, runs


def plural(count: int, noun: str) -> str:
    return f"{count} {noun}" + ("" if count == 1 else "s")


def run_note(runs, rows, plans) -> str:
    """The results' opening note: machine, load, and which run measured what."""
    parts = []
    for k, r in enumerate(runs):
        load = f", load average {r['load']:.1f} at its start" if "load" in r else ""
        parts.append(
            f"run {k + 1} ({r['started']}{load}): {plural(r['solves'], 'solve case')}, "
            f"{plural(r['plans'], 'memory plan')}"
        )
    return (
        f"Measured on {runs[-1]['machine']}, a 2-core machine shared with other jobs: absolute "
        "times are noisy, each row's ratios are from one process. "
        + "; ".join(parts)
        + (" (later runs appended with `--append`)." if len(runs) > 1 else ".")
        + f" {plural(len(rows), 'solve case')} and {plural(len(plans), 'memory plan')} in all."
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="2D 128 and 256 at three lam, 3D 32^3 at lam 1e-4"
    )
    parser.add_argument(
        "--case",
        nargs=2,
        action="append",
        default=[],
        metavar=("N", "LAM"),
        help="a 2D N x N case at LAM (1e5 points), run after the set chosen; repeatable",
    )
    parser.add_argument(
        "--memory",
        type=int,
        nargs="*",
        default=[],
        metavar="N",
        help="also XLA's memory plans (compile only) of 2D N x N solves, after the solves",
    )
    parser.add_argument(
        "--memory-dtypes",
        nargs="+",
        default=["float64", "float32"],
        choices=["float64", "float32"],
        help="patch inverse dtypes of the memory plans (default both)",
    )
    parser.add_argument(
        "--no-solves", action="store_true", help="no default set: only --case and --memory"
    )
    parser.add_argument(
        "--append", action="store_true", help="keep the results already in --results, add these"
    )
    parser.add_argument(
        "--rerender", action="store_true", help="rewrite multigrid.md from the JSON, no measuring"
    )
    parser.add_argument("--results", default=RESULTS, help="folder for multigrid.{md,json}")
    args = parser.parse_args()
    if args.rerender:

        def render(data):
            rows, plans, runs = load_results(args.results)
            return markdown(rows, plans, run_note(runs, rows, plans))

        print(rerender_beside(os.path.join(args.results, "multigrid.json"), render))
        return
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    lams = (1e-4, 1e-8, 1e-14)
    if args.no_solves:
        cases = []
    elif args.quick:
        cases = [(n, 10**5, lam, 2) for n in (128, 256) for lam in lams] + [(32, 10**5, 1e-4, 3)]
    else:
        cases = [(n, 10**5, lam, 2) for n in (128, 256, 512, 1024) for lam in lams] + [
            (n, 10**5, lam, 3) for n in (32, 48, 64) for lam in (1e-4, 1e-8)
        ]
    cases += [(int(n), 10**5, float(lam), 2) for n, lam in args.case]
    mg = multigrid_solver()
    rows, plans, runs = [], [], []
    if args.append:
        rows, plans, runs = load_results(args.results)
    run = dict(
        started=datetime.datetime.now().isoformat(timespec="minutes"),
        load=os.getloadavg()[0],
        machine=machine(),
        solves=0,
        plans=0,
    )
    runs.append(run)
    tasks = [("solve", case) for case in cases] + [
        ("memory", (n, dtype)) for n in args.memory for dtype in args.memory_dtypes
    ]

    def write():
        # After every task, so that an interrupted run keeps what it measured.
        payload = dict(
            date=datetime.date.today().isoformat(),
            machine=machine(),
            rtol=RTOL,
            runs=runs,
            rows=rows,
            memory_plans=plans,
        )
        write_results(
            "multigrid", payload, markdown(rows, plans, run_note(runs, rows, plans)), args.results
        )

    for kind, task in tasks:
        if kind == "solve":
            rows.append(dict(run_case(*task, mg), run=len(runs)))
            run["solves"] += 1
            out = rows[-1]
        else:
            n, dtype = task
            _, _, memory = mg if dtype == "float64" else multigrid_solver(jnp.float32)
            plans.append(dict(n=n, ndim=2, patch_dtype=dtype, **memory((n, n), 2), run=len(runs)))
            run["plans"] += 1
            out = plans[-1]
        print({k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in out.items()}, flush=True)
        write()


if __name__ == "__main__":
    main()
