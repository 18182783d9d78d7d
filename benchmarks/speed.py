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
import time
from functools import partial

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))

# --------------------------------------------------------------------------- configuration

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
#: The exact solve's objective lambda (sweep, RBF comparison and target).
LSQ_LAM = 1e-4

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
    {"label": "paper's Example 4: glyph_B, 639 pts", "shape": "glyph_B", "points": 639,
     "grid": 15, "tau": 1e-3, "lam": 0.0216},
    {"label": "lobes, 640 pts", "shape": "lobes", "points": 640, "grid": 15,
     "tau": 1e-3, "lam": 2e-3},
]
EXAMPLE4_TOL, EXAMPLE4_MAX_STEPS = 1e-7, 20_000
#: Fresh processes each Example-4 fit runs in (median cold and warm times over them).
EXAMPLE4_RUNS = 3

#: Targets (seconds, bytes, ratios). The values are requirements, not measurements.
TARGET_IURS_STEP_S = 0.040  # IURS step at 1e6 points / 128 x 128
TARGET_IURS_PEAK_B = 2 * 2**30  # its peak memory (above the post-import baseline)
TARGET_NORMAL_STEP_S = 0.002  # NormalIPIA step at 128 x 128, any m
TARGET_LSQ_S = 1.5  # LeastSquares end to end at 1e6 / 128 x 128, warm
TARGET_EX4_WARM_S, TARGET_EX4_COLD_S = 0.012, 1.5
TARGET_RBF_RATIO, TARGET_RBF_POINTS = 100.0, 5_000
#: "Equal" Chamfer: within this relative margin of the RBF's (the refined distances of
#: refined_distances).
CHAMFER_TOLERANCE = 0.05
TARGET_POINTS, TARGET_GRID = 1_000_000, 128

#: Lower bound on an IURS step's arithmetic: it applies the collocation D (eq. 23) or its
#: transpose at least this many times, 16 multiply-adds a sample each (see bounds_table).
IURS_STEP_PASSES, MACS_PER_PASS = 6, 16
#: Side of the float64 matrix product that measures the machine's multiply-add rate.
CEILING_N = 2000

#: An environment in which glibc's malloc asks for transparent huge pages (glibc >= 2.35,
#: Linux THP in "madvise" or "always" mode). XLA's CPU buffers come from malloc; with 4 KB
#: pages every step of a large problem page-faults its fresh buffers in again. The target
#: measurements are repeated in it (the library itself cannot set it: glibc reads it at
#: process start).
HUGEPAGE_ENV = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}

#: The RBF comparison at TARGET_RBF_POINTS also runs jurs with these settings given (the
#: rest automatic): finer grids and smoothings far below the default, the way towards an
#: exact interpolant's accuracy on a smooth curve, but unsafe as defaults
#: (benchmarks/smoothing.py measures why). The target's verdict takes the fastest of them
#: that is as accurate as the RBF.
RBF_GIVEN = [{"grid": 64, "smoothing": 1e-10}, {"grid": 128, "smoothing": 1e-10},
             {"grid": 128, "smoothing": 1e-13}, {"grid": 256, "smoothing": 1e-13}]

WORKER_TIMEOUT_S = 900
#: A first call slower than this gets a single warm repeat (LeastSquares at 256 x 256).
LONG_CALL_S = 20.0
#: Steps a fit runs beyond its first in the in-fit step measurement (work_fit_steps).
FIT_STEPS = 20
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


def time_repeated(fn, *args, budget_s: float = 2.0, max_repeats: int = 20) -> dict:
    """Time ``fn(*args)``: one first call (compiling, if ``fn`` is jitted), then warm calls
    until ``budget_s`` is spent, at least 3 and at most ``max_repeats``, fewer when a call
    is slow (2 after a first call above ``budget_s``, 1 after one above ``LONG_CALL_S``)
    so that slow configurations do not take minutes each.

    Returns ``{"first_s", "warm_s" (median), "min_s", "compile_s" (first - warm, >= 0),
    "repeats", "output"}``; the minimum shows the uncontended speed on a shared machine.
    """
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    min_repeats = 1 if first > LONG_CALL_S else 2 if first > budget_s else 3
    times = []
    while len(times) < max_repeats and (len(times) < min_repeats or sum(times) < budget_s):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    warm = float(np.median(times))
    return {"first_s": first, "warm_s": warm, "min_s": min(times),
            "compile_s": max(first - warm, 0.0), "repeats": len(times), "output": out}


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
    init = time_repeated(jax.jit(solver.init, compiler_options=options), problem, spline,
                         budget_s=0.5)
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
    return {"build_s": build, **_timing(init, "init_"), **_timing(timed, "step_"),
            "step_page_faults": faults,
            "bucket_size": int(problem.local.bucket_size),
            "slots": int(problem.samples.shape[0]), "device": _device_name(jax),
            **_memory(base)}


def work_lstsq(spec: dict) -> dict:
    """``jurs.fit(..., solver=LeastSquares(lam))`` end to end, from NumPy points to a
    solved spline: problem building (host layout), assembly of D^T D and D^T b, solve."""
    jax, jurs = _start_jax()
    points, normals = jurs.datasets.example1(spec["m"])
    base = _baseline()
    solver = jurs.LeastSquares(lam=spec["lam"])

    def fit():  # every setting given: no automatic choices (jurs.auto_settings) in the timing
        return jurs.fit(points, normals, grid=spec["grid"], solver=solver, offset=OFFSET,
                        eps=EPS)

    timed = time_repeated(fit, budget_s=STEP_BUDGET_S, max_repeats=10)
    sol = timed["output"]
    return {**_timing(timed, "fit_"), "result": result_name(jurs, sol),
            "E_ave": float(sol.metrics["E_ave"]), "device": _device_name(jax),
            **_memory(base)}


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
        timed = time_repeated(lambda: jurs.fit(points, normals, solver=solver, **kwargs),
                              budget_s=3.0, max_repeats=7)
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        sol = jax.block_until_ready(jurs.fit(points, normals, solver=solver, **kwargs))
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
        assert int(sol.stats["num_steps"]) == steps
        fits[steps] = {**_timing(timed), "page_faults": faults}
    one, many = fits[1], fits[1 + k]
    return {"fits": {str(n): v for n, v in fits.items()}, "steps": k,
            "step_s": (many["warm_s"] - one["warm_s"]) / k,
            "step_min_s": (many["min_s"] - one["min_s"]) / k,
            "compiler_options": options,
            "device": _device_name(jax), **_memory(base)}


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
    timed = time_repeated(lambda: port.step(problem, state, **kwargs), budget_s=3.0,
                          max_repeats=10)
    return {"build_s": build, **_timing(timed, "step_"), **_memory(base)}


