"""The measurements of ``benchmarks/speed.py`` and ``benchmarks/gpu_speed.py``: the workers,
each run in a fresh process (``run_worker`` starts ``python -m benchmarks._speed_workers
--worker SPEC`` in the repository root, which prints one ``RESULT`` JSON line), the settings
both scripts measure with, and the Example-4 orchestration both run.

A worker's peak resident set size (VmHWM) belongs to that measurement alone. This module
imports no JAX at module level: each worker starts JAX itself.
"""

from __future__ import annotations

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

from ._common import time_repeated

#: The repository root: a worker runs there as ``python -m benchmarks._speed_workers``.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# --------------------------------------------------------------------------- settings

#: Solvers of the step sweep: (key, label, constructor name and keyword arguments).
STEP_SOLVERS = {
    "iurs": ("IURS (tau=1e-2, lam=1e-3)", "IURS", {"tau": 1e-2, "lam": 1e-3}),
    "ipia": ("IPIA", "IPIA", {}),
    "normal_ipia": ("NormalIPIA", "NormalIPIA", {}),
}
#: The exact solve's objective lambda (sweep and RBF comparison).
LSQ_LAM = 1e-4
#: The large problem of the huge-page, compiler-option and in-fit step measurements.
LARGE_POINTS, LARGE_GRID = 1_000_000, 128

#: Grid resolution of the zero-set analysis (the same for jurs and the RBF).
ANALYSIS_RESOLUTION = 512
#: Dense samples of the exact Example 1 curve (spacing about 3e-5), the Chamfer reference.
REFERENCE_POINTS = 1_000_000
#: The refined distances (see refined_distances): zero-set samples along the contour, at
#: this many per box diagonal, and reference points projected onto the zero set. Every
#: sample costs the RBF 15 evaluations (3 Newton rounds of a value and a central-difference
#: gradient), each a sum over its 3m centres: these counts bound the RBF's analysis time.
REFINED_SAMPLES_PER_DIAGONAL = 2000
REFINED_REFERENCE_SAMPLES = 2000
OFFSET, EPS = 0.1, 0.01

#: The Example-4-size full fit: a 640-point closed shape, 15 x 15, regularised IURS to tol.
#: The paper's Example 4 settings (its lambda, 1.155 s in its Table 2) on the project's
#: stand-in shape, and a smaller lambda on a smooth shape, which takes many more steps.
EXAMPLE4 = [
    {
        "label": "paper's Example 4: glyph_B, 639 pts",
        "shape": "glyph_B",
        "points": 639,
        "grid": 15,
        "tau": 1e-3,
        "lam": 0.0216,
    },
    {
        "label": "lobes, 640 pts",
        "shape": "lobes",
        "points": 640,
        "grid": 15,
        "tau": 1e-3,
        "lam": 2e-3,
    },
]
EXAMPLE4_TOL, EXAMPLE4_MAX_STEPS = 1e-7, 20_000
#: Fresh processes each Example-4 fit runs in (median cold and warm times over them).
EXAMPLE4_RUNS = 3

#: The RBF comparison at GIVEN_RBF_POINTS also runs jurs with these settings given (the
#: rest automatic): finer grids and smoothings far below the default, the way towards an
#: exact interpolant's accuracy on a smooth curve, but unsafe as defaults
#: (benchmarks/smoothing.py measures why).
GIVEN_RBF_POINTS = 5_000
RBF_GIVEN = [
    {"grid": 64, "smoothing": 1e-10},
    {"grid": 128, "smoothing": 1e-10},
    {"grid": 128, "smoothing": 1e-13},
    {"grid": 256, "smoothing": 1e-13},
]

WORKER_TIMEOUT_S = 900
#: Steps a fit runs beyond its first in the in-fit step measurement (work_fit_steps).
FIT_STEPS = 20
#: The step sweep also times steps in one jitted loop (time_step_loop): as many steps as
#: take about LOOP_S seconds by the standalone step time, within these bounds.
LOOP_S, LOOP_STEPS_MIN, LOOP_STEPS_MAX = 0.05, 5, 200
#: Passes a jitted loop runs when pass_times times one pass over the samples.
PASS_REPEATS = 2000
#: Seconds of warm repeats per timed call (at least 3 repeats, see time_repeated).
STEP_BUDGET_S = 1.5


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
    """The numbers of ``time_repeated``, keys prefixed, without the output."""
    return {prefix + k: v for k, v in t.items() if k != "output"}


def result_name(jurs, sol) -> str:
    """The short name of ``sol.result`` (``successful``, ``max_steps_reached``, ...)."""
    return sol.status


def device_name(jax) -> str:
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
        "device": device_name(jax),
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
        "device": device_name(jax),
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
    from jurs._fit.call import reassociates

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
        "device": device_name(jax),
        **_memory(base),
    }


def work_port(spec: dict) -> dict:
    """One step of the dense NumPy port of Algorithm 1 (after one untimed step, as for jurs)."""
    import jurs.datasets

    from . import _numpy_port as port

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
        "device": device_name(jax),
        **memory,
    }


def pass_times(jax, problem, repeats: int = PASS_REPEATS) -> dict:
    """The passes over the samples that an IURS step makes, each timed alone: seconds per
    pass, the fastest of a few runs of ``repeats`` passes in one jitted loop (so no
    dispatch counts). ``F2``: W and F(wC) in one pass (jurs's kernels, as IURS calls them);
    ``F1``: F(wC) alone; ``T2``: T of two per-sample vectors (D^T r with D's column sums,
    or the two sums of the weight gradient). An IURS step makes one F2, one F1 and two T2."""
    import jax.numpy as jnp

    from jurs._model.spline import transpose_and_sum, values_apart

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
    [`jurs.levelset.refined_chamfer_hausdorff`][]).

    [`jurs.levelset.analyze_grid`][] resamples the marching-squares zero set at half a
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
    import jurs.levelset as ls

    from ._baselines import evaluate_rbf, evaluate_rbf_grid, rbf_fit

    points, normals = jurs.datasets.example1(spec["m"])
    reference = jurs.datasets.example1(REFERENCE_POINTS)[0]
    out = {"device": device_name(jax)}
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
            [sys.executable, "-m", "benchmarks._speed_workers", "--worker", json.dumps(spec)],
            capture_output=True,
            text=True,
            timeout=WORKER_TIMEOUT_S,
            cwd=ROOT,
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


def step_passes_s(ex4) -> float | None:
    """Seconds of one IURS step's passes over the samples, each timed alone
    (``pass_times``): one F2, one F1 and two T2."""
    p = ex4.get("passes")
    return p["F2_s"] + p["F1_s"] + 2 * p["T2_s"] if p else None


def passes_floor_s(ex4) -> float | None:
    """The fit's steps times ``step_passes_s``: what jurs's kernels for the passes
    alone take over the fit, with no bookkeeping, dispatch or metrics."""
    step = step_passes_s(ex4)
    return step * ex4["num_steps"] if step is not None and "num_steps" in ex4 else None


if __name__ == "__main__":
    if sys.argv[1:2] != ["--worker"] or len(sys.argv) != 3:
        sys.exit("usage: python -m benchmarks._speed_workers --worker SPEC (run by run_worker)")
    worker_main(sys.argv[2])
