"""CG on the THB hierarchy's normal equations: Jacobi (``solve_host_cg``, the default on a
CPU) against the multilevel V-cycle over the hierarchy's nested spaces
(``jurs._linalg.thb_multigrid``) run on the host (``fit_adaptive(method="host_multigrid")``)
and in JAX (``method="multigrid"``: its first call, compilation included, and a warm one),
and against pyamg's smoothed aggregation (when pyamg is installed), on the same assembled
problems, back to back in one process: steps to ``DEFAULT_RTOL``, set-up and solve time.

The problems are ``fit_adaptive``'s: its settings, layout, samples and lambda
(``hierarchy_layout``, ``assemble_adaptive_problem``, ``scale_free_lam``). Curves: Example 1
at 4000 points, finest 256 to 2048 cells; surfaces: the torus at 20k points, finest 32 to
128 cells.

    python -m benchmarks.thb_multigrid [--quick]

writes ``benchmarks/results/thb_multigrid.{md,json}`` (``--name``: another name).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jurs  # noqa: E402
from jurs._fit.adaptive import (  # noqa: E402
    DEFAULT_RTOL,
    hierarchy_layout,
    solve_host_cg,
    solve_multigrid,
)
from jurs._fit.settings import auto_settings, scale_free_lam  # noqa: E402
from jurs._linalg.sparse import normal_system  # noqa: E402
from jurs._linalg.thb_multigrid import ThbMultigrid  # noqa: E402
from jurs._problem.adaptive import assemble_adaptive_problem  # noqa: E402
from jurs._solution.verdicts import judged_points  # noqa: E402

from ._common import machine, md_table, write_results  # noqa: E402

MAX_STEPS = 5000
CASES = [
    ("Example 1, 4000 points", "curve", [256, 512, 1024, 2048]),
    ("torus, 20k points", "surface", [32, 64, 128]),
]
QUICK = [
    ("Example 1, 4000 points", "curve", [256, 1024]),
    ("torus, 20k points", "surface", [32, 64]),
]


def cloud_of(kind: str):
    if kind == "curve":
        return jurs.datasets.example1(4000)
    return jurs.datasets.torus(20_000)


def fit_problem(points, normals, finest: int):
    """``(problem, matrices, lam)`` as ``fit_adaptive`` builds them for ``finest``."""
    cloud = jurs.Cloud(points, normals)
    settings = auto_settings(cloud)
    keep = judged_points(cloud, settings)
    points, normals = cloud.points[keep], np.asarray(cloud.normals, float)[keep]
    ndim = points.shape[1]
    layout = hierarchy_layout(settings, ndim, finest, None, None, None, None)
    problem, matrices = assemble_adaptive_problem(points, normals, **layout)
    hierarchy = problem.hierarchy
    cells = np.asarray(hierarchy.cells(hierarchy.num_levels - 1))
    cell = float(np.max((layout["upper"] - layout["lower"]) / cells))
    diagonal = float(np.linalg.norm(points.max(0) - points.min(0)))
    lam = scale_free_lam(
        settings.smoothing, 3 * len(points), diagonal, layout["lower"], layout["upper"], cell
    )
    return problem, matrices, lam


def cg_steps(matrix, rhs, preconditioner):
    """``(x, steps)`` of SciPy's CG to ``DEFAULT_RTOL``."""
    from scipy.sparse.linalg import cg

    steps = 0

    def count(_):
        nonlocal steps
        steps += 1

    x, _ = cg(
        matrix, rhs, rtol=DEFAULT_RTOL, atol=0.0, maxiter=MAX_STEPS, M=preconditioner,
        callback=count,
    )  # fmt: skip
    return x, steps


def load() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


