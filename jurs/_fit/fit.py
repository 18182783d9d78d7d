"""``jurs.fit``: points and normals in, a fitted implicit spline out.

The flow, each step once: the cloud checked and measured (``jurs.Cloud``), normals
estimated where none are given, the settings chosen where not given
(``jurs._fit.settings.choose_settings``), the problem laid out (padded to the size
ladder), the compiled solve (``jurs._fit.call``), then the host's verdicts
(``jurs._solution.verdicts.judge``). On the hierarchy (``on_hierarchy``) the layout and
solve are ``jurs._fit.adaptive``'s; [`jurs.fit_adaptive`][] takes its cloud
(``fit_cloud``), settings (``fit_settings``) and fit from here too."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections import OrderedDict
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._cloud.cloud import Cloud
from .._jit import as_arrays
from .._model.spline import ImplicitSpline
from .._problem.adaptive import assemble_adaptive_problem, assembled_metrics
from .._problem.memory import check_fit_memory
from .._problem.padding import padded_problem
from .._problem.problem import make_problem
from .._problem.sizes import DEFAULT_MARGIN
from .._problem.validate import (
    check_values,
    is_concrete,
    normalise_grid,
    shape_of,
    validate_settings,
)
from .._solution.solution import (
    Solution,
    raise_unless_reconstruction,
)
from .._solution.verdicts import judge, judged_points
from .._threads import release_freed_memory
from ..solvers import AbstractSolver, LeastSquares
from ..solvers._parts import solves_in_parts
from .adaptive import (
    UNIFORM_RESIDUAL_SPACINGS,
    auto_finest,
    check_hierarchy_solver,
    exact_solve,
    hierarchy_lam,
    hierarchy_layout,
    hierarchy_rtol,
    hierarchy_solution,
    hierarchy_stride,
    noise_decides,
    solve_on_hierarchy,
    solver_lam,
    uniform_residual,
    wants_adaptive,
)
from .adaptive_sharding import solve_sharded
from .call import check_start, solve_fit
from .processes import fit_across_processes
from .progress import chunked_run
from .settings import Settings, choose_settings, default_solver, set_aside_mask
from .sharding import input_sharding, place_fit, spans_processes

#: Problems a ``jurs.Cloud`` keeps, the latest first, for fits that repeat settings.
KEPT_PROBLEMS = 4
#: Clouds [`fit`][jurs.fit] keeps, by content, for fits that repeat their points (a loop
#: over lambdas, solvers or grids): the same arrays are then checked, measured and laid
#: out once. Only clouds of at most ``KEPT_CLOUD_POINTS`` points, where that host work
#: is most of a fit, so that what is kept stays small.
KEPT_CLOUDS = 4
KEPT_CLOUD_POINTS = 1 << 15
_kept_clouds: OrderedDict = OrderedDict()
#: The bases [`fit`][jurs.fit] takes: chosen from the data, the uniform grid, the hierarchy.
BASES = ("auto", "uniform", "adaptive")
#: Why a ``jurs.Cloud`` is refused on the hierarchy (``on_hierarchy``, ``jurs.fit_adaptive``).
CLOUD_REFUSAL = (
    "fit_adaptive(cloud): pass a jurs.Cloud with its normals and no mask, and no normals beside it"
)


def _content_key(*arrays) -> tuple | None:
    """A key naming the arrays by their content, dtype, shape and placement; None for
    clouds past ``KEPT_CLOUD_POINTS`` points."""
    key = []
    for array in arrays:
        if array is None:
            key.append(None)
            continue
        try:
            shape = tuple(np.shape(array))
        except (TypeError, ValueError):  # ragged: the Cloud names what is wrong
            return None
        if not shape or shape[0] > KEPT_CLOUD_POINTS:
            return None
        host = np.ascontiguousarray(np.asarray(array))
        if host.dtype.kind not in "fiub":  # not numbers: the Cloud refuses them
            return None
        digest = hashlib.blake2b(host.tobytes(), digest_size=16).digest()
        placement = str(getattr(array, "sharding", None))
        key.append((type(array).__name__, shape, host.dtype.str, placement, digest))
    return tuple(key)


def _cloud_of(points, normals, mask) -> Cloud:
    """``Cloud(points, normals, mask)``, the one built before where the same arrays were
    fitted lately (``KEPT_CLOUDS``): its checks, measurements and laid-out problems are
    then reused. A cloud whose points repeat is built anew each time, so that its warning
    is given each time."""
    key = _content_key(points, normals, mask)
    if key is not None and key in _kept_clouds:
        _kept_clouds.move_to_end(key)
        return _kept_clouds[key]
    cloud = Cloud(points, normals, mask)
    if key is not None and cloud.repeated == 0:
        _kept_clouds[key] = cloud
        while len(_kept_clouds) > KEPT_CLOUDS:
            _kept_clouds.popitem(last=False)
    return cloud


def fit_cloud(points, normals, mask=None) -> tuple[Cloud, dict | None]:
    """``(cloud, estimated)``: the cloud a fit of concrete ``points`` is made on, checked
    once: a ``jurs.Cloud`` with normals as it is; the one built lately for the same arrays
    (``_cloud_of``); or, without normals, one with outward normals from
    [`jurs.estimate_normals`][], ``estimated`` then what the estimation found (a dict,
    without the per-point confidence; else None)."""
    if isinstance(points, Cloud) and points.normals is not None:
        return points, None
    if normals is not None:
        return _cloud_of(points, normals, mask), None
    if (points.given_mask if isinstance(points, Cloud) else mask) is not None:
        raise ValueError(
            "normals=None estimates normals from the whole cloud: it takes no "
            "mask (estimate them with jurs.estimate_normals, then pad)"
        )
    from .._cloud.normals import estimate_normals  # SciPy's graphs: loaded when first needed

    given = points.given_points if isinstance(points, Cloud) else points
    normals, info = estimate_normals(given, return_info=True)
    return Cloud(given, normals), {k: v for k, v in info._asdict().items() if k != "confidence"}


def fit_settings(
    cloud: Cloud, settings: Settings | None, grid, offset, eps, domain,
    margin: float = DEFAULT_MARGIN, smoothing=None, solver: AbstractSolver | None = None,
) -> tuple[Settings | None, tuple[int, ...]]:  # fmt: skip
    """``(settings, shape)`` of a fit of ``cloud``, the values given checked first
    (``check_values``, ``validate_settings``): ``settings`` where given (chosen before, by
    the caller), else chosen here (``choose_settings``) where any of ``grid``, ``offset``,
    ``eps`` and ``solver`` is missing, else None (every setting given); ``shape`` the
    uniform grid, given or the settings', on which the fit's memory is checked once."""
    check_values(offset=offset, eps=eps, margin=margin, domain=domain)
    validate_settings(
        cloud.points, cloud.normals, cloud.mask, offset=offset, domain=domain, extent=cloud.extent
    )
    shape = None if grid is None else normalise_grid(grid, cloud.ndim)
    if settings is not None:
        shape = settings.grid if shape is None else shape
        check_fit_memory(shape, len(cloud), default_solver(settings) if solver is None else solver)
    elif shape is None or offset is None or eps is None or solver is None:
        # The memory on the chosen grid is checked there, before its first solve.
        settings = choose_settings(
            cloud, shape, offset, eps, domain, margin, smoothing, solver=solver
        )
        shape = settings.grid
    else:
        check_fit_memory(shape, len(cloud), solver)
    return settings, shape


def _problem_of(
    cloud: Cloud, shape, offset, eps, domain, margin, bucket_size, dtype, settings, on_host=False
):
    """The cloud's problem, padded to the size ladder (points set aside by ``settings``
    masked out), built on the host once per set of settings and kept on the cloud
    (``KEPT_PROBLEMS``): a fit that repeats its settings lays nothing out again.
    ``on_host``: one sample a slot, laid out in NumPy (for the exact solve in parts)."""
    support = set_aside_mask(cloud.points, settings)
    if support is not None:  # the box that holds the points set aside too
        domain = settings.domain
    try:
        key = (
            shape,
            float(offset),
            float(eps),
            None if domain is None else tuple(map(tuple, np.asarray(domain, float).tolist())),
            float(margin),
            bucket_size,
            np.dtype(dtype).name,
            None if settings is None else settings.set_aside,
            on_host,
        )
    except (TypeError, ValueError):  # traced settings (under grad): nothing to keep
        key = None
    kept = cloud.kept_problems
    if key is not None and key in kept:
        kept.move_to_end(key)
        return kept[key]
    problem = padded_problem(
        cloud.given_points,
        cloud.normals,
        cloud.given_mask,
        shape,
        offset,
        eps,
        domain,
        margin,
        bucket_size,
        dtype,
        support,
        on_host,
    )
    if key is not None and is_concrete(problem):
        kept[key] = problem
        while len(kept) > KEPT_PROBLEMS:
            kept.popitem(last=False)
    return problem


def _forget_large_problem(cloud: Cloud, problem) -> None:
    """Drops ``problem`` from those the cloud keeps (``_problem_of``) where the cloud has
    more than ``KEPT_CLOUD_POINTS`` points: a grid's trial refused for the hierarchy, whose
    laid-out samples would otherwise be held through the hierarchy's assembly and solve,
    the fit's peak. A smaller cloud keeps it for the next fit of the same settings."""
    if len(cloud) <= KEPT_CLOUD_POINTS:
        return
    kept = cloud.kept_problems
    for key in [key for key, value in kept.items() if value is problem]:
        del kept[key]


