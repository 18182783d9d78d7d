"""Speed and memory of jurs against the paper's own algorithm in NumPy and against SciPy's RBF.

One command measures everything and writes ``benchmarks/results/speed.{json,md}``
(``--quick``: a few-minute smoke run on small sizes, written to ``speed_quick.{json,md}``):

1. **Sweep** over Example 1 clouds of m points (3m samples) and square grids: per solver
   step of ``IURS(tau=1e-2, lam=1e-3)``, ``IPIA()`` and ``NormalIPIA()`` (whose one-off
   assembly of D^T D is its ``init``, timed on its own), the warm time, the compile time
   (first call minus warm) and the peak memory; and ``LeastSquares(lam=1e-4)`` end to end
   through ``jurs.fit`` (problem building + assembly + solve), first call and warm. At
   the target size the IURS step is also timed inside ``jurs.fit`` (fits of 1 and 21
   steps), and the step on its own again with huge pages and ``jurs.COMPILER_OPTIONS``.
2. **Baselines**: ``_numpy_port.py``, the paper's Algorithm 1 with a dense collocation
   matrix rebuilt every step (where that matrix fits in ``DENSE_LIMIT_BYTES``), against the
   jurs IURS step; and ``scipy.interpolate.RBFInterpolator`` (thin-plate) on the same
   offset samples against ``jurs.fit(points, normals)`` with its automatic settings, fit
   time and the refined Chamfer distance to the exact curve, plus zero-set component counts.
3. **Targets**: measured value against target, PASS / MISS, at the top of the report.

Every measurement runs in a fresh subprocess (``--worker``), so its peak resident set size
(VmHWM) belongs to that measurement alone; the report gives the peak and the peak minus
the RSS after imports, JAX start-up and data creation.

    python benchmarks/speed.py [--quick]
    python benchmarks/speed.py --from-json benchmarks/results/speed.json   # re-render only

Runs on whatever device JAX picks (CPU here; a GPU if JAX sees one), in float64, and
records the device.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from functools import partial

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))

# The sizes, settings and targets live in _speed_config, the verdicts and the markdown in
# _speed_report, the timer in _common (all next to this script, which is on sys.path when
# it runs; none of them imports JAX when imported: each worker starts it itself).
from _common import (  # noqa: E402
    elapsed_log,
    machine,
    rerender_beside,
    time_repeated,
    write_results,
)
from _speed_config import (  # noqa: E402
    ANALYSIS_RESOLUTION,
    CEILING_N,
    DENSE_LIMIT_BYTES,
    EPS,
    EXAMPLE4,
    EXAMPLE4_MAX_STEPS,
    EXAMPLE4_RUNS,
    EXAMPLE4_TOL,
    FIT_STEPS,
    FULL_SWEEP,
    HUGEPAGE_ENV,
    LOOP_S,
    LOOP_STEPS_MAX,
    LOOP_STEPS_MIN,
    LSQ_LAM,
    OFFSET,
    PASS_REPEATS,
    QUICK_RBF_POINTS,
    QUICK_SWEEP,
    RBF_GIVEN,
    RBF_GRIDS,
    RBF_MAX_PREDICTED_S,
    REFERENCE_POINTS,
    REFINED_REFERENCE_SAMPLES,
    REFINED_SAMPLES_PER_DIAGONAL,
    STEP_BUDGET_S,
    STEP_SOLVERS,
    TARGET_GRID,
    TARGET_POINTS,
    TARGET_RBF_POINTS,
    WORKER_TIMEOUT_S,
)
from _speed_report import arithmetic_bounds, evaluate_targets, report  # noqa: E402

# --------------------------------------------------------------------------- measuring (workers)


def _status_bytes(field: str) -> int | None:
    """A ``kB`` field of /proc/self/status (VmRSS, VmHWM) in bytes; None off Linux."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def rss_bytes() -> int:
    """Current resident set size (falls back to the peak where /proc is missing)."""
    return _status_bytes("VmRSS") or peak_bytes()


