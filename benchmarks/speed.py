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

# The timer and the result files live in _common (next to this script, which is on
# sys.path when it runs; it imports no JAX: each worker starts JAX itself).
from _common import (  # noqa: E402
    LONG_CALL_S,
    elapsed_log,
    machine,
    rerender_beside,
    time_repeated,
    write_results,
)

# --------------------------------------------------------------------------- settings

#: Sweep: points m -> grids (N = M). Fine grids on few points are pruned (with 3m samples
#: far below N*M coefficients the fit is mostly undetermined and says nothing new about
#: speed), and so is part of the rest, to keep the whole run near 30 minutes on 2 cores.
FULL_SWEEP = {
    100: (8, 16, 32),
    1_000: (8, 16, 32, 64),
    10_000: (16, 32, 64, 128),
    100_000: (16, 32, 64, 128, 256),
    1_000_000: (8, 32, 128, 256),  # 8: the only grid where the dense NumPy port fits at 1e6
}
QUICK_SWEEP = {1_000: (16,), 10_000: (128,)}

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

#: The dense port runs where one 3m x NM float64 matrix is at most this big (B and D, and
#: the temporaries of a step, are each this size).
DENSE_LIMIT_BYTES = 2 * 10**9

#: RBF comparison: points -> a coarser jurs grid, shown for context beside the defaults
#: (which choose their own grid, at most 96 a side).
RBF_GRIDS = {100: 16, 300: 24, 1_000: 32, 2_000: 48, 5_000: 64}
QUICK_RBF_POINTS = (300,)
#: Skip the next RBF size when its fit is predicted (O(m^3) from the last one) to exceed this.
RBF_MAX_PREDICTED_S = 150.0
#: Grid resolution of the zero-set analysis (the same for jurs and the RBF).
ANALYSIS_RESOLUTION = 512
#: Dense samples of the exact Example 1 curve (spacing about 3e-5), the Chamfer reference.
REFERENCE_POINTS = 1_000_000
#: The refined distances (see refined_distances): zero-set samples along the contour, at
#: this many per box diagonal, and reference points projected onto the zero set. Every
#: sample costs the RBF 15 evaluations (3 Newton rounds of a value and a central-difference
#: gradient), 10 s at 5000 points.
REFINED_SAMPLES_PER_DIAGONAL = 2000
REFINED_REFERENCE_SAMPLES = 2000
OFFSET, EPS = 0.1, 0.01

#: The Example-4-size full fit: a 640-point closed shape, 15 x 15, regularised IURS to tol.
#: The paper's Example 4 settings (its lambda, 1.155 s in its Table 2) on the project's
#: stand-in shape, and a smaller lambda on a smooth shape, which converges ten times slower.
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

#: Side of the float64 matrix product that measures the machine's multiply-add rate.
CEILING_N = 2000

#: An environment in which glibc's malloc asks for transparent huge pages (glibc >= 2.35,
#: Linux THP in "madvise" or "always" mode). XLA's CPU buffers come from malloc; with 4 KB
#: pages every step of a large problem page-faults its fresh buffers in again. The large
#: problem's measurements are repeated in it (the library itself cannot set it: glibc
#: reads it at process start).
HUGEPAGE_ENV = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}

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
    """The numbers of :func:`time_repeated`, keys prefixed, without the output."""
    return {prefix + k: v for k, v in t.items() if k != "output"}


def result_name(jurs, sol) -> str:
    """The short name of ``sol.result`` (``successful``, ``max_steps_reached``, ...)."""
    return sol.status


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


# --------------------------------------------------------------------------- report


def _find(rows, **keys):
    for r in rows:
        if all(r.get(k) == v for k, v in keys.items()):
            return r
    return None


def _env_text(env: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in env.items())


def step_passes_s(ex4) -> float | None:
    """Seconds of one IURS step's passes over the samples, each timed alone
    (:func:`pass_times`): one F2, one F1 and two T2."""
    p = ex4.get("passes")
    return p["F2_s"] + p["F1_s"] + 2 * p["T2_s"] if p else None


def passes_floor_s(ex4) -> float | None:
    """The fit's steps times :func:`step_passes_s`: what jurs's kernels for the passes
    alone take over the fit, with no bookkeeping, dispatch or metrics."""
    step = step_passes_s(ex4)
    return step * ex4["num_steps"] if step is not None and "num_steps" in ex4 else None


def _given_label(options: dict, code: bool = False) -> str:
    q = "`" if code else ""
    return ", ".join(f"{q}{k}={v:g}{q}" for k, v in options.items())