def _traced_fit(
    points, normals, grid, solver, offset, eps, domain, margin, init, mask, bucket_size, throw
):
    """[`fit`][jurs.fit] of traced points (under the caller's jit, grad or vmap): every
    setting given, the problem traced with them, no host checks."""
    if grid is None or offset is None or eps is None or solver is None:
        raise ValueError(
            "automatic settings need concrete points (they are chosen on the host); inside "
            "jit/grad/vmap pass grid, offset and eps explicitly, e.g. from "
            "jurs.auto_settings(points, normals) called outside"
        )
    if normals is None:
        raise ValueError(
            "normals=None estimates normals on the host from concrete points; "
            "under jit, grad or vmap pass normals (jurs.estimate_normals)"
        )
    shape = normalise_grid(grid, _point_dimension(points))
    check_start(shape, solver, init)
    check_fit_memory(shape, len(points), solver)
    dtype = jnp.result_type(float)
    problem = make_problem(
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
    )
    return solve_fit(problem, as_arrays(solver, dtype), init, throw)[0]


def _uniform_only(
    grid, solver, init, mask, bucket_size, run, points, normals, basis="auto"
) -> list[str]:
    """The arguments of a [`fit`][jurs.fit] call that only the uniform grid takes, by
    name; empty where the adaptive basis can fit it. Points sharded over the devices of
    one process take the automatic choice as unsharded (the grid's residual measured on
    the whole cloud on the host, the hierarchy fitted sharded:
    ``jurs._fit.adaptive_sharding``); points split over processes are fitted on the
    adaptive basis only when it is asked for (``basis="adaptive"``)."""
    given = dict(grid=grid, solver=solver, init=init, mask=mask, bucket_size=bucket_size)
    if basis == "adaptive":  # fit_adaptive takes a solver, or refuses it with the reason
        del given["solver"]
    names = [name for name, value in given.items() if value is not None]
    if run is not None:
        names.append("callback")
    if spans_processes(points, normals):
        if basis != "adaptive":
            names.append("points split over processes")
    elif not isinstance(points, Cloud) and not is_concrete(points, normals):
        names.append("traced points")
    return names