def peak_bytes() -> int:
    """Peak resident set size of this process (VmHWM; ru_maxrss, in kB on Linux, as fallback)."""
    return _status_bytes("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _start_jax():
    """Import jax and jurs in float64 and start the backend, so that the memory baseline
    taken next already holds the runtime and the measurement holds only the work."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import jurs

    jax.block_until_ready(jnp.zeros(8) + 1.0)
    return jax, jurs


def _baseline() -> int:
    gc.collect()
    return rss_bytes()


def _memory(base: int) -> dict:
    """Peak RSS, the baseline and their difference; plus the accelerator's own peak where
    the device reports one (host RSS does not see GPU memory)."""
    peak = peak_bytes()
    out = {"rss_base_b": base, "peak_b": peak, "peak_over_base_b": peak - base}
    try:
        import jax

        stats = jax.devices()[0].memory_stats() or {}
        if jax.devices()[0].platform != "cpu" and "peak_bytes_in_use" in stats:
            out["device_peak_b"] = int(stats["peak_bytes_in_use"])
    except Exception:  # noqa: BLE001 - memory stats are optional everywhere
        pass
    return out


def _timing(t: dict, prefix: str = "") -> dict:
    """The numbers of :func:`time_repeated`, keys prefixed, without the output."""
    return {prefix + k: v for k, v in t.items() if k != "output"}


def result_name(jurs, sol) -> str:
    """The short name of ``sol.result`` (``successful``, ``max_steps_reached``, ...)."""
    for name in ("successful", "max_steps_reached", "failed", "nonfinite"):
        if bool(sol.result == getattr(jurs.RESULTS, name)):
            return name
    return "unknown"


def _device_name(jax) -> str:
    d = jax.devices()[0]
    return f"{d.platform}:{d.device_kind}"


def work_step(spec: dict) -> dict:
    """One solver step at (m, grid), timed as benchmarks/step_speed.py does: a jitted
    ``solver.step`` on a state one step in (so the weights have moved), cache cleared so the
    first timed call compiles. ``init`` (for NormalIPIA: the assembly of D^T D) is timed too."""
    jax, jurs = _start_jax()
    import jax.numpy as jnp

    points, normals = jurs.datasets.example1(spec["m"])
    base = _baseline()
    _, ctor, kwargs = STEP_SOLVERS[spec["solver"]]
    solver = getattr(jurs, ctor)(**kwargs)
    grid = (spec["grid"], spec["grid"])

    t0 = time.perf_counter()
    problem = jax.block_until_ready(jurs.make_problem(points, normals, grid=grid))
    build = time.perf_counter() - t0
    spline = jurs.ImplicitSpline(jnp.zeros(grid), jnp.ones(grid), problem.lower, problem.upper)
    # The step compiled with jurs.COMPILER_OPTIONS when asked (see run_tuned).
    options = jurs.COMPILER_OPTIONS if spec.get("compiler_options") else None
    init = time_repeated(
        jax.jit(solver.init, compiler_options=options), problem, spline, budget_s=0.5
    )
    state, _ = init["output"]

    @partial(jax.jit, compiler_options=options)
    def step(solver, problem, state):
        return solver.step(problem, state)

    state, _ = step(solver, problem, state)  # a state with moved weights
    step.clear_cache()  # so the first timed call compiles, as a user's first call does
    timed = time_repeated(step, solver, problem, state, budget_s=STEP_BUDGET_S)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    jax.block_until_ready(step(solver, problem, state))
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
    looped = time_step_loop(jax, solver, problem, state, timed["warm_s"], options)
    return {
        "build_s": build,
        **_timing(init, "init_"),
        **_timing(timed, "step_"),
        "step_page_faults": faults,
        **looped,
        "bucket_size": int(problem.local.bucket_size),
        "slots": int(problem.samples.shape[0]),
        "device": _device_name(jax),
        **_memory(base),
    }


def time_step_loop(jax, solver, problem, state, step_s: float, options=None) -> dict:
    """Steps as a solve runs them: ``k`` steps in one jitted ``fori_loop`` carrying the
    state, as the driver's loop in ``jurs.fit`` does, timed per step. A step called on its
    own returns its whole state in fresh buffers every call: NormalIPIA's state holds the
    assembled D^T D (6.4 MB at 128 x 128), copied each time, which costs it more than its
    stencil product; a loop updates its carry in place. ``k`` is chosen from the
    standalone step time ``step_s`` so that one loop takes about ``LOOP_S``."""
    import jax.numpy as jnp

    k = int(np.clip(round(LOOP_S / max(step_s, 1e-9)), LOOP_STEPS_MIN, LOOP_STEPS_MAX))

    @partial(jax.jit, static_argnums=3, compiler_options=options)
    def steps(solver, problem, state, k):
        energy = jnp.zeros((), problem.samples.dtype)
        return jax.lax.fori_loop(
            0, k, lambda _, carry: solver.step(problem, carry[0]), (state, energy)
        )

    timed = time_repeated(steps, solver, problem, state, k, budget_s=STEP_BUDGET_S)
    return {
        "loop_steps": k,
        "loop_step_warm_s": timed["warm_s"] / k,
        "loop_step_min_s": timed["min_s"] / k,
        "loop_compile_s": timed["compile_s"],
    }


def work_lstsq(spec: dict) -> dict:
    """``jurs.fit(..., solver=LeastSquares(lam))`` end to end, from NumPy points to a
    solved spline: problem building (host layout), assembly of D^T D and D^T b, solve."""
    jax, jurs = _start_jax()
    points, normals = jurs.datasets.example1(spec["m"])
    base = _baseline()
    solver = jurs.LeastSquares(lam=spec["lam"])

    def fit():  # every setting given: no automatic choices (jurs.auto_settings) in the timing
        return jurs.fit(points, normals, grid=spec["grid"], solver=solver, offset=OFFSET, eps=EPS)

    timed = time_repeated(fit, budget_s=STEP_BUDGET_S, max_repeats=10)
    sol = timed["output"]
    return {
        **_timing(timed, "fit_"),
        "result": result_name(jurs, sol),
        "E_ave": float(sol.metrics["E_ave"]),
        "device": _device_name(jax),
        **_memory(base),
    }


def work_fit_steps(spec: dict) -> dict:
    """The IURS step as it runs inside ``jurs.fit``: fits of ``1`` and ``1 + k`` steps
    (``k = spec.get("steps", FIT_STEPS)``; ``tol = 0``, so both run all their steps), end to
    end from NumPy arrays; the difference of their warm medians over ``k`` is the cost of a
    step in the fit's loop. Unlike a step called on its own, it does not include what every
    call pays once: building the problem, the init and final energy passes, and page-faulting
    the call's fresh buffers (counted here per fit call)."""
    jax, jurs = _start_jax()
    from jurs._fit import reassociates

    points, normals = jurs.datasets.example1(spec["m"])
    kwargs = {"grid": spec["grid"], "offset": OFFSET, "eps": EPS}
    # Whether jurs.fit compiles this fit with the options (the problem freed before the
    # memory baseline).
    options = reassociates(jurs.make_problem(points, normals, **kwargs), jurs.IURS())
    base = _baseline()
    fits, k = {}, spec.get("steps", FIT_STEPS)
    for steps in (1, 1 + k):
        solver = jurs.IURS(tau=1e-2, lam=1e-3, tol=0.0, max_steps=steps)
        timed = time_repeated(
            lambda: jurs.fit(points, normals, solver=solver, **kwargs), budget_s=3.0, max_repeats=7
        )
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        sol = jax.block_until_ready(jurs.fit(points, normals, solver=solver, **kwargs))
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
        assert int(sol.stats["num_steps"]) == steps
        fits[steps] = {**_timing(timed), "page_faults": faults}
    one, many = fits[1], fits[1 + k]
    return {
        "fits": {str(n): v for n, v in fits.items()},
        "steps": k,
        "step_s": (many["warm_s"] - one["warm_s"]) / k,
        "step_min_s": (many["min_s"] - one["min_s"]) / k,
        "compiler_options": options,
        "device": _device_name(jax),
        **_memory(base),
    }


def work_port(spec: dict) -> dict:
    """One step of the dense NumPy port of Algorithm 1 (after one untimed step, as for jurs)."""
    import _numpy_port as port

    import jurs.datasets

    points, normals = jurs.datasets.example1(spec["m"])
    base = _baseline()
    t0 = time.perf_counter()
    problem = port.Problem(points, normals, grid=spec["grid"], offset=OFFSET, eps=EPS)
    build = time.perf_counter() - t0
    kwargs = {"tau": 1e-2, "lam": 1e-3}
    state = port.step(problem, port.init(problem, kwargs["lam"]), **kwargs)
    timed = time_repeated(lambda: port.step(problem, state, **kwargs), budget_s=3.0, max_repeats=10)
    return {"build_s": build, **_timing(timed, "step_"), **_memory(base)}


def work_example4(spec: dict) -> dict:
    """A full regularised IURS fit to ``tol``: the first call in this fresh process (cold,
    compilation included; imports timed apart) and warm calls."""
    t0 = time.perf_counter()
    jax, jurs = _start_jax()
    import jurs.shapes  # noqa: F811 (the submodule, after the timed import)

    import_s = time.perf_counter() - t0
    points, normals = jurs.shapes.get(spec["shape"], spec["points"])
    base = _baseline()
    solver = jurs.IURS(
        tau=spec["tau"], lam=spec["lam"], tol=EXAMPLE4_TOL, max_steps=EXAMPLE4_MAX_STEPS
    )

    def fit():  # the paper's offsets (d = 0.1, eps = 0.01), every setting given
        return jurs.fit(points, normals, grid=spec["grid"], solver=solver, offset=OFFSET, eps=EPS)

    timed = time_repeated(fit, budget_s=2.0)
    sol = timed["output"]
    memory = _memory(base)  # before the pass timings below add their own compilations
    passes = None
    if spec.get("passes", True):  # the fit's problem, as jurs.fit builds it
        passes = pass_times(
            jax, jurs.make_problem(points, normals, grid=spec["grid"], offset=OFFSET, eps=EPS)
        )
    return {
        "import_s": import_s,
        "cold_s": timed["first_s"],
        **_timing(timed),
        "num_steps": int(sol.stats["num_steps"]),
        "result": result_name(jurs, sol),
        "E_ave": float(sol.metrics["E_ave"]),
        "E_max": float(sol.metrics["E_max"]),
        "passes": passes,
        "device": _device_name(jax),
        **memory,
    }


def pass_times(jax, problem, repeats: int = PASS_REPEATS) -> dict:
    """The passes over the samples that an IURS step makes, each timed alone: seconds per
    pass, the fastest of a few runs of ``repeats`` passes in one jitted loop (so no
    dispatch counts). ``F2``: W and F(wC) in one pass (jurs's kernels, as IURS calls them);
    ``F1``: F(wC) alone; ``T2``: T of two per-sample vectors (D^T r with D's column sums,
    or the two sums of the weight gradient). An IURS step makes one F2, one F1 and two T2."""
    import jax.numpy as jnp

    from jurs._spline import transpose_and_sum, values_apart

    local, shape = problem.local, problem.shape
    grids = jnp.ones((2,) + tuple(shape), problem.samples.dtype)
    vectors = jnp.ones((2, local.to_layout(problem.mask).shape[0]), grids.dtype)

    def t_pass(local, x):
        return transpose_and_sum(local, x, shape, layout=True)[0]

    def looped(fn, x):
        # Each pass feeds the next through a scalar, so none can be skipped or hoisted. The
        # layout is an argument, as in a fit: as a constant, XLA would fold it into kernels.
        def run(local, x):
            body = lambda _, x: x * (1.0 + 1e-30 * jnp.sum(fn(local, x)))
            return jax.lax.fori_loop(0, repeats, body, x)

        return time_repeated(jax.jit(run), local, x, budget_s=0.5)["min_s"] / repeats

    # F as the solver calls it: in a kernel of its own, in the kernels' layout.
    return {
        "F2_s": looped(values_apart, grids),
        "F1_s": looped(values_apart, grids[0]),
        "T2_s": looped(t_pass, vectors),
        "repeats": repeats,
    }


def refined_distances(xs, ys, values, reference, fn) -> dict:
    """Chamfer / Hausdorff of the zero set of ``fn`` (sampled as ``values`` on ``xs, ys``)
    to the reference curve, refined: no sampling floor (see
    :func:`jurs.levelset.refined_chamfer_hausdorff`).

    :func:`jurs.levelset.analyze_grid` resamples the marching-squares zero set at half a
    grid cell (0.01 at resolution 512 here), so its Chamfer distance cannot fall below about
    an eighth of a cell whatever the fit; contour points resampled densely still carry
    marching squares' own error (about 1e-5 here), under which accurate fits tie. Here the
    contour, resampled at ``REFINED_SAMPLES_PER_DIAGONAL`` points per box diagonal, is moved
    onto the zero set by Newton steps (along a spline's own gradient, central differences
    for other functions) and measured to the segments of ``REFERENCE_POINTS`` samples of
    the exact curve, and ``REFINED_REFERENCE_SAMPLES`` of those are projected onto the zero
    set."""
    import jurs.levelset as ls

    spacing = np.hypot(xs[-1] - xs[0], ys[-1] - ys[0]) / REFINED_SAMPLES_PER_DIAGONAL
    zero = [ls.resample(poly, spacing) for poly, _ in ls.contour_lines(xs, ys, values)]
    zero = np.concatenate(zero) if zero else np.empty((0, 2))
    return ls.refined_chamfer_hausdorff(
        fn, zero, reference, closed=True, reference_samples=REFINED_REFERENCE_SAMPLES
    )


def _level_set(xs, ys, values, points, reference, fn, offset=OFFSET) -> dict:
    """The level-set report (components, Chamfer at the analysis grid's floor) and the
    refined distances, for one function sampled on the common grid."""
    import jurs.levelset as ls

    out = ls.analyze_grid(xs, ys, values, points, offset=offset, reference=reference).as_dict()
    refined = refined_distances(xs, ys, values, reference, fn)
    out.update(
        {
            "refined_chamfer": refined["chamfer"],
            "refined_hausdorff": refined["hausdorff"],
            "unconverged": refined["unconverged_zero"] + refined["unconverged_reference"],
        }
    )
    return out


def work_rbf(spec: dict) -> dict:
    """RBFInterpolator (thin-plate) vs ``jurs.fit(points, normals)`` with its defaults at m
    points: fit times and the zero sets' distances to the exact curve. The RBF solves the
    offset samples and targets the defaults chose (the same 3m samples); both are sampled
    on the default fit's box and grid (the analysis of ``rbf_report``). For context, jurs
    also on the coarser grid of RBF_GRIDS with the same settings otherwise, and with
    ``RBF_GIVEN`` where ``spec["given"]``."""
    jax, jurs = _start_jax()
    from _baselines import evaluate_rbf, evaluate_rbf_grid, rbf_fit

    import jurs.levelset as ls

    points, normals = jurs.datasets.example1(spec["m"])
    reference = jurs.datasets.example1(REFERENCE_POINTS)[0]
    out = {"device": _device_name(jax)}
    timed = time_repeated(lambda: jurs.fit(points, normals), budget_s=2.0)
    settings = timed["output"].settings
    # The box does not depend on the grid, so every fit and the RBF share xs, ys.
    xs, ys, _ = ls.sampling_grid(*settings.domain, ANALYSIS_RESOLUTION)
    coarse = dict(
        grid=spec["grid"],
        offset=settings.offset,
        eps=settings.eps,
        solver=jurs.LeastSquares(lam=settings.lam),
    )

    def given(options):  # automatic settings around the given ones, timed too
        return jurs.fit(points, normals, **options)

    def measured(run):
        spline = run["output"].spline
        return {
            "grid": list(spline.shape),
            "lam": float(run["output"].metrics["lam"]),
            "offset": settings.offset,
            "eps": settings.eps,
            **_timing(run),
            **_level_set(
                xs,
                ys,
                ls.evaluate_grid(spline, xs, ys),
                points,
                reference,
                spline,
                offset=settings.offset,
            ),
        }

    out["jurs_main"] = measured(timed)
    out["jurs_coarse"] = measured(
        time_repeated(lambda: jurs.fit(points, normals, **coarse), budget_s=2.0)
    )
    if spec.get("given"):
        out["jurs_given"] = [
            {"given": options, **measured(time_repeated(lambda: given(options), budget_s=2.0))}
            for options in RBF_GIVEN
        ]
    rbf, rbf_s = rbf_fit(points, normals, offset=settings.offset, eps=settings.eps)
    t0 = time.perf_counter()
    values = evaluate_rbf_grid(rbf, xs, ys)  # the same box and grid as the jurs fits
    grid_eval_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["rbf"] = {
        "fit_s": rbf_s,
        "grid_eval_s": grid_eval_s,
        **_level_set(
            xs,
            ys,
            values,
            points,
            reference,
            lambda xy: evaluate_rbf(rbf, xy),
            offset=settings.offset,
        ),
        "analysis_s": time.perf_counter() - t0,
    }
    return out


def work_ceiling(spec: dict) -> dict:
    """The machine's attainable float64 multiply-add rate: a NumPy matrix product (BLAS,
    every core) of side ``n``, its fastest warm call."""
    n = spec["n"]
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)), rng.random((n, n))
    best = time_repeated(lambda: a @ b, budget_s=1.0)["min_s"]
    return {"n": n, "seconds": best, "macs_per_s": n**3 / best}


