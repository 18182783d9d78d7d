"""The layout and host solves of ``jurs.fit_adaptive`` (``fit_adaptive.py``): the exact fit
(``LeastSquares``' minimiser of ``E_d + lam R``) on a THB hierarchy whose finest cells lie
only in a band around the data.

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

import abc
import functools
import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array, lax

from .._cloud.cloud import Cloud
from .._cloud.measure import PROBES, strided_probes
from .._linalg.pcg import conjugate_gradients, host_conjugate_gradients, jacobi_inverse
from .._linalg.sparse import PaddedCoo, normal_product, normal_system, ordered_rows
from .._linalg.thb_multigrid import ThbMultigrid, VCycle, multigrid_cg
from .._model.adaptive import AdaptiveSpline
from .._model.precision import on_device, scalar_array
from .._problem.adaptive import (
    AdaptiveProblem,
    adaptive_metrics,
    column_squares,
    normal_matvec,
    normal_rhs,
    problem_matrices,
    sample_basis,
)
from .._problem.sizes import padded_to, round_size
from .._solution.solution import RESULTS, Solution
from .._solution.verdicts import judged_points, values_and_distances
from ..solvers import (
    IPIA,
    IURS,
    AbstractSolver,
    HeldOutLeastSquares,
    HeldOutLeastSquaresState,
    LeastSquares,
    NormalIPIA,
    RobustLeastSquares,
    RobustLeastSquaresState,
)
from ..solvers._held_out import capped_distance, held_out_points, stops_search
from .settings import Settings, scale_free_lam
from .sharding import input_sharding, spans_processes

#: Cells of the coarsest level along the longest side, at least: it fixes the sign of g far
#: from the data, where a few cells suffice.
BASE_CELLS = 8
#: Finest cells along the longest side, at most (2D, 3D): the keys of a level are int32,
#: and beyond these the band's functions outgrow a workstation's memory (docs/performance.md).
MAX_FINEST = {2: 4096, 3: 1024}
#: The band, in cells of each level, around the cells that hold samples (curve, surface).
#: On seven traced outlines (benchmarks/_realdata_cases.py, clean) a band of 1 gave the
#: same Chamfer distance as 2 to four digits, Hausdorff within 0.7 % and every ring, with
#: 40-45 % fewer active functions (docs/design.md section 8). A surface keeps 2: on the
#: clean 1e5-point bunny a band of 1 halved the functions for the same Chamfer and
#: Hausdorff distances, but its samples near the narrower band reach coarser, truncated
#: functions, so ``D`` and ``2 G^T W G`` held more entries a row and CG's steps cost more
#: than the functions saved (docs/performance.md, "A surface's band").
DEFAULT_BAND = {2: 1, 3: 2}
#: The finest cell in point spacings (curve, surface). A curve's adaptive fit takes
#: cells of one spacing, where the uniform grid takes 1.5: on two traced outlines
#: (benchmarks/_realdata_cases.py camera and text, clean), Chamfer fell 8 % and 18 % from
#: 1.5 to 1.0 and 2-4 % more at 0.75, for 50 % more active functions. A surface keeps the
#: uniform grid's 3 (not yet measured on the hierarchy).
CELL_SPACINGS = {2: 1.0, 3: 3.0}
#: CG stops at this residual, relative to ``|D^T b|``. Far below what moves a fit: on a
#: 1e5-point surface the coefficients then lie within 1e-4 eps of the converged ones
#: (docs/performance.md, "CG's stop rule"), a shift of the zero set far below a lattice
#: spacing, while the last orders of magnitude to 1e-10 cost CG a third of its steps.
DEFAULT_RTOL = 1e-7
#: CG's stop rule in float32, where ``DEFAULT_RTOL`` is below rounding.
FLOAT32_RTOL = 1e-5
#: ``host_cg`` multiplies by the assembled normal matrix (``normal_system``) where the
#: samples are at least this many times the functions, and by ``D`` and ``R`` (three
#: passes over their entries a step) otherwise. The assembled matrix holds about 120-140
#: entries a function in 3D against ``D``'s 64 a sample, so with many samples a function
#: its steps cost a fraction of the others and its assembly (``gram``) pays for itself
#: within a solve; with few (a clean cloud's fine band), it holds more entries than
#: ``D`` and ``R`` together (docs/performance.md, "The hierarchy's CG on the assembled
#: matrix").
ASSEMBLED_SAMPLES_PER_FUNCTION = 2.0
#: A direct solve whose relative residual exceeds this met a singular matrix.
DIRECT_RTOL = 1e-6
#: [`jurs.fit`][] with ``basis="auto"`` takes the adaptive basis where the uniform grid's
#: cells are at least this many times wider than the data ask for (``Settings.data_cell``):
#: nearer, the hierarchy's finest level is about the uniform grid itself, and buys no detail
#: for its cost (the noisy bunny of benchmarks/results/surfaces_adaptive.md, its finest
#: level 48 cells against the uniform grid's 45, fitted 4x slower for 5 % less Chamfer).
AUTO_REFINEMENT = 1.5
#: The automatic choice's limits on a surface: at most this many finest cells along the
#: longest side, and at most ``AUTO_MAX_SURFACE_POINTS`` points fitted on the hierarchy. At
#: 1e5 points the hierarchy's fits (finest 64-384 cells, 87k-660k functions) beat screened
#: Poisson at its best depth of 8, 9 and 10 in Chamfer and Hausdorff distance on all five
#: shapes of benchmarks/surfaces.py, clean and noisy, where the uniform grid lost on the
#: bunny and the airplane (their time and memory: benchmarks/results/surfaces_adaptive_1e5.md,
#: docs/performance.md). Memory and time follow the active functions, which grow with the
#: points at three spacings a cell: at 1e6 points the cells the data ask for (about 3x
#: finer) would hold some 6 million functions, about ten times the largest measured. So a
#: larger cloud's hierarchy fits an evenly strided subsample of at most
#: ``AUTO_MAX_SURFACE_POINTS`` points (``hierarchy_stride``), with settings chosen for it:
#: on the 1e6-point bunny that beat the 48-cell grid fitted to every point, clean and noisy
#: (docs/design.md section 8, "The automatic choice of basis").
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
#: A cloud whose scatter about local quadratics (``Settings.noise``, sigma: noise, or
#: detail finer than a point's neighbours) is at least this many spacings goes to the
#: hierarchy without fitting the capped grid first. A capped grid follows part of such
#: scatter: the lowest residual measured against it was the clean coins' (0.030 spacings at
#: sigma 0.082, 0.23 times 1.6 sigma, 1.6 sigma being the 90th percentile of a normal
#: scatter's distances); at that ratio a sigma of 0.1 spacings still reads 0.037, above
#: ``UNIFORM_RESIDUAL_SPACINGS``. Every capped trial measured at such scatter was refused
#: (the realdata benchmark's traced outlines, sigma 0.11-0.41: residuals 0.12-0.99; the
#: surfaces benchmark's noisy clouds, 0.9: 2.9-4.5), and every kept one read sigma 0.008 or
#: less (docs/design.md section 8, "The automatic choice of basis").
NOISY_SPACINGS = 0.1


def wants_adaptive(settings: Settings, data_cell: float | None = None) -> bool:
    """Whether [`jurs.fit`][] with ``basis="auto"`` may fit a cloud with ``settings`` on
    the adaptive basis: where the automatic uniform grid (``settings.grid``) was capped, its
    cells at least ``AUTO_REFINEMENT`` times wider than the data ask for (``data_cell``,
    default ``settings.data_cell``). It does where the capped grid's fit then leaves the
    data (``uniform_residual``). A surface above ``AUTO_MAX_SURFACE_POINTS`` points fits
    a subsample on the hierarchy (``hierarchy_stride``), and [`jurs.fit`][] asks again with
    the subsample's ``data_cell``: on a dense noisy cloud the whole cloud's noise estimate
    reads too little noise (docs/surfaces.md, "Dense noisy clouds"), which would call the
    grid capped where the subsample's says it is not."""
    if settings.data_cell is None:  # the grid was given
        return False
    asked = settings.data_cell if data_cell is None else data_cell
    return settings.cell_width >= AUTO_REFINEMENT * asked