def _point_dimension(points) -> int:
    """The d of ``(m, d)`` points; 2 for anything else (make_problem names the error)."""
    try:
        shape = shape_of(points)
    except (TypeError, ValueError):
        return 2
    return shape[1] if len(shape) == 2 and shape[1] in (2, 3) else 2


def fit(
    points: Float[ArrayLike, "m d"] | Cloud,
    normals: Float[ArrayLike, "m d"] | None = None,
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
    settings: Settings | None = None,
    checks: bool = True,
    callback: Callable[[int, int], None] | None = None,
    throw: bool = True,
    basis: str = "auto",
) -> Solution:
    """Fit an implicit spline whose zero set passes through ``points``.

    With nothing but points and normals, the grid, the offset d, eps and the solver are
    chosen from the data ([`jurs.auto_settings`][]: cells a few point spacings or noise
    widths wide, d from the spacing and noise, the exact solve [`jurs.LeastSquares`][]
    with a scale-free lambda, chosen by held-out points on noisy curves); ``sol.settings``
    records the choices. Points that stand alone, away from the shape, are then set aside
    (``sol.settings.set_aside``) and the rest fitted by ``RobustLeastSquares`` (Huber), and
    the fit is checked against the data: parts cut, gaps bridged or points left far from
    the zero set make the verdict ``doubtful``, with a warning and the reasons in
    ``sol.stats["doubts"]`` (docs/guide/settings.md). Give any setting to override it; the
    paper's Example 1 settings are ``grid=(9, 9), offset=0.1, eps=0.01``.

    Where the data ask for finer cells than the automatic uniform grid affords (dense or
    detailed clouds: the grid capped at ``jurs.auto_settings``' ``max_grid``) and the capped
    grid's zero set does not follow the data closely, the fit is made on the adaptive basis
    instead ([`jurs.fit_adaptive`][]: fine cells in a band around the data, coarse ones
    elsewhere) and ``sol.spline`` is a [`jurs.AdaptiveSpline`][] (``basis`` below).

    Args:
        points: ``(m, 2)`` data points of a curve, or ``(m, 3)`` of a surface (then
            ``sol.spline`` is a trivariate g(x, y, z); see [`jurs.levelset.mesh`][]);
            or a ``jurs.Cloud``, checked and measured once for all its fits (then
            ``normals`` and ``mask`` come from it).
        normals: outward normals shaped like ``points`` (normalised here); None estimates
            and orients them first ([`jurs.estimate_normals`][], on the host: concrete
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
        bucket_size: sample layout, see [`jurs.make_problem`][] (None chooses).
        smoothing: the dimensionless strength of the default solver's lambda
            ([`jurs.auto_settings`][]); None chooses. Only with ``solver=None``: a solver
            given keeps its own lambda.
        settings: automatic settings chosen before ([`jurs.auto_settings`][] of the same
            cloud): the fit takes its grid, offset and eps from them (where not given) and,
            with ``solver=None``, their solver, points set aside and doubt checks, as if it
            had chosen them, without choosing again.
        checks: judge the fit against its cloud on the host (top-level calls only): the
            orientation of the normals (``inconsistent_normals``) and, with automatic
            settings, the doubts (``doubtful``). False skips them, for a caller who knows
            the data; a ``jurs.Cloud`` passed again makes the orientation check once.
        callback: called as ``callback(steps_done, max_steps)`` while the fit runs: an
            iterative solver (IPIA, IURS) then runs in chunks of steps on the one problem
            (``jurs._fit.progress.solve_in_chunks``, the same result), others in one
            call, reported when done. Top-level calls only.
        throw: raise ``equinox.EquinoxRuntimeError`` when the verdict says the fit is not a
            reconstruction (``failed``, ``nonfinite``, ``inconsistent_normals``,
            ``weights_at_floor``, ``weights_at_ceiling``; never for ``max_steps_reached``). With
            ``throw=False`` the Solution is returned and ``sol.result`` / ``sol.status`` say what
            happened (a non-finite run keeps its last finite iterate). Called outside any JAX
            transformation, the fit is checked once it has run, so this call then waits for it.
        basis: ``"auto"`` (default): where the uniform grid is capped, its cells
            ``jurs._fit.adaptive.AUTO_REFINEMENT`` times wider than the data ask for
            (``sol.settings.data_cell``; on a surface at most ``AUTO_MAX_FINEST_3D``
            finest cells a side), the uniform grid is fitted first and kept if 90 % of the
            points lie within ``UNIFORM_RESIDUAL_SPACINGS`` (0.02) spacings of its zero
            set, else the fit is made on the adaptive basis; ``sol.stats["uniform_residual"]``
            records that distance. A surface of more than ``AUTO_MAX_SURFACE_POINTS``
            (150000) points is fitted there on an evenly strided subsample of at most that
            many, with settings chosen for it (``sol.settings`` are the subsample's;
            ``sol.stats["hierarchy_points"]`` and ``["hierarchy_stride"]`` say which), its
            verdicts judged on the subsample; the grid's trial fits every point, its
            residual and the noise below then in the subsample's spacings. A cloud
            whose scatter (``sol.settings.noise``) is at least ``NOISY_SPACINGS`` (0.1)
            spacings, at which every capped grid measured was refused, goes to the
            adaptive basis without the grid's trial (``sol.stats["noise_spacings"]``
            records the scatter).
            Elsewhere the uniform grid. Any of ``grid``, ``solver``, ``init``,
            ``mask``, ``bucket_size``, a ``callback``, points split over processes, or
            traced points keep the uniform grid; points sharded over the devices of one
            process take the same choice as unsharded (the hierarchy then fitted with the
            sharded points: docs/sharding.md, "Adaptive fits"). ``"uniform"``: the uniform
            grid always. ``"adaptive"``: [`jurs.fit_adaptive`][] with the settings chosen here
            (it takes none of the uniform-only arguments above but ``solver``, and points
            sharded over devices or processes): a [`jurs.LeastSquares`][],
            [`jurs.RobustLeastSquares`][] or [`jurs.HeldOutLeastSquares`][] given fits the
            hierarchy with its own ``lam`` (the weight of the hierarchy's R); other solvers
            are refused with the reason.

    Returns:
        [`jurs.Solution`][]. Jit-compiled inside; traceable, so ``jax.grad`` and
        ``jax.vmap`` go through it once ``grid``, ``offset``, ``eps`` and ``solver`` are
        given (automatic choices need concrete points; input checks run only on concrete
        inputs).

    Large problems (more than ``jurs._model.spline.TABLE_MAX_SLOTS`` samples, or
    ``bucket_size > 1`` given) fitted by jurs's own solvers outside any JAX transformation
    are compiled with [`jurs.COMPILER_OPTIONS`][], which vectorise their per-bucket sums
    (``benchmarks/results/speed.md`` times the IURS step at 1e6 points with and without
    them). The result then differs from the same fit under a caller's ``jit`` at rounding
    level.

    Shape-stable: a concrete cloud without a ``mask`` is padded to a power of two
    (``jurs._problem.sizes.padded_count``: ..., 512, 1024, 2048, ...; four sizes an octave
    above 2^18 points) with masked-out points, and its sample layout sized from that, so
    that a new cloud in the same octave reuses the compiled fit instead of compiling
    again; automatic grids fall into classes, a curve's one grid an octave of points
    (``jurs._fit.settings.choose_grid``). The padding changes the result
    only at rounding level. With [`jurs.enable_compilation_cache`][], new processes load
    compiled (and traced) fits from the cache folder.

    Several devices: points (or normals) split along the point axis by a ``NamedSharding``
    over several devices are solved there, per-sample work on each device's samples and
    grid-sized sums all-reduced; in one process the sample layout is built from the whole
    cloud on the host. Points held by several processes (``jax.distributed``) are laid out
    by each process for its own rows; those fits need ``grid``, ``offset``, ``eps``,
    ``domain`` and ``solver`` given, and skip the checks that read the whole cloud
    (docs/sharding.md).
    """
    run = None if callback is None else functools.partial(chunked_run, callback=callback)
    sol, _ = _fit(
        points,
        normals,
        grid=grid,
        solver=solver,
        offset=offset,
        eps=eps,
        domain=domain,
        margin=margin,
        init=init,
        mask=mask,
        bucket_size=bucket_size,
        smoothing=smoothing,
        settings=settings,
        checks=checks,
        throw=throw,
        run=run,
        basis=basis,
    )
    return sol