def measure(name: str, kind: str, finest: int) -> dict:
    points, normals = cloud_of(kind)
    problem, matrices, lam = fit_problem(points, normals, finest)
    hierarchy = problem.hierarchy
    row: dict[str, Any] = dict(
        case=name, finest=finest, levels=hierarchy.num_levels, active=hierarchy.num_active,
        load_before=load(),
    )  # fmt: skip
    start = time.perf_counter()
    reference, steps, _ = solve_host_cg(problem, matrices, lam, DEFAULT_RTOL, MAX_STEPS)
    row.update(jacobi_steps=steps, jacobi_s=time.perf_counter() - start)

    start = time.perf_counter()
    matrix, rhs = normal_system(matrices, problem.targets, lam)
    multigrid = ThbMultigrid(hierarchy, matrix)
    setup = time.perf_counter() - start
    start = time.perf_counter()
    x, steps = cg_steps(matrix, rhs, multigrid.operator())
    scale = np.linalg.norm(reference)
    row.update(
        spaces=list(multigrid.sizes), multigrid_steps=steps, multigrid_setup_s=setup,
        multigrid_solve_s=time.perf_counter() - start,
        multigrid_difference=float(np.linalg.norm(x - reference) / scale),
    )  # fmt: skip
    del multigrid
    for call in ("first", "warm"):  # set-up on the host, transfer and the compiled solve
        start = time.perf_counter()
        x, steps, _ = solve_multigrid(problem, matrices, lam, DEFAULT_RTOL, MAX_STEPS, np.float64)
        row[f"jax_{call}_s"] = time.perf_counter() - start
    row.update(jax_steps=steps, jax_difference=float(np.linalg.norm(x - reference) / scale))
    try:
        import pyamg  # pyright: ignore[reportMissingImports]
    except ImportError:
        pyamg = None
    if pyamg is not None:
        start = time.perf_counter()
        preconditioner = pyamg.smoothed_aggregation_solver(matrix).aspreconditioner()
        setup = time.perf_counter() - start
        start = time.perf_counter()
        x, steps = cg_steps(matrix, rhs, preconditioner)
        row.update(
            pyamg_steps=steps, pyamg_setup_s=setup, pyamg_solve_s=time.perf_counter() - start,
            pyamg_difference=float(np.linalg.norm(x - reference) / scale),
        )  # fmt: skip
    row["load_after"] = load()
    print(row, flush=True)
    return row


def report(rows: list[dict[str, Any]], options: str = "") -> str:
    def s(value):
        return "-" if value is None else f"{value:.2f}"

    table = md_table(
        [
            "case", "finest", "levels", "active", "spaces", "Jacobi steps", "Jacobi s",
            "MG steps", "MG set-up s", "MG solve s", "MG in JAX steps",
            "MG in JAX first s", "MG in JAX warm s", "pyamg steps", "pyamg set-up s",
            "pyamg solve s", "load (1 min) before / after",
        ],
        [
            [
                r["case"], r["finest"], r["levels"], r["active"],
                " / ".join(str(n) for n in r["spaces"]), r["jacobi_steps"], s(r["jacobi_s"]),
                r["multigrid_steps"], s(r["multigrid_setup_s"]), s(r["multigrid_solve_s"]),
                r["jax_steps"], s(r["jax_first_s"]), s(r["jax_warm_s"]),
                r.get("pyamg_steps", "-"), s(r.get("pyamg_setup_s")),
                s(r.get("pyamg_solve_s")),
                f"{r['load_before'].split(',')[0]} / {r['load_after'].split(',')[0]}",
            ]
            for r in rows
        ],
    )  # fmt: skip
    worst = max(max(r["multigrid_difference"], r["jax_difference"]) for r in rows)
    lines = [
        "# CG on the THB hierarchy: Jacobi, the nested-space V-cycle, pyamg",
        "",
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine()}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; "
        f"written by `python -m benchmarks.thb_multigrid{' ' + options if options else ''}`. "
        "All four solves of a row ran "
        "back to back in one process; the machine was shared (its load average beside "
        "each row), so compare steps first and times only within a row.",
        "",
        "Stop rule `|r| <= 1e-10 |D^T b|`. *spaces*: unknowns of the nested spaces "
        "V_0 .. V_L. *MG set-up*: the normal matrix, the prolongations, the Galerkin "
        "operators and the patch inverses; Jacobi's CG needs none of them (it applies "
        "`D^T D + lam G` by products with D). *MG in JAX*: the same cycle and CG run in "
        "JAX (`solve_multigrid`: the host set-up, the transfer and the compiled solve), "
        "its first call with compilation and a warm one. pyamg: "
        "`smoothed_aggregation_solver(A).aspreconditioner()` on the same matrix, "
        "defaults.",
        "",
        *table,
        "",
        f"Largest relative difference of the V-cycles' solutions from Jacobi's: {worst:.1e}.",
        "",
    ]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description="THB multigrid against Jacobi and pyamg")
    parser.add_argument("--quick", action="store_true", help="two sizes a case")
    parser.add_argument("--name", default="thb_multigrid", help="results file names")
    args = parser.parse_args()
    rows = []
    for name, kind, sizes in QUICK if args.quick else CASES:
        for finest in sizes:
            rows.append(measure(name, kind, finest))
    write_results(args.name, {"rows": rows}, report(rows, " ".join(sys.argv[1:])))


if __name__ == "__main__":
    main()