def hierarchy_stride(points: int, ndim: int) -> int:
    """The stride of the evenly strided subsample of ``points`` points that [`jurs.fit`][]'s
    automatic choice fits on the hierarchy: 1 on a curve and on a surface of at most
    ``AUTO_MAX_SURFACE_POINTS`` points, else the smallest that keeps at most that many."""
    return 1 if ndim == 2 else max(1, -(-int(points) // AUTO_MAX_SURFACE_POINTS))


def noise_decides(settings: Settings) -> bool:
    """Whether the cloud's noise alone (``settings.noise``, at least ``NOISY_SPACINGS``
    spacings) would refuse the capped grid's trial fit (``uniform_residual``), so that
    [`jurs.fit`][] goes to the hierarchy without it."""
    return settings.noise >= NOISY_SPACINGS * settings.spacing


def uniform_residual(spline, cloud: Cloud, settings: Settings, spacing=None) -> float:
    """The 90th percentile of the data points' distances to the zero set of ``spline``, in
    ``spacing``s (None: the cloud's, ``settings.spacing``; [`jurs.fit`][] passes the
    spacing of the subsample a large surface's hierarchy would fit, ``hierarchy_stride``):
    at most ``PROBES`` points evenly strided, those set aside by the settings left out.
    [`jurs.fit`][] keeps a capped uniform fit where this is at most
    ``UNIFORM_RESIDUAL_SPACINGS``, and fits on the hierarchy otherwise."""
    points = cloud.points[judged_points(cloud, settings)]
    at = strided_probes(len(points), PROBES)
    _, distance = values_and_distances(spline, points if at is None else points[at])
    # A nonfinite distance (a fit that failed) counts as far.
    distance = np.where(np.isfinite(distance), distance, np.inf)
    return float(np.quantile(distance, 0.9) / (settings.spacing if spacing is None else spacing))


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
    problem: AdaptiveProblem,
    lam,
    rtol: float = DEFAULT_RTOL,
    max_steps: int = 10_000,
    precondition: Callable[[Array], Array] | None = None,
):
    """``(control, steps, relative residual, metrics)``: the minimiser of ``E_d + lam R``
    on the problem's hierarchy (w = 1) by preconditioned CG; pure JAX, differentiable in
    the problem's samples and targets and in ``lam``. ``precondition``: CG's
    preconditioner, e.g. the V-cycle of ``multilevel_preconditioner`` (None: Jacobi).

    One compiled program for each size of problem and each ``rtol``, ``max_steps`` and
    preconditioner: called outside ``jax.jit``, the basis, the right-hand side and the CG
    loop would otherwise each compile op by op, several times the solve's own time.
    """
    lam = scalar_array(lam, problem.targets.dtype)  # a new value compiles nothing
    return _compiled_solve_adaptive(problem, lam, rtol, max_steps, precondition)


@eqx.filter_jit
def _compiled_solve_adaptive(problem, lam, rtol, max_steps, precondition):
    basis = sample_basis(problem)
    matvec = normal_matvec(problem, lam, basis)
    rhs = normal_rhs(problem, basis)
    if precondition is None:
        # The preconditioner changes the path, not the solution: no derivative through it.
        diagonal = lax.stop_gradient(problem.data_diagonal + lam * problem.regulariser_diagonal)
        # A function no sample and no counted neighbour pair reaches has a zero row: keep
        # it at 0 (its preconditioned residual is 0) instead of dividing by 0.
        inverse = jacobi_inverse(diagonal)
        preconditioner = lambda r: inverse * r  # noqa: E731
    else:
        preconditioner = precondition
    control, steps, residual = conjugate_gradients(
        matvec, rhs, precondition=preconditioner, rtol=rtol, max_steps=max_steps
    )
    return control, steps, residual, adaptive_metrics(problem, control, lam, basis)


def multilevel_preconditioner(
    problem: AdaptiveProblem, lam: float, dtype=None, **options
) -> VCycle:
    """The V-cycle over the hierarchy's nested spaces for the normal matrix of a concrete
    ``problem`` with ``lam`` (``jurs._linalg.thb_multigrid``), as a JAX function for
    ``solve_adaptive(precondition=...)``: set up on the host from the problem's values at
    the time, it is a constant of the solve (no derivative flows through a
    preconditioner, only through the system it preconditions). ``options`` go to
    ``ThbMultigrid``."""
    from scipy.sparse import csr_matrix

    matrix, _ = normal_system(problem_matrices(problem), problem.targets, float(lam))
    multigrid = ThbMultigrid(problem.hierarchy, csr_matrix(matrix), **options)
    return multigrid.on_device(jnp.result_type(float) if dtype is None else dtype)


#: Smallest padded length of the arrays of an assembled CG solve (``size_class``).
MIN_CLASS = 256


def size_class(count: int) -> int:
    """The padded length for ``count`` entries: the next of four sizes an octave
    (``jurs._problem.sizes.round_size``: 4, 5, 6 or 7 times a power of two, at most 25 %
    padding), at least ``MIN_CLASS``. A solve compiled for one class serves every problem
    whose arrays fall in it."""
    return max(MIN_CLASS, round_size(count))


@jax.jit
def _assembled_cg(
    collocation: PaddedCoo,
    regulariser: PaddedCoo,
    targets,
    row_weights,
    diagonal,
    lam,
    rtol,
    max_steps,
    start,
):
    """CG on ``(D^T S D + lam 2 G^T W G) c = D^T S b`` (``S`` the samples' row weights)
    from the padded ``D`` and ``2 G^T W G``, started at ``start``: every shape is a size
    class, so a new cloud of a similar size compiles nothing. Padded functions have a zero
    row, right-hand side and diagonal, and stay 0."""

    def matvec(c):
        weighted = row_weights * (collocation @ c)
        return collocation.transpose_apply(weighted) + lam * (regulariser @ c)

    inverse = jacobi_inverse(diagonal)
    return conjugate_gradients(
        matvec,
        collocation.transpose_apply(row_weights * targets),
        precondition=lambda r: inverse * r,
        start=start,
        rtol=rtol,
        max_steps=max_steps,
    )


def normal_diagonal(problem: AdaptiveProblem, lam: float, matrices, row_weights=None) -> np.ndarray:
    """The diagonal of ``D^T S D + lam 2 G^T W G`` (the CG's Jacobi preconditioner), on the
    host, in float64: ``S`` the samples' ``row_weights`` (None: all 1, the problem's own
    diagonal; else read from ``D``, the first of the host ``matrices``)."""
    if row_weights is None:
        data = np.asarray(problem.data_diagonal, float)
    else:
        data = column_squares(matrices[0], problem.hierarchy.num_active, row_weights)
    return data + lam * np.asarray(problem.regulariser_diagonal, float)


def solve_assembled(
    problem: AdaptiveProblem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    dtype,
    row_weights=None,
    start=None,
    rows=None,
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)``: ``solve_adaptive``'s CG (the same
    preconditioner, the same stop rule) on the host-assembled matrices ``(D, 2 G^T W G)``
    of ``assemble_adaptive_problem``, padded to size classes (``size_class``) so that the
    compiled solve is shared between clouds. Not differentiable; the answer agrees with
    ``solve_adaptive``'s to the CG tolerance. ``row_weights`` (S,) weigh the samples'
    rows (None: 1); ``start`` (n,) is CG's first iterate (None: 0). ``rows``: ``D`` in
    its products' order (``ordered_rows``; None: made here)."""
    collocation, regulariser = matrices
    count, n = collocation.shape
    n_class, count_class = size_class(n), size_class(count)
    diagonal = normal_diagonal(problem, lam, matrices, row_weights)
    weights = np.ones(count) if row_weights is None else np.asarray(row_weights, float)
    first = np.zeros(n) if start is None else np.asarray(start, float)
    ordered, order = ordered_rows(collocation) if rows is None else rows
    control, steps, residual = _assembled_cg(
        PaddedCoo.from_scipy(ordered, size_class(collocation.nnz), (count_class, n_class), dtype),
        PaddedCoo.from_scipy(regulariser, size_class(regulariser.nnz), (n_class, n_class), dtype),
        on_device(padded_to(np.asarray(problem.targets)[order], count_class), dtype),
        on_device(padded_to(weights[order], count_class), dtype),
        on_device(padded_to(diagonal, n_class), dtype),
        on_device(lam, dtype),
        on_device(rtol, dtype),
        on_device(max_steps, np.int32),
        on_device(padded_to(first, n_class), dtype),
    )
    return np.asarray(control)[:n], int(steps), float(residual)


