"""``jurs.fit``: points and normals in, a fitted implicit spline out."""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .._model.io import SPLINE_KEYS, check_spline_arrays
from .._model.spline import ImplicitSpline
from .._problem.problem import (
    DEFAULT_MARGIN,
    _is_concrete,
    _shape,
    check_memory,
    fit_memory,
    flipped_normal_fraction,
    normalise_grid,
    orientation_sample,
    padded_problem,
    tangential_normal_fraction,
    unit_normals,
)
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message
from ..solvers import AbstractSolver, LeastSquares, RobustLeastSquares, solve
from .compile import COMPILER_OPTIONS, call_stored
from .settings import auto_settings, feature_width, strided_probes
from .sharding import (
    PROCESS_SETTINGS,
    input_sharding,
    is_sharded,
    place_fit,
    process_problem,
    replicate_across_processes,
    spans_processes,
)


def _as_arrays(tree, dtype):
    """Python floats -> 0-d arrays, so new hyperparameter values do not recompile."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if isinstance(x, float) else x, tree
    )


#: More than this fraction of the points with normals flipped against their neighbours
#: (:func:`jurs._problem.problem.flipped_normal_fraction`), or with normals along the curve
#: (:func:`jurs._problem.problem.tangential_normal_fraction`), makes a fit
#: ``inconsistent_normals``: consistent clouds measured 0 and at most 0.03 (0.12 flipped
#: on a horse sampled coarser than its legs); half or every other normal flipped 0.5,
#: random normals about 0.5 along the curve.
MAX_FLIPPED_FRACTION = 0.2
MAX_TANGENTIAL_FRACTION = 0.2


def _check_orientation(sol, points, normals, mask):
    """``sol`` with ``metrics["flipped_normal_fraction"]`` and
    ``metrics["tangential_normal_fraction"]`` and, where more than
    :data:`MAX_FLIPPED_FRACTION` of the normals are flipped against their neighbours or
    more than :data:`MAX_TANGENTIAL_FRACTION` lie along the curve, the verdict
    ``RESULTS.inconsistent_normals`` in place of success or max_steps (half-flipped or
    random normals fitted "successfully" into 2 or 20 loops). Host side. Unlike an input
    error this is a verdict, as optimistix reports a failed solve in ``sol.result``: the
    fit ran; :func:`fit` raises it with ``throw=True`` and returns it otherwise."""
    p, n = np.asarray(points, float), np.asarray(normals, float)
    if mask is not None:
        keep = np.asarray(mask).astype(bool)
        p, n = p[keep], n[keep]
    sample = orientation_sample(p, n)  # one KD-tree for both checks
    flipped = flipped_normal_fraction(p, n, sample)
    along = tangential_normal_fraction(p, n, sample)
    metrics = dict(
        sol.metrics,
        flipped_normal_fraction=jnp.asarray(flipped),
        tangential_normal_fraction=jnp.asarray(along),
    )
    result = sol.result
    bad = flipped > MAX_FLIPPED_FRACTION or along > MAX_TANGENTIAL_FRACTION
    if bad and bool((result == RESULTS.successful) | (result == RESULTS.max_steps_reached)):
        result = RESULTS.inconsistent_normals
    return dataclasses.replace(sol, metrics=metrics, result=result)


#: A fit is ``doubtful`` where more than this fraction of its points (and more than 2)
#: sit across a thin part or a narrow gap (less than a cell wide) from a point whose side
#: the fit gets wrong (:func:`crossed_features`): a neck pinched, two parts fused, a tip
#: cut short. The clean shapes of the quality suite (2000 points) measured 0-5 such
#: points (0.25 %, the wedges of glyphs' sharp inner corners, rounded off within a cell);
#: a 100:1 ellipse 92 (its tips cut short), a 1000:1 one 260. Surfaces of 1e5 points
#: (20000 probed; sphere, torus, bunny, airplane): 0 clean; with noise of 0.5 % of the
#: diagonal 0 on sphere and torus, 174 on the bunny (ears) and 361 on the airplane (wings,
#: noise 0.6x their width), of which the clean cloud's fit put 99 and 228 midpoints on
#: the pair's side: parts the noisy fit cut.
MAX_CROSSED_FRACTION = 0.005
#: ... or where more than this fraction of the points (those set aside excepted) lie
#: farther from the zero set than the fit resolves (:func:`far_point_fraction`): fits of
#: four shapes with 1 % noise left 0-1.5 % of their points there, with 10 % of the
#: points displaced by 0.1 of the diagonal 1-1.5 %.
MAX_FAR_FRACTION = 0.02
#: Far points lie beyond this many times the spread of the points' distances to the zero
#: set (:func:`far_point_fraction`): 6e-5 of Gaussian noise does; noisy clouds (1 % of
#: the diagonal) had 1.3-2.1 % of their points beyond 2 d, d being set from an estimate
#: of the noise below the true one.
FAR_SPREAD = 4.0
#: Points at most this many are measured for the far-point check (evenly strided).
DOUBT_PROBES = 20000


#: The checks evaluate the fit at point counts rounded up to a power of two (at least
#: this), so that a new cloud reuses their compiled evaluations: with a count of its
#: own, each new cloud of Example 1 (3000-3300 points, grid 64) spent 0.56-0.62 s
#: compiling them, most of its 0.66-0.70 s fit. Powers of two, not the fit's own ladder
#: (:func:`jurs._problem.sizes.round_size`, four sizes an octave): padding these evaluations
#: costs milliseconds, a compilation about half a second, and the count of pairs across
#: thin parts varies from cloud to cloud within one of the fit's size bands.
MIN_CHECK_BUCKET = 1024


@jax.jit
def zero_set_distance(spline: ImplicitSpline, points: jax.Array) -> jax.Array:
    """First-order distance ``|g(p)| / |grad g(p)|`` from each point to the zero set."""

    def one(p):
        value, gradient = jax.value_and_grad(lambda x: spline(x[None])[0])(p)
        return jnp.abs(value) / jnp.maximum(jnp.linalg.norm(gradient), 1e-300)

    return jax.vmap(one)(points)


@jax.jit
def _spline_values(spline: ImplicitSpline, points: jax.Array) -> jax.Array:
    return spline(points)


def evaluate_bucketed(fn, spline: ImplicitSpline, points) -> np.ndarray:
    """``fn(spline, points)`` (a jitted per-point evaluation) on the host's ``(n, d)``
    ``points``, padded with copies of the first to a power of two of at least
    :data:`MIN_CHECK_BUCKET` rows and cut back to ``n``: clouds of different sizes share
    one compiled evaluation."""
    points = np.asarray(points, float)
    n = len(points)
    if n == 0:
        return np.empty(0)
    size = max(MIN_CHECK_BUCKET, 1 << (n - 1).bit_length())
    padded = np.concatenate([points, np.repeat(points[:1], size - n, axis=0)])
    return np.asarray(fn(spline, jnp.asarray(padded, spline.control.dtype)))[:n]


def far_point_fraction(spline: ImplicitSpline, points, offset: float) -> tuple[float, float]:
    """``(fraction, threshold)``: the fraction of ``points`` (at most :data:`DOUBT_PROBES`,
    evenly strided) whose :func:`zero_set_distance` exceeds the largest of 2 d, half a
    cell, and :data:`FAR_SPREAD` times the distances' own robust spread (1.4826 times their
    median): the distance within which a fit's zero set lies of its data where it follows
    them (the offsets reach d; a grid's cell bounds what its zero set can follow; noisy
    points scatter about it by their noise, which d may underestimate)."""
    p = np.asarray(points, float)
    at = strided_probes(len(p), DOUBT_PROBES)
    p = p if at is None else p[at]
    cell = spline.cell_width
    distance = evaluate_bucketed(zero_set_distance, spline, p)
    spread = 1.4826 * float(np.nanmedian(distance)) if np.isfinite(distance).any() else 0.0
    threshold = max(2.0 * float(offset), 0.5 * cell, FAR_SPREAD * spread)
    return float(np.mean(~(distance <= threshold))), threshold


def crossed_features(spline: ImplicitSpline, points, normals, spacing: float) -> int:
    """How many of ``points`` (at most :data:`DOUBT_PROBES`, evenly strided) face a point
    less than a cell away across a thin part or a narrow gap
    (:func:`jurs._fit.settings.feature_width`) while the fit puts the midpoint between the two
    on the wrong side: outside for a thin part (normals pointing away from each other),
    inside for a gap. Each such pair is a part cut or a gap bridged by the zero set."""
    p, n = np.asarray(points, float), unit_normals(np.asarray(normals, float), np)
    at = strided_probes(len(p), DOUBT_PROBES)
    own = np.arange(len(p)) if at is None else at
    _, partner = feature_width(p, n, spline.cell_width, spacing, own)
    paired = partner >= 0
    if not paired.any():
        return 0
    a, b = p[own[paired]], p[partner[paired]]
    inside = np.sum((b - a) * n[own[paired]], axis=1) < 0  # a thin part, not a gap
    value = evaluate_bucketed(_spline_values, spline, 0.5 * (a + b))
    return int(np.sum(np.where(inside, value > 0, value < 0)))


def _check_doubts(sol, settings, points, normals, mask, offset):
    """``sol`` with ``metrics["far_point_fraction"]``, ``stats["doubts"]`` (the reasons to
    doubt the zero set, in words) and, where there is one, the verdict
    ``RESULTS.doubtful`` in place of success, and a warning. Host side."""
    p = np.asarray(points, float)
    keep = np.ones(len(p), bool) if mask is None else np.asarray(mask).astype(bool)
    if settings is not None and settings.set_aside:
        keep[list(settings.set_aside)] = False
    far, threshold = far_point_fraction(sol.spline, p[keep], offset)
    crossed, thin = 0, 0.0 if settings is None else settings.thin_fraction
    if settings is not None:
        crossed = crossed_features(sol.spline, p[keep], np.asarray(normals)[keep], settings.spacing)
    doubts = []
    if crossed > max(2, MAX_CROSSED_FRACTION * min(int(keep.sum()), DOUBT_PROBES)):
        doubts.append(
            f"{crossed} points sit across a thin part or a narrow gap (less than a cell "
            "wide) from a point the zero set puts on the wrong side: parts are cut or "
            "bridged there. A finer grid= (cells about as wide as the features) or "
            "denser sampling resolves them"
            + (
                f"; {thin:.1%} of the points lie on features narrower than half a cell of this grid"
                if thin > 0
                else ""
            )
        )
    if far > MAX_FAR_FRACTION:
        doubts.append(
            f"{far:.1%} of the points lie farther than {threshold:.3g} from the zero set: "
            "the fit does not follow the data there (features too fine for the grid, "
            "outliers or inconsistent normals)"
        )
    metrics = dict(
        sol.metrics, far_point_fraction=jnp.asarray(far), crossed_features=jnp.asarray(crossed)
    )
    stats = dict(sol.stats, doubts=tuple(doubts))
    result = sol.result
    if doubts and bool(result == RESULTS.successful):
        result = RESULTS.doubtful
        warnings.warn("jurs.fit: doubtful fit: " + "; ".join(doubts), stacklevel=4)
    return dataclasses.replace(sol, metrics=metrics, stats=stats, result=result)


def _point_dimension(points) -> int:
    """The d of ``(m, d)`` points; 2 for anything else (make_problem names the error)."""
    try:
        shape = _shape(points)
    except (TypeError, ValueError):
        return 2
    return shape[1] if len(shape) == 2 and shape[1] in (2, 3) else 2


def _estimated_normals(points, mask):
    """``(normals, info)`` for :func:`fit` called without normals: outward normals from
    :func:`jurs.estimate_normals` and its findings (a dict, without the per-point
    confidence)."""
    if mask is not None:
        raise ValueError(
            "normals=None estimates normals from the whole cloud: it takes no "
            "mask (estimate them with jurs.estimate_normals, then pad)"
        )
    if not _is_concrete(points):
        raise ValueError(
            "normals=None estimates normals on the host from concrete points; "
            "under jit, grad or vmap pass normals (jurs.estimate_normals)"
        )
    from .._cloud.normals import estimate_normals  # SciPy's graphs: loaded when first needed

    normals, info = estimate_normals(points, return_info=True)
    return normals, {k: v for k, v in info._asdict().items() if k != "confidence"}


def _run(problem, solver, init, throw):
    return solve(solver, problem, init, throw=throw)


_solve = eqx.filter_jit(_run)
# The same compiled with COMPILER_OPTIONS, for large problems at top level (see fit).
# (filter_jit passes jax.jit's keywords on; its stub lists none of them.)
_solve_reassociating = eqx.filter_jit(_run, compiler_options=COMPILER_OPTIONS)  # pyright: ignore[reportCallIssue]


def _at_top_level(tree) -> bool:
    """Whether no leaf of ``tree`` is traced and a jit called here runs as an outermost
    computation, not staged into a caller's jit (XLA takes compiler options only there)."""
    if not _is_concrete(tree):
        return False
    # JAX has no public "am I being staged out" check (jax-ml/jax#18544): a value made here
    # comes back as a tracer exactly when a jit, make_jaxpr, scan, cond, ... is tracing.
    # Under grad or vmap with no leaf of theirs in ``tree`` the jit runs on the concrete
    # arrays, outside them, where compiler options are taken (and ``throw`` is checked
    # on the host). A device_put compiles nothing.
    return not isinstance(jax.device_put(np.float32(0)), Tracer)


