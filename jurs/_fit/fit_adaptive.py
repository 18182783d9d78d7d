"""[`jurs.fit_adaptive`][]: the fit on a THB hierarchy, in one process or sharded over
several devices or processes. This module checks its options; points over several
processes go to ``adaptive_sharding.fit_adaptive_across_processes``, others take
[`jurs.fit`][]'s flow (``fit.py``: the cloud, the settings, then ``on_hierarchy``). The
layout and host solves are ``adaptive.py``'s (with the reasoning), the sharded ones
``adaptive_sharding.py``'s.
"""

from __future__ import annotations

from jaxtyping import ArrayLike, Float

from .._cloud.cloud import Cloud
from .._solution.solution import Solution
from ..solvers import AbstractSolver
from .adaptive import METHODS, check_hierarchy_solver, solver_lam
from .adaptive_sharding import fit_adaptive_across_processes
from .fit import CLOUD_REFUSAL, fit_cloud, fit_settings, on_hierarchy
from .settings import Settings
from .sharding import spans_processes


def fit_adaptive(
    points: Float[ArrayLike, "m d"] | Cloud,
    normals: Float[ArrayLike, "m d"] | None = None,
    *,
    finest: int | None = None,
    band: int | None = None,
    offset: float | None = None,
    eps: float | None = None,
    domain=None,
    smoothing: float | None = None,
    lam: float | None = None,
    rtol: float | None = None,
    max_steps: int = 10_000,
    settings: Settings | None = None,
    method: str | None = None,
    dtype=None,
    checks: bool = True,
    throw: bool = True,
    solver: AbstractSolver | None = None,
) -> Solution:
    """Fit an implicit spline on an adaptive (THB) basis: fine cells in a band around the
    data, coarse ones elsewhere, so that the cost grows with the shape's boundary rather
    than with its box.

    Args:
        points, normals: ``(m, 2)`` or ``(m, 3)``; normals outward (estimated with
            [`jurs.estimate_normals`][] when None). Or a ``jurs.Cloud`` with its normals
            (then ``normals`` is None), checked and measured once for all its fits.
        finest: cells of the finest level along the box's longest side; None chooses the
            cell from the data, ``max(s, 4 sigma)`` (``3 s`` on a surface;
            ``CELL_SPACINGS``), at most ``MAX_FINEST`` cells.
        band: cells of each level kept fine around the cells that hold samples (at least
            1); None takes ``DEFAULT_BAND``: 1 on a curve, 2 on a surface.
        offset, eps, domain, smoothing: as in [`jurs.auto_settings`][]; chosen from the
            data when None. ``lam`` overrides the lambda made from ``smoothing``.
        rtol, max_steps: the conjugate gradients' stop rule; ``rtol`` None takes
            ``DEFAULT_RTOL`` (1e-7) in float64 and ``FLOAT32_RTOL`` (1e-5) in float32
            (a residual of 1e-7 is at float32's rounding, and CG would run to
            ``max_steps``).
        method: ``"direct"`` (a sparse factorisation on the host, QDLDL), ``"cg"``
            (conjugate gradients in JAX, the path that runs on a GPU), ``"host_cg"``
            (the same conjugate gradients run by SciPy on the host, faster on a CPU),
            ``"multigrid"`` (conjugate gradients in JAX preconditioned by a V-cycle over
            the hierarchy's nested spaces: 10-30 steps where Jacobi takes hundreds, each
            dearer; docs/multigrid.md, "The multilevel solve of the hierarchy") or
            ``"host_multigrid"`` (the same solve run by SciPy on the host);
            None takes ``"direct"`` for a curve; for a surface, whose factor fills in
            (3D nested dissection fill grows as n^(4/3)), ``"host_cg"`` where JAX's
            default device is a CPU and the points are not sharded, ``"cg"`` otherwise.
        dtype: of the fit's arrays; None takes JAX's default float (float64 with
            ``jax_enable_x64``). A direct solve factorises in float64 on the host either
            way.
        settings: the [`jurs.Settings`][] to take offset, eps, domain and smoothing from
            (skips the measurement). The points it sets aside (``settings.set_aside``:
            points that stand alone) are left out of the fit, as [`jurs.fit`][] leaves
            them out.
        checks: judge the fit against its cloud on the host, as [`jurs.fit`][] judges
            its automatic fits: the orientation of the normals (``inconsistent_normals``)
            and the doubts (``doubtful``: parts cut or bridged, points far from the zero
            set, closed components away from the data; the reasons in
            ``sol.stats["doubts"]``). False skips them.
        throw: raise ``equinox.EquinoxRuntimeError`` when the verdict says the fit is not a
            reconstruction (``nonfinite``, ``inconsistent_normals``; never for
            ``max_steps_reached`` or ``doubtful``), as [`jurs.fit`][] does.
        solver: None (the exact solve with ``lam``), [`jurs.LeastSquares`][] (the same,
            with its ``lam``), [`jurs.RobustLeastSquares`][] (its reweighted solves:
            outliers weighed down, ``sol.state.point_weights`` one per point fitted, in the
            cloud's order without the points ``settings`` set aside) or
            [`jurs.HeldOutLeastSquares`][] (its ``lam`` chosen among the candidates by
            held-out points: ``sol.state.lam``, ``sol.state.scores``). A solver keeps its
            own ``lam``, the weight of the hierarchy's ``R`` (pass no ``lam`` beside it).
            Other solvers run on the uniform grid only and are refused with the reason.
            A robust fit and a held-out choice run in one process, on points not sharded.

    Returns:
        A [`jurs.Solution`][] whose ``spline`` is a [`jurs.AdaptiveSpline`][];
        ``sol.stats`` holds ``num_steps`` (CG steps), ``residual``, ``levels``,
        ``active`` (functions per level) and ``finest`` (cells per axis of the finest
        level over the box). ``result`` is ``successful``, ``max_steps_reached`` (CG
        stopped first) or ``nonfinite``, or with ``checks`` the verdicts above.

    Points (and normals) sharded along the point axis over several devices, or split over
    several processes (``jax.distributed``), fit where they lie
    (``jurs._fit.adaptive_sharding``, docs/sharding.md "Adaptive fits"): CG splits the
    samples' rows over the devices and reduces only active-function-sized sums; a direct
    solve reads every shard on the host (one process), or factorises the processes'
    summed normal equations in each (over processes, where the settings are chosen over
    every process's points and the host checks are not run). ``sol.stats["devices"]``
    counts the devices.

    Differentiable: with the structure fixed (the same points' leaves), ``jax.grad``
    through [`jurs.internal.make_adaptive_problem`][] and the solve is exact (the solve
    sits behind ``lax.custom_linear_solve``).
    """
    if method is not None and method not in METHODS:
        raise ValueError(
            f"method must be one of {', '.join(map(repr, METHODS))} or None, got {method!r}"
        )
    if band is not None and band < 1:
        raise ValueError(f"band must be at least 1 cell, got {band}")
    check_hierarchy_solver(solver)
    lam = solver_lam(solver, lam, points, normals)
    if spans_processes(points, normals):  # each process assembles its own samples' rows
        return fit_adaptive_across_processes(
            points, normals, finest=finest, band=band, offset=offset, eps=eps, domain=domain,
            smoothing=smoothing, lam=lam, rtol=rtol, max_steps=max_steps, settings=settings,
            method=method, dtype=dtype, throw=throw,
        )  # fmt: skip
    if isinstance(points, Cloud) and (
        normals is not None or points.normals is None or points.mask is not None
    ):
        raise ValueError(CLOUD_REFUSAL)
    # Checked once (NaN, shapes, zero normals, degenerate clouds) and exact repeats
    # merged, whether or not the settings are given; kept as jurs.fit keeps its clouds.
    cloud, estimated = fit_cloud(points, normals)
    if settings is None:  # as jurs.auto_settings chooses them, where jurs.fit differs:
        # ``smoothing`` makes the hierarchy's lambda only (settings.smoothing is chosen),
        # and the offset chosen is not checked against a ``domain`` given.
        settings = fit_settings(cloud, None, None, offset, eps, domain)[0]
        assert settings is not None  # chosen
    return on_hierarchy(
        cloud, settings, finest=finest, band=band, offset=offset, eps=eps,
        smoothing=smoothing, lam=lam, rtol=rtol, max_steps=max_steps, method=method,
        dtype=dtype, checks=checks, throw=throw, solver=solver,
        noted=dict(estimated_normals=estimated),
    )  # fmt: skip