def solve_host_cg(
    problem: AdaptiveProblem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    row_weights=None,
    start=None,
    system=None,
    rows=None,
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)``: ``solve_assembled``'s CG (the exact
    diagonal as preconditioner, the stop rule ``|r| <= rtol |D^T b|``) run on the host
    (``host_conjugate_gradients``), on the host matrices ``(D, 2 G^T W G)`` in CSR, their
    products split over the host's threads (``normal_product``). Not differentiable.
    ``row_weights``, ``start`` and ``rows`` as ``solve_assembled``'s. ``system``: the assembled
    ``normal_system((D, 2 G^T W G), b, lam, row_weights)``, whose matrix CG then multiplies
    by instead (``ASSEMBLED_SAMPLES_PER_FUNCTION``: the same equations, in fewer entries
    where samples outnumber functions).

    On a CPU it is the faster of the two: SciPy's products with the CSR matrices beat
    XLA's segment sums over the same entries (docs/design.md section 8,
    docs/performance.md). On a GPU, ``solve_assembled``.
    """
    if system is None:
        collocation, regulariser = (matrix.tocsr() for matrix in matrices)
        diagonal = normal_diagonal(problem, lam, matrices, row_weights)
        # All weights 1 multiply exactly: the unweighted fit is unchanged by them.
        weights = 1.0 if row_weights is None else np.asarray(row_weights, float)
        rhs = collocation.T @ (weights * np.asarray(problem.targets, float))
        ordered, order = ordered_rows(collocation) if rows is None else rows
        ordered_weights = None if row_weights is None else np.asarray(row_weights, float)[order]
        product = normal_product(ordered, regulariser, lam, ordered_weights)
    else:
        matrix, rhs = system
        diagonal = matrix.diagonal()
        product = normal_product(None, matrix, 1.0)
    inverse = jacobi_inverse(diagonal, np)
    with product as matvec:
        control, steps, _ = host_conjugate_gradients(
            matvec,
            rhs,
            precondition=lambda r: inverse * r,
            start=start,
            rtol=rtol,
            max_steps=max_steps,
        )
        residual = matvec(control) - rhs  # the true residual, not the recurrence's
    scale = max(float(np.linalg.norm(rhs)), np.finfo(float).tiny)
    return control, steps, float(np.linalg.norm(residual)) / scale


@jax.jit
def _multigrid_cg(normal: PaddedCoo, rhs, cycle, rtol, max_steps, start):
    """CG on ``normal c = rhs`` (the padded assembled normal matrix) from ``start``,
    preconditioned by one V-cycle a step."""
    return conjugate_gradients(
        normal.__matmul__, rhs, precondition=cycle, start=start, rtol=rtol, max_steps=max_steps
    )


def solve_multigrid(
    problem: AdaptiveProblem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    dtype,
    row_weights=None,
    start=None,
    system=None,
    **options,
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)`` as ``solve_host_multigrid`` returns them,
    the CG and its V-cycles run in JAX (``ThbMultigrid.on_device``): the set-up on the
    host, the solve one compiled loop on JAX's default device. Every array is padded to a
    size class (``size_class``), so that hierarchies of similar sizes share one compiled
    solve. Not differentiable in the problem (``solve_adaptive`` with
    ``multilevel_preconditioner`` is)."""
    from scipy.sparse import csr_matrix

    matrix, rhs = system or normal_system(matrices, problem.targets, lam, row_weights)
    n = matrix.shape[0]
    n_class = size_class(n)
    multigrid = ThbMultigrid(problem.hierarchy, csr_matrix(matrix), **options)
    first = np.zeros(n) if start is None else np.asarray(start, float)
    control, steps, residual = _multigrid_cg(
        PaddedCoo.from_scipy(matrix, size_class(matrix.nnz), (n_class, n_class), dtype),
        on_device(padded_to(rhs, n_class), dtype),
        multigrid.on_device(dtype, pad=size_class),
        on_device(rtol, dtype),
        on_device(max_steps, np.int32),
        on_device(padded_to(first, n_class), dtype),
    )
    return np.asarray(control)[:n], int(steps), float(residual)