def fit_in_chunks(
    points,
    normals,
    *,
    solver: AbstractSolver,
    chunk: int | None = None,
    checkpoints=(),
    callback: Callable[[int, int], None] | None = None,
    **fit_kwargs,
):
    """Run ``jurs.fit`` with ``solver`` in chunks of ``chunk`` steps.

    The fit [`jurs.fit`][] makes of the same arguments (one cloud, one problem, the
    same settings, checks and verdicts), its solve run by ``solve_in_chunks``
    (``jurs._fit.progress``).

    Args:
        solver: the solver; its ``max_steps`` is the total number of steps.
        chunk: steps per call at most (default ``chunk_size``); a chunk also ends at
            each checkpoint.
        checkpoints: step counts at which to keep the spline (e.g. ``(0, 10, 50, 200)``).
        callback: called as ``callback(steps_done, max_steps)`` after every chunk.
        **fit_kwargs: as for [`jurs.fit`][] (grid, offset, eps, domain, margin, init,
            mask, bucket_size, settings, checks); ``throw`` (default True) applies to the
            run's final verdict.

    Returns:
        ``(solution, snapshots)``: the final [`jurs.Solution`][], with ``num_steps`` and
        ``energy_history`` of the whole run, and a dict ``{step: spline}`` for the
        checkpoints reached (a run that converges early stops there).
    """
    unknown = set(fit_kwargs) - set(_CHUNKED_OPTIONS)
    if unknown:
        raise TypeError(f"fit_in_chunks got unexpected keyword arguments {sorted(unknown)}")
    defaults = fit.__kwdefaults__ or {}
    options = {name: fit_kwargs.get(name, defaults[name]) for name in _CHUNKED_OPTIONS}
    run = functools.partial(chunked_run, chunk=chunk, checkpoints=checkpoints, callback=callback)
    sol, snapshots = _fit(points, normals, solver=solver, run=run, **options)
    return sol, snapshots