def _reassociation_pays(problem, solver) -> bool:
    """For solvers that declare themselves safe with :data:`jurs.COMPILER_OPTIONS`
    (``reassociation_safe``) on problems in the bucketed power form (the large ones, where
    the per-bucket sums are and where the options were measured to pay)."""
    local = problem.local
    return type(solver).reassociation_safe and local.terms is None and local.bucket_size > 1


def reassociates(problem, solver, init=None) -> bool:
    """Whether :func:`jurs.fit` compiles this solve with :data:`jurs.COMPILER_OPTIONS`:
    where they pay (:func:`_reassociation_pays`), when called at top level."""
    return _reassociation_pays(problem, solver) and _at_top_level((problem, solver, init))


def _resolved_settings(points, normals, grid, offset, eps, solver, domain, margin, mask, smoothing):
    """``(settings, grid, offset, eps, solver)``: those not given chosen from the data."""
    if smoothing is not None and solver is not None:
        raise ValueError(
            "smoothing sets the default solver's lambda; with a solver given, set its lam instead"
        )
    if grid is not None and offset is not None and eps is not None and solver is not None:
        return None, grid, offset, eps, solver
    if mask is not None:
        raise ValueError(
            "automatic settings do not take a mask; pass grid, offset, eps "
            "and solver explicitly for padded batches"
        )
    settings = auto_settings(
        points,
        normals,
        grid=grid,
        offset=offset,
        eps=eps,
        domain=domain,
        margin=margin,
        smoothing=smoothing,
    )
    if solver is None:
        solver = default_solver(settings)
    return settings, settings.grid, settings.offset, settings.eps, solver