def solve_host_multigrid(
    problem: AdaptiveProblem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    row_weights=None,
    start=None,
    system=None,
    **options,
) -> tuple[np.ndarray, int, float]:
    """``(control, steps, relative residual)`` as ``solve_host_cg`` returns them (the stop
    rule ``|r| <= rtol |D^T S b|``; ``row_weights``, ``start`` and ``system`` as its), by CG on the
    assembled normal equations (``normal_system``) preconditioned by one V-cycle a step
    over the hierarchy's nested spaces (``jurs._linalg.thb_multigrid.ThbMultigrid``;
    ``options`` go to it; docs/multigrid.md, "The multilevel solve of the hierarchy").
    Not differentiable."""
    from scipy.sparse import csr_matrix

    matrix, rhs = system or normal_system(matrices, problem.targets, lam, row_weights)
    return multigrid_cg(
        problem.hierarchy, csr_matrix(matrix), rhs, rtol, max_steps, start=start, **options
    )


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


def solve_direct(problem: AdaptiveProblem, lam: float, matrices=None, row_weights=None):
    """``(control, relative residual)`` by a sparse direct factorisation on the host: no
    derivative, concrete problems only. ``matrices``: the problem's ``(D, 2 G^T W G)``
    (``assemble_adaptive_problem`` returns them), assembled here when None;
    ``row_weights`` (S,) weigh the samples' rows (None: 1).

    The normal matrix is symmetric positive definite, so an LDL^T without pivoting does:
    QDLDL (the ``qdldl`` package, OSQP's factorisation: a small pip wheel for every
    platform, AMD ordering). Measured on two traced outlines (23.9k and 34.6k functions),
    it factorised and solved faster than SciPy's SuperLU with COLAMD, the best
    of SuperLU's orderings here (docs/design.md section 8). A matrix QDLDL cannot factorise
    (a zero pivot: numerically singular, e.g. ``lam = 0`` with functions no sample
    reaches) goes to SuperLU, whose pivoting gives an answer whose residual says so.
    """
    if matrices is None:
        matrices = problem_matrices(problem)
    matrix, rhs = normal_system(matrices, problem.targets, lam, row_weights)
    return solve_normal(matrix.tocsc(), rhs)