WORKERS = {
    "step": work_step,
    "fit_steps": work_fit_steps,
    "lstsq": work_lstsq,
    "port": work_port,
    "example4": work_example4,
    "rbf": work_rbf,
    "ceiling": work_ceiling,
}


def worker_main(spec_json: str) -> None:
    """Entry point of a measuring subprocess: one JSON result line on stdout."""
    sys.path.insert(0, HERE)
    spec = json.loads(spec_json)
    result = WORKERS[spec["kind"]](spec)
    print("RESULT " + json.dumps(result), flush=True)


# --------------------------------------------------------------------------- orchestration


def run_worker(spec: dict, log, env: dict | None = None) -> dict:
    """Run one measurement in a fresh Python process (with ``env`` added to this one's
    environment); ``{"error": ...}`` if it fails."""
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(spec)],
            capture_output=True,
            text=True,
            timeout=WORKER_TIMEOUT_S,
            cwd=HERE,
            env={**os.environ, **(env or {})},
        )
    except subprocess.TimeoutExpired:
        result = {"error": f"timed out after {WORKER_TIMEOUT_S} s"}
    else:
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if proc.returncode == 0 and lines:
            result = json.loads(lines[-1][len("RESULT ") :])
        else:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            result = {"error": f"exit {proc.returncode}: " + " | ".join(tail)}
    log(
        f"{time.perf_counter() - t0:6.1f} s  {json.dumps(spec)}"
        + (f" {env}" if env else "")
        + (f"  ERROR {result['error']}" if "error" in result else "")
    )
    return result


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
    sys.path.insert(0, HERE)
    import _numpy_port as port

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
            {"kind": "rbf", "m": m, "grid": RBF_GRIDS[m], "given": m == TARGET_RBF_POINTS}, log
        )
        rows.append({"m": m, "grid": RBF_GRIDS[m], **res})
        last = (m, res)
    return rows