#: Reweighted solves at most in the default robust fit (:func:`default_solver`): each is
#: one exact solve.
DEFAULT_ROBUST_STEPS = 8
#: ... and its stop rule: ``E_rob`` changing by at most this fraction between steps.
DEFAULT_ROBUST_RTOL = 1e-3


def default_solver(settings) -> AbstractSolver:
    """The solver :func:`fit` uses with the automatic ``settings``: the exact solve
    ``LeastSquares(lam=settings.lam)``; where points were set aside as standing alone
    (``settings.set_aside``), the robust reweighting ``RobustLeastSquares(lam, loss="huber")``
    of the rest, which also weighs down points that stray less far (Huber's loss is
    convex: it never sets an inlier aside, unlike Cauchy's or Tukey's, measured to drop
    the points of curved parts on coarse grids)."""
    if settings.set_aside:
        return RobustLeastSquares(
            lam=settings.lam, loss="huber", max_steps=DEFAULT_ROBUST_STEPS, rtol=DEFAULT_ROBUST_RTOL
        )
    return LeastSquares(lam=settings.lam)


def set_aside_mask(points, settings):
    """``(m,)`` weights, 0 at the points ``settings`` set aside, or None where none were: the
    ``mask`` that fits without them (also for a caller that passes the automatic settings
    to :func:`fit` explicitly)."""
    if settings is None or not settings.set_aside:
        return None
    support = np.ones(len(points))
    support[list(settings.set_aside)] = 0.0
    return support


