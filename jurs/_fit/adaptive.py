"""``jurs.fit_adaptive``: the exact fit (``LeastSquares``' minimiser of ``E_d + lam R``) on a
THB hierarchy whose finest cells lie only in a band around the data.

Settings come from the same measurements as [`jurs.auto_settings`][] (offset d, eps, the
smoothing, the box); what changes is the resolution. A uniform grid is capped by the box
(``DEFAULT_MAX_GRID``); here the finest cell follows the data alone, ``max(k s, 4 sigma)``
with ``k = CELL_SPACINGS`` (one spacing on a curve, where a uniform grid takes 1.5; three
on a surface), and the levels above it are coarse everywhere but near the samples.

A curve's normal equations are assembled on the host and factorised (QDLDL's LDL^T); a
surface's are solved by conjugate gradients in JAX on the same assembled matrices, padded
to size classes so that a new cloud of a similar size compiles nothing, preconditioned
by their exact diagonal, which on the hierarchical basis keeps the step count nearly flat
as levels are added (docs/design.md section 8).
"""

from __future__ import annotations

import math
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import ArrayLike, Float

from .._cloud.cloud import Cloud
from .._cloud.measure import PROBES, strided_probes
from .._linalg.pcg import conjugate_gradients
from .._model.adaptive import AdaptiveSpline
from .._model.precision import on_device
from .._problem.adaptive import (
    AdaptiveProblem,
    adaptive_metrics,
    assemble_adaptive_problem,
    assembled_metrics,
    normal_matrices,
    normal_matvec,
    normal_rhs,
    sample_basis,
)
from .._problem.sizes import round_size
from .._solution.solution import RAISED_RESULTS, RESULTS, Solution, error_message
from .._solution.verdicts import evaluate_bucketed, judge, judged_points
from .settings import Settings, auto_settings, scale_free_lam
from .sharding import input_sharding, spans_processes

#: Cells of the coarsest level along the longest side, at least: it fixes the sign of g far
#: from the data, where a few cells suffice.
BASE_CELLS = 8
#: Finest cells along the longest side, at most (2D, 3D): the keys of a level are int32,
#: and beyond these the band's functions outgrow a 2-core machine's memory.
MAX_FINEST = {2: 4096, 3: 1024}
#: The band, in cells of each level, around the cells that hold samples (curve, surface).
#: On seven traced outlines (benchmarks/_realdata_cases.py, clean) a band of 1 gave the
#: same Chamfer distance as 2 to four digits, Hausdorff within 0.7 % and every ring, with
#: 40-45 % fewer active functions (docs/design.md section 8). A surface keeps 2 until
#: measured.
DEFAULT_BAND = {2: 1, 3: 2}
#: The finest cell in point spacings (curve, surface). A curve's adaptive fit takes
#: cells of one spacing, where the uniform grid takes 1.5: on two traced outlines
#: (benchmarks/_realdata_cases.py camera and text, clean), Chamfer fell 8 % and 18 % from
#: 1.5 to 1.0 and 2-4 % more at 0.75, for 50 % more active functions. A surface keeps the
#: uniform grid's 3 (not yet measured on the hierarchy).
CELL_SPACINGS = {2: 1.0, 3: 3.0}
#: CG stops at this residual, relative to ``|D^T b|``.
DEFAULT_RTOL = 1e-10
#: CG's stop rule in float32, where ``DEFAULT_RTOL`` is below rounding.
FLOAT32_RTOL = 1e-5
#: A direct solve whose relative residual exceeds this met a singular matrix.
DIRECT_RTOL = 1e-6
#: [`jurs.fit`][] with ``basis="auto"`` takes the adaptive basis where the uniform grid's
#: cells are at least this many times wider than the data ask for (``Settings.data_cell``):
#: nearer, the hierarchy's finest level is about the uniform grid itself, and buys no detail
#: for its cost (the noisy bunny of benchmarks/results/surfaces_adaptive.md, its finest
#: level 48 cells against the uniform grid's 45, fitted 4x slower for 5 % less Chamfer).
AUTO_REFINEMENT = 1.5
#: The automatic choice's limits on a surface: at most this many finest cells along the
#: longest side, and clouds of at most ``AUTO_MAX_SURFACE_POINTS`` points (larger ones keep
#: the uniform grid). At 1e5 points the hierarchy's fits (finest 64-384 cells, 87k-660k
#: functions) beat screened Poisson at its best depth of 8, 9 and 10 in Chamfer and
#: Hausdorff distance on all five shapes of benchmarks/surfaces.py, clean and noisy, where
#: the uniform grid lost on the bunny and the airplane; its warm fit took 20-60 s and 1.4-3.5
#: GB (benchmarks/results/surfaces_adaptive_1e5.md, 2-core CPU, CG on the host). Memory
#: and time follow the active functions (3.0-3.5 GB and 49-60 s at 575k-660k), which grow
#: with the points at three spacings a cell: at 1e6 points the cells the data ask for
#: (about 3x finer) would hold some 6 million functions, tens of GB, so there the grid is
#: kept (docs/design.md section 8).
AUTO_MAX_FINEST_3D = 384
AUTO_MAX_SURFACE_POINTS = 150_000
#: Where the uniform grid is capped, [`jurs.fit`][] fits it first and keeps it where its
#: zero set follows the data: 90 % of the points within this many spacings of it
#: (``uniform_residual``). On the quality suite's clean outlines the capped grid's fits
#: read 0.008-0.011 spacings on smooth shapes (ellipse, rose, lobes, annulus, Example 1,
#: glyphs) and the hierarchy's fits there matched their Chamfer distance to 2 % at 1.1-2x
#: the time; on shapes with detail the grid misses they read 0.030 (coins) and 0.067
#: (horse), where the hierarchy's Hausdorff distance was 2-3.5x smaller (docs/design.md
#: section 8, "The automatic choice of basis").
UNIFORM_RESIDUAL_SPACINGS = 0.02