def _ms(s):
    """Seconds as ms below one second (3 significant digits)."""
    return "—" if s is None else (f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s")


def _range(runs) -> str:
    """``low-high`` of a list of per-process times."""
    return f"{_s(min(runs))}-{_s(max(runs))}"


def _us(s):
    return "—" if s is None else f"{s * 1e6:.3g} us"


def _s(s):
    return "—" if s is None else f"{s:.3g} s"


def _gb(b):
    if b is None:
        return "—"
    return f"{b / 2**30:.2f} GiB" if abs(b) >= 2**30 else f"{b / 2**20:.0f} MiB"


def _x(ratio):
    """A speed ratio: 2 significant digits, so that 0.61x does not print as 1x."""
    return "—" if ratio is None else f"{ratio:.2g}x" if ratio < 100 else f"{ratio:.0f}x"


def _table(header, rows):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _err(res):
    return f"error: {res['error'][:80]}" if "error" in res else None


def _grid(grid) -> str:
    """``128`` -> ``128x128``; ``(92, 96)`` -> ``92x96``."""
    return "x".join(map(str, grid)) if isinstance(grid, (list, tuple)) else f"{grid}x{grid}"


def _where(r) -> list:
    """The m and grid cells of a sweep row."""
    return [f"{r['m']:.0e}", _grid(r["grid"])]


def _measured_row(cells, res, width: int, values) -> list:
    """``cells``, then ``values()`` (``width`` cells), or ``res``'s error padded to ``width``."""
    return cells + ([_err(res)] + [""] * (width - 1) if _err(res) else values())


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
                _measured_row(
                    _where(r),
                    res,
                    7 + len(extra),
                    lambda: (
                        [
                            f"{_ms(res['step_warm_s'])} ({_ms(res['step_min_s'])})",
                            f"{_ms(res['loop_step_warm_s'])} ({_ms(res['loop_step_min_s'])})",
                            res["loop_steps"],
                            _s(res["step_compile_s"]),
                            _gb(res["peak_over_base_b"]),
                            _gb(res["peak_b"]),
                            _s(res["build_s"]),
                        ]
                        + ([_ms(res["init_warm_s"]), _s(res["init_first_s"])] if extra else [])
                    ),
                )
            )
        lines += [f"## {label}: one step", ""]
        lines += _table(
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
            _measured_row(
                _where(r),
                res,
                6,
                lambda: [
                    f"{_s(res['fit_warm_s'])} ({_s(res['fit_min_s'])})",
                    _s(res["fit_first_s"]),
                    _gb(res["peak_over_base_b"]),
                    _gb(res["peak_b"]),
                    res.get("result", "—"),
                    f"{res['E_ave']:.2e}",
                ],
            )
        )
    lines += [f"## LeastSquares(lam={LSQ_LAM:g}) end to end through jurs.fit", ""]
    lines += _table(
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
        "(its iterates equal jurs.IURS's: `tests/test_numpy_port.py`). Same tau = 1e-2, "
        f"lam = 1e-3. Run where one dense matrix is <= {DENSE_LIMIT_BYTES / 1e9:g} GB.",
        "",
    ]
    rows = []
    for r in port_rows:
        p = r["port"]
        rows.append(
            _measured_row(
                _where(r) + [_gb(r["dense_b"])],
                p,
                5,
                lambda: [
                    _s(p["build_s"]),
                    _ms(p["step_warm_s"]),
                    _ms(r["jurs_iurs_step_s"]),
                    _x(r["ratio"]),
                    _gb(p["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(
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
        if not _err(r) and "skipped" not in r
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
        if _err(r) or "skipped" in r:
            rows.append([r["m"], _err(r) or f"skipped: {r['skipped']}"] + [""] * 10)
            continue
        j, b, c = r["jurs_main"], r["rbf"], r["jurs_coarse"]
        rows.append(
            [
                r["m"],
                _grid(j["grid"]),
                f"{j['offset']:.3g}",
                _s(b["fit_s"]),
                _ms(j["warm_s"]),
                _s(j["first_s"]),
                f"{_x(b['fit_s'] / j['warm_s'])} / {_x(b['fit_s'] / j['first_s'])}",
                f"{j['refined_chamfer']:.2e} / {b['refined_chamfer']:.2e}",
                f"{j['refined_hausdorff']:.2e} / {b['refined_hausdorff']:.2e}",
                f"{j['chamfer']:.2e} / {b['chamfer']:.2e}",
                f"{j['num_components']}/{j['num_supplementary']} vs "
                f"{b['num_components']}/{b['num_supplementary']}",
                f"{_grid(c['grid'])}: {c['refined_chamfer']:.2e}, "
                f"{c['num_components']}/{c['num_supplementary']}, {_ms(c['warm_s'])} "
                f"({_x(b['fit_s'] / c['warm_s'])})",
            ]
        )
    lines += _table(
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
        if not r.get("jurs_given") or _err(r):
            continue
        b = r["rbf"]
        lines += [
            "",
            f"At m = {r['m']}, jurs with settings given (the rest automatic, timed "
            "too): finer grids and smoothings far below the default. Such smoothings "
            "grow supplementary components on glyphs and traced outlines "
            "(`benchmarks/results/smoothing.md`), so the defaults do not use them. "
            f"The RBF: refined Chamfer {b['refined_chamfer']:.2e}, Hausdorff "
            f"{b['refined_hausdorff']:.2e}, fit {_s(b['fit_s'])}.",
            "",
        ]
        rows = [
            [
                _given_label(e["given"], code=True),
                _grid(e["grid"]),
                f"{e['lam']:.3g}",
                _ms(e["warm_s"]),
                _x(b["fit_s"] / e["warm_s"]),
                f"{e['refined_chamfer']:.2e} ({_x(e['refined_chamfer'] / b['refined_chamfer'])})",
                f"{e['refined_hausdorff']:.2e}",
                f"{e['num_components']}/{e['num_supplementary']}",
            ]
            for e in r["jurs_given"]
        ]
        lines += _table(
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
        cells = [r["label"], _grid(r["grid"]), f"{r['tau']:g}", f"{r['lam']:g}"]
        runs = r.get("cold_runs_s") or []
        cached_runs = r.get("cold_cached_runs_s") or []
        cached = f"{_s(r['cold_cached_s'])} ({_range(cached_runs)})" if cached_runs else "—"
        rows.append(
            _measured_row(
                cells,
                r,
                8,
                lambda: [
                    r["num_steps"],
                    r["result"],
                    f"{_ms(r['warm_s'])} ({_ms(r['min_s'])})",
                    _s(r["cold_s"]),
                    _range(runs) if runs else "—",
                    cached,
                    _s(r["import_s"]),
                    f"{r['E_ave']:.2e}",
                ],
            )
        )
    lines += _table(
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
            _us(r["passes"]["F2_s"]),
            _us(r["passes"]["F1_s"]),
            _us(r["passes"]["T2_s"]),
            _us(step_passes_s(r)),
            _us(r["warm_s"] / r["num_steps"]),
            _ms(passes_floor_s(r)),
            _ms(r["warm_s"]),
        ]
        for r in timed
    ]
    lines += _table(
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
    big = _find(sweep, m=LARGE_POINTS, grid=LARGE_GRID)
    if not tuned or not big:
        return []
    env = _env_text(tuned["env"])
    lines = [
        "## Large problems: huge pages and compiler options",
        "",
        f"The same workers at {LARGE_POINTS:.0e} points, {_grid(LARGE_GRID)}. "
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
        _measured_row(
            [name],
            r,
            3,
            lambda r=r: [
                f"{_ms(r['step_warm_s'])} ({_ms(r['step_min_s'])})",
                r.get("step_page_faults", "—"),
                _gb(r["peak_over_base_b"]),
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
            _measured_row(
                [name],
                r,
                3,
                lambda r=r: [
                    f"{_s(r['fit_warm_s'])} ({_s(r['fit_min_s'])})",
                    "—",
                    _gb(r["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(["measurement", "warm (min)", "page faults", "peak over base"], rows)
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
            _measured_row(
                [name],
                r,
                7,
                lambda r=r: [
                    "yes" if r["compiler_options"] else "no",
                    r["steps"],
                    f"{_ms(r['step_s'])} ({_ms(r['step_min_s'])})",
                    _ms(r["fits"]["1"]["warm_s"]),
                    _ms(r["fits"][str(1 + r["steps"])]["warm_s"]),
                    f"{r['fits']['1']['page_faults']} / "
                    f"{r['fits'][str(1 + r['steps'])]['page_faults']}",
                    _gb(r["peak_over_base_b"]),
                ],
            )
        )
    lines += _table(
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
    (:func:`_common.rerender_beside`). Verdicts an older run saved (``targets``,
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
    data = {
        "date": time.strftime("%Y-%m-%d"),
        "quick": args.quick,
        "machine": machine(),
        "device": _device_name(jax),
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