def automatic_fit_checks(sol, settings, points, normals):
    """The checks :func:`fit` makes after a fit with automatic ``settings``
    (:func:`_check_doubts`), for a fit made with them passed explicitly."""
    return _check_doubts(sol, settings, points, normals, None, settings.offset)


def _checked_shape(points, grid, solver, init) -> tuple[int, ...]:
    """The grid's shape, once the solver, the memory it takes and ``init`` are checked."""
    shape = normalise_grid(grid, _point_dimension(points))
    _check_start(shape, solver, init)
    check_memory(
        "grid=" + "x".join(map(str, shape)),  # points are checked by make_problem
        fit_memory(shape, 3 * (len(points) if hasattr(points, "__len__") else 0), solver),
    )
    return shape


def _check_start(shape, solver, init) -> None:
    """TypeError or ValueError unless ``solver`` is a jurs solver and ``init`` (if given) a
    finite spline on the grid ``shape``."""
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    if init is not None and not isinstance(init, ImplicitSpline):
        raise TypeError(f"init must be a jurs.ImplicitSpline, got {type(init).__name__}")
    if init is not None and tuple(init.shape) != shape:
        raise ValueError(f"init spline has grid {init.shape}, expected {shape}")
    if init is not None and _is_concrete(init):  # a NaN start ran into RESULTS.nonfinite
        check_spline_arrays({k: np.asarray(getattr(init, k)) for k in SPLINE_KEYS}, "init: ")