def wants_adaptive(settings: Settings, points: int) -> bool:
    """Whether [`jurs.fit`][] with ``basis="auto"`` may fit ``points`` points on the
    adaptive basis: where the automatic uniform grid (``settings.grid``) was capped, its
    cells at least ``AUTO_REFINEMENT`` times wider than the data ask for
    (``settings.data_cell``), and, on a surface, the cloud within
    ``AUTO_MAX_SURFACE_POINTS``. It does where the capped grid's fit then leaves the data
    (``uniform_residual``)."""
    if settings.data_cell is None:  # the grid was given
        return False
    ndim = len(settings.grid)
    if ndim == 3 and points > AUTO_MAX_SURFACE_POINTS:
        return False
    return settings.cell_width >= AUTO_REFINEMENT * settings.data_cell


def uniform_residual(spline, cloud: Cloud, settings: Settings) -> float:
    """The 90th percentile of the data points' distances to the zero set of ``spline``, in
    the cloud's spacings (``settings.spacing``): at most ``PROBES`` points evenly strided,
    those set aside by the settings left out. [`jurs.fit`][] keeps a capped uniform fit
    where this is at most ``UNIFORM_RESIDUAL_SPACINGS``, and fits on the hierarchy
    otherwise."""
    points = cloud.points[judged_points(cloud, settings)]
    at = strided_probes(len(points), PROBES)
    _, distance = evaluate_bucketed(spline, points if at is None else points[at])
    # A nonfinite distance (a fit that failed) counts as far.
    distance = np.where(np.isfinite(distance), distance, np.inf)
    return float(np.quantile(distance, 0.9) / settings.spacing)


def auto_finest(settings: Settings) -> int | None:
    """The ``finest`` an automatic adaptive fit takes: None (chosen from the data) on a
    curve, and on a surface at most ``AUTO_MAX_FINEST_3D`` cells along the longest side."""
    if len(settings.grid) == 2:
        return None
    lower, upper = (np.asarray(v, float) for v in settings.domain)
    longest = float((upper - lower).max())
    asked = longest / data_finest_cell(settings, 3)  # finest cells the data ask for
    return AUTO_MAX_FINEST_3D if asked > AUTO_MAX_FINEST_3D else None


def data_finest_cell(settings: Settings, ndim: int) -> float:
    """The finest cell the data ask of the hierarchy: ``max(c s, 4 sigma)``, ``c =
    CELL_SPACINGS`` (one spacing on a curve, three on a surface)."""
    return max(CELL_SPACINGS[ndim] * settings.spacing, 4.0 * settings.noise)


def adaptive_layout(
    lower: np.ndarray, upper: np.ndarray, finest_cell: float
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...], int]:
    """``(lower, upper, base, levels)``: square cells of width ``finest_cell * 2^levels`` at
    level 0, at least ``BASE_CELLS`` along the longest side, the box grown at its upper end
    to a whole number of them."""
    extent = np.asarray(upper, float) - np.asarray(lower, float)
    longest = float(extent.max())
    levels = max(0, int(math.floor(math.log2(longest / (BASE_CELLS * finest_cell)))))
    coarse = finest_cell * 2**levels
    base = tuple(max(1, math.ceil(e / coarse - 1e-9)) for e in extent)
    upper = np.asarray(lower, float) + coarse * np.asarray(base, float)
    return np.asarray(lower, float), upper, base, levels