def run_tuned(log) -> dict:
    """The IURS step and the exact solve at the target size again, in ``HUGEPAGE_ENV``; and
    the step compiled with ``jurs.COMPILER_OPTIONS`` (as ``jurs.fit`` compiles large
    problems), without and with it."""
    step = {"kind": "step", "m": TARGET_POINTS, "grid": TARGET_GRID, "solver": "iurs"}
    lstsq = {"kind": "lstsq", "m": TARGET_POINTS, "grid": TARGET_GRID, "lam": LSQ_LAM}
    return {
        "env": HUGEPAGE_ENV,
        "iurs": run_worker(step, log, HUGEPAGE_ENV),
        "lstsq": run_worker(lstsq, log, HUGEPAGE_ENV),
        "iurs_options": run_worker({**step, "compiler_options": True}, log),
        "iurs_both": run_worker({**step, "compiler_options": True}, log, HUGEPAGE_ENV),
    }


def run_fit_steps(log) -> dict:
    """The IURS step inside ``jurs.fit`` at the target size, as it is and in ``HUGEPAGE_ENV``."""
    spec = {"kind": "fit_steps", "m": TARGET_POINTS, "grid": TARGET_GRID}
    return {
        "env": HUGEPAGE_ENV,
        "default": run_worker(spec, log),
        "hugepages": run_worker(spec, log, HUGEPAGE_ENV),
    }