def work_example4(spec: dict) -> dict:
    """A full regularised IURS fit to ``tol``: the first call in this fresh process (cold,
    compilation included; imports timed apart) and warm calls."""
    t0 = time.perf_counter()
    jax, jurs = _start_jax()
    import jurs.shapes

    import_s = time.perf_counter() - t0
    points, normals = jurs.shapes.get(spec["shape"], spec["points"])
    base = _baseline()
    solver = jurs.IURS(tau=spec["tau"], lam=spec["lam"], tol=EXAMPLE4_TOL,
                       max_steps=EXAMPLE4_MAX_STEPS)

    def fit():  # the paper's offsets (d = 0.1, eps = 0.01), every setting given
        return jurs.fit(points, normals, grid=spec["grid"], solver=solver, offset=OFFSET,
                        eps=EPS)

    timed = time_repeated(fit, budget_s=2.0)
    sol = timed["output"]
    memory = _memory(base)  # before the pass timings below add their own compilations
    passes = None
    if spec.get("passes", True):  # the fit's problem, as jurs.fit builds it
        passes = pass_times(jax, jurs.make_problem(points, normals, grid=spec["grid"],
                                                   offset=OFFSET, eps=EPS))
    return {"import_s": import_s, "cold_s": timed["first_s"], **_timing(timed),
            "num_steps": int(sol.stats["num_steps"]), "result": result_name(jurs, sol),
            "E_ave": float(sol.metrics["E_ave"]), "E_max": float(sol.metrics["E_max"]),
            "passes": passes, "device": _device_name(jax), **memory}


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
    return {"F2_s": looped(values_apart, grids), "F1_s": looped(values_apart, grids[0]),
            "T2_s": looped(t_pass, vectors), "repeats": repeats}


def refined_distances(xs, ys, values, reference, fn, grad=None) -> dict:
    """Chamfer / Hausdorff of the zero set of ``fn`` (sampled as ``values`` on ``xs, ys``)
    to the reference curve, refined: no sampling floor (see
    :func:`jurs.levelset.refined_chamfer_hausdorff`).

    :func:`jurs.levelset.analyze_grid` resamples the marching-squares zero set at half a
    grid cell (0.01 at resolution 512 here), so its Chamfer distance cannot fall below about
    an eighth of a cell whatever the fit; contour points resampled densely still carry
    marching squares' own error (about 1e-5 here), under which accurate fits tie. Here the
    contour, resampled at ``REFINED_SAMPLES_PER_DIAGONAL`` points per box diagonal, is moved
    onto the zero set by Newton steps (``grad``: the gradient, default central differences)
    and measured to the segments of ``REFERENCE_POINTS`` samples of the exact curve, and
    ``REFINED_REFERENCE_SAMPLES`` of those are projected onto the zero set."""
    import jurs.levelset as ls

    spacing = np.hypot(xs[-1] - xs[0], ys[-1] - ys[0]) / REFINED_SAMPLES_PER_DIAGONAL
    zero = [ls.resample(poly, spacing) for poly, _ in ls.contour_lines(xs, ys, values)]
    zero = np.concatenate(zero) if zero else np.empty((0, 2))
    return ls.refined_chamfer_hausdorff(fn, zero, reference, grad=grad, closed=True,
                                        reference_samples=REFINED_REFERENCE_SAMPLES)


def _level_set(xs, ys, values, points, reference, fn, grad=None, offset=OFFSET) -> dict:
    """The level-set report (components, Chamfer at the analysis grid's floor) and the
    refined distances, for one function sampled on the common grid."""
    import jurs.levelset as ls

    out = ls.analyze_grid(xs, ys, values, points, offset=offset, reference=reference).as_dict()
    refined = refined_distances(xs, ys, values, reference, fn, grad)
    out.update({"refined_chamfer": refined["chamfer"],
                "refined_hausdorff": refined["hausdorff"],
                "unconverged": refined["unconverged_zero"] + refined["unconverged_reference"]})
    return out


def _spline_functions(jax, spline):
    """``(values, gradients)`` of a fitted spline at ``(n, 2)`` NumPy points, jitted."""
    import equinox as eqx

    value = eqx.filter_jit(lambda s, xy: s(xy))
    gradient = eqx.filter_jit(lambda s, xy: s.grad(xy))
    return (lambda xy: np.asarray(value(spline, xy)),
            lambda xy: np.asarray(gradient(spline, xy)))


def work_rbf(spec: dict) -> dict:
    """RBFInterpolator (thin-plate) vs ``jurs.fit(points, normals)`` with its defaults at m
    points: fit times and the zero sets' distances to the exact curve. The RBF solves the
    offset samples and targets the defaults chose (the same 3m samples); both are sampled
    on the default fit's box and grid (the analysis of ``rbf_report``). For context, jurs
    also on the coarser grid of RBF_GRIDS with the same settings otherwise, and with
    ``RBF_GIVEN`` where ``spec["given"]``."""
    jax, jurs = _start_jax()
    import jurs.levelset as ls
    from _baselines import evaluate_rbf, evaluate_rbf_grid, rbf_fit

    points, normals = jurs.datasets.example1(spec["m"])
    reference = jurs.datasets.example1(REFERENCE_POINTS)[0]
    out = {"device": _device_name(jax)}
    timed = time_repeated(lambda: jurs.fit(points, normals), budget_s=2.0)
    settings = timed["output"].settings
    # The box does not depend on the grid, so every fit and the RBF share xs, ys.
    xs, ys, _ = ls.sampling_grid(*settings.domain, ANALYSIS_RESOLUTION)
    coarse = dict(grid=spec["grid"], offset=settings.offset, eps=settings.eps,
                  solver=jurs.LeastSquares(lam=settings.lam))

    def given(options):  # automatic settings around the given ones, timed too
        st = jurs.auto_settings(points, normals, **options)
        return jurs.fit(points, normals, grid=st.grid, offset=st.offset, eps=st.eps,
                        solver=jurs.LeastSquares(lam=st.lam))

    def report(run):
        spline = run["output"].spline
        return {"grid": list(spline.shape), "lam": float(run["output"].metrics["lam"]),
                "offset": settings.offset, "eps": settings.eps, **_timing(run),
                **_level_set(xs, ys, ls.evaluate_grid(spline, xs, ys), points, reference,
                             *_spline_functions(jax, spline), offset=settings.offset)}

    out["jurs_main"] = report(timed)
    out["jurs_coarse"] = report(time_repeated(lambda: jurs.fit(points, normals, **coarse),
                                              budget_s=2.0))
    if spec.get("given"):
        out["jurs_given"] = [{"given": options, **report(time_repeated(
            lambda: given(options), budget_s=2.0))} for options in RBF_GIVEN]
    rbf, rbf_s = rbf_fit(points, normals, offset=settings.offset, eps=settings.eps)
    t0 = time.perf_counter()
    values = evaluate_rbf_grid(rbf, xs, ys)  # the same box and grid as the jurs fits
    grid_eval_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out["rbf"] = {"fit_s": rbf_s, "grid_eval_s": grid_eval_s,
                  **_level_set(xs, ys, values, points, reference,
                               lambda xy: evaluate_rbf(rbf, xy), offset=settings.offset),
                  "analysis_s": time.perf_counter() - t0}
    return out