#: The keywords fit_in_chunks passes on to jurs.fit (with jurs.fit's defaults).
_CHUNKED_OPTIONS = (
    "grid",
    "offset",
    "eps",
    "domain",
    "margin",
    "init",
    "mask",
    "bucket_size",
    "smoothing",
    "settings",
    "checks",
    "throw",
)


def estimate_doubt(sol: Solution, estimated: dict | None) -> Solution:
    """``sol`` with one more doubt where its verdict is ``inconsistent_normals`` on normals
    that jurs estimated itself (``estimated``: what ``fit_cloud`` found, None for normals
    given): the verdict's general advice, to orient the normals and fit again, is
    circular there, and the way out is other normals."""
    if estimated is None or sol.status != "inconsistent_normals":
        return sol
    doubt = (
        f"the normals were estimated by jurs (jurs.estimate_normals, {estimated['k']} "
        "neighbours a point) and the fit finds them inconsistent: the estimate could not "
        "orient this cloud (parts thinner or sparser than its neighbourhoods, pieces of "
        "an open scan seen from both sides, a nearly flat sheet). Estimating them again "
        "gives the same: pass the cloud's own normals (a scanner's or a mesh's), or "
        "normals estimated with another k (jurs.estimate_normals(points, k=...)) once "
        "checked"
    )
    doubts = tuple(sol.stats.get("doubts") or ()) + (doubt,)
    return dataclasses.replace(sol, stats=dict(sol.stats, doubts=doubts))


