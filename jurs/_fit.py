"""``jurs.fit``: points and normals in, a fitted implicit spline out."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ._compile import COMPILER_OPTIONS, call_stored, padded_count
from ._defaults import auto_settings
from ._io import SPLINE_KEYS, check_spline_arrays
from ._problem import (
    DEFAULT_MARGIN,
    _is_concrete,
    _shape,
    check_memory,
    flipped_normal_fraction,
    make_problem,
    normalise_grid,
    orientation_sample,
    tangential_normal_fraction,
)
from ._sharding import is_sharded, place_fit
from ._solution import RAISED_RESULTS, RESULTS, Solution, error_message
from ._spline import ImplicitSpline
from .solvers import IPIA, IURS, AbstractSolver, LeastSquares, solve


def _as_arrays(tree, dtype):
    """Python floats -> 0-d arrays, so new hyperparameter values do not recompile."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if isinstance(x, float) else x, tree
    )


def padded_cloud(points, normals):
    """``(points, normals, mask)`` padded to :func:`jurs._compile.padded_count` points with
    masked-out copies of the first point (inside any box the cloud fits in), or None where
    the inputs are traced or malformed (make_problem then reports them as given).

    Why: a compiled fit is specialised to its array shapes; clouds padded to one of a few
    sizes, with a layout sized from that (``make_problem(stable_shapes=True)``), reuse one
    compilation. Masked points take no part in the fit, so the result is the unpadded one
    up to rounding (the per-bucket sums group the samples differently).
    """
    if not _is_concrete(points, normals):
        return None
    try:  # ragged lists: make_problem names them
        p, n = np.asarray(points), np.asarray(normals)
    except (TypeError, ValueError):
        return None
    if p.ndim != 2 or p.shape[1] not in (2, 3) or n.shape != p.shape or p.shape[0] < 3:
        return None
    m = p.shape[0]
    extra = padded_count(m) - m
    mask = np.arange(m + extra) < m
    return (
        np.concatenate([p, np.repeat(p[:1], extra, axis=0)]),
        np.concatenate([n, np.repeat(n[:1], extra, axis=0)]),
        mask,
    )


#: More than this fraction of the points with normals flipped against their neighbours
#: (:func:`jurs._problem.flipped_normal_fraction`), or with normals along the curve
#: (:func:`jurs._problem.tangential_normal_fraction`), makes a fit
#: ``inconsistent_normals``: consistent clouds measured 0 and at most 0.03 (0.12 flipped
#: on a horse sampled coarser than its legs); half or every other normal flipped 0.5,
#: random normals about 0.5 along the curve.
MAX_FLIPPED_FRACTION = 0.2
MAX_TANGENTIAL_FRACTION = 0.2


#: Peak bytes a fit holds per coefficient: the exact solve and the normal-equation form
#: assemble the 49-point stencil of D^T D and solve with it (LeastSquares measured 0.8 GB,
#: 3.1 KB a coefficient, at 512 x 512, peak resident memory above the process' baseline
#: on this 2-core CPU; XLA asked for 2.5 KB a coefficient at 10000 x 10000); the
#: per-sample iterations hold a few grids (IURS: 0.19 GB at 64 x 64 and at 256 x 256,
#: compilation included). At 2000 x 2000 it held 10 GB (2.5 KB a coefficient) after 8
#: minutes and was still growing: the limit is twice the largest rate measured, so that a
#: fit it lets through does not run the machine out of memory.
BYTES_PER_COEFFICIENT = 8192
BYTES_PER_COEFFICIENT_ITERATIVE = 1024
#: Peak bytes per sample (positions, basis values, residuals).
BYTES_PER_SAMPLE = 256
#: The same for surfaces (3D), from peak resident sets on this 2-core CPU: the 343-point
#: stencil, the per-cell moments it is folded from and the fold's intermediates (a 64^3 fit
#: of 2e4 points peaked at 4.8 GB, 18 KB a coefficient), and each sample's 64 gathered
#: coefficients and basis products (1e6 points at 48^3 peaked at 10 GB: 2.9 KB a sample
#: after the grid's share).
BYTES_PER_COEFFICIENT_3D = 20480
BYTES_PER_SAMPLE_3D = 3072


def fit_memory(shape, num_samples: int, solver) -> float:
    """Estimated peak bytes of a fit on an ``(N, M)`` (or ``(N, M, K)``) grid with
    ``num_samples`` samples (:data:`BYTES_PER_COEFFICIENT`, :data:`BYTES_PER_SAMPLE` and
    their 3D counterparts)."""
    surface = len(shape) == 3
    if isinstance(solver, (IPIA, IURS)):
        per_coefficient = BYTES_PER_COEFFICIENT_ITERATIVE
    else:
        per_coefficient = BYTES_PER_COEFFICIENT_3D if surface else BYTES_PER_COEFFICIENT
    per_sample = BYTES_PER_SAMPLE_3D if surface else BYTES_PER_SAMPLE
    return float(per_coefficient * np.prod(shape) + per_sample * num_samples)


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
    from ._orientation import estimate_normals  # SciPy's graphs: loaded when first needed

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
    solver = LeastSquares(lam=settings.lam) if solver is None else solver
    return settings, settings.grid, settings.offset, settings.eps, solver