def solve_normal(matrix, rhs: np.ndarray) -> tuple[np.ndarray, float]:
    """``(control, relative residual)`` of ``matrix c = rhs`` (a SciPy CSC symmetric
    positive definite matrix) by ``solve_direct``'s factorisation, on the host."""
    try:
        import qdldl

        # QDLDL reads the upper triangle; cut here in one pass over the entries (its own
        # cut goes through SciPy's triu, which sorts them again; docs/performance.md).
        control = qdldl.Solver(_upper_triangle(matrix), upper=True).solve(rhs)
    except (ImportError, RuntimeError):
        from scipy.sparse.linalg import splu

        control = splu(matrix, permc_spec="COLAMD").solve(rhs)
    scale = max(float(np.linalg.norm(rhs)), np.finfo(float).tiny)
    return control, float(np.linalg.norm(matrix @ control - rhs)) / scale


class HierarchySolve(abc.ABC):
    """The normal equations of one hierarchy problem, solved by one method: called as
    ``solve(row_weights=None, start=None, lam=None) -> (control, steps, relative
    residual)`` with the samples' row weights, CG's first iterate and the lambda (None:
    the one it was made with), for the solvers of ``solve_on_hierarchy``. Each method is
    a subclass (``SOLVES``, by the names of ``METHODS``), which ``exact_solve`` picks.

    What a method's solves share is kept here: the assembled normal equations
    (``normal_system``) of the last row weights, since a search over lambda solves with
    the same weights and moves its matrix by the change of lambda times ``R``; and ``D``
    in its products' order (``ordered_rows``), made for the first CG by ``D``, since a
    reweighting's or a search's solves multiply by the same rows."""

    def __init__(self, problem: AdaptiveProblem, matrices, lam, rtol, max_steps, dtype):
        self.problem, self.matrices, self.lam = problem, matrices, lam
        self.rtol, self.max_steps, self.dtype = rtol, max_steps, dtype
        self._kept: dict = {}
        self._ordered: tuple | None = None

    def __call__(self, row_weights=None, start=None, lam=None) -> tuple[np.ndarray, int, float]:
        return self.solve(row_weights, start, self.lam if lam is None else float(lam))

    @abc.abstractmethod
    def solve(self, row_weights, start, lam: float) -> tuple[np.ndarray, int, float]:
        """``(control, steps, relative residual)`` for these row weights, start and lam."""

    def system(self, row_weights, lam: float):
        """``(matrix, rhs)``: the assembled normal equations for ``row_weights`` and
        ``lam``, kept for the next solve with the same weights."""
        key = None if row_weights is None else np.asarray(row_weights, float).tobytes()
        kept = self._kept
        if kept and kept["key"] == key:
            matrix, rhs = kept["system"]
            if lam != kept["lam"]:
                matrix = (matrix + (lam - kept["lam"]) * self.matrices[1]).tocsr()
        else:
            kept.clear()  # one at a time: each is about the normal matrix's size
            matrix, rhs = normal_system(self.matrices, self.problem.targets, lam, row_weights)
        kept.update(key=key, lam=lam, system=(matrix, rhs))
        return matrix, rhs

    def rows(self) -> tuple:
        """``D`` in its products' order and that order (``ordered_rows``), made once."""
        if self._ordered is None:
            self._ordered = ordered_rows(self.matrices[0].tocsr())
        return self._ordered

    def cg_arguments(self, row_weights, start, lam: float) -> dict[str, Any]:
        """The arguments the CG solves below share, by name."""
        return dict(
            problem=self.problem, matrices=self.matrices, lam=lam, rtol=self.rtol,
            max_steps=self.max_steps, row_weights=row_weights, start=start,
        )  # fmt: skip