def on_hierarchy(
    cloud: Cloud, settings: Settings, *, finest=None, band=None, offset=None, eps=None,
    smoothing=None, lam=None, rtol=None, max_steps: int = 10_000, method=None, dtype=None,
    checks: bool = True, throw: bool = True, solver: AbstractSolver | None = None,
    noted: dict | None = None,
) -> Solution:  # fmt: skip
    """The fit of ``cloud`` (with normals, no mask) on the adaptive basis with
    ``settings``, in this process: [`jurs.fit_adaptive`][]'s, with its arguments, and
    [`jurs.fit`][]'s on the hierarchy. ``lam``: the solver's (``solver_lam``), or None
    for the lambda made from the smoothing (``hierarchy_lam``). ``noted``: entries for
    ``sol.stats`` (None values left out), e.g. what the normal estimation found."""
    if cloud.mask is not None:  # jurs.fit(cloud, settings=..., basis="adaptive")
        raise ValueError(CLOUD_REFUSAL)
    keep = judged_points(cloud, settings)  # the cloud has no mask: all but those set aside
    points = cloud.points[keep]
    normals = np.asarray(cloud.normals, float)[keep]
    ndim = points.shape[1]
    # Points sharded over devices (one process): CG keeps each device's samples there.
    sharding = input_sharding(cloud.given_points, cloud.given_normals)
    if method is None:
        on_cpu = sharding is None and jax.default_backend() == "cpu"
        method = "direct" if ndim == 2 else "host_cg" if on_cpu else "cg"
    layout = hierarchy_layout(settings, ndim, finest, band, offset, eps, dtype)
    dtype = layout["dtype"]
    problem, matrices = assemble_adaptive_problem(points, normals, **layout)
    if lam is None:
        diagonal = float(np.linalg.norm(points.max(0) - points.min(0)))
        lam = hierarchy_lam(
            settings, smoothing, 3 * len(points), diagonal, layout, problem.hierarchy
        )
    lam, rtol = float(lam), hierarchy_rtol(rtol, dtype)
    state, settled = None, True
    if method == "cg" and sharding is not None:
        control, steps, residual, metrics = solve_sharded(
            problem, matrices, lam, float(rtol), int(max_steps), dtype, sharding
        )
    else:  # a factorisation, or CG on the assembled matrices (SciPy, or JAX compiled)
        # host_cg reads every sample on the host, as a direct solve does.
        solve = exact_solve(method, problem, matrices, lam, float(rtol), int(max_steps), dtype)
        chosen: AbstractSolver = LeastSquares(lam=lam) if solver is None else solver
        control, steps, residual, state, settled = solve_on_hierarchy(
            chosen, problem, matrices, solve
        )
        del solve  # and the assembled normal equations it keeps
        lam = lam if state is None else float(chosen.fitted_lam(state))
        metrics = assembled_metrics(problem, matrices, control, lam)
    del matrices  # the verdicts read the spline, not the samples' matrices and positions
    # The devices the solve ran over, where the points are sharded (a direct solve: the host).
    stats = (
        {} if sharding is None else {"devices": len(sharding.device_set) if method == "cg" else 1}
    )
    sol = hierarchy_solution(
        problem.hierarchy, control, metrics, settings, method=method, steps=steps,
        residual=residual, rtol=rtol, dtype=dtype, settled=settled, state=state, **stats,
    )  # fmt: skip
    del problem
    if checks:
        sol = judge(sol, cloud, settings, layout["offset"])
    sol = estimate_doubt(sol, (noted or {}).get("estimated_normals"))
    raise_unless_reconstruction(sol, throw)
    noted = {name: value for name, value in (noted or {}).items() if value is not None}
    return dataclasses.replace(sol, stats=dict(sol.stats, **noted)) if noted else sol