def work_ceiling(spec: dict) -> dict:
    """The machine's attainable float64 multiply-add rate: a NumPy matrix product (BLAS,
    every core) of side ``n``, its fastest warm call."""
    n = spec["n"]
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)), rng.random((n, n))
    best = time_repeated(lambda: a @ b, budget_s=1.0)["min_s"]
    return {"n": n, "seconds": best, "macs_per_s": n**3 / best}


WORKERS = {"step": work_step, "fit_steps": work_fit_steps, "lstsq": work_lstsq, "port": work_port,
           "example4": work_example4, "rbf": work_rbf, "ceiling": work_ceiling}


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
        proc = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker",
                               json.dumps(spec)], capture_output=True, text=True,
                              timeout=WORKER_TIMEOUT_S, cwd=HERE, env={**os.environ, **(env or {})})
    except subprocess.TimeoutExpired:
        result = {"error": f"timed out after {WORKER_TIMEOUT_S} s"}
    else:
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if proc.returncode == 0 and lines:
            result = json.loads(lines[-1][len("RESULT "):])
        else:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            result = {"error": f"exit {proc.returncode}: " + " | ".join(tail)}
    log(f"{time.perf_counter() - t0:6.1f} s  {json.dumps(spec)}" + (f" {env}" if env else "")
        + (f"  ERROR {result['error']}" if "error" in result else ""))
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
        rows.append({"m": r["m"], "grid": r["grid"], "dense_b": size, "port": res,
                     "jurs_iurs_step_s": ours, "ratio": ratio})
    return rows


def run_rbf(points_list, log) -> list[dict]:
    """RBF vs jurs at growing m, stopping before an RBF fit predicted to take too long."""
    rows, last = [], None
    for m in points_list:
        if last is not None and "rbf" in last[1]:
            predicted = last[1]["rbf"]["fit_s"] * (m / last[0]) ** 3
            if predicted > RBF_MAX_PREDICTED_S:
                log(f"skip RBF at m={m}: predicted {predicted:.0f} s")
                rows.append({"m": m, "grid": RBF_GRIDS[m],
                             "skipped": f"RBF fit predicted to take {predicted:.0f} s"})
                continue
        res = run_worker({"kind": "rbf", "m": m, "grid": RBF_GRIDS[m],
                          "given": m == TARGET_RBF_POINTS}, log)
        rows.append({"m": m, "grid": RBF_GRIDS[m], **res})
        last = (m, res)
    return rows


def run_tuned(log) -> dict:
    """The IURS step and the exact solve at the target size again, in ``HUGEPAGE_ENV``; and
    the step compiled with ``jurs.COMPILER_OPTIONS`` (as ``jurs.fit`` compiles large
    problems), without and with it."""
    step = {"kind": "step", "m": TARGET_POINTS, "grid": TARGET_GRID, "solver": "iurs"}
    lstsq = {"kind": "lstsq", "m": TARGET_POINTS, "grid": TARGET_GRID, "lam": LSQ_LAM}
    return {"env": HUGEPAGE_ENV,
            "iurs": run_worker(step, log, HUGEPAGE_ENV),
            "lstsq": run_worker(lstsq, log, HUGEPAGE_ENV),
            "iurs_options": run_worker({**step, "compiler_options": True}, log),
            "iurs_both": run_worker({**step, "compiler_options": True}, log, HUGEPAGE_ENV)}


def run_fit_steps(log) -> dict:
    """The IURS step inside ``jurs.fit`` at the target size, as it is and in ``HUGEPAGE_ENV``."""
    spec = {"kind": "fit_steps", "m": TARGET_POINTS, "grid": TARGET_GRID}
    return {"env": HUGEPAGE_ENV, "default": run_worker(spec, log),
            "hugepages": run_worker(spec, log, HUGEPAGE_ENV)}


def run_example4(log, runs: int = EXAMPLE4_RUNS) -> list[dict]:
    """Each Example-4 fit in ``runs`` fresh processes (the passes timed in the first only):
    a cold time is one sample a process, and on a shared machine one sample is noise. The
    row keeps the first run's numbers with the median cold and warm times over the runs
    (and every run's in ``cold_runs_s`` / ``warm_runs_s``)."""
    rows = []
    for cfg in EXAMPLE4:
        results = [run_worker({"kind": "example4", **cfg, "passes": i == 0}, log)
                   for i in range(runs)]
        ok = [r for r in results if "error" not in r]
        row = {**cfg, **(ok[0] if ok else results[0])}
        if ok:
            row["cold_runs_s"] = [r["cold_s"] for r in ok]
            row["warm_runs_s"] = [r["warm_s"] for r in ok]
            row["cold_s"] = float(np.median(row["cold_runs_s"]))
            row["warm_s"] = float(np.median(row["warm_runs_s"]))
            row["min_s"] = min(r["min_s"] for r in ok)
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- targets

def _find(rows, **keys):
    for r in rows:
        if all(r.get(k) == v for k, v in keys.items()):
            return r
    return None


def _verdict(value, limit, higher_is_better=False) -> str:
    if value is None:
        return "not measured"
    ok = value >= limit if higher_is_better else value <= limit
    return "PASS" if ok else "MISS"