def _checked_shape(points, grid, solver, init) -> tuple[int, ...]:
    """The grid's shape, once the solver, the memory it takes and ``init`` are checked."""
    shape = normalise_grid(grid, _point_dimension(points))
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    check_memory(
        "grid=" + "x".join(map(str, shape)),  # points are checked by make_problem
        fit_memory(shape, 3 * (len(points) if hasattr(points, "__len__") else 0), solver),
    )
    if init is not None and not isinstance(init, ImplicitSpline):
        raise TypeError(f"init must be a jurs.ImplicitSpline, got {type(init).__name__}")
    if init is not None and tuple(init.shape) != shape:
        raise ValueError(f"init spline has grid {init.shape}, expected {shape}")
    if init is not None and _is_concrete(init):  # a NaN start ran into RESULTS.nonfinite
        check_spline_arrays({k: np.asarray(getattr(init, k)) for k in SPLINE_KEYS}, "init: ")
    return shape


def _padded_problem(points, normals, mask, shape, offset, eps, domain, margin, bucket_size, dtype):
    """:func:`make_problem` of the cloud, padded (:func:`padded_cloud`) when it has no mask."""
    # The problem is built outside the solver's jit: its sample layout is chosen on the
    # host from concrete data (see make_problem); under a caller's jit/grad/vmap it is traced.
    padded = padded_cloud(points, normals) if mask is None else None
    if padded is not None:  # shape-stable: clouds of similar size share one compiled fit
        points, normals, mask = padded
    return make_problem(
        points,
        normals,
        grid=shape,
        offset=offset,
        eps=eps,
        domain=domain,
        margin=margin,
        mask=mask,
        bucket_size=bucket_size,
        dtype=dtype,
        stable_shapes=padded is not None,
    )


def _solve_fit(problem, solver, init, throw, given):
    """The solve; at top level ``throw`` and the orientation of ``given`` checked on the host."""
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
    sol = _check_orientation(sol, *given)
    if throw and sol.status in RAISED_RESULTS:
        raise eqx.EquinoxRuntimeError(error_message(sol.status))
    return sol


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
    with a scale-free lambda); ``sol.settings`` records the choices. Give any of them to
    override; the paper's Example 1 settings are ``grid=(9, 9), offset=0.1, eps=0.01``.

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

    Large problems (more than :data:`jurs._spline.TABLE_MAX_SLOTS` samples, or
    ``bucket_size > 1`` given) fitted by jurs's own solvers outside any JAX transformation
    are compiled with :data:`jurs.COMPILER_OPTIONS`, which vectorise their per-bucket sums
    (``benchmarks/results/speed.md`` times the IURS step at 1e6 points with and without
    them). The result then differs from the same fit under a caller's ``jit`` at rounding
    level.

    Shape-stable: a concrete cloud without a ``mask`` is padded to one of four sizes an
    octave (:func:`jurs._compile.padded_count`: ..., 896, 1024, 1280, 1536, ...) with
    masked-out points, and its sample layout sized from that, so that a new cloud of a
    similar size reuses the compiled fit instead of compiling again; automatic grids are
    rounded up likewise (:func:`jurs._defaults.choose_grid`). The padding changes the result
    only at rounding level. With :func:`jurs.enable_compilation_cache`, new processes load
    compiled (and traced) fits from the cache folder.

    Several devices: points (or normals) split along the point axis by a ``NamedSharding``
    over several devices are solved there, per-sample work on each device's samples and
    grid-sized sums all-reduced; the sample layout is still built from the whole cloud on
    the host, in one process (docs/sharding.md).
    """
    estimated = None
    if normals is None:
        normals, estimated = _estimated_normals(points, mask)
    settings, grid, offset, eps, solver = _resolved_settings(
        points, normals, grid, offset, eps, solver, domain, margin, mask, smoothing
    )
    shape = _checked_shape(points, grid, solver, init)
    dtype = jnp.result_type(float)
    given = (points, normals, mask)  # before padding, for the orientation check
    problem = _padded_problem(
        points, normals, mask, shape, offset, eps, domain, margin, bucket_size, dtype
    )
    # Points sharded over several devices: the problem split over them (jurs._sharding).
    problem, solver, init = place_fit(points, normals, problem, _as_arrays(solver, dtype), init)
    sol = _solve_fit(problem, solver, init, throw, given)
    if estimated is not None:
        sol = dataclasses.replace(sol, stats=dict(sol.stats, estimated_normals=estimated))
    return sol if settings is None else dataclasses.replace(sol, settings=settings)