@dataclasses.dataclass(frozen=True)
class _HierarchyCloud:
    """What [`jurs.fit`][]'s fit on the hierarchy takes: ``cloud`` with ``settings`` chosen
    for it, a large surface's evenly strided subsample (every ``stride``-th point) where
    ``stride > 1``; ``trial``: the whole cloud's settings, which the grid's trial takes."""

    cloud: Cloud
    settings: Settings
    trial: Settings
    stride: int = 1


def _hierarchy_cloud(
    cloud: Cloud, settings: Settings, given_values, strided: bool
) -> _HierarchyCloud:
    """The ``_HierarchyCloud`` of ``cloud`` with ``settings``: where ``strided`` (the
    automatic choice of basis) and the cloud has no mask, a large surface's subsample
    (``hierarchy_stride``) with settings chosen for it from ``given_values`` (those of
    [`jurs.fit`][] that fix settings, no solver among them)."""
    stride = hierarchy_stride(len(cloud), cloud.ndim) if strided and cloud.mask is None else 1
    if stride == 1 or cloud.normals is None:
        return _HierarchyCloud(cloud, settings, settings)
    fitted = Cloud(cloud.points[::stride], cloud.normals[::stride])
    chosen, _ = fit_settings(fitted, None, *given_values)
    if chosen is None:  # settings are chosen wherever no solver is given
        raise ValueError("a strided subsample's settings need the solver left to the fit")
    return _HierarchyCloud(fitted, chosen, settings, stride)