class DirectSolve(HierarchySolve):
    """``solve_normal``'s factorisation of the assembled normal equations (no start)."""

    def solve(self, row_weights, start, lam):
        matrix, rhs = self.system(row_weights, lam)
        control, residual = solve_normal(matrix.tocsc(), rhs)
        return control, 0, residual


class HostCGSolve(HierarchySolve):
    """``solve_host_cg``: by the assembled matrix where samples outnumber functions
    (``assembled_pays``), else by ``D`` in its products' order and ``R``."""

    def solve(self, row_weights, start, lam):
        shared = self.cg_arguments(row_weights, start, lam)
        if assembled_pays(self.matrices[0]):
            return solve_host_cg(**shared, system=self.system(row_weights, lam))
        return solve_host_cg(**shared, rows=self.rows())


class DeviceCGSolve(HierarchySolve):
    """``solve_assembled``: the same CG compiled by JAX, on the padded matrices."""

    def solve(self, row_weights, start, lam):
        shared = self.cg_arguments(row_weights, start, lam)
        return solve_assembled(**shared, dtype=self.dtype, rows=self.rows())


class HostMultigridSolve(HierarchySolve):
    """``solve_host_multigrid``: CG with a V-cycle over the nested spaces, in SciPy."""

    def solve(self, row_weights, start, lam):
        shared = self.cg_arguments(row_weights, start, lam)
        return solve_host_multigrid(**shared, system=self.system(row_weights, lam))


class MultigridSolve(HierarchySolve):
    """``solve_multigrid``: CG with a V-cycle over the nested spaces, compiled by JAX."""

    def solve(self, row_weights, start, lam):
        shared = self.cg_arguments(row_weights, start, lam)
        return solve_multigrid(**shared, dtype=self.dtype, system=self.system(row_weights, lam))


#: The hierarchy's linear solves by name (``exact_solve``): a factorisation on the host;
#: CG with Jacobi in JAX or on the host (SciPy); CG with a V-cycle over the nested spaces
#: in JAX or on the host.
SOLVES: dict[str, type[HierarchySolve]] = {
    "direct": DirectSolve,
    "cg": DeviceCGSolve,
    "host_cg": HostCGSolve,
    "multigrid": MultigridSolve,
    "host_multigrid": HostMultigridSolve,
}
#: The names of ``SOLVES``: the ``method`` a hierarchy fit takes.
METHODS = tuple(SOLVES)


def exact_solve(
    method: str, problem: AdaptiveProblem, matrices, lam, rtol, max_steps, dtype
) -> HierarchySolve:
    """The hierarchy's normal equations of ``problem`` (with its host ``matrices``)
    solved by ``method`` (one of ``METHODS``): a ``HierarchySolve``, called as
    ``solve(row_weights=None, start=None, lam=None)``."""
    return SOLVES[method](problem, matrices, lam, rtol, max_steps, dtype)


def assembled_pays(collocation) -> bool:
    """Whether ``host_cg`` multiplies by the assembled normal matrix: where ``D``'s rows
    (the samples) are at least ``ASSEMBLED_SAMPLES_PER_FUNCTION`` times its columns."""
    rows, functions = collocation.shape
    return rows >= ASSEMBLED_SAMPLES_PER_FUNCTION * functions