def solve_adaptive(
    problem: AdaptiveProblem, lam, rtol: float = DEFAULT_RTOL, max_steps: int = 10_000
):
    """``(control, steps, relative residual, metrics)``: the minimiser of ``E_d + lam R``
    on the problem's hierarchy (w = 1) by preconditioned CG; pure JAX, differentiable in
    the problem's samples and targets and in ``lam``."""
    basis = sample_basis(problem)
    matvec = normal_matvec(problem, lam, basis)
    rhs = normal_rhs(problem, basis)
    # The preconditioner changes the path, not the solution: no derivative through it.
    diagonal = lax.stop_gradient(problem.data_diagonal + lam * problem.regulariser_diagonal)
    # A function no sample and no counted neighbour pair reaches has a zero row: keep it
    # at 0 (its preconditioned residual is 0) instead of dividing by 0.
    inverse = jnp.where(diagonal > 0, 1.0 / jnp.where(diagonal > 0, diagonal, 1.0), 0.0)
    control, steps, residual = conjugate_gradients(
        matvec, rhs, precondition=lambda r: inverse * r, rtol=rtol, max_steps=max_steps
    )
    return control, steps, residual, adaptive_metrics(problem, control, lam, basis)


#: Smallest padded length of the arrays of an assembled CG solve (``size_class``).
MIN_CLASS = 256


def size_class(count: int) -> int:
    """The padded length for ``count`` entries: the next of four sizes an octave
    (``jurs._problem.sizes.round_size``: 4, 5, 6 or 7 times a power of two, at most 25 %
    padding), at least ``MIN_CLASS``. A solve compiled for one class serves every problem
    whose arrays fall in it."""
    return max(MIN_CLASS, round_size(count))


def _padded(values: np.ndarray, length: int, fill=0) -> np.ndarray:
    out = np.full((length,) + values.shape[1:], fill, values.dtype)
    out[: values.shape[0]] = values
    return out


def _coo(matrix, nnz: int, dtype):
    """``(rows, cols, values)`` of a SciPy sparse matrix padded to ``nnz`` entries with
    zeros at (0, 0), which add exactly nothing."""
    coo = matrix.tocoo()
    return (
        on_device(_padded(coo.row.astype(np.int32), nnz)),
        on_device(_padded(coo.col.astype(np.int32), nnz)),
        on_device(_padded(coo.data, nnz), dtype),
    )


@jax.jit
def _assembled_cg(collocation, regulariser, targets, diagonal, lam, rtol, max_steps):
    """CG on ``(D^T D + lam 2 G^T W G) c = D^T b`` from the padded COO entries of ``D``
    and ``2 G^T W G``: every shape is a size class, so a new cloud of a similar size
    compiles nothing. Padded functions have a zero row, right-hand side and diagonal,
    and stay 0."""
    rows, cols, values = collocation
    reg_rows, reg_cols, reg_values = regulariser
    n, count = diagonal.shape[0], targets.shape[0]

    def apply(c):  # D c
        return jax.ops.segment_sum(values * c[cols], rows, count)

    def transpose(v):  # D^T v
        return jax.ops.segment_sum(values * v[rows], cols, n)

    def matvec(c):
        regular = jax.ops.segment_sum(reg_values * c[reg_cols], reg_rows, n)
        return transpose(apply(c)) + lam * regular

    inverse = jnp.where(diagonal > 0, 1.0 / jnp.where(diagonal > 0, diagonal, 1.0), 0.0)
    return conjugate_gradients(
        matvec,
        transpose(targets),
        precondition=lambda r: inverse * r,
        rtol=rtol,
        max_steps=max_steps,
    )


def normal_diagonal(problem: AdaptiveProblem, lam: float) -> np.ndarray:
    """The diagonal of ``D^T D + lam 2 G^T W G`` (the CG's Jacobi preconditioner), on the
    host, in float64."""
    return np.asarray(problem.data_diagonal, float) + lam * np.asarray(
        problem.regulariser_diagonal, float
    )