def _solve_fit(problem, solver, init, throw, given, settings=None):
    """The solve; at top level ``throw`` and the orientation of ``given`` (``(points,
    normals, mask)``; None: not checked, no host holds the cloud) checked on the host."""
    top_level = _at_top_level((problem, solver, init))
    run = _solve_reassociating if top_level and _reassociation_pays(problem, solver) else _solve
    if not top_level:
        return run(problem, solver, init, throw)
    # ``throw`` checked on the host after the call, not by a host callback inside it:
    # a compiled fit with a callback is never written to JAX's persistent compilation
    # cache, and without one a new process loads the fit instead of compiling it.
    # With jurs.enable_compilation_cache, the plain compilation also goes through the
    # store of exported fits: a new process skips its tracing too (call_stored).
    sol = (
        run(problem, solver, init, False)
        if run is _solve_reassociating or is_sharded(problem)  # the store is one-device
        else call_stored(_run, run, problem, solver, init, False)
    )
    if given is not None:
        sol = _check_orientation(sol, *given)
    # Automatic settings: the data were not looked at by a person.
    if settings is not None and given is not None:
        points, normals, mask = given
        sol = _check_doubts(sol, settings, points, normals, mask, problem.offset)
    if throw and sol.status in RAISED_RESULTS:
        raise eqx.EquinoxRuntimeError(error_message(sol.status))
    return sol


