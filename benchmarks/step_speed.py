"""Warm time of one IURS / I-PIA step on a large cloud, and the first call's compile time;
then two whole fits.

Default: 1e5 points of Example 1 (3e5 samples), 64 x 64 grid, float64. The baseline, run in
the same process, is the same step on the generic layout (one sample a bucket, the layout
every traced fit uses); the ratio shows what the cell-bucketed layout buys. NormalIPIA's
step does not touch the samples (its one-off assembly is in ``init``, not timed here), so
its two layouts time the same.

Whole fits through ``jurs.fit`` (d = 0.1, eps = 0.01): a small regularised IURS fit run to
tolerance (640 points of the ``lobes`` outline, 15 x 15, tau = 1e-3, lam = 0.002,
tol = 1e-7; cold = first call in this process, compilation included), and the exact
regularised solve ``LeastSquares(lam=1e-4)`` on the cloud and grid above, end to end
(problem building, D^T D stencil assembly, linear solve, metrics).

    python -m benchmarks.step_speed [--points 100000] [--grid 64]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

import jurs  # noqa: E402
import jurs.shapes  # noqa: E402

from ._common import machine, time_repeated, write_results  # noqa: E402

#: No time budget: every timing takes its ``max_repeats`` warm calls (20 by default).
INF = float("inf")


@jax.jit
def _step(solver, problem, state):
    return solver.step(problem, state)


def measure(points, normals, grid, solver, bucket_size):
    t0 = time.perf_counter()
    problem = jax.block_until_ready(
        jurs.make_problem(points, normals, grid=grid, bucket_size=bucket_size)
    )
    build = time.perf_counter() - t0
    spline = jurs.ImplicitSpline(jnp.zeros(grid), jnp.ones(grid), problem.lower, problem.upper)
    init = jax.jit(solver.init)
    init_s = time_repeated(init, problem, spline, budget_s=INF, max_repeats=3)["warm_s"]
    state, _ = init(problem, spline)
    state, _ = _step(solver, problem, state)  # a state with moved weights
    _step.clear_cache()  # so the first timed call compiles, as a user's first call does
    timed = time_repeated(_step, solver, problem, state, budget_s=INF)
    first, warm = timed["first_s"], timed["warm_s"]
    return {
        "layout": f"bucket_size={problem.local.bucket_size}",
        "slots": int(problem.samples.shape[0]),
        "build_s": build,
        "init_s": init_s,
        "compile_s": first - warm,
        "warm_ms": warm * 1e3,
    }


def whole_fits(points, normals, grid):
    small_points, small_normals = jurs.shapes.get("lobes", 640)
    iurs = jurs.IURS(tau=1e-3, lam=0.002, tol=1e-7, max_steps=20000)
    timed = time_repeated(
        lambda: jurs.fit(
            small_points, small_normals, grid=(15, 15), solver=iurs, offset=0.1, eps=0.01
        ),
        budget_s=INF,
        max_repeats=5,
    )
    cold, warm, sol = timed["first_s"], timed["warm_s"], timed["output"]
    steps = int(sol.stats["num_steps"])
    small = {
        "fit": "IURS (tau=1e-3, lam=0.002, tol=1e-7), lobes 640 points, 15x15",
        "cold_s": cold,
        "warm_s": warm,
        "steps": steps,
        "per_step_us": warm / steps * 1e6,
    }
    exact = jurs.LeastSquares(lam=1e-4)
    timed = time_repeated(
        lambda: jurs.fit(points, normals, grid=grid, solver=exact, offset=0.1, eps=0.01),
        budget_s=INF,
        max_repeats=3,
    )
    cold, warm, sol = timed["first_s"], timed["warm_s"], timed["output"]
    large = {
        "fit": f"LeastSquares(lam=1e-4), {points.shape[0]} points, {grid[0]}x{grid[1]}",
        "cold_s": cold,
        "warm_s": warm,
        "steps": int(sol.stats["num_steps"]),
    }
    return [small, large]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--grid", type=int, default=64)
    args = parser.parse_args(argv)
    grid = (args.grid, args.grid)
    points, normals = jurs.datasets.example1(args.points)
    rows = []
    for name, solver in [
        ("IURS (tau=1e-2, lam=1e-3)", jurs.IURS(tau=1e-2, lam=1e-3)),
        ("IPIA", jurs.IPIA()),
        ("IPIA, normal-equation form (NormalIPIA)", jurs.NormalIPIA()),
    ]:
        fast = measure(points, normals, grid, solver, None)
        base = measure(points, normals, grid, solver, 1)
        rows.append(
            {
                "solver": name,
                "fast": fast,
                "baseline": base,
                "speedup": base["warm_ms"] / fast["warm_ms"],
            }
        )

    fits = whole_fits(points, normals, grid)

    lines = [
        f"# One solver step: {args.points} points ({3 * args.points} samples), grid "
        f"{grid[0]}x{grid[1]}, float64",
        "",
        f"Machine: {machine()}",
        "",
        "| solver | layout | slots | warm step | first call compile | problem build | warm init | "
        "baseline (generic layout) warm | speedup |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        f, b = r["fast"], r["baseline"]
        lines.append(
            f"| {r['solver']} | {f['layout']} | {f['slots']} | {f['warm_ms']:.1f} ms | "
            f"{f['compile_s']:.2f} s | {f['build_s']:.2f} s | {f['init_s'] * 1e3:.1f} ms | "
            f"{b['warm_ms']:.1f} ms | "
            f"{r['speedup']:.1f}x |"
        )
    lines += [
        "",
        "## Whole fits (jurs.fit, d = 0.1, eps = 0.01)",
        "",
        "| fit | steps | warm | per step | cold (first call, compiles) |",
        "|---|---|---|---|---|",
    ]
    for f in fits:
        per_step = f"{f['per_step_us']:.0f} us" if "per_step_us" in f else "—"
        lines.append(
            f"| {f['fit']} | {f['steps']} | {f['warm_s'] * 1e3:.0f} ms | {per_step} | "
            f"{f['cold_s']:.2f} s |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    write_results(
        f"step_speed_{args.points}_{args.grid}",
        {"points": args.points, "grid": grid, "machine": machine(), "rows": rows, "fits": fits},
        text,
    )


if __name__ == "__main__":
    main()