def _target(label, measured, value, limit, required, higher_is_better=False) -> dict:
    return {"target": label, "measured": measured, "required": required,
            "verdict": _verdict(value, limit, higher_is_better), "value": value, "limit": limit}


def _env_text(env: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in env.items())


def _step_target(label, measured, seconds, peak_b) -> dict:
    """An IURS-step target row under both limits: time and peak memory."""
    row = _target(label, measured, seconds, TARGET_IURS_STEP_S,
                  f"<= {_ms(TARGET_IURS_STEP_S)}, <= {_gb(TARGET_IURS_PEAK_B)}")
    if peak_b > TARGET_IURS_PEAK_B:
        row["verdict"] = "MISS"
    return row


def evaluate_targets(sweep, rbf, example4, bounds=(), tuned=None, fit_steps=None) -> list[dict]:
    """Each target: what was measured, the requirement and PASS/MISS (from measurements)."""
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID) or {"iurs": {}, "lstsq": {}}
    where = f"{TARGET_POINTS:.0e} points, {TARGET_GRID}x{TARGET_GRID}"
    iurs, lsq = big["iurs"], big["lstsq"]
    step_bound = (_find(bounds, key="iurs_step") or {}).get("bound_s")
    bound_text = f"; arithmetic bound {_ms(step_bound)}" if step_bound else ""
    out = []
    in_fit = (fit_steps or {}).get("default", {})
    if "step_s" in in_fit:
        out.append(_step_target(
            f"IURS step inside jurs.fit, {where}, warm (fits of 1 and {1 + in_fit['steps']} "
            f"steps, difference of medians / {in_fit['steps']})",
            f"{_ms(in_fit['step_s'])} (from the fastest fits: {_ms(in_fit['step_min_s'])})"
            + ("; compiled with jurs.COMPILER_OPTIONS, as jurs.fit does at this size"
               if in_fit["compiler_options"] else "") + bound_text
            + f"; peak {_gb(in_fit['peak_over_base_b'])} over base (problem build included)",
            in_fit["step_s"], in_fit["peak_over_base_b"]))
    out += [
        _target(f"IURS step called on its own (a jitted solver.step, no compiler options), "
                f"{where}, warm (median)", _ms(iurs.get("step_warm_s")) + bound_text,
                iurs.get("step_warm_s"), TARGET_IURS_STEP_S, f"<= {_ms(TARGET_IURS_STEP_S)}"),
        _target(f"IURS peak memory, the step on its own, {where} (peak RSS minus RSS after "
                "imports and data)",
                f"{_gb(iurs.get('peak_over_base_b'))} (peak RSS {_gb(iurs.get('peak_b'))})",
                iurs.get("peak_over_base_b"), TARGET_IURS_PEAK_B,
                f"<= {_gb(TARGET_IURS_PEAK_B)}"),
    ]
    for key, how in (("iurs", "with {env} in the environment"),
                     ("iurs_both", "compiled with jurs.COMPILER_OPTIONS, with {env}")):
        variant = (tuned or {}).get(key, {})
        if "step_warm_s" not in variant:
            continue
        out.append(_step_target(
            f"The step on its own and its peak memory, {how.format(env=_env_text(tuned['env']))}",
            f"{_ms(variant['step_warm_s'])}; {_gb(variant['peak_over_base_b'])} over base",
            variant["step_warm_s"], variant["peak_over_base_b"]))
    normal = sorted((r["m"], r["normal_ipia"]["step_warm_s"]) for r in sweep
                    if r["grid"] == TARGET_GRID and "step_warm_s" in r["normal_ipia"])
    worst = max(normal, key=lambda x: x[1]) if normal else (None, None)
    out.append(_target(
        f"NormalIPIA step, {TARGET_GRID}x{TARGET_GRID}, warm, worst over m",
        f"{_ms(worst[1])} (" + ", ".join(f"{_ms(t)} at m = {m:.0e}" for m, t in normal) + ")"
        if normal else "—",
        worst[1], TARGET_NORMAL_STEP_S, f"<= {_ms(TARGET_NORMAL_STEP_S)}"))
    out.append(_target(
        f"LeastSquares(lam={LSQ_LAM:g}) through jurs.fit, {where}, end to end incl. assembly",
        f"warm {_s(lsq.get('fit_warm_s'))}, first call {_s(lsq.get('fit_first_s'))}",
        lsq.get("fit_warm_s"), TARGET_LSQ_S, f"<= {_s(TARGET_LSQ_S)} (warm)"))
    for ex4 in example4:
        label = (f"Full IURS fit: {ex4['label']}, {ex4['grid']}x{ex4['grid']}, "
                 f"tau={ex4['tau']:g}, lam={ex4['lam']:g}, tol={EXAMPLE4_TOL:g}")
        warm = _target(label + ", warm", _ms(ex4.get("warm_s")) + _steps(ex4),
                       ex4.get("warm_s"), TARGET_EX4_WARM_S, f"<= {_ms(TARGET_EX4_WARM_S)}")
        bound = _find(bounds, label=ex4["label"])
        if bound and bound.get("bound_s") is not None:
            warm["measured"] += f"; arithmetic bound {_ms(bound['bound_s'])}"
            if bound["bound_s"] > TARGET_EX4_WARM_S:
                warm["verdict"] = "MISS (below the arithmetic bound)"
        floor = passes_floor_s(ex4)
        if floor is not None:
            warm["measured"] += f"; jurs's passes alone {_ms(floor)}"
            if floor > TARGET_EX4_WARM_S and warm["verdict"] == "MISS":
                warm["verdict"] = "MISS (jurs's passes alone exceed it)"
        out.append(warm)
        out.append(_target(label + ", cold (first call in a fresh process, compile included)",
                           _s(ex4.get("cold_s")) + _spread(ex4.get("cold_runs_s")),
                           ex4.get("cold_s"), TARGET_EX4_COLD_S, f"<= {_s(TARGET_EX4_COLD_S)}"))
    out += _rbf_targets(rbf)
    return out


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