def solve_assembled(
    problem: AdaptiveProblem, matrices, lam: float, rtol: float, max_steps: int, dtype
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)``: ``solve_adaptive``'s CG (the same
    preconditioner, the same stop rule) on the host-assembled matrices ``(D, 2 G^T W G)``
    of ``assemble_adaptive_problem``, padded to size classes (``size_class``) so that the
    compiled solve is shared between clouds. Not differentiable; the answer agrees with
    ``solve_adaptive``'s to the CG tolerance."""
    collocation, regulariser = matrices
    count, n = collocation.shape
    n_class = size_class(n)
    diagonal = normal_diagonal(problem, lam)
    control, steps, residual = _assembled_cg(
        _coo(collocation, size_class(collocation.nnz), dtype),
        _coo(regulariser, size_class(regulariser.nnz), dtype),
        on_device(_padded(np.asarray(problem.targets), size_class(count)), dtype),
        on_device(_padded(diagonal, n_class), dtype),
        on_device(lam, dtype),
        on_device(rtol, dtype),
        on_device(max_steps, np.int32),
    )
    return np.asarray(control)[:n], int(steps), float(residual)


def solve_host_cg(
    problem: AdaptiveProblem, matrices, lam: float, rtol: float, max_steps: int
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)``: ``solve_assembled``'s CG (the exact
    diagonal as preconditioner, the stop rule ``|r| <= rtol |D^T b|``) run by SciPy on the
    host, on the host matrices ``(D, 2 G^T W G)`` in CSR. Not differentiable.

    On a CPU it is the faster of the two: a product with the CSR matrices took 9.5 ms
    where XLA's segment sums over the same entries took 26 ms (a 20000-point bunny,
    128k functions, 2-core CPU; docs/design.md section 8). On a GPU, ``solve_assembled``.
    """
    from scipy.sparse import diags
    from scipy.sparse.linalg import LinearOperator, cg

    collocation, regulariser = (matrix.tocsr() for matrix in matrices)
    transposed = collocation.T.tocsr()
    n = collocation.shape[1]
    diagonal = normal_diagonal(problem, lam)
    inverse = np.where(diagonal > 0, 1.0 / np.where(diagonal > 0, diagonal, 1.0), 0.0)

    def matvec(c):
        return transposed @ (collocation @ c) + lam * (regulariser @ c)

    # LinearOperator(shape, matvec=...) builds a custom operator in __new__, which the
    # type stubs do not follow.
    normal = LinearOperator((n, n), matvec=matvec, dtype=float)  # pyright: ignore[reportCallIssue]
    rhs = transposed @ np.asarray(problem.targets, float)
    steps = 0

    def count(_):
        nonlocal steps
        steps += 1

    control, _ = cg(
        normal,
        rhs,
        rtol=rtol,
        atol=0.0,
        maxiter=max_steps,
        M=diags(inverse),
        callback=count,
    )
    scale = max(float(np.linalg.norm(rhs)), np.finfo(float).tiny)
    return control, steps, float(np.linalg.norm(matvec(control) - rhs)) / scale


def _upper_triangle(matrix):
    """The upper triangle (diagonal included) of a square CSC matrix, as CSC with sorted
    row indices."""
    from scipy.sparse import csc_matrix

    matrix.sort_indices()
    n = matrix.shape[1]
    columns = np.repeat(np.arange(n), np.diff(matrix.indptr))
    keep = matrix.indices <= columns
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(columns[keep], minlength=n), out=indptr[1:])
    return csc_matrix((matrix.data[keep], matrix.indices[keep], indptr), shape=matrix.shape)


def solve_direct(problem: AdaptiveProblem, lam: float, matrices=None):
    """``(control, relative residual)`` by a sparse direct factorisation on the host: no
    derivative, concrete problems only. ``matrices``: the problem's ``(D, 2 G^T W G)``
    (``assemble_adaptive_problem`` returns them), assembled here when None.

    The normal matrix is symmetric positive definite, so an LDL^T without pivoting does:
    QDLDL (the ``qdldl`` package, OSQP's factorisation: a small pip wheel for every
    platform, AMD ordering). Measured on two traced outlines (23.9k and 34.6k functions),
    it factorised and solved 1.3-2.5x faster than SciPy's SuperLU with COLAMD, the best
    of SuperLU's orderings here (docs/design.md section 8). A matrix QDLDL cannot factorise
    (a zero pivot: numerically singular, e.g. ``lam = 0`` with functions no sample
    reaches) goes to SuperLU, whose pivoting gives an answer whose residual says so.
    """
    if matrices is None:
        basis = np.asarray(sample_basis(problem))
        matrices = normal_matrices(problem.hierarchy, np.asarray(problem.positions), basis)
    collocation, regulariser = matrices
    matrix = (collocation.T @ collocation + lam * regulariser).tocsc()
    rhs = collocation.T @ np.asarray(problem.targets, float)
    return solve_normal(matrix, rhs)


def solve_normal(matrix, rhs: np.ndarray) -> tuple[np.ndarray, float]:
    """``(control, relative residual)`` of ``matrix c = rhs`` (a SciPy CSC symmetric
    positive definite matrix) by ``solve_direct``'s factorisation, on the host."""
    try:
        import qdldl

        # QDLDL reads the upper triangle; cut here in one pass over the entries (its own
        # cut goes through SciPy's triu, which sorts them again: 0.2-0.5 s at 24k functions).
        control = qdldl.Solver(_upper_triangle(matrix), upper=True).solve(rhs)
    except (ImportError, RuntimeError):
        from scipy.sparse.linalg import splu

        control = splu(matrix, permc_spec="COLAMD").solve(rhs)
    scale = max(float(np.linalg.norm(rhs)), np.finfo(float).tiny)
    return control, float(np.linalg.norm(matrix @ control - rhs)) / scale