def _fit(
    points,
    normals,
    *,
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
    settings,
    checks,
    throw,
    run=None,
    basis="auto",
):
    """[`fit`][jurs.fit], its solve made by ``run(problem, solver, init, throw)``
    (default the compiled call, ``jurs._fit.call.solve_fit``) returning ``(solution,
    top_level, extra)``; returns ``(solution, extra)``. [`jurs.fit_in_chunks`][] runs
    the same flow with a chunked solve."""
    uniform_only = _uniform_only(grid, solver, init, mask, bucket_size, run, points, normals, basis)
    if basis not in BASES:
        raise ValueError(f"basis must be one of {', '.join(map(repr, BASES))}, got {basis!r}")
    if basis == "adaptive" and uniform_only:
        raise ValueError(
            "basis='adaptive' fits by exact least squares on a hierarchy chosen from the "
            f"data; it takes no {', '.join(uniform_only)} (leave them out, or basis='uniform')"
        )
    given_solver = solver  # the hierarchy takes the caller's, not the default one
    if basis == "adaptive":
        check_hierarchy_solver(solver)
    if spans_processes(points, normals):  # each process lays out its own part (jurs._fit.sharding)
        if run is not None:
            raise ValueError("a fit over several processes runs in one call: no callback")
        args = grid, solver, offset, eps, domain, margin, init, mask, bucket_size, smoothing, throw
        return fit_across_processes(points, normals, *args, basis=basis), None
    if smoothing is not None and solver is not None:
        raise ValueError(
            "smoothing sets the default solver's lambda; with a solver given, set its lam instead"
        )
    if isinstance(points, Cloud):
        if normals is not None or mask is not None:
            raise ValueError("fit(cloud): the cloud holds its normals and mask; pass neither")
    elif not is_concrete(points, normals, mask):
        if run is not None:
            raise ValueError("a chunked run or a callback needs concrete points (on the host)")
        args = grid, solver, offset, eps, domain, margin, init, mask, bucket_size, throw
        return _traced_fit(points, normals, *args), None
    # The cloud, checked once; its measurements are kept for every fit of it.
    cloud, estimated = fit_cloud(points, normals, mask)
    automatic = solver is None and cloud.mask is None
    doubted = settings is None or solver is None  # chosen here, or the solver with them
    offset_given = offset
    given_values = grid, offset, eps, domain, margin, smoothing, solver
    settings, shape = fit_settings(cloud, settings, *given_values)
    if settings is not None:  # chosen before (by the caller) or here: the values not given
        offset = settings.offset if offset is None else offset
        eps = settings.eps if eps is None else eps
        solver = default_solver(settings) if solver is None else solver
    # The chosen offset, in the box given (fit_adaptive, which fits settings.domain, does
    # not check it).
    if domain is not None and offset_given is None:
        args = cloud.points, cloud.normals, cloud.mask
        validate_settings(*args, offset=offset, domain=domain, extent=cloud.extent)
    # Where the automatic uniform grid is capped below what the data ask for, it is fitted
    # first and kept if its zero set follows the data; otherwise the hierarchy is fitted.
    escalate = (
        basis == "auto" and not uniform_only and settings is not None and wants_adaptive(settings)
    )

    # A large surface's hierarchy fits an evenly strided subsample with settings of its own
    # (``hierarchy_stride``); the noise and the grid's trial are then measured in the
    # spacings of those points, which bound the detail that fit can resolve.
    hierarchy = None  # what a fit on the hierarchy takes, where one may be made
    if settings is not None and (escalate or basis == "adaptive"):
        hierarchy = _hierarchy_cloud(cloud, settings, given_values, strided=escalate)
        escalate = escalate and wants_adaptive(settings, hierarchy.settings.data_cell)
    escalation = hierarchy if escalate else None  # the fit the grid's trial may give way to

    def on_the_hierarchy(hierarchy: _HierarchyCloud, noted: dict, **given):
        """The fit on the hierarchy, what led to it noted in its stats."""
        noted = dict(estimated_normals=estimated, **noted)
        if hierarchy.stride > 1:
            noted.update(hierarchy_stride=hierarchy.stride, hierarchy_points=len(hierarchy.cloud))
        finest = auto_finest(hierarchy.settings)
        sol = on_hierarchy(
            hierarchy.cloud, hierarchy.settings, finest=finest, checks=checks, throw=throw,
            noted=noted, **given,
        )  # fmt: skip
        return sol, None

    if hierarchy is not None and basis == "adaptive":
        # A robust solver is refused on points sharded over devices, as fit_adaptive refuses it.
        lam = solver_lam(given_solver, None, cloud.given_points, cloud.given_normals)
        return on_the_hierarchy(hierarchy, {}, offset=offset, eps=eps, lam=lam, solver=given_solver)
    if escalation is not None and noise_decides(escalation.settings):
        # The grid's trial would be refused.
        scatter = escalation.settings.noise / escalation.settings.spacing
        return on_the_hierarchy(escalation, dict(noise_spacings=scatter))
    check_start(shape, solver, init)
    dtype = jnp.result_type(float)
    # The exact solve in parts reads one sample a slot: laid out on the host, nothing
    # compiled for the layout of a new count of points (a fit that does not take the
    # parts after all, e.g. under a transformation, solves this layout whole).
    in_parts = (
        run is None
        and bucket_size is None
        and input_sharding(cloud.given_points, cloud.given_normals) is None
        and solves_in_parts(len(cloud), shape, solver, init)
    )
    problem = _problem_of(
        cloud,
        shape,
        offset,
        eps,
        domain,
        margin,
        bucket_size,
        dtype,
        settings if automatic else None,
        in_parts,
    )
    # Points sharded over several devices: the problem split over them (jurs._fit.sharding).
    problem, solver, init = place_fit(
        cloud.given_points, cloud.given_normals, problem, as_arrays(solver, dtype), init
    )
    if run is None:
        # An escalated fit's failure is the hierarchy's to raise, not the grid's.
        trial = escalation is not None
        (sol, top_level), extra = solve_fit(problem, solver, init, throw and not trial), None
    else:
        sol, top_level, extra = run(problem, solver, init, throw)
    if escalation is not None and top_level:
        residual = (
            uniform_residual(sol.spline, cloud, escalation.trial, escalation.settings.spacing)
            if sol.status == "successful"
            else float("inf")
        )
        if residual > UNIFORM_RESIDUAL_SPACINGS:
            _forget_large_problem(cloud, problem)
            del sol, extra, problem  # the trial's arrays, freed before the hierarchy's
            release_freed_memory()
            return on_the_hierarchy(escalation, dict(uniform_residual=residual))
        sol = dataclasses.replace(sol, stats=dict(sol.stats, uniform_residual=residual))
    if top_level:
        if checks:
            outliers = type(solver).expects_outliers
            sol = judge(sol, cloud, settings if doubted else None, offset, outliers)
        sol = estimate_doubt(sol, estimated)
        raise_unless_reconstruction(sol, throw)
    if estimated is not None:
        sol = dataclasses.replace(sol, stats=dict(sol.stats, estimated_normals=estimated))
    return (sol if settings is None else dataclasses.replace(sol, settings=settings)), extra