def run_example4(log, runs: int = EXAMPLE4_RUNS) -> list[dict]:
    """Each Example-4 fit in ``runs`` fresh processes (the passes timed in the first only):
    a cold time is one sample a process, and on a shared machine one sample is noise. The
    row keeps the first run's numbers with the median cold and warm times over the runs
    (and every run's in ``cold_runs_s`` / ``warm_runs_s``). Then ``runs`` more processes
    share JAX's persistent compilation cache, filled by one process before them: their
    cold times are ``cold_cached_runs_s``, the first call of a process that loads the
    compiled fit instead of compiling it."""
    rows = []
    for cfg in EXAMPLE4:
        results = [
            run_worker({"kind": "example4", **cfg, "passes": i == 0}, log) for i in range(runs)
        ]
        ok = [r for r in results if "error" not in r]
        row = {**cfg, **(ok[0] if ok else results[0])}
        if ok:
            row["cold_runs_s"] = [r["cold_s"] for r in ok]
            row["warm_runs_s"] = [r["warm_s"] for r in ok]
            row["cold_s"] = float(np.median(row["cold_runs_s"]))
            row["warm_s"] = float(np.median(row["warm_runs_s"]))
            row["min_s"] = min(r["min_s"] for r in ok)
        with tempfile.TemporaryDirectory(prefix="jurs-compilation-cache-") as cache:
            # Every compilation kept, however short (JAX's default keeps those above 1 s).
            env = {
                "JAX_COMPILATION_CACHE_DIR": cache,
                "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            }
            spec = {"kind": "example4", **cfg, "passes": False}
            filled = "error" not in run_worker(spec, log, env)
            # Without a filled cache the next process would compile: no cached time then.
            cached = (
                [
                    r["cold_s"]
                    for r in (run_worker(spec, log, env) for _ in range(runs))
                    if "error" not in r
                ]
                if filled
                else []
            )
        if cached:
            row["cold_cached_runs_s"] = cached
            row["cold_cached_s"] = float(np.median(cached))
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- main


def rerender(path: str) -> None:
    """Targets and markdown again from saved measurements (no measuring), rewritten beside
    ``path`` (:func:`_common.rerender_beside`)."""

    def render(data):
        data["bounds"] = arithmetic_bounds(data["sweep"], data["example4"], data.get("ceiling"))
        data["targets"] = evaluate_targets(
            data["sweep"],
            data["rbf"],
            data["example4"],
            data["bounds"],
            data.get("tuned"),
            data.get("fit_steps"),
        )
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
        help="re-render the report (and the targets) from a results JSON",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker_main(args.worker)
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
    bounds = arithmetic_bounds(sweep, example4, ceiling)
    data = {
        "quick": args.quick,
        "machine": machine(),
        "device": _device_name(jax),
        "sweep_config": {str(m): list(g) for m, g in sweep_config.items()},  # JSON keys
        "targets": evaluate_targets(sweep, rbf, example4, bounds, tuned, fit_steps),
        "sweep": sweep,
        "port": port,
        "rbf": rbf,
        "example4": example4,
        "tuned": tuned,
        "fit_steps": fit_steps,
        "ceiling": ceiling,
        "ceiling_start": ceiling_start,
        "bounds": bounds,
        "load_average": load_average,
        "runtime_s": time.perf_counter() - start,
    }
    text = report(data)
    print(text)
    write_results("speed_quick" if args.quick else "speed", data, text)


if __name__ == "__main__":
    main()