def arithmetic_bounds(sweep, example4, ceiling) -> list[dict]:
    """Lower bounds on the warm time of the IURS targets from their arithmetic alone: steps
    x ``IURS_STEP_PASSES`` x ``MACS_PER_PASS`` x samples multiply-adds at the machine's
    measured rate (``ceiling``). The step count is the iteration's (eq. 38 at ``tol``), not
    the implementation's: an implementation of Algorithm 1 that computes at most at that rate
    cannot run faster on this machine."""
    rate = (ceiling or {}).get("macs_per_s")
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID)
    rows = []
    if big and "step_warm_s" in big["iurs"]:
        rows.append({"key": "iurs_step", "label": f"IURS step, {TARGET_POINTS:.0e} points, "
                              f"{TARGET_GRID}x{TARGET_GRID}", "samples": 3 * TARGET_POINTS,
                     "steps": 1, "measured_s": big["iurs"]["step_warm_s"],
                     "target_s": TARGET_IURS_STEP_S})
    rows += [{"label": ex4["label"], "samples": 3 * ex4["points"], "steps": ex4["num_steps"],
              "measured_s": ex4["warm_s"], "target_s": TARGET_EX4_WARM_S}
             for ex4 in example4 if "num_steps" in ex4]
    for r in rows:
        r["macs"] = r["steps"] * IURS_STEP_PASSES * MACS_PER_PASS * r["samples"]
        r["bound_s"] = r["macs"] / rate if rate else None
    return rows


def _given_label(options: dict, code: bool = False) -> str:
    q = "`" if code else ""
    return ", ".join(f"{q}{k}={v:g}{q}" for k, v in options.items())


def _accurate(j, b) -> bool:
    """jurs's refined Chamfer equal to or below the RBF's ("equal": within
    ``CHAMFER_TOLERANCE``)."""
    return j["refined_chamfer"] <= (1 + CHAMFER_TOLERANCE) * b["refined_chamfer"]


def _rbf_targets(rbf) -> list[dict]:
    """>= 100x faster than RBFInterpolator at 5000 points with equal or better Chamfer
    (the refined Chamfer, "equal" meaning within ``CHAMFER_TOLERANCE``): for the defaults,
    and for the fastest of the ``RBF_GIVEN`` settings that is as accurate as the RBF (or,
    if none is, the most accurate of them)."""
    r = _find(rbf, m=TARGET_RBF_POINTS)
    label = (f"jurs.fit(points, normals) defaults vs RBFInterpolator at {TARGET_RBF_POINTS} "
             "points on the same offset samples: fit-time ratio (warm jurs, automatic "
             "settings included), refined Chamfer to the exact curve")
    required = (f">= {TARGET_RBF_RATIO:.0f}x and Chamfer <= {1 + CHAMFER_TOLERANCE:g} x RBF's")
    if r is None or "rbf" not in r:
        done = [x for x in rbf if "rbf" in x]
        note = (f"not run (largest m measured: {done[-1]['m']}, ratio "
                f"{_x(done[-1]['rbf']['fit_s'] / done[-1]['jurs_main']['warm_s'])})"
                ) if done else "not run"
        return [{"target": label, "measured": note, "required": required,
                 "verdict": "not measured"}]
    out = [_rbf_verdict(label, required, r["jurs_main"], r["rbf"])]
    given = r.get("jurs_given") or []
    if given:
        accurate = [j for j in given if _accurate(j, r["rbf"])]
        if accurate:
            best = min(accurate, key=lambda j: j["warm_s"])
            which = "the fastest of them as accurate as the RBF"
        else:
            best = min(given, key=lambda j: j["refined_chamfer"])
            which = "none as accurate as the RBF; the most accurate"
        out.append(_rbf_verdict(
            f"The same with settings given ({len(given)} tried, see the RBF section; {which}: "
            f"{_given_label(best['given'])}; for context: unsafe as defaults, see "
            "smoothing.md)", required, best, r["rbf"]))
    return out


def _rbf_verdict(label, required, j, b) -> dict:
    ratio = b["fit_s"] / j["warm_s"]
    ok = ratio >= TARGET_RBF_RATIO and _accurate(j, b)
    return {"target": label,
            "measured": f"{_x(ratio)} (jurs first call: {_x(b['fit_s'] / j['first_s'])}); "
                        f"Chamfer jurs {j['refined_chamfer']:.2e} vs RBF "
                        f"{b['refined_chamfer']:.2e}, "
                        f"{_x(j['refined_chamfer'] / b['refined_chamfer'])} the RBF's "
                        f"(grid {'x'.join(map(str, j['grid']))})",
            "required": required, "verdict": "PASS" if ok else "MISS"}


# --------------------------------------------------------------------------- report