@functools.singledispatch
def solve_on_hierarchy(
    solver, problem: AdaptiveProblem, matrices, solve
) -> tuple[np.ndarray, int, float, Any, bool]:
    """``(control, steps, relative residual, state, converged)`` of ``solver``'s fit on the
    hierarchy, its linear solves made by ``solve`` (``exact_solve``). Chosen by the
    solver's type: the exact solve (``LeastSquares``), its reweighting
    (``RobustLeastSquares``) and its lambda chosen by held-out points
    (``HeldOutLeastSquares``); other solvers are refused (``check_hierarchy_solver``).
    The fit's lambda is ``solver.fitted_lam(state)``."""
    raise ValueError(hierarchy_refusal(solver))


def hierarchy_refusal(solver) -> str:
    """Why ``solver`` does not fit on the hierarchy, in one message."""
    name = type(solver).__name__
    if isinstance(solver, (IPIA, IURS, NormalIPIA)):
        why = (
            "the paper's iterations update a uniform grid's control points and weights "
            "step by step (its Laplacian, eq. 33), which the hierarchy has no grid for"
        )
    else:
        why = f"{name} runs on the uniform grid's problem"
    return (
        f"basis='adaptive' fits with jurs.LeastSquares, jurs.RobustLeastSquares or "
        f"jurs.HeldOutLeastSquares (the exact solve, its reweighting, its lambda chosen by "
        f"held-out points), or with no solver (the lambda chosen from the data); "
        f"{why}: fit it with basis='uniform'"
    )


def check_hierarchy_solver(solver) -> None:
    """TypeError unless ``solver`` is None or a jurs solver; ValueError for one that does
    not fit on the hierarchy (``solve_on_hierarchy`` has no registration for it)."""
    if solver is None:
        return
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    if solve_on_hierarchy.dispatch(type(solver)) is solve_on_hierarchy.dispatch(object):
        raise ValueError(hierarchy_refusal(solver))


@solve_on_hierarchy.register
def _(
    solver: LeastSquares, problem: AdaptiveProblem, matrices, solve
) -> tuple[np.ndarray, int, float, Any, bool]:
    control, steps, residual = solve()
    return control, steps, residual, None, True


@solve_on_hierarchy.register
def _(
    solver: RobustLeastSquares, problem: AdaptiveProblem, matrices, solve
) -> tuple[np.ndarray, int, float, Any, bool]:
    # The uniform grid's IRLS (RobustLeastSquares.step) on the host: each step one exact
    # solve with the points' weights on their three samples' rows, then the same
    # reweighting (RobustLeastSquares.reweigh) and the same stop rule as the driver's.
    collocation, regulariser = matrices
    targets = np.asarray(problem.targets, float)
    m = len(targets) // 3
    real = jnp.ones(m, bool)

    def reweighed(control, previous):
        r = collocation @ control - targets  # samples [P, P + d n, P - d n] (eq. 4-5)
        e = np.sqrt(np.sum((r * r).reshape(3, m), axis=0))
        regularisation = float(control @ (regulariser @ control))
        return solver.reweigh(jnp.asarray(e), real, problem.eps, regularisation, previous)

    control = np.zeros(collocation.shape[1])
    _, scale, energy = reweighed(control, None)
    weights = jnp.ones(m)  # the first solve is the plain fit (JAX's default float)
    total, residual, settled, converged = 0, 0.0, False, False
    for step in range(solver.max_steps):
        start = None if step == 0 else control
        control, steps, residual = solve(np.tile(np.asarray(weights, float), 3), start)
        total += steps
        weights, scale, new = reweighed(control, scale)
        change = abs(float(new) - float(energy))
        settled = change <= solver.rtol * abs(float(new))
        energy = new
        if not np.isfinite(float(new)):
            break
        if change < solver.tol or (settled and solver.rtol > 0):
            converged = True
            break
    state = RobustLeastSquaresState(
        control=jnp.asarray(control),
        point_weights=weights,
        scale=scale,
        result=lx.RESULTS.successful,
        energy=energy,
        settled=jnp.asarray(settled),
        solved=jnp.asarray(True),
    )
    return control, total, residual, state, converged