def fit_across_processes(
    points,
    normals,
    grid,
    solver,
    offset,
    eps,
    domain,
    margin,
    init,
    mask,
    bucket_size,
    smoothing,
    throw,
):
    """:func:`jurs.fit` of points and normals held by several processes (global
    ``jax.Array`` s split along the point axis, :func:`jurs._fit.sharding.spans_processes`);
    every process calls it with the same settings. The sample layout is built per process
    (:func:`jurs._fit.sharding.process_problem`), the solve is the one jitted function over
    all devices, and the fitted spline is replicated on every device. What reads the whole
    cloud on a host is not run: the automatic settings (ValueError unless ``grid``,
    ``offset``, ``eps``, ``domain`` and ``solver`` are given), the estimation of normals,
    the orientation and doubt checks, the padding to stable sizes and the store of
    exported fits (docs/sharding.md)."""
    if normals is None:
        raise ValueError(
            "normals=None estimates normals from the whole cloud, which no process holds "
            "here: estimate them per process (jurs.estimate_normals) and pass them split "
            "like the points"
        )
    given = dict(grid=grid, offset=offset, eps=eps, domain=domain, solver=solver)
    missing = [name for name in PROCESS_SETTINGS if given[name] is None]
    if missing or smoothing is not None:
        raise ValueError(
            "points split over several processes: the automatic settings read the whole "
            "cloud, which no process holds; pass "
            + (", ".join(missing) if missing else "a solver with its lam, not smoothing")
            + " explicitly (a fit over several processes needs all of "
            + f"{', '.join(PROCESS_SETTINGS)}), "
            "e.g. from jurs.auto_settings(points, normals) on a subsample in one process, "
            "solver=jurs.LeastSquares(lam=settings.lam)"
        )
    if mask is not None:
        raise ValueError("mask: fits over several processes take no mask (docs/sharding.md)")
    for name, x in (("points", points), ("normals", normals)):
        if not isinstance(x, jax.Array) or x.is_fully_addressable or x.ndim != 2:
            raise ValueError(
                f"{name}: over several processes pass points and normals both as global "
                "(m, d) jax.Arrays split the same way along the point axis "
                "(jax.make_array_from_process_local_data)"
            )
    shape = normalise_grid(grid, int(points.shape[1]))
    _check_start(shape, solver, init)  # memory: per process, by process_problem
    dtype = jnp.result_type(float)
    problem = process_problem(
        points, normals, shape, offset, eps, domain, margin, bucket_size, dtype, solver
    )
    sharding = input_sharding(points, normals)
    assert sharding is not None
    solver = replicate_across_processes(_as_arrays(solver, dtype), sharding)
    init = replicate_across_processes(init, sharding)
    return _solve_fit(problem, solver, init, throw, None)