def _ms(s):
    """Seconds as ms below one second (3 significant digits)."""
    return "—" if s is None else (f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s")


def _range(runs) -> str:
    """``low-high`` of a list of per-process times."""
    return f"{_s(min(runs))}-{_s(max(runs))}"


def _spread(runs) -> str:
    """`` (median of n processes: low-high)`` for a list of per-process times."""
    if not runs or len(runs) < 2:
        return ""
    return f" (median of {len(runs)} processes: {_range(runs)})"


def _us(s):
    return "—" if s is None else f"{s * 1e6:.3g} us"


def _s(s):
    return "—" if s is None else f"{s:.3g} s"


def _gb(b):
    if b is None:
        return "—"
    return f"{b / 2**30:.2f} GiB" if abs(b) >= 2**30 else f"{b / 2**20:.0f} MiB"


def _steps(r):
    return f" ({r['num_steps']} steps, {r['result']})" if "num_steps" in r else ""


def _x(ratio):
    """A speed ratio: 2 significant digits, so that 0.61x does not print as 1x."""
    return "—" if ratio is None else f"{ratio:.2g}x" if ratio < 100 else f"{ratio:.0f}x"


def _table(header, rows):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _err(res):
    return f"error: {res['error'][:80]}" if "error" in res else None


def _where(r) -> list:
    """The m and grid cells of a sweep row."""
    return [f"{r['m']:.0e}", f"{r['grid']}x{r['grid']}"]


def _measured_row(cells, res, width: int, values) -> list:
    """``cells``, then ``values()`` (``width`` cells), or ``res``'s error padded to ``width``."""
    return cells + ([_err(res)] + [""] * (width - 1) if _err(res) else values())


def report(data: dict) -> str:
    """The markdown report (also printed)."""
    lines = [f"# Speed{' (QUICK run: small sizes only)' if data['quick'] else ''}", "",
             f"Machine: {data['machine']}. Device of the measurements: {data['device']}. "
             f"float64. Whole run: {data['runtime_s'] / 60:.1f} min.",
             "", "Load average when the run began (other work on the machine, before this "
             "run added its own): "
             + (f"{data['load_average']:.1f}" if "load_average" in data else "not recorded")
             + ". Timings taken beside other work are indicative.", ""]
    lines += [f"Note: {n}" for n in data.get("notes", [])] + [""] * bool(data.get("notes"))
    lines += ["## Targets", ""]
    lines += _table(["target", "measured", "required", "verdict"],
                    [[t["target"], t["measured"], t["required"], t["verdict"]]
                     for t in data["targets"]])
    lines += ["", "## What is measured", "",
              "* Data: the paper's Example 1 curve, `jurs.datasets.example1(m)`; 3m samples "
              "(points and both offsets, d = 0.1, eps = 0.01), box = bounding box + 10 %.",
              "* **Warm step**: median time of a jitted `solver.step(problem, state)` on a state "
              "one step in (weights already moved), as in `benchmarks/step_speed.py`; "
              "**compile** = first call minus warm (the jit cache is cleared first). Repeats: "
              f"until about {STEP_BUDGET_S:g} s are spent, at least 3 (2 after a first call "
              f"above that, 1 after one above {LONG_CALL_S:g} s), at most 20; the minimum is "
              "shown in brackets "
              "(closest to an unshared machine).",
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
              + ("; the device's own peak is in the JSON." if data["device"].split(":")[0] != "cpu"
                 else "."),
              "* Grid sweep: " + "; ".join(f"m = {int(m):.0e}: {', '.join(map(str, g))}"
                                          for m, g in data["sweep_config"].items())
              + " (pruned: fine grids on few points, and part of the rest to keep the run "
              "short; the 1e6 x 8 x 8 point is there for the NumPy baseline).", ""]
    lines += _sweep_tables(data["sweep"])
    lines += _port_table(data["port"])
    lines += _rbf_table(data["rbf"])
    lines += _example4_table(data["example4"])
    lines += _bounds_table(data.get("bounds", []), data.get("ceiling"))
    lines += _tuned_table(data.get("tuned"), data["sweep"], data.get("fit_steps"))
    return "\n".join(lines) + "\n"


def _sweep_tables(sweep) -> list[str]:
    lines = []
    for key, (label, _, _) in STEP_SOLVERS.items():
        extra = ["assembly (init) warm", "assembly first call"] if key == "normal_ipia" else []
        rows = []
        for r in sweep:
            res = r[key]
            rows.append(_measured_row(_where(r), res, 5 + len(extra), lambda: [
                f"{_ms(res['step_warm_s'])} ({_ms(res['step_min_s'])})",
                _s(res["step_compile_s"]), _gb(res["peak_over_base_b"]), _gb(res["peak_b"]),
                _s(res["build_s"])] + ([_ms(res["init_warm_s"]), _s(res["init_first_s"])]
                                       if extra else [])))
        lines += [f"## {label}: one step", ""]
        lines += _table(["m", "grid", "warm step (min)", "compile", "peak over base", "peak RSS",
                         "problem build"] + extra, rows)
        lines.append("")
    rows = []
    for r in sweep:
        res = r["lstsq"]
        rows.append(_measured_row(_where(r), res, 6, lambda: [
            f"{_s(res['fit_warm_s'])} ({_s(res['fit_min_s'])})", _s(res["fit_first_s"]),
            _gb(res["peak_over_base_b"]), _gb(res["peak_b"]), res.get("result", "—"),
            f"{res['E_ave']:.2e}"]))
    lines += [f"## LeastSquares(lam={LSQ_LAM:g}) end to end through jurs.fit", ""]
    lines += _table(["m", "grid", "warm (min)", "first call", "peak over base", "peak RSS",
                     "result", "E_ave"], rows)
    return lines + [""]


def _port_table(port_rows) -> list[str]:
    lines = ["## Baseline: the paper's Algorithm 1 in NumPy (dense D rebuilt every step)", "",
             "`benchmarks/_numpy_port.py`: dense B (3m x NM) from "
             "`scipy.interpolate.BSpline.design_matrix` once; per step W = B w, "
             "D = B * w / W, mu = 2 / max column sum of D, eq. 33 and the weight gradient "
             "(its iterates equal jurs.IURS's: `tests/test_numpy_port.py`). Same tau = 1e-2, "
             f"lam = 1e-3. Run where one dense matrix is <= {DENSE_LIMIT_BYTES / 1e9:g} GB.", ""]
    rows = []
    for r in port_rows:
        p = r["port"]
        rows.append(_measured_row(_where(r) + [_gb(r["dense_b"])], p, 5, lambda: [
            _s(p["build_s"]), _ms(p["step_warm_s"]), _ms(r["jurs_iurs_step_s"]),
            _x(r["ratio"]), _gb(p["peak_over_base_b"])]))
    lines += _table(["m", "grid", "one dense matrix", "build B", "NumPy step", "jurs IURS step",
                     "NumPy / jurs", "NumPy peak over base"], rows)
    return lines + [""]


def _rbf_table(rbf_rows) -> list[str]:
    lines = ["## Baseline: scipy RBFInterpolator (thin-plate) vs jurs defaults", "",
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
             "Last column, for context: jurs with the same settings on the coarser grid G.",
             ""]
    rows = []
    for r in rbf_rows:
        if _err(r) or "skipped" in r:
            rows.append([r["m"], _err(r) or f"skipped: {r['skipped']}"] + [""] * 10)
            continue
        j, b, c = r["jurs_main"], r["rbf"], r["jurs_coarse"]
        rows.append([
            r["m"], "x".join(map(str, j["grid"])), f"{j['offset']:.3g}",
            _s(b["fit_s"]), _ms(j["warm_s"]), _s(j["first_s"]),
            f"{_x(b['fit_s'] / j['warm_s'])} / {_x(b['fit_s'] / j['first_s'])}",
            f"{j['refined_chamfer']:.2e} / {b['refined_chamfer']:.2e}",
            f"{j['refined_hausdorff']:.2e} / {b['refined_hausdorff']:.2e}",
            f"{j['chamfer']:.2e} / {b['chamfer']:.2e}",
            f"{j['num_components']}/{j['num_supplementary']} vs "
            f"{b['num_components']}/{b['num_supplementary']}",
            f"{'x'.join(map(str, c['grid']))}: {c['refined_chamfer']:.2e}, "
            f"{c['num_components']}/{c['num_supplementary']}, {_ms(c['warm_s'])} "
            f"({_x(b['fit_s'] / c['warm_s'])})"])
    lines += _table(["m", "jurs grid", "d", "RBF fit", "jurs warm", "jurs first call",
                     "RBF / jurs (warm / first)", "refined Chamfer jurs / RBF",
                     "refined Hausdorff jurs / RBF", "analysis Chamfer jurs / RBF",
                     "components jurs vs RBF",
                     "coarser grid G: refined Chamfer, components, warm (RBF / it)"], rows)
    for r in rbf_rows:
        if not r.get("jurs_given") or _err(r):
            continue
        b = r["rbf"]
        lines += ["", f"At m = {r['m']}, jurs with settings given (the rest automatic, timed "
                  "too): finer grids and smoothings far below the default. Such smoothings "
                  "grow supplementary components on glyphs and traced outlines "
                  "(`benchmarks/results/smoothing.md`), so the defaults do not use them. "
                  f"The RBF: refined Chamfer {b['refined_chamfer']:.2e}, Hausdorff "
                  f"{b['refined_hausdorff']:.2e}, fit {_s(b['fit_s'])}.", ""]
        rows = [[_given_label(e["given"], code=True), "x".join(map(str, e["grid"])),
                 f"{e['lam']:.3g}", _ms(e["warm_s"]), _x(b["fit_s"] / e["warm_s"]),
                 f"{e['refined_chamfer']:.2e} ({_x(e['refined_chamfer'] / b['refined_chamfer'])})",
                 f"{e['refined_hausdorff']:.2e}",
                 f"{e['num_components']}/{e['num_supplementary']}"]
                for e in r["jurs_given"]]
        lines += _table(["given", "grid", "lambda", "jurs warm", "RBF / jurs",
                         "refined Chamfer (x the RBF's)", "refined Hausdorff",
                         "components"], rows)
    return lines + [""]


def _example4_table(rows_in) -> list[str]:
    lines = ["## Full regularised IURS fits of Example-4 size", "",
             f"`jurs.fit(points, normals, grid=15, solver=IURS(tau, lam, tol={EXAMPLE4_TOL:g}, "
             f"max_steps={EXAMPLE4_MAX_STEPS}))` on `jurs.shapes.get(shape, points)`. Cold: "
             "the first call in a fresh process, compilation included (imports timed apart); "
             "warm: median of later calls. Each fit runs in several fresh processes: cold and "
             "warm are the medians over them, with the range of the cold times and the fastest "
             "warm call.", ""]
    rows = []
    for r in rows_in:
        cells = [r["label"], f"{r['grid']}x{r['grid']}", f"{r['tau']:g}", f"{r['lam']:g}"]
        runs = r.get("cold_runs_s") or []
        rows.append(_measured_row(cells, r, 7, lambda: [
            r["num_steps"], r["result"], f"{_ms(r['warm_s'])} ({_ms(r['min_s'])})",
            _s(r["cold_s"]), _range(runs) if runs else "—",
            _s(r["import_s"]), f"{r['E_ave']:.2e}"]))
    lines += _table(["fit", "grid", "tau", "lam", "steps", "result", "warm (fastest)", "cold",
                     "cold range", "imports", "E_ave"], rows)
    timed = [r for r in rows_in if r.get("passes") and "num_steps" in r]
    if not timed:
        return lines + [""]
    lines += ["", "Where the warm time goes: the passes over the samples that every IURS step "
              "makes, each timed alone in a jitted loop of "
              f"{timed[0]['passes']['repeats']} passes (fastest run), as jurs's kernels run "
              "them. F2: W and F(wC) at the new weights (eq. 14); F1: F(wC) at the new C "
              "(eq. 35); T2: D^T r with D's column sums (eqs. 33, 25), and the two sums of "
              "the weight gradient (eq. 19). Times the fit's steps they are a floor for "
              "these kernels, with no bookkeeping, dispatch or metrics; not a floor for "
              "the method (see the arithmetic bounds below).", ""]
    rows = [[r["label"], _us(r["passes"]["F2_s"]), _us(r["passes"]["F1_s"]),
             _us(r["passes"]["T2_s"]), _us(step_passes_s(r)), _us(r["warm_s"] / r["num_steps"]),
             _ms(passes_floor_s(r)), _ms(r["warm_s"])] for r in timed]
    lines += _table(["fit", "F2", "F1", "T2", "a step's passes (F2 + F1 + 2 T2)",
                     "warm fit / steps", "passes x steps", "warm fit"], rows)
    return lines + [""]


def _bounds_table(bounds, ceiling) -> list[str]:
    if not bounds or not ceiling or "macs_per_s" not in ceiling:
        return []
    lines = ["## Lower bounds from the arithmetic of Algorithm 1", "",
             "An IURS step as eqs. 19-35 define it applies the collocation D (eq. 23) or its "
             f"transpose at least {IURS_STEP_PASSES} times, each {MACS_PER_PASS} multiply-adds "
             "a sample: W and F(wC) at the new weights (eq. 14), D^T r and D's column sums "
             "(eqs. 33 and 25), F(wC) at the new C for the energy (eq. 35), and the weight "
             "gradient at the new (C, w) for the next step (eq. 19). Nothing else is counted: "
             "no division, gather, scatter or memory traffic. At the machine's measured "
             f"multiply-add rate, a float64 NumPy matrix product of side {ceiling['n']} on "
             f"every core ({ceiling['macs_per_s'] / 1e9:.3g} G multiply-adds/s, the rate tuned "
             "BLAS code reaches on this machine), a fit takes at least steps x that "
             "arithmetic; the steps are the iteration's "
             f"(eq. 38 at tol = {EXAMPLE4_TOL:g}), not the implementation's. Where the bound "
             "exceeds the target, no implementation of the paper's method that computes at most "
             "as fast as tuned BLAS meets it here.", ""]
    rows = [[b["label"], b["samples"], b["steps"], f"{b['macs']:.3g}", _ms(b["bound_s"]),
             _ms(b["target_s"]), _ms(b["measured_s"]),
             "target below the bound" if b["bound_s"] > b["target_s"] else "not excluded"]
            for b in bounds]
    lines += _table(["what", "samples", "steps", "multiply-adds", "bound", "target",
                     "measured (warm)", "verdict of the bound"], rows)
    return lines + [""]


def _tuned_table(tuned, sweep, fit_steps=None) -> list[str]:
    big = _find(sweep, m=TARGET_POINTS, grid=TARGET_GRID)
    if not tuned or not big:
        return []
    env = _env_text(tuned["env"])
    lines = ["## Large problems: huge pages and compiler options", "",
             f"The same workers at {TARGET_POINTS:.0e} points, {TARGET_GRID}x{TARGET_GRID}. "
             f"*Huge pages*: `{env}` in the environment, so glibc's malloc, from which "
             "XLA's CPU buffers come, asks for transparent huge pages (glibc >= 2.35; Linux "
             "THP in `madvise` or `always` mode); with 4 KB pages every call page-faults its "
             "fresh buffers in again. glibc reads it at start-up: a setting of the process, "
             "not of the library. *Options*: the step jitted with `jurs.COMPILER_OPTIONS` "
             "(as `jurs.fit` compiles large problems: floating-point reassociation, so LLVM "
             "vectorises the per-bucket sums; "
             "NaN, Inf, division and functions keep IEEE semantics). *Page faults*: minor "
             "faults of one warm step.", ""]
    variants = [("IURS step", big["iurs"]), ("IURS step, huge pages", tuned["iurs"]),
                ("IURS step, options", tuned.get("iurs_options", {})),
                ("IURS step, huge pages and options", tuned.get("iurs_both", {}))]
    rows = [_measured_row([name], r, 3, lambda r=r: [
        f"{_ms(r['step_warm_s'])} ({_ms(r['step_min_s'])})", r.get("step_page_faults", "—"),
        _gb(r["peak_over_base_b"])]) for name, r in variants if r]
    for name, r in ((f"LeastSquares(lam={LSQ_LAM:g}) fit", big["lstsq"]),
                    (f"LeastSquares(lam={LSQ_LAM:g}) fit, huge pages", tuned["lstsq"])):
        rows.append(_measured_row([name], r, 3, lambda r=r: [
            f"{_s(r['fit_warm_s'])} ({_s(r['fit_min_s'])})", "—", _gb(r["peak_over_base_b"])]))
    lines += _table(["measurement", "warm (min)", "page faults", "peak over base"], rows)
    lines += _fit_steps_table(fit_steps)
    return lines + [""]


def _fit_steps_table(fit_steps) -> list[str]:
    if not fit_steps:
        return []
    env = _env_text(fit_steps["env"])
    lines = ["", "**The step inside a fit.** `jurs.fit(points, normals, grid, solver=IURS("
             "tau=1e-2, lam=1e-3, tol=0, max_steps=n), offset, eps)` end to end for n = 1 and "
             "n = 1 + k; a step costs the difference of the warm medians over k. The fit's "
             "steps run in one compiled loop, whose buffers are allocated and page-faulted "
             "once per call, not per step; at this size `jurs.fit` compiles its own solvers "
             "with `jurs.COMPILER_OPTIONS` (column *options*). *Page faults*: minor faults "
             "of one warm fit call.", ""]
    rows = []
    for name, r in (("as it is", fit_steps["default"]), (f"with {env}", fit_steps["hugepages"])):
        rows.append(_measured_row([name], r, 7, lambda r=r: [
            "yes" if r["compiler_options"] else "no", r["steps"],
            f"{_ms(r['step_s'])} ({_ms(r['step_min_s'])})",
            _ms(r["fits"]["1"]["warm_s"]), _ms(r["fits"][str(1 + r["steps"])]["warm_s"]),
            f"{r['fits']['1']['page_faults']} / {r['fits'][str(1 + r['steps'])]['page_faults']}",
            _gb(r["peak_over_base_b"])]))
    lines += _table(["environment", "options", "k", "step (from fastest fits)", "fit, 1 step",
                     "fit, 1 + k steps", "page faults (1 / 1 + k steps)", "peak over base"],
                    rows)
    return lines


# --------------------------------------------------------------------------- main

def rerender(path: str) -> None:
    """Targets and markdown again from saved measurements (no measuring): rewrites
    ``<name>.{json,md}`` beside ``path``, ``<name>`` being the JSON file's name (so a copy
    re-renders where it lies, and the committed results only from their own JSON)."""
    with open(path) as fh:
        data = json.load(fh)
    data["bounds"] = arithmetic_bounds(data["sweep"], data["example4"], data.get("ceiling"))
    data["targets"] = evaluate_targets(data["sweep"], data["rbf"], data["example4"],
                                       data["bounds"], data.get("tuned"), data.get("fit_steps"))
    text = report(data)
    print(text)
    sys.path.insert(0, HERE)
    from _common import write_results

    path = os.path.abspath(path)
    write_results(os.path.splitext(os.path.basename(path))[0], data, text,
                  os.path.dirname(path))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="small sizes only (a few minutes); writes speed_quick.*")
    parser.add_argument("--from-json", metavar="PATH",
                        help="re-render the report (and the targets) from a results JSON")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker_main(args.worker)
    if args.from_json:
        return rerender(args.from_json)

    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, HERE)
    from _common import machine, write_results

    start = time.perf_counter()
    load_average = os.getloadavg()[0]

    def log(msg):
        print(f"[{time.perf_counter() - start:7.1f} s] {msg}", file=sys.stderr, flush=True)

    sweep_config = QUICK_SWEEP if args.quick else FULL_SWEEP
    sweep = run_sweep(sweep_config, log)
    port = run_port(sweep, log)
    tuned = None if args.quick else run_tuned(log)
    fit_steps = None if args.quick else run_fit_steps(log)
    example4 = run_example4(log)
    rbf = run_rbf(QUICK_RBF_POINTS if args.quick else tuple(RBF_GRIDS), log)
    ceiling = run_worker({"kind": "ceiling", "n": CEILING_N}, log)
    bounds = arithmetic_bounds(sweep, example4, ceiling)
    data = {"quick": args.quick, "machine": machine(),
            "device": _device_name(jax),
            "sweep_config": {str(m): list(g) for m, g in sweep_config.items()},  # JSON keys
            "targets": evaluate_targets(sweep, rbf, example4, bounds, tuned, fit_steps),
            "sweep": sweep, "port": port, "rbf": rbf, "example4": example4,
            "tuned": tuned, "fit_steps": fit_steps,
            "ceiling": ceiling, "bounds": bounds, "load_average": load_average,
            "runtime_s": time.perf_counter() - start}
    text = report(data)
    print(text)
    write_results("speed_quick" if args.quick else "speed", data, text)


if __name__ == "__main__":
    main()