def finest_cell_width(settings: Settings, ndim: int, finest: int | None) -> float:
    """The finest level's cell in ``settings.domain``: ``fit_adaptive``'s ``finest``
    cells along the longest side, or where None the data's (``data_finest_cell``), at
    most ``MAX_FINEST`` cells. ValueError for a ``finest`` outside 8 .. ``MAX_FINEST``."""
    lower, upper = (np.asarray(v, float) for v in settings.domain)
    longest = float((upper - lower).max())
    if finest is None:
        return max(data_finest_cell(settings, ndim), longest / MAX_FINEST[ndim])
    if not 8 <= int(finest) <= MAX_FINEST[ndim]:
        raise ValueError(
            f"finest must be between 8 and {MAX_FINEST[ndim]} cells in {ndim}D, got {finest}"
        )
    return longest / int(finest)


def hierarchy_layout(settings: Settings, ndim: int, finest, band, offset, eps, dtype) -> dict:
    """The keywords of ``assemble_adaptive_problem`` for a ``fit_adaptive`` call: the box
    and levels of the hierarchy (``adaptive_layout`` of ``settings.domain`` for the finest
    cell, ``finest_cell_width``), its band, and the offset, eps and dtype given or chosen."""
    cell = finest_cell_width(settings, ndim, finest)
    lower, upper = (np.asarray(v, float) for v in settings.domain)
    lower, upper, base, levels = adaptive_layout(lower, upper, cell)
    return dict(
        lower=lower,
        upper=upper,
        base=base,
        levels=levels,
        band=DEFAULT_BAND[ndim] if band is None else int(band),
        offset=settings.offset if offset is None else float(offset),
        eps=settings.eps if eps is None else float(eps),
        dtype=jnp.dtype(dtype or jnp.result_type(float)),
    )


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
            ``DEFAULT_RTOL`` in float64 and ``FLOAT32_RTOL`` in float32 (a residual of
            1e-10 is below float32's rounding, and CG would run to ``max_steps``).
        method: ``"direct"`` (a sparse factorisation on the host, QDLDL), ``"cg"``
            (conjugate gradients in JAX, the path that runs on a GPU), ``"host_cg"``
            (the same conjugate gradients run by SciPy on the host, faster on a CPU) or
            ``"multigrid"`` (SciPy's conjugate gradients on the host preconditioned by a
            V-cycle over the hierarchy's nested spaces: 10-30 steps where Jacobi takes
            hundreds, each dearer; docs/multigrid.md, "The multilevel solve of the
            hierarchy");
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
    if method not in (None, "direct", "cg", "host_cg", "multigrid"):
        raise ValueError(
            f"method must be 'direct', 'cg', 'host_cg', 'multigrid' or None, got {method!r}"
        )
    if band is not None and band < 1:
        raise ValueError(f"band must be at least 1 cell, got {band}")
    if spans_processes(points, normals):  # each process assembles its own samples' rows
        from .adaptive_sharding import fit_adaptive_across_processes

        return fit_adaptive_across_processes(
            points, normals, finest=finest, band=band, offset=offset, eps=eps, domain=domain,
            smoothing=smoothing, lam=lam, rtol=rtol, max_steps=max_steps, settings=settings,
            method=method, dtype=dtype, throw=throw,
        )  # fmt: skip
    if isinstance(points, Cloud):
        if normals is not None or points.normals is None or points.mask is not None:
            raise ValueError(
                "fit_adaptive(cloud): pass a jurs.Cloud with its normals and no mask, "
                "and no normals beside it"
            )
        cloud = points
    else:
        if normals is None:
            from .._cloud.normals import estimate_normals

            normals = cast(np.ndarray, estimate_normals(points))
        # Checked once (NaN, shapes, zero normals, degenerate clouds) and exact repeats
        # merged, whether or not the settings are given.
        cloud = Cloud(points, normals)
    if settings is None:
        settings = auto_settings(cloud, offset=offset, eps=eps, domain=domain)
    keep = judged_points(cloud, settings)  # the cloud has no mask: all but those set aside
    points_np = cloud.points[keep]
    normals_np = np.asarray(cloud.normals, float)[keep]
    ndim = points_np.shape[1]
    # Points sharded over devices (one process): CG keeps each device's samples there.
    sharding = input_sharding(cloud.given_points, cloud.given_normals)
    if method is None:
        on_cpu = sharding is None and jax.default_backend() == "cpu"
        method = "direct" if ndim == 2 else "host_cg" if on_cpu else "cg"
    layout = hierarchy_layout(settings, ndim, finest, band, offset, eps, dtype)
    lower, upper, dtype = layout["lower"], layout["upper"], layout["dtype"]
    problem, matrices = assemble_adaptive_problem(points_np, normals_np, **layout)
    hierarchy = problem.hierarchy
    finest_level = hierarchy.num_levels - 1
    finest_cell = float(np.max((upper - lower) / np.asarray(hierarchy.cells(finest_level))))
    if lam is None:
        strength = settings.smoothing if smoothing is None else float(smoothing)
        diagonal = float(np.linalg.norm(points_np.max(0) - points_np.min(0)))
        lam = scale_free_lam(strength, 3 * len(points_np), diagonal, lower, upper, finest_cell)
    if rtol is None:
        rtol = DEFAULT_RTOL if dtype == jnp.float64 else FLOAT32_RTOL
    if method == "direct":
        control_np, residual = solve_direct(problem, float(lam), matrices)
        control, steps = on_device(control_np, dtype), 0
        metrics = assembled_metrics(problem, matrices, control_np, float(lam))
        # A direct solve is exact up to rounding; a residual far above it means the
        # factorisation met a (numerically) singular matrix.
        tolerance = max(rtol, DIRECT_RTOL)
    elif method == "cg" and sharding is not None:
        from .adaptive_sharding import solve_sharded

        control_np, steps, residual, metrics = solve_sharded(
            problem, matrices, float(lam), float(rtol), int(max_steps), dtype, sharding
        )
        control = on_device(control_np, dtype)
        tolerance = rtol
    else:  # CG on the assembled matrices: SciPy on the host, or JAX (padded, compiled)
        args = (problem, matrices, float(lam), float(rtol), int(max_steps))
        # host_cg reads every sample on the host, as a direct solve does.
        if method == "multigrid":
            from .adaptive_multigrid import solve_host_multigrid

            control_np, steps, residual = solve_host_multigrid(*args)
        else:
            control_np, steps, residual = (
                solve_host_cg(*args) if method == "host_cg" else solve_assembled(*args, dtype)
            )
        control = on_device(control_np, dtype)
        metrics = assembled_metrics(problem, matrices, control_np, float(lam))
        tolerance = rtol
    spline = AdaptiveSpline(hierarchy, control, on_device(np.ones(control.shape), dtype))
    finite = bool(np.all(np.isfinite(np.asarray(control))))
    converged = float(residual) <= tolerance
    result = (
        RESULTS.successful
        if finite and converged
        else RESULTS.max_steps_reached
        if finite
        else RESULTS.nonfinite
    )
    stats = {
        "method": method,
        "num_steps": int(steps),
        "residual": float(residual),
        "levels": hierarchy.num_levels,
        "active": hierarchy.active_counts,
        "finest": hierarchy.cells(finest_level),
    }
    if sharding is not None:  # the devices the solve ran over (a direct solve: the host)
        stats["devices"] = len(sharding.device_set) if method == "cg" else 1
    sol = Solution(spline, metrics, stats, result, None, settings)
    if checks:
        sol = judge(sol, cloud, settings, layout["offset"])
    if throw and sol.status in RAISED_RESULTS:
        raise eqx.EquinoxRuntimeError(error_message(sol.status))
    return sol
