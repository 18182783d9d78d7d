"""Multigrid (jurs._multigrid.Multigrid) against direct solves of the same normal equations.

For Example 1 sampled with ``m`` points on an ``n x n`` grid and a lam, the system
``(D^T D + 2 lam L) C = D^T b`` (unseen coefficients pinned, as LeastSquares does) is solved
by: the multigrid-preconditioned CG (warm time of the jitted solve, CG steps = V-cycles
after the full-multigrid start), SciPy's sparse direct solve (SuperLU via ``spsolve``;
scikit-sparse's CHOLMOD does not build against this machine's SuiteSparse 5.12), and the
block Cholesky of grid lines where it fits (``n^3 <= DIRECT_MAX_ENTRIES``), all in one
process. Reported: times and ratios, steps per decade of the energy-error estimate, the
residual, the objective's relative gap to SuperLU's optimum, and XLA's memory estimate of
the multigrid solve (arguments + temporaries).

    python benchmarks/multigrid.py --quick   # 128 and 256, lam 1e-4 and 1e-14, 1e5 points
    python benchmarks/multigrid.py           # 128..1024, lam 1e-4..1e-14, 1e4..1e6 points
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _common import machine, write_results  # noqa: E402

RTOL = 1e-6  # energy-error reduction asked of the multigrid solve


def system(n: int, m: int, lam: float):
    import jax.numpy as jnp

    import jurs
    from jurs import _normal

    points, normals = jurs.datasets.example1(m)
    problem = jurs.make_problem(points, normals, grid=n)
    normal = jurs.normal_equations(problem)
    stencil = normal.regularised(lam)
    diag = _normal.stencil_diagonal(stencil)
    stencil = stencil.at[..., 3, 3].set(jnp.where(diag <= 0, 1.0, diag))
    return stencil, jnp.where(diag <= 0, 0.0, normal.rhs), float(normal.target_norm2)


def multigrid_solver(rtol):
    import equinox as eqx
    import jax
    import lineax as lx

    from jurs import _multigrid, _normal

    @eqx.filter_jit
    def solve(stencil, rhs):
        operator = lx.FunctionLinearOperator(lambda c: _normal.stencil_matvec(stencil, c),
                                             jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                             lx.positive_semidefinite_tag)
        sol = lx.linear_solve(operator, rhs, _multigrid.Multigrid(rtol=rtol, max_steps=500),
                              options={"stencil": stencil}, throw=False)
        return sol.value, sol.stats["num_steps"], sol.stats["relative_error2"]

    return solve


def timed(fn, *args):
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0, first


def xla_memory(fn, *args) -> float:
    """Bytes XLA plans for a jitted call: arguments, outputs and temporaries."""
    import jax

    compiled = jax.jit(fn).lower(*args).compile().memory_analysis()
    if compiled is None:
        return float("nan")
    return float(compiled.argument_size_in_bytes + compiled.output_size_in_bytes
                 + compiled.temp_size_in_bytes)


def run_case(n, m, lam, solve):
    import jax
    import scipy.sparse.linalg as spl

    from jurs import _normal

    stencil, rhs, b2 = system(n, m, lam)
    (x, steps, error2), mg_s, mg_first = timed(solve, stencil, rhs)
    a = _normal.stencil_to_scipy(stencil).tocsc()
    b = np.asarray(rhs).ravel()
    t0 = time.perf_counter()
    exact = spl.spsolve(a, b)
    lu_s = time.perf_counter() - t0
    x = np.asarray(x).ravel()

    def objective(c):
        return float(c @ (a @ c) - 2 * c @ b + b2)

    row = dict(n=n, m=m, lam=lam, steps=int(steps), mg_s=mg_s, mg_compile_s=mg_first - mg_s,
               superlu_s=lu_s, speedup_vs_superlu=lu_s / mg_s,
               gap=(objective(x) - objective(exact)) / objective(exact),
               residual=float(np.linalg.norm(a @ x - b) / np.linalg.norm(b)),
               superlu_residual=float(np.linalg.norm(a @ exact - b) / np.linalg.norm(b)),
               steps_per_decade=float(int(steps) / max(-0.5 * np.log10(float(error2)), 1e-9)),
               mg_bytes=xla_memory(lambda s, r: solve(s, r)[0], stencil, rhs))
    if n**3 <= _normal.DIRECT_MAX_ENTRIES:
        direct = jax.jit(_normal.stencil_cholesky_solve)
        _, row["block_cholesky_s"], _ = timed(direct, stencil, rhs)
    return row


def markdown(rows, note) -> str:
    lines = [
        "# Multigrid vs direct solves of the normal equations", "",
        f"{note}", "",
        "Example 1 (`m` points, offsets at 0.1) on `n x n` grids; system "
        "`(D^T D + 2 lam L) C = D^T b`, unseen coefficients pinned. `MG` is the warm time of "
        f"the jitted `Multigrid(rtol={RTOL})` solve (full-multigrid start + CG, one V-cycle a "
        "step); `SuperLU` SciPy's `spsolve` of the same CSR matrix; `block Chol.` jurs' "
        "block Cholesky of grid lines (only where `n^3 <= DIRECT_MAX_ENTRIES`). `gap` is the "
        "objective's relative gap to SuperLU's optimum, `res` the relative residual, "
        "`steps/dec` CG steps per decade of the energy-error estimate `sqrt(r.Mr / b.Mb)`, "
        "`memory` XLA's plan for the multigrid solve (arguments, outputs, temporaries).", "",
        "| n | m | lam | steps | steps/dec | MG | SuperLU | SuperLU/MG | block Chol. | gap | "
        "res | memory | compile |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        chol = f"{r['block_cholesky_s']:.2f} s" if "block_cholesky_s" in r else "-"
        lines.append(
            f"| {r['n']} | {r['m']:.0e} | {r['lam']:.0e} | {r['steps']} | "
            f"{r['steps_per_decade']:.1f} | {r['mg_s']:.2f} s | {r['superlu_s']:.2f} s | "
            f"{r['speedup_vs_superlu']:.2f} | {chol} | {r['gap']:.1e} | {r['residual']:.1e} | "
            f"{r['mg_bytes'] / 2**20:.0f} MiB | {r['mg_compile_s']:.0f} s |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="128 and 256, two lams, 1e5 points")
    args = parser.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.quick:
        cases = [(n, 10**5, lam) for n in (128, 256) for lam in (1e-4, 1e-14)]
    else:
        cases = ([(n, 10**5, lam) for n in (128, 256, 512, 1024) for lam in (1e-4, 1e-8, 1e-14)]
                 + [(256, m, 1e-8) for m in (10**4, 10**6)])
    solve = multigrid_solver(RTOL)
    rows = []
    today = datetime.date.today().isoformat()
    for n, m, lam in cases:
        rows.append(run_case(n, m, lam, solve))
        print({k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in rows[-1].items()},
              flush=True)
        # Written after every case, so that an interrupted run keeps what it measured.
        note = (f"Measured {today} on {machine()} (a 2-core machine shared with other jobs: "
                "absolute times are noisy, ratios are from the same run). "
                f"{len(rows)} of {len(cases)} cases of this run.")
        write_results("multigrid", {"date": today, "machine": machine(), "rtol": RTOL,
                                    "rows": rows}, markdown(rows, note))


if __name__ == "__main__":
    main()