@solve_on_hierarchy.register
def _(
    solver: HeldOutLeastSquares, problem: AdaptiveProblem, matrices, solve
) -> tuple[np.ndarray, int, float, Any, bool]:
    # The uniform grid's search (HeldOutLeastSquares.step) on the host: the same points
    # held out (held_out_points), each candidate fitted to the kept points (the held-out
    # points' three rows weighted 0) at its lambda scaled by the kept share, scored by the
    # held-out points' capped distance to its zero set (capped_distance), the same early
    # stop; then the best candidate refitted on all points. Each solve starts from the
    # last (a factorisation ignores it).
    collocation, _ = matrices
    m = collocation.shape[0] // 3  # samples [P, P + d n, P - d n] (eq. 4-5)
    held = np.asarray(held_out_points(m, float(solver.holdout), np))
    kept_rows = np.tile((~held).astype(float), 3)
    share = float(np.sum(~held)) / max(m, 1)
    offset = float(problem.offset)
    candidates = np.asarray(solver.lam, float)
    scores = np.full(candidates.shape, np.nan)
    control, total = None, 0
    for i, lam in enumerate(candidates):
        control, steps, _ = solve(kept_rows, control, lam * share)
        total += steps
        g = (collocation @ control).reshape(3, m)
        distance = capped_distance(g[0], g[1], g[2], offset, np)
        scores[i] = np.mean(distance[held] ** 2) if held.any() else 0.0
        if solver.early_stop and i >= 1 and stops_search(scores[i], scores[i - 1]):
            break
    lam = candidates[int(np.argmin(np.where(np.isnan(scores), np.inf, scores)))]
    control, steps, residual = solve(None, control, lam)
    state = HeldOutLeastSquaresState(
        control=jnp.asarray(control),
        lam=jnp.asarray(lam, problem.targets.dtype),
        scores=jnp.asarray(scores),
        done=jnp.asarray(True),
        result=lx.RESULTS.successful,
    )
    return control, total + steps, residual, state, True


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


def solver_lam(solver, lam=None, points=None, normals=None) -> float | None:
    """The ``lam`` of a fit on the hierarchy by ``solver`` (one ``check_hierarchy_solver``
    has passed: each entry checks its solver first): the solver's own, else ``lam``
    (None: made from the smoothing, ``hierarchy_lam``); None for a solver that chooses
    among candidates (``HeldOutLeastSquares``: the fit reports its choice). Refuses a
    ``lam`` beside a solver, and a robust fit or a held-out choice of ``points`` sharded
    over devices or processes (they run on one host)."""
    if solver is None:
        return lam
    if lam is not None:
        raise ValueError("pass lam or a solver, not both: a solver keeps its own lam")
    # A solver that reweighs its points (expects outliers), or that chooses its lambda
    # among candidates, does so on one host.
    candidates = type(solver).chooses_lam
    if (type(solver).expects_outliers or candidates) and (
        spans_processes(points, normals) or input_sharding(points, normals) is not None
    ):
        what = "a robust fit" if type(solver).expects_outliers else "a held-out choice of lambda"
        raise ValueError(
            f"{what} on the hierarchy runs in one process on points that are not "
            "sharded; gather them first, or fit with jurs.LeastSquares"
        )
    return None if candidates else float(solver.lam)


def hierarchy_lam(settings: Settings, smoothing, samples: int, diagonal: float, layout, hierarchy):
    """The lambda of a hierarchy fit given none: ``scale_free_lam`` of the ``smoothing``
    (None: ``settings.smoothing``) for ``samples`` samples, the data's bounding-box
    ``diagonal``, the box of ``layout`` (``hierarchy_layout``) and the ``hierarchy``'s
    finest cell, so that one smoothing weighs the same on any hierarchy."""
    lower, upper = layout["lower"], layout["upper"]
    cell = float(np.max((upper - lower) / np.asarray(hierarchy.cells(hierarchy.num_levels - 1))))
    strength = settings.smoothing if smoothing is None else float(smoothing)
    return scale_free_lam(strength, samples, diagonal, lower, upper, cell)


def hierarchy_rtol(rtol, dtype) -> float:
    """CG's stop rule: ``rtol``, else ``DEFAULT_RTOL`` in float64 and ``FLOAT32_RTOL`` in
    float32 (where a residual of ``DEFAULT_RTOL`` is below rounding)."""
    return rtol if rtol is not None else DEFAULT_RTOL if dtype == jnp.float64 else FLOAT32_RTOL


def hierarchy_solution(
    hierarchy, control: np.ndarray, metrics: dict, settings: Settings, *, method: str,
    steps: int, residual: float, rtol: float, dtype, settled=True, state=None, **stats,
) -> Solution:  # fmt: skip
    """The [`jurs.Solution`][] of a hierarchy solve by ``method`` that left ``control``
    (w = 1) after ``steps`` steps at the relative ``residual``: ``successful`` where finite,
    within ``rtol`` (a direct solve: ``DIRECT_RTOL``; far above rounding, its matrix was
    singular) and ``settled`` (the solver's own rule), else ``max_steps_reached`` where
    finite, else ``nonfinite``. Its stats: the solve's, the hierarchy's, then ``stats``."""
    coefficients = on_device(control, dtype)
    spline = AdaptiveSpline(hierarchy, coefficients, on_device(np.ones(control.shape), dtype))
    tolerance = max(rtol, DIRECT_RTOL) if method == "direct" else rtol
    finite = bool(np.all(np.isfinite(np.asarray(coefficients))))
    if finite and float(residual) <= tolerance and settled:
        result = RESULTS.successful
    else:
        result = RESULTS.max_steps_reached if finite else RESULTS.nonfinite
    stats = {
        "method": method,
        "num_steps": int(steps),
        "residual": float(residual),
        "levels": hierarchy.num_levels,
        "active": hierarchy.active_counts,
        "finest": hierarchy.cells(hierarchy.num_levels - 1),
        **stats,
    }
    return Solution(spline, metrics, stats, result, state, settings)