def fit(
    points,
    normals=None,
    *,
    grid=None,
    solver: AbstractSolver | None = None,
    offset=None,
    eps=None,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    init: ImplicitSpline | None = None,
    mask=None,
    bucket_size: int | None = None,
    smoothing: float | None = None,
    throw: bool = True,
) -> Solution:
    """Fit an implicit spline whose zero set passes through ``points``.

    With nothing but points and normals, the grid, the offset d, eps and the solver are
    chosen from the data (:func:`jurs.auto_settings`: cells a few point spacings or noise
    widths wide, d from the spacing and noise, the exact solve :class:`jurs.LeastSquares`
    with a scale-free lambda, chosen by held-out points on noisy curves); ``sol.settings``
    records the choices. Points that stand alone, away from the shape, are then set aside
    (``sol.settings.set_aside``) and the rest fitted by ``RobustLeastSquares`` (Huber), and
    the fit is checked against the data: parts cut, gaps bridged or points left far from
    the zero set make the verdict ``doubtful``, with a warning and the reasons in
    ``sol.stats["doubts"]`` (docs/guide/settings.md). Give any setting to override it; the
    paper's Example 1 settings are ``grid=(9, 9), offset=0.1, eps=0.01``.

    Args:
        points: ``(m, 2)`` data points of a curve, or ``(m, 3)`` of a surface (then
            ``sol.spline`` is a trivariate g(x, y, z); see :func:`jurs.levelset.mesh`).
        normals: outward normals shaped like ``points`` (normalised here); None estimates
            and orients them first (:func:`jurs.estimate_normals`, on the host: concrete
            points only, no ``mask``), and ``sol.stats["estimated_normals"]`` then holds
            what the estimation found (``k``, ``components``, ``patches``, ...).
        grid: ``N`` or ``(N, M)`` basis functions along x and y (>= 4; ``(N, M, K)`` in
            3D); None chooses.
        solver: any jurs solver; None: ``LeastSquares(lam=settings.lam)``, the regularised
            exact solve. A solver given keeps its own lambda.
        offset: d, distance of the offset samples (eq. 4); None chooses.
        eps: target value at the offsets (eq. 5); None takes ``eps = d``.
        domain: ``((x_min, y_min), (x_max, y_max))`` or None for the samples' bounding box
            plus ``margin`` x its longest side.
        init: starting spline on the same box and grid; default C = 0, w = 1.
        mask: optional ``(m,)`` booleans, False marking padding points that take no part
            (for ``jax.vmap`` over clouds padded to one size).
        bucket_size: sample layout, see :func:`jurs.make_problem` (None chooses).
        smoothing: the dimensionless strength of the default solver's lambda
            (:func:`jurs.auto_settings`); None chooses. Only with ``solver=None``: a solver
            given keeps its own lambda.
        throw: raise ``equinox.EquinoxRuntimeError`` when the verdict says the fit is not
            a reconstruction (``failed``, ``nonfinite``, ``inconsistent_normals``,
            ``weights_at_floor``; never for ``max_steps_reached``). With ``throw=False``
            the Solution is returned and ``sol.result`` / ``sol.status`` say what
            happened (a non-finite run keeps its last finite iterate). Called outside any JAX
            transformation, the fit is checked once it has run, so this call then waits
            for it.

    Returns:
        :class:`jurs.Solution`. Jit-compiled inside; traceable, so ``jax.grad`` and
        ``jax.vmap`` go through it once ``grid``, ``offset``, ``eps`` and ``solver`` are
        given (automatic choices need concrete points; input checks run only on concrete
        inputs).

    Large problems (more than :data:`jurs._model.spline.TABLE_MAX_SLOTS` samples, or
    ``bucket_size > 1`` given) fitted by jurs's own solvers outside any JAX transformation
    are compiled with :data:`jurs.COMPILER_OPTIONS`, which vectorise their per-bucket sums
    (``benchmarks/results/speed.md`` times the IURS step at 1e6 points with and without
    them). The result then differs from the same fit under a caller's ``jit`` at rounding
    level.

    Shape-stable: a concrete cloud without a ``mask`` is padded to one of four sizes an
    octave (:func:`jurs._problem.sizes.padded_count`: ..., 896, 1024, 1280, 1536, ...) with
    masked-out points, and its sample layout sized from that, so that a new cloud of a
    similar size reuses the compiled fit instead of compiling again; automatic grids are
    rounded up likewise (:func:`jurs._fit.settings.choose_grid`). The padding changes the result
    only at rounding level. With :func:`jurs.enable_compilation_cache`, new processes load
    compiled (and traced) fits from the cache folder.

    Several devices: points (or normals) split along the point axis by a ``NamedSharding``
    over several devices are solved there, per-sample work on each device's samples and
    grid-sized sums all-reduced; in one process the sample layout is built from the whole
    cloud on the host. Points held by several processes (``jax.distributed``) are laid out
    by each process for its own rows; those fits need ``grid``, ``offset``, ``eps``,
    ``domain`` and ``solver`` given, and skip the checks that read the whole cloud
    (docs/sharding.md).
    """
    if spans_processes(points, normals):  # each process lays out its own part (jurs._fit.sharding)
        args = grid, solver, offset, eps, domain, margin, init, mask, bucket_size, smoothing, throw
        return fit_across_processes(points, normals, *args)
    estimated, solver_given = None, solver
    if normals is None:
        normals, estimated = _estimated_normals(points, mask)
    settings, grid, offset, eps, solver = _resolved_settings(
        points, normals, grid, offset, eps, solver, domain, margin, mask, smoothing
    )
    shape = _checked_shape(points, grid, solver, init)
    dtype = jnp.result_type(float)
    given = (points, normals, mask)  # before padding, for the orientation check
    automatic = solver_given is None and mask is None
    support = set_aside_mask(points, settings) if automatic else None
    if support is not None:  # the box that holds the points set aside too
        domain = settings.domain  # pyright: ignore[reportOptionalMemberAccess]
    problem = padded_problem(
        points, normals, mask, shape, offset, eps, domain, margin, bucket_size, dtype, support
    )
    # Points sharded over several devices: the problem split over them (jurs._fit.sharding).
    problem, solver, init = place_fit(points, normals, problem, _as_arrays(solver, dtype), init)
    sol = _solve_fit(problem, solver, init, throw, given, settings)
    if estimated is not None:
        sol = dataclasses.replace(sol, stats=dict(sol.stats, estimated_normals=estimated))
    return sol if settings is None else dataclasses.replace(sol, settings=settings)
