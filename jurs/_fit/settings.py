"""Automatic fit settings from the point cloud: grid, offset d, eps and lambda.

A user with a point cloud does not know which grid, offset or lambda to pick; the paper
tunes them per example. [`auto_settings`][jurs.auto_settings] reads them off the data with a
KD-tree, in NumPy on the host (the choices are discrete: a grid size cannot be traced).
Every choice is *equivariant*: translating, rotating or uniformly scaling the cloud moves
the settings with it (lengths scale, counts and the scale-free smoothing do not change), so
the zero set moves with the data.

Measured quantities (all from the data, in data units):

* ``spacing`` s: the median distance from a point to its nearest neighbour.
* ``noise`` sigma: the median, over points, of the RMS residual of a quadratic fitted to
  the point's same-facing neighbours in their principal frame (see ``estimate_noise``);
  about 0 on clean samples of a smooth curve, the positional noise otherwise.

Choices (the reasoning is in each function's docstring):

* ``offset`` d (``choose_offset``): half a spacing, or two noise widths, shrunk where
  it would cross thin parts; ``eps = d``, so g is close to a signed distance near the data.
  (The fit is linear in the targets, so eps only scales g; it changes neither the zero set
  nor lambda.)
* ``grid`` (``choose_grid``): cells a few spacings or noise widths wide, at most
  ``max_grid`` basis functions along the longer side.
* ``lam`` (``scale_free_lam``): the objective's lambda of ``E_d + lam R`` from a
  dimensionless ``smoothing`` (``choose_smoothing``).

The default solver for these settings is the exact solve, [`jurs.LeastSquares`][]: one
linear solve reaches the minimum that the paper's iterations approach step by step.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from jaxtyping import ArrayLike, Float

if TYPE_CHECKING:  # SciPy's spatial module loads on the first fit, not on import
    # SciPy ships no stub for its compiled cKDTree, so a type checker sees no such class;
    # KDTree, its pure-Python subclass with the same query(), stands in for it here.
    from scipy.spatial import KDTree as cKDTree

import equinox as eqx
import jax.numpy as jnp

from .._cloud.cloud import Cloud
from .._cloud.measure import (
    PROBES,
    estimate_noise,
    feature_width,
    offset_agreement,
    point_spacing,
    strided_probes,
)
from .._cloud.outliers import MAX_SET_ASIDE, isolated_points
from .._problem.memory import check_fit_memory
from .._problem.padding import padded_problem
from .._problem.problem import auto_domain, offset_samples
from .._problem.sizes import DEFAULT_MARGIN, round_octave, round_size
from .._problem.validate import (
    check_nonnegative,
    check_values,
    is_concrete,
    normalise_grid,
    validate_settings,
)
from ..solvers import AbstractSolver, LeastSquares, RobustLeastSquares
from ..solvers._held_out import select_lam

# Compiled once per problem shape; clouds padded to one size share it.
_select_lam = eqx.filter_jit(select_lam)

#: Default largest grid (basis functions along the longer side).
DEFAULT_MAX_GRID = 96
#: Default largest grid of a surface (3D). The 343-point stencil of D^T D holds 2.7 KB a
#: coefficient in float64, and the assembly's per-cell moments as much again; memory and
#: the final CG's steps on that stencil grow with the coefficients, and 48^3 has 2.4x
#: fewer than 64^3, whose fits were too slow and large for a default (docs/surfaces.md,
#: "Accuracy, speed and limits"; docs/performance.md, "Measurements behind the defaults").
DEFAULT_MAX_GRID_3D = 48
#: Cell side in point spacings, by dimension (see ``choose_grid``). On a surface a
#: cell of side ``c s`` is crossed by about ``c^2`` points against ``c`` on a curve, so 3
#: spacings already pin its coefficients; 1.5 would give about 8x the coefficients, and
#: the exact solve's cost grows with them, for little accuracy (docs/performance.md,
#: "Measurements behind the defaults").
CELL_SPACINGS = {2: 1.5, 3: 3.0}
#: Most coefficients a curve's grid is refined to for thin features (``choose_grid``):
#: the exact solve's block Cholesky costs about ``N M^3`` (M the shorter side), 3.2x that
#: of 96 x 96 at 128 x 128.
MAX_FEATURE_COEFFICIENTS = 128 * 128
#: Share of the points whose feature width sets the finest cell (``feature_width``):
#: the narrowest 0.5 %, so that a short neck of a few points counts, a single odd point not.
FEATURE_QUANTILE = 0.005
#: A feature is resolved when it is at least this many cells wide: the clean shapes of
#: the quality suite fit well with few of their points on narrower features, and a 100:1
#: ellipse, its whole length such a feature, did not (docs/design.md section 6;
#: docs/performance.md, "Measurements behind the defaults").
FEATURE_CELLS = 0.5
#: Smallest automatic grid along either side.
MIN_GRID = 8


@dataclasses.dataclass(frozen=True)
class Settings:
    """What [`auto_settings`][jurs.auto_settings] chose, and the measurements it chose
    from.

    Attributes:
        grid: ``(N, M)`` basis functions along x and y (``(N, M, K)`` for a surface).
        offset: d, distance of the offset samples (eq. 4).
        eps: target value at the offsets (eq. 5); equal to ``offset``.
        lam: the objective's lambda in ``E_d + lam R`` (for [`jurs.LeastSquares`][]).
        smoothing: the dimensionless strength ``lam`` was made from.
        domain: ``((x_min, y_min), (x_max, y_max))``, the box the grid covers (with z for a
            surface).
        spacing, noise: the measurements (see the module docstring).
        held_out: where the smoothing was chosen by held-out points
            (``choose_smoothing``), ``((smoothing, score), ...)`` for every candidate
            tried (from the smallest up, until the score rises by more than 5 %), the
            score being the held-out points' mean squared distance to the candidate's
            zero set; None otherwise.
        set_aside: indices of the points that stand alone (``isolated_points``): they
            took no part in the measurements, and [`jurs.fit`][] fits without them.
        thin_fraction: the fraction of the points on features (thin parts, narrow gaps:
            ``feature_width``) narrower than ``FEATURE_CELLS`` cells of ``grid``;
            0 for a surface (not measured).
        data_cell: the cell width the data ask for (``data_cell``), before the cap on
            the grid; None where the grid was given. Where ``grid``'s cells are wider,
            [`jurs.fit`][] takes the adaptive basis (``jurs._fit.adaptive.wants_adaptive``).
    """

    grid: tuple[int, ...]
    offset: float
    eps: float
    lam: float
    smoothing: float
    domain: tuple[tuple[float, ...], tuple[float, ...]]
    spacing: float
    noise: float
    held_out: tuple[tuple[float, float], ...] | None = None
    set_aside: tuple[int, ...] = ()
    thin_fraction: float = 0.0
    data_cell: float | None = None

    @property
    def cell_width(self) -> float:
        """The widest cell of ``grid`` over ``domain`` (the grid's knot span)."""
        lower, upper = (np.asarray(v, float) for v in self.domain)
        return float(np.max((upper - lower) / (np.asarray(self.grid, float) - 3)))

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Dimensionless smoothing on clean clouds, and the most a noisy surface gets (see
#: ``noise_smoothing``).
CLEAN_SMOOTHING = 1e-6
NOISY_SMOOTHING = 1e-3
#: A clean surface's smoothing: lower than a curve's, since a surface's cells hold many
#: more points (about ``c^2`` against ``c`` for a cell of ``c`` spacings) and the data pin
#: the fit down between them. At 1e-6 the membrane term's pull on the surface was most of
#: the error of clean fits; 1e-7 brought every clean shape of benchmarks/surfaces.py
#: closer to its true surface, in fewer CG steps, while smaller values grew bubbles
#: (docs/surfaces.md, "Accuracy, speed and limits"; docs/performance.md, "Measurements
#: behind the defaults").
CLEAN_SURFACE_SMOOTHING = 1e-7
#: The dimensionless smoothings a curve's lambda is chosen among by held-out points
#: (``choose_smoothing``): decades from the clean floor to the noisy end.
SMOOTHING_CANDIDATES = (1e-6, 1e-5, 1e-4, 1e-3)
#: Below this ratio ``2 sigma / d`` the cloud is clean at the scale of its offsets and
#: gets ``CLEAN_SMOOTHING`` without a held-out selection (which would choose it too:
#: see ``choose_smoothing``).
CLEAN_NOISE_RATIO = 0.1


def choose_offset(
    points: np.ndarray,
    normals: np.ndarray,
    spacing: float,
    noise: float,
    tree: cKDTree | None = None,
    at=None,
) -> float:
    """Offset d: ``max(s / 2, 2 sigma)``, shrunk where it would cross thin parts.

    Why: d is a finite-difference step for the normal. Half a spacing keeps the offsets
    inside the band where the data define the curve (on clean data smaller d measured
    better, down to s / 2); on noisy data the offsets must clear the noise, or the
    inner and outer samples of neighbouring points interleave, hence ``2 sigma``.

    Thin parts: offsets that cross a thin part of the shape, or the gap between two parts,
    land on the wrong side of the data nearest to them (``offset_agreement``). Among
    ``d0, 0.7 d0, 0.7^2 d0, ...`` the largest is taken whose agreement is within 1 % of the
    best on that ladder: on clean smooth data d0 itself (agreement 1), and on noisy data too
    (smaller offsets only agree less, noise being closer), but less than d0 where d0 crosses.
    """
    d0 = max(0.5 * spacing, 2.0 * noise)
    ladder = d0 * 0.7 ** np.arange(6)
    first = offset_agreement(points, normals, d0, tree, at)
    if first >= 0.99:  # within 1 % of any agreement (all are <= 1): d0, as the rule says
        return float(d0)
    agreement = np.concatenate([[first], offset_agreement(points, normals, ladder[1:], tree, at)])
    return float(ladder[np.argmax(agreement >= agreement.max() - 0.01)])


def choose_grid(
    lower: np.ndarray,
    upper: np.ndarray,
    spacing: float,
    noise: float,
    max_grid: int = DEFAULT_MAX_GRID,
    feature: float = np.inf,
) -> tuple[int, ...]:
    """Basis functions along each axis (x and y, and z for a surface): cells of side ``h =
    max(1.5 s, 4 sigma)`` (``3 s`` on a surface, ``CELL_SPACINGS``), the same along
    every axis, with at most ``max_grid`` functions along the longest side and at least
    ``MIN_GRID`` along each; then, on a curve whose narrowest ``feature`` (thin parts,
    narrow gaps: ``feature_width``) is under ``FEATURE_CELLS`` cells wide, finer
    cells down to that width, beyond ``max_grid`` but within
    ``MAX_FEATURE_COEFFICIENTS`` coefficients and never below one spacing or 4 sigma.

    Why: a cell must hold a few points along the curve for the least-squares fit to pin
    its coefficients (1.5 spacings: finer cells no longer fit clean data closer), and on
    noisy data a few noise widths, so that each coefficient averages out the noise instead
    of following it (4 sigma fit closer than 2 or 8; docs/performance.md, "Measurements
    behind the defaults"). The cap bounds time and memory: the exact
    solve grows with the number of coefficients, not with m. A feature narrower than about
    half a cell is cut or bridged (a neck pinched, two rings fused), whatever the number of
    points: there the data need the finer grid, and the budget in coefficients (not in
    functions a side) lets elongated shapes have it cheaply.

    Grid classes, so that clouds of similar size and extent get the same grid and share
    one compiled fit: on a curve, the longest side's cell count is rounded up to a power
    of two (``round_octave``: 8, 16, 32, 64) where that stays under the cap, and the cells
    along every side narrowed to match (one grid an octave of points for one shape); then
    every count is rounded up to ``jurs._problem.sizes.round_size`` (four sizes an
    octave), within the cap. Cells get narrower than chosen, never wider: a curve's up to
    half as wide (at most 4x the coefficients). Between 64 cells and the cap, and on a
    surface, only the four sizes an octave apply. docs/design.md section 5 ("Compiled
    shapes") gives the measurements behind these classes and the alternatives tried.
    """
    extent = np.asarray(upper, float) - np.asarray(lower, float)
    h = max(data_cell(extent.size, spacing, noise), float(extent.max()) / (max_grid - 3))
    cap = max(max_grid - 3, 1)
    if extent.size == 2 and feature < FEATURE_CELLS * h:
        finest = max(_feature_cell(feature, spacing, noise), _budget_cell(extent))
        if finest < h:
            h, cap = finest, np.inf
    cells = np.maximum(1, np.ceil(extent / h - 1e-9).astype(int))
    longest = int(np.argmax(extent))
    count = round_octave(int(cells[longest]))
    if extent.size == 2 and count <= cap and extent.max() > 0:
        # A curve's grid class: the longest side's cell count rounded up to a power of two
        # under the cap, the cells along every side narrowed to match, so that one shape
        # gets one grid an octave of points (the other sides follow the aspect).
        h = float(extent[longest]) / count
        cells = np.maximum(1, np.ceil(extent / h - 1e-9).astype(int))
    return tuple(int(max(MIN_GRID, min(round_size(c), max(cap, c)) + 3)) for c in cells)


def data_cell(ndim: int, spacing: float, noise: float, feature: float = np.inf) -> float:
    """The cell width the data ask for, before any cap on the grid: ``max(c s, 4 sigma)``
    (``c = CELL_SPACINGS``), and on a curve whose narrowest ``feature`` is under
    ``FEATURE_CELLS`` such cells wide, the feature's cell (``_feature_cell``).
    ``choose_grid`` takes it where its cap allows; where it does not, [`jurs.fit`][]
    takes the adaptive basis (``jurs._fit.adaptive.wants_adaptive``)."""
    h = max(CELL_SPACINGS[ndim] * spacing, 4.0 * noise)
    if ndim == 2 and feature < FEATURE_CELLS * h:
        h = min(h, _feature_cell(feature, spacing, noise))
    return h


def _feature_cell(feature: float, spacing: float, noise: float) -> float:
    """The cell that resolves a feature ``feature`` wide (``FEATURE_CELLS`` of it), never
    below one spacing or 4 sigma: finer cells would follow the noise, not the feature."""
    return max(feature / FEATURE_CELLS, spacing, 4.0 * noise)


def _budget_cell(extent: np.ndarray) -> float:
    """The narrowest square cell whose grid over ``extent`` (with its 3 extra functions a
    side, and ``jurs._problem.sizes.round_size``'s rounding up of at most 25 %) stays within
    ``MAX_FEATURE_COEFFICIENTS``."""
    budget = MAX_FEATURE_COEFFICIENTS / 1.25**extent.size

    def count(h):
        return float(np.prod(np.ceil(extent / h) + 3))

    lo, hi = float(extent.max()) / 1e5, float(extent.max())  # count(hi) is small
    for _ in range(60):  # bisection in log h
        mid = float(np.sqrt(lo * hi))
        lo, hi = (mid, hi) if count(mid) > budget else (lo, mid)
    return hi


def choose_smoothing(offset: float, noise: float, ndim: int = 2) -> float | None:
    """Dimensionless smoothing from the measurements, or None where the data must choose.

    * Clean clouds (``2 sigma / d`` below ``CLEAN_NOISE_RATIO``): ``clean_smoothing``.
    * Other curves: None. [`auto_settings`][jurs.auto_settings] then chooses among
      ``SMOOTHING_CANDIDATES`` the one whose fit of 80 % of the points passes nearest
      the other 20 % (``jurs.solvers._held_out.select_lam``).
    * Other surfaces: ``noise_smoothing`` (a held-out selection would cost four more of
      their iterative solves).

    Why held-out points and not the noise estimate: sigma measures how far points stray
    from a smooth local fit, and a pixel staircase traced from an image, polygon corners
    or uneven spacing stray as much as noise does (docs/design.md section 6), yet they are
    the shape, not noise. Points held out from such a curve lie on what the kept points
    trace, and the fit that follows it closely predicts them best; points displaced by
    independent noise are predicted best by a fit that averages the neighbours. So the
    choice needs no noise model, only the data. The floor stays: smaller smoothings let
    supplementary loops grow away from the data, where no point says so
    (``benchmarks/results/smoothing.md``); the clean shortcut saves the selection's solves
    where it would pick the floor (it did on every clean shape measured).
    """
    ratio = 2.0 * noise / offset if offset > 0 else 1.0
    if ratio < CLEAN_NOISE_RATIO:
        return clean_smoothing(ndim)
    return None if ndim == 2 else noise_smoothing(offset, noise, ndim)


def clean_smoothing(ndim: int) -> float:
    """The smoothing of clean clouds: ``CLEAN_SMOOTHING`` for curves,
    ``CLEAN_SURFACE_SMOOTHING`` for surfaces."""
    return CLEAN_SMOOTHING if ndim == 2 else CLEAN_SURFACE_SMOOTHING


def noise_smoothing(offset: float, noise: float, ndim: int = 3) -> float:
    """A surface's dimensionless smoothing (curves choose theirs by held-out points,
    ``choose_smoothing``): from ``clean_smoothing`` on clean clouds to
    ``NOISY_SMOOTHING`` where noise sets the offset (``2 sigma >= d``), on the fourth
    power of ``2 sigma / d`` between.

    Why: R (eq. 31) is a membrane energy, about ``2 int |grad g|^2``; it keeps g free of
    spurious zeros away from the data and the system well posed, but near the data it
    pulls on the slope of g and so on the curve. On clean data a smaller one fits closer,
    for a little more solve time; still smaller ones fit smooth curves closer yet but
    break other shapes (a glyph's Hausdorff distance, supplementary loops), also where
    every cell holds many points (``benchmarks/results/smoothing.md``); on noisy data a
    larger one fits better (the data no longer deserve to be followed exactly). Between,
    the ramp stays low while the noise is well inside the offset (it barely moves the
    offsets' sides): outlines traced from images, whose pixel-scale wiggles measure as a
    little noise, fit closer on the fourth power than on the square; data whose noise
    sets d get 1e-3 either way. The measurements behind these choices are in
    docs/performance.md, "Measurements behind the defaults"."""
    ratio = min(1.0, 2.0 * noise / offset) if offset > 0 else 1.0
    clean = clean_smoothing(ndim)
    return float(clean + (NOISY_SMOOTHING - clean) * ratio**4)


def scale_free_lam(
    smoothing: float, num_samples: int, diagonal: float, lower, upper, cell: float | None = None
) -> float:
    """The objective's lambda of ``E_d + lam R`` for a dimensionless ``smoothing``:
    ``lam = smoothing * S * l^2 / A``, S samples, l the data's bounding-box diagonal, A the
    area of the box; for a surface ``lam = smoothing * S * l^2 * h / V`` with V the volume
    of the box and ``h`` its ``cell`` width.

    Why this scaling: E_d sums S squared residuals, so it grows with S; R is about
    ``2 int_box |grad g|^2`` whatever the grid (each neighbour difference of C is about
    ``h |grad g|`` and there are about ``A / h^2`` of them), so it grows with A and not with
    N, M. Dividing both out compares a mean squared residual with a mean squared slope
    times ``l^2``, a length squared that scales with the data. With eps proportional to d,
    g scales with the units like a length, and lam is then the same for the same shape
    whatever m, the grid, the units, a translation or a rotation.

    In 3D there are about ``V / h^3`` differences of about ``h |grad g|`` each, so R is
    about ``2 int_box |grad g|^2 / h``: it grows as the grid is refined, and the factor
    ``h`` keeps lam R the same for the same g on any grid (and ``l^2 h / V`` is again
    scale-free)."""
    extent = np.asarray(upper, float) - np.asarray(lower, float)
    volume = float(np.prod(extent))
    if extent.size == 2:
        per_length = 1.0
    elif cell is None:
        raise ValueError("a surface's lambda needs its cell width")
    else:
        per_length = float(cell) ** (extent.size - 2)
    return float(smoothing * num_samples * diagonal**2 * per_length / volume)


def held_out_smoothing(cloud, support, shape, offset, eps, domain, unit: float):
    """``(smoothing, record)``: the ``SMOOTHING_CANDIDATES`` entry chosen by held-out
    points (``jurs.solvers._held_out.select_lam``) on the fit's own problem (padded
    as [`jurs.fit`][] pads it, so clouds of similar size share the compiled selection),
    and ``((smoothing, score), ...)`` for the candidates tried (from the smallest up, until
    the score rises by more than 5 %)."""
    dtype = jnp.result_type(float)
    problem = padded_problem(
        cloud.points, cloud.normals, None, shape, offset, eps, domain, 0.0, None, dtype, support
    )
    candidates = np.asarray(SMOOTHING_CANDIDATES)
    scores = np.asarray(_select_lam(problem, jnp.asarray(candidates * unit))[1], float)
    tried = ~np.isnan(scores)
    best = int(np.argmin(np.where(np.isfinite(scores), scores, np.inf)))  # as select_lam
    record = tuple(zip(map(float, candidates[tried]), map(float, scores[tried])))
    return float(candidates[best]), record


def auto_settings(
    points: Float[ArrayLike, "m d"] | Cloud,
    normals: Float[ArrayLike, "m d"] | None = None,
    *,
    grid=None,
    offset=None,
    eps=None,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    smoothing: float | None = None,
    max_grid: int | None = None,
) -> Settings:
    """Choose the grid, offset d, eps and lambda for ``points`` and ``normals``, ``(m, 2)``
    for a curve or ``(m, 3)`` for a surface, or for a ``jurs.Cloud`` (then
    ``normals`` is None: the cloud holds them, and its measurements are kept for the fit).

    Any of ``grid``, ``offset``, ``eps``, ``domain`` and ``smoothing`` given is kept and the
    others are chosen around it (see the module docstring and each ``choose_*`` function).
    Needs concrete (untraced) points: the choices are made on the host. Inside ``jax.jit``,
    ``jax.grad`` or ``jax.vmap`` call this once outside and pass the settings in.

    ``max_grid``: the largest automatic grid along the longest side; None takes
    ``DEFAULT_MAX_GRID`` in 2D, ``DEFAULT_MAX_GRID_3D`` in 3D.

    Returns:
        [`Settings`][jurs.Settings].
    """
    if not is_concrete(points, normals):
        raise ValueError(
            "automatic settings need concrete points (they are chosen on the host); inside "
            "jit/grad/vmap pass grid, offset and eps explicitly, e.g. from "
            "jurs.auto_settings(points, normals) called outside"
        )
    # The same checks as make_problem's, before anything is computed from the inputs
    # (a NaN domain was reported as "lam must be finite").
    check_values(offset=offset, eps=eps, margin=margin, domain=domain)
    if isinstance(points, Cloud):
        cloud = points
        if normals is not None:
            raise ValueError("auto_settings(cloud): the cloud holds its normals; pass none")
    else:
        cloud = Cloud(points, normals)
    if cloud.normals is None:
        raise ValueError("auto_settings needs outward normals (jurs.estimate_normals)")
    validate_settings(cloud.points, cloud.normals, None, offset=offset, domain=domain)
    shape = None if grid is None else normalise_grid(grid, cloud.ndim)
    return choose_settings(cloud, shape, offset, eps, domain, margin, smoothing, max_grid)


def choose_settings(
    cloud: Cloud,
    shape: tuple[int, ...] | None,
    offset=None,
    eps=None,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    smoothing: float | None = None,
    max_grid: int | None = None,
    solver=None,
) -> Settings:
    """[`auto_settings`][jurs.auto_settings] of a ``jurs.Cloud`` whose settings given
    were checked (``jurs._problem.validate.check_values``, a normalised ``shape``). The
    memory the fit will take on the chosen grid, with ``solver`` (None: the default), is
    checked here, once, before the first solve on it (the held-out choice of lambda)."""
    if cloud.mask is not None:
        raise ValueError(
            "automatic settings do not take a mask; pass grid, offset, eps "
            "and solver explicitly for padded batches"
        )
    if smoothing is not None:
        check_nonnegative("smoothing", smoothing)
    ndim = cloud.ndim
    if max_grid is None:
        max_grid = DEFAULT_MAX_GRID if ndim == 2 else DEFAULT_MAX_GRID_3D
    if (
        isinstance(max_grid, bool)
        or not isinstance(max_grid, (int, np.integer))
        or max_grid < MIN_GRID
    ):
        raise ValueError(f"max_grid must be an int >= {MIN_GRID}, got {max_grid!r}")
    assert cloud.normals is not None
    p, n = cloud.points, cloud.normals
    tree = cloud.tree
    isolated = isolated_points(p, tree, n)
    if isolated.mean() > MAX_SET_ASIDE:  # no dense shape to stand apart from: keep all
        isolated[:] = False
    # Large clouds are measured at an evenly strided subset (the same points wherever the
    # cloud is placed), against the whole cloud.
    at = cloud.probes
    if isolated.any():  # measure the shape without them
        p, n = p[~isolated], n[~isolated]
        tree = cloud.tree_without(tuple(int(i) for i in np.flatnonzero(isolated)))
        at = strided_probes(len(p), PROBES)
    spacing = point_spacing(p, tree, at)
    noise = estimate_noise(p, n, tree, at=at)
    d = choose_offset(p, n, spacing, noise, tree, at) if offset is None else float(offset)
    e = d if eps is None else float(eps)
    if domain is None:  # the box make_problem will take
        # offset_samples takes NumPy arrays with xp=np; its annotation says jax.Array only.
        samples = offset_samples(cloud.points, cloud.normals, d, e, np)[0]  # pyright: ignore[reportArgumentType]
        lower, upper = auto_domain(samples, margin, xp=np)
    else:
        lower, upper = (np.asarray(c, float) for c in domain)
    width = None
    if ndim == 2:  # widths below two cells of the coarsest grid this would choose
        radius = 2.0 * float(np.max(upper - lower)) / (max_grid - 3)
        width = feature_width(p, n, radius, spacing, at)[0]
    feature = np.inf if width is None else float(np.sort(width)[int(FEATURE_QUANTILE * width.size)])
    chosen = shape is None
    if chosen:
        shape = choose_grid(lower, upper, spacing, noise, max_grid, feature)
    # Once per fit, before the first solve on the grid (the held-out choice below).
    check_fit_memory(shape, len(cloud), solver)
    diagonal = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    cell = float(np.max((upper - lower) / (np.asarray(shape) - 3)))
    thin = 0.0 if width is None else float(np.mean(width < FEATURE_CELLS * cell))
    # lam is linear in the smoothing: lam = smoothing * unit.
    unit = scale_free_lam(1.0, 3 * len(p), diagonal, lower, upper, cell)
    beta = choose_smoothing(d, noise, ndim) if smoothing is None else float(smoothing)
    held_out = None
    if beta is None:
        support = None if not isolated.any() else (~isolated).astype(float)
        beta, held_out = held_out_smoothing(cloud, support, shape, d, e, (lower, upper), unit)
    lam = beta * unit
    return Settings(
        grid=shape,
        offset=d,
        eps=e,
        lam=lam,
        smoothing=beta,
        domain=(tuple(map(float, lower)), tuple(map(float, upper))),
        spacing=spacing,
        noise=noise,
        held_out=held_out,
        set_aside=tuple(int(i) for i in np.flatnonzero(isolated)),
        thin_fraction=thin,
        data_cell=data_cell(ndim, spacing, noise, feature) if chosen else None,
    )


#: Reweighted solves at most in the default robust fit (``default_solver``): each is
#: one exact solve.
DEFAULT_ROBUST_STEPS = 8


#: ... and its stop rule: ``E_rob`` changing by at most this fraction between steps.
DEFAULT_ROBUST_RTOL = 1e-3


def default_solver(settings) -> AbstractSolver:
    """The solver ``fit`` uses with the automatic ``settings``: the exact solve
    ``LeastSquares(lam=settings.lam)``; where points were set aside as standing alone
    (``settings.set_aside``), the robust reweighting ``RobustLeastSquares(lam, loss="huber")``
    of the rest, which also weighs down points that stray less far (Huber's loss is
    convex: it never sets an inlier aside, unlike Cauchy's or Tukey's, which dropped the
    points of curved parts on coarse grids: docs/design.md section 6)."""
    if settings.set_aside:
        return RobustLeastSquares(
            lam=settings.lam, loss="huber", max_steps=DEFAULT_ROBUST_STEPS, rtol=DEFAULT_ROBUST_RTOL
        )
    return LeastSquares(lam=settings.lam)


def set_aside_mask(points, settings):
    """``(m,)`` weights, 0 at the points ``settings`` set aside, or None where none were: the
    ``mask`` that fits without them (also for a caller that passes the automatic settings
    to ``fit`` explicitly)."""
    if settings is None or not settings.set_aside:
        return None
    support = np.ones(len(points))
    support[list(settings.set_aside)] = 0.0
    return support
