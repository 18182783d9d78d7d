"""Zero sets of curves (2D splines): extraction, supplementary components, distances.

The definitions are in the docstring of [`jurs.levelset`][]."""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Sequence, cast

import contourpy
import equinox as eqx
import numpy as np
import numpy.typing as npt
from jaxtyping import Float
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from .._cloud.carried import MIN_CARRIED_FRACTION, carried_samples
from .._model.adaptive import AdaptiveSpline
from .._model.band import HULL_TOLERANCE, band_lattice
from .._model.lattice import FinestSpline
from .._model.spline import ImplicitSpline
from .._problem.memory import check_memory
from ._trimming import check_rim, check_trim, trim_curves

if TYPE_CHECKING:
    from contourpy._contourpy import LineReturn_SeparateCode

#: Default number of grid nodes along the longer side of the box.
DEFAULT_RESOLUTION = 512
#: Peak bytes per grid node of [`analyze`][jurs.levelset.analyze] (node coordinates, their
#: stacked and padded copies, the values and contourpy's working arrays).
#: The default supplementary threshold is at least this fraction of the fit's cell
#: ([`analyze_grid`][jurs.levelset.analyze_grid]): on 1e6 points of a circle, d = 3e-6 on
#: a grid capped at 96 a side (cells 0.024), the one accurate component lay more than 2 d
#: from the data and was counted supplementary. An eighth of a cell stays below 2 d on the
#: automatic settings' grids (cells at most 16 d) and on the paper's Example 1 (9 x 9, d =
#: 0.1).
FIT_CELL_FRACTION = 0.125
BYTES_PER_NODE = 128
#: Default tiny-loop size, in grid cells of perimeter.
DEFAULT_TINY_CELLS = 4.0
#: Default supplementary threshold, as a multiple of the offset d.
DEFAULT_THRESHOLD_FACTOR = 2.0


def sampling_grid(
    lower: Float[npt.ArrayLike, " 2"],
    upper: Float[npt.ArrayLike, " 2"],
    resolution: int = DEFAULT_RESOLUTION,
) -> tuple[Float[np.ndarray, " nx"], Float[np.ndarray, " ny"], float]:
    """Grid nodes over the box ``[lower, upper]``: ``resolution`` along the longer side, the
    same spacing along the shorter one (at least 2 nodes). Returns ``(xs, ys, h)`` with
    ``h`` the spacing along the longer side."""
    lower = np.asarray(lower, dtype=float).reshape(2)
    upper = np.asarray(upper, dtype=float).reshape(2)
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
        raise TypeError(f"resolution must be an int, got {resolution!r}")
    if int(resolution) < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    if not (np.isfinite(lower).all() and np.isfinite(upper).all() and (upper > lower).all()):
        raise ValueError(f"box must be finite with lower < upper, got {lower}, {upper}")
    extent = upper - lower
    counts = np.maximum(2, np.round((int(resolution) - 1) * extent / extent.max()).astype(int) + 1)
    check_memory(
        f"resolution={int(resolution)}", BYTES_PER_NODE * float(np.prod(counts)), device=False
    )
    xs = np.linspace(lower[0], upper[0], counts[0])
    ys = np.linspace(lower[1], upper[1], counts[1])
    return xs, ys, float(extent.max() / (int(resolution) - 1))


@eqx.filter_jit
def evaluate_spline(spline, xy):
    return spline(xy)


def evaluate_grid(
    spline,
    xs: Float[npt.ArrayLike, " nx"],
    ys: Float[npt.ArrayLike, " ny"],
    *,
    chunk: int = 1 << 15,
) -> Float[np.ndarray, "ny nx"]:
    """``values[j, i] = g(xs[i], ys[j])`` as a NumPy array.

    Evaluated in fixed-size chunks (the last one padded) under one jit, so grids of any
    size reuse one compiled function per spline grid shape and dtype. An adaptive spline
    is evaluated on the host, nothing compiled (``jurs._model.lattice.FinestSpline``).
    """
    return _grid_values(spline, xs, ys, chunk)


@functools.singledispatch
def _grid_values(spline, xs, ys, chunk: int) -> np.ndarray:
    """``evaluate_grid``'s values of a spline on a grid, or of any function: fixed-size
    chunks under one jit."""
    gx, gy = np.meshgrid(np.asarray(xs), np.asarray(ys))
    dtype = np.asarray(spline.control).dtype if hasattr(spline, "control") else np.float64
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1).astype(dtype)
    n = len(xy)
    padded = np.concatenate([xy, np.repeat(xy[-1:], -n % chunk, axis=0)])
    out = np.concatenate(
        [
            np.asarray(evaluate_spline(spline, padded[k : k + chunk]))
            for k in range(0, len(padded), chunk)
        ]
    )
    return out[:n].reshape(gx.shape).astype(float)


@_grid_values.register
def _(spline: AdaptiveSpline, xs, ys, chunk: int) -> np.ndarray:
    # On the host through the finest level's coefficients: nothing compiled.
    axes = [np.asarray(xs, np.float64).reshape(-1), np.asarray(ys, np.float64).reshape(-1)]
    return spline.lattice(axes).T


def _box(spline, box):
    if box is None:
        return np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    lower, upper = box
    return np.asarray(lower, float), np.asarray(upper, float)


def contour_lines(
    xs: Float[npt.ArrayLike, " nx"],
    ys: Float[npt.ArrayLike, " ny"],
    values: Float[npt.ArrayLike, "ny nx"],
    level: float = 0.0,
) -> list[tuple[Float[np.ndarray, "k 2"], bool]]:
    """Marching-squares polylines of ``values`` (shape ``(len(ys), len(xs))``) at ``level``.

    Returns a list of ``(polyline (k, 2), closed)``. NaN/Inf values are masked out. Closed
    polylines repeat their first point at the end.
    """
    gen = contourpy.contour_generator(
        np.asarray(xs, float),
        np.asarray(ys, float),
        np.asarray(values, float),
        name="serial",
        line_type=contourpy.LineType.SeparateCode,
    )
    # LineType.SeparateCode above: the stubs type lines() as the union over all line types
    lines, codes = cast("LineReturn_SeparateCode", gen.lines(float(level)))
    return [(np.asarray(p, float), bool(len(c) and c[-1] == 79)) for p, c in zip(lines, codes)]


def zero_level_set(
    spline, resolution: int = DEFAULT_RESOLUTION, box=None, level: float = 0.0
) -> list[tuple[Float[np.ndarray, "k 2"], bool]]:
    """The zero-level set of ``spline`` over ``box`` (default the spline's box) as polylines.

    Returns a list of ``(polyline (k, 2), closed)`` pairs; see the module docstring. An
    adaptive spline ([`jurs.AdaptiveSpline`][]) is evaluated only on the grid's blocks
    where g may reach the level; the lines are the full grid's (docs/design.md section 8,
    "Contouring the band").
    """
    xs, ys, _ = sampling_grid(*_box(spline, box), resolution)
    return contour_lines(xs, ys, _contour_values(spline, xs, ys, level), level)


@functools.singledispatch
def _contour_values(
    spline, xs: Float[npt.ArrayLike, " nx"], ys: Float[npt.ArrayLike, " ny"], level: float = 0.0
) -> Float[np.ndarray, "ny nx"]:
    """The grid [`contour_lines`][jurs.levelset.contour_lines] needs for ``{g = level}``:
    [`evaluate_grid`][jurs.levelset.evaluate_grid]'s values, except that an adaptive
    spline ([`jurs.AdaptiveSpline`][]) is evaluated only on the blocks of 16 x 16 cells
    where g may reach the level (``jurs/_model/band.py``; docs/design.md section 8,
    "Contouring the band"). The other nodes, in blocks with every node strictly on one
    side of the level, hold a value of g from their side: the lines are the full grid's."""
    return evaluate_grid(spline, xs, ys)


@_contour_values.register
def _(spline: AdaptiveSpline, xs, ys, level: float = 0.0) -> np.ndarray:
    return _band_values(spline, xs, ys, level)[0]


def _band_values(spline: AdaptiveSpline, xs, ys, level: float, evaluator=None):
    """``(values (ny, nx), evaluated (ny, nx), plan)`` of ``band_lattice``, through
    ``evaluator`` (the spline's ``on_host()``) where one was built already."""
    axes = [np.asarray(xs, np.float64).reshape(-1), np.asarray(ys, np.float64).reshape(-1)]
    evaluator = spline.on_host() if evaluator is None else evaluator
    values, evaluated, plan = band_lattice(evaluator, axes, float(level))
    return values.T, evaluated.T, plan


def _zero_area(values: np.ndarray, zero_tol: float) -> float:
    """The fraction of nodes where ``|g| <= zero_tol * max|g|``."""
    scale = float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 0.0
    return float(np.mean(np.abs(values) <= zero_tol * scale))


@functools.singledispatch
def _sampled(spline, xs, ys, zero_tol: float) -> tuple[np.ndarray, float]:
    """The values ``analyze`` contours (``_contour_values`` at level 0) and the zero-area
    fraction of the full grid's values.

    For an adaptive spline's band the fraction is exact when it can be decided without
    the nodes left out: with ``R`` the largest ``|A_num / A_den|`` of its coefficients
    (all denominators positive), ``|g| <= R`` on the spline's box and every node left
    out has ``|g| > HULL_TOLERANCE R``. So when ``zero_tol`` times the grid's ``max|g|``
    stays below that, no node left out counts, and when no band node lies between
    ``zero_tol`` times the band's ``max|g|`` (a lower bound of the grid's) and ``zero_tol``
    times an upper bound of it, the band's count is the grid's. Otherwise the whole grid
    is evaluated for it."""
    values = evaluate_grid(spline, xs, ys)
    return values, _zero_area(values, zero_tol)


@_sampled.register
def _(spline: AdaptiveSpline, xs, ys, zero_tol: float) -> tuple[np.ndarray, float]:
    evaluator = spline.on_host()  # the cascade once, for the band and the bound
    values, evaluated, _ = _band_values(spline, xs, ys, 0.0, evaluator)
    ratio = _coefficient_ratio(evaluator)
    band = np.abs(values[evaluated])
    if ratio is not None and band.size and np.isfinite(band).all():
        # Outside the spline's box (a larger ``box``) g extrapolates past R: those nodes
        # are all in the band, so max|g| is at most the larger of R and the band's.
        low, high = zero_tol * float(band.max()), zero_tol * max(ratio, float(band.max()))
        if high < HULL_TOLERANCE * ratio and not np.any((band > low) & (band <= high)):
            return values, float(np.count_nonzero(band <= low)) / values.size
    return values, _zero_area(evaluate_grid(spline, xs, ys), zero_tol)


def _coefficient_ratio(evaluator: FinestSpline) -> float | None:
    """``max |A_num / A_den|`` over an adaptive spline's cascaded coefficients (its
    ``FinestSpline``); None when a denominator is not positive (no bound on ``|g|``
    then)."""
    numerator, denominator = evaluator.cascaded
    if not np.all(denominator > 0):
        return None
    return float(np.max(np.abs(numerator / denominator), initial=0.0))


def polyline_length(polyline: Float[npt.ArrayLike, "k 2"]) -> float:
    """Sum of the segment lengths of a ``(k, 2)`` polyline."""
    p = np.asarray(polyline, float)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


def resample(polyline: Float[npt.ArrayLike, "k 2"], spacing: float) -> Float[np.ndarray, "l 2"]:
    """Points along ``polyline`` at arc-length spacing at most ``spacing`` (ends included)."""
    p = np.asarray(polyline, float)
    if len(p) < 2:
        return p.copy()
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    if s[-1] == 0.0:
        return p[:1].copy()
    t = np.linspace(0.0, s[-1], int(np.ceil(s[-1] / spacing)) + 1)
    return np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)


def chamfer_hausdorff(
    a: Float[npt.ArrayLike, "k 2"], b: Float[npt.ArrayLike, "l 2"]
) -> tuple[float, float]:
    """Symmetric Chamfer and Hausdorff distances between point sets ``a (k, 2)`` and
    ``b (l, 2)`` (see the module docstring); ``(inf, inf)`` if either is empty."""
    a = np.asarray(a, float).reshape(-1, 2)
    b = np.asarray(b, float).reshape(-1, 2)
    if len(a) == 0 or len(b) == 0:
        return float("inf"), float("inf")
    d_ab = cKDTree(b).query(a)[0]
    d_ba = cKDTree(a).query(b)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean())), float(max(d_ab.max(), d_ba.max()))


@dataclasses.dataclass(frozen=True)
class Component:
    """One connected polyline of the zero-level set.

    Attributes:
        polyline: ``(k, 2)`` vertices (closed ones repeat the first at the end).
        closed: True for a loop, False for a curve ending on the box border or, trimmed
            ([`analyze`][jurs.levelset.analyze]'s ``trim``), where it leaves the data.
        length: arc length.
        mean_distance: arc-length mean distance to the nearest data point.
        far_fraction: fraction of its length farther than the threshold from the data.
        supplementary: ``far_fraction > 0.5`` (its arc-length median distance is above the
            threshold) or, for a closed loop, ``carried_fraction`` below
            ``MIN_CARRIED_FRACTION`` (a half): a loop the data do not account for.
        tiny: a closed loop shorter than ``tiny_cells`` grid cells.
        carried_fraction: fraction of its length whose nearest data point lies within the
            threshold and nearer to this component than to any other
            (``carried_samples``): 0 for a loop beside data that another curve passes
            through, about 1 for a curve that follows its data.
    """

    polyline: np.ndarray
    closed: bool
    length: float
    mean_distance: float
    far_fraction: float
    supplementary: bool
    tiny: bool
    carried_fraction: float = 1.0

    @property
    def ends(self) -> Float[np.ndarray, "2 2"] | None:
        """The two end points ``[[x0, y0], [x1, y1]]`` of an open curve; None for a
        closed one."""
        return None if self.closed else self.polyline[[0, -1]].copy()


@dataclasses.dataclass(frozen=True)
class LevelSetReport:
    """What [`analyze`][jurs.levelset.analyze] measured. ``as_dict()`` gives the numbers as
    plain floats/ints.

    Attributes:
        components: every [`Component`][jurs.levelset.Component], longest first.
        threshold: distance above which a component is supplementary.
        cell_size: grid spacing h.
        resolution: grid nodes along the longer side.
        chamfer, hausdorff: distances between the zero set and the reference (or data).
        tiny_cells: tiny-loop size in cells.
        zero_area_fraction: fraction of grid nodes where g is numerically 0.
        reference: ``"reference curve"`` or ``"data points"``, what they were measured to.
        trim: the trim in local spacings the curves were cut to, None when untrimmed.
    """

    components: tuple
    threshold: float
    cell_size: float
    resolution: int
    tiny_cells: float
    zero_area_fraction: float
    chamfer: float
    hausdorff: float
    reference: str
    trim: float | None = None

    @property
    def num_components(self) -> int:
        return len(self.components)

    @property
    def supplementary(self) -> list:
        """The supplementary components."""
        return [c for c in self.components if c.supplementary]

    @property
    def num_supplementary(self) -> int:
        return len(self.supplementary)

    @property
    def supplementary_length(self) -> float:
        return float(sum(c.length for c in self.supplementary))

    @property
    def total_length(self) -> float:
        return float(sum(c.length for c in self.components))

    @property
    def num_tiny_loops(self) -> int:
        return sum(c.tiny for c in self.components)

    def as_dict(self) -> dict:
        """The summary numbers (JSON-ready), prefixed by nothing: ``num_components``,
        ``num_supplementary``, ``supplementary_length``, ``total_length``,
        ``num_tiny_loops``, ``chamfer``, ``hausdorff``, ``threshold``, ``cell_size``,
        ``resolution``, ``tiny_cells``, ``zero_area_fraction``, ``distance_reference``,
        ``trim``, ``num_open`` and ``end_points`` (per component, longest first: its two
        end points, None for a closed one)."""
        return {
            "num_components": self.num_components,
            "num_supplementary": self.num_supplementary,
            "supplementary_length": self.supplementary_length,
            "total_length": self.total_length,
            "num_tiny_loops": self.num_tiny_loops,
            "chamfer": self.chamfer,
            "hausdorff": self.hausdorff,
            "threshold": self.threshold,
            "cell_size": self.cell_size,
            "resolution": self.resolution,
            "tiny_cells": self.tiny_cells,
            "zero_area_fraction": self.zero_area_fraction,
            "distance_reference": self.reference,
            "trim": self.trim,
            "num_open": sum(not c.closed for c in self.components),
            "end_points": [
                None if c.closed else np.asarray(c.ends).tolist() for c in self.components
            ],
        }


def classify(
    lines,
    points: Float[npt.ArrayLike, "m 2"],
    *,
    threshold: float,
    cell_size: float,
    tiny_cells: float = DEFAULT_TINY_CELLS,
) -> list[Component]:
    """Turn ``(polyline, closed)`` pairs into [`Component`][jurs.levelset.Component] s,
    longest first, measuring their distance to the data ``points (m, 2)`` with a KD-tree
    and which data each carries (``carried_samples``, at segment midpoints)."""
    tree = cKDTree(np.asarray(points, float).reshape(-1, 2))
    polys = [np.asarray(poly, float).reshape(-1, 2) for poly, _ in lines]
    # Each component's samples: its segments' midpoints (a single point: itself).
    samples = [0.5 * (p[1:] + p[:-1]) if len(p) >= 2 else p for p in polys]
    labels = np.repeat(np.arange(len(polys)), [len(x) for x in samples])
    stacked = np.concatenate(samples) if samples else np.empty((0, 2))
    # A cell's diagonal: marching squares cuts a pinch below it into loops side by side.
    diagonal = float(np.sqrt(2.0) * cell_size)
    distance, carried = carried_samples(stacked, labels, tree, threshold, diagonal)
    starts = np.cumsum([0] + [len(x) for x in samples])
    out = []
    for k, (poly, (_, closed)) in enumerate(zip(polys, lines)):
        dist, mine = distance[starts[k] : starts[k + 1]], carried[starts[k] : starts[k + 1]]
        if len(poly) >= 2:
            seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
            length = float(seg.sum())
        else:
            seg, length = None, 0.0
        # Arc-length weighted; a curve of zero length weighs its points alike.
        weight = seg if length > 0 else None
        mean = float(np.average(dist, weights=weight))
        far = float(np.average(dist > threshold, weights=weight))
        share = float(np.average(mine, weights=weight))
        out.append(
            Component(
                poly,
                bool(closed),
                length,
                mean,
                far,
                far > 0.5 or bool(closed and share < MIN_CARRIED_FRACTION),
                bool(closed and length < tiny_cells * cell_size),
                share,
            )
        )
    out.sort(key=lambda c: -c.length)
    return out


def analyze(
    spline,
    points: Float[npt.ArrayLike, "m 2"],
    *,
    offset: float = 0.1,
    threshold: float | None = None,
    reference: Float[npt.ArrayLike, "k 2"] | None = None,
    resolution: int = DEFAULT_RESOLUTION,
    box=None,
    tiny_cells: float = DEFAULT_TINY_CELLS,
    zero_tol: float = 1e-12,
    trim: float | bool | None = None,
    rim: float | bool | None = True,
) -> LevelSetReport:
    """Extract and measure the zero-level set of ``spline`` (see the module docstring).

    Args:
        spline: an [`jurs.ImplicitSpline`][] (anything jit-callable on ``(n, 2)`` arrays
            with ``lower``/``upper`` works, given ``box``; for other functions, e.g. NumPy
            or SciPy ones, sample them yourself and call
            [`analyze_grid`][jurs.levelset.analyze_grid]).
        points: ``(m, 2)`` data points the fit was made from.
        offset: d of the fit; the default threshold is ``2 d`` (or an eighth of a cell
            of the spline's grid, where more).
        threshold: distance above which a component is supplementary (overrides ``offset``).
        reference: optional ``(k, 2)`` dense samples of the true curve for the Chamfer and
            Hausdorff distances; default the data points.
        resolution: grid nodes along the longer side of the box (default 512). An
            adaptive spline is evaluated only on the grid's blocks where g may reach 0,
            with the full grid's lines and zero-area fraction as the result.
        box: ``((x_min, y_min), (x_max, y_max))``; default the spline's box.
        tiny_cells: closed loops shorter than this many grid cells count as tiny.
        zero_tol: relative level below which g counts as identically zero (for
            ``zero_area_fraction``).
        trim: open curves (a coastline, a profile): None (default) or False measures the
            whole zero set over the box; a positive number cuts it to the part within
            that many local spacings of ``points``, True to ``DEFAULT_TRIM`` (2.5)
            spacings, by [`trim_curves`][jurs.levelset.trim_curves]: a curve is split
            where it leaves the data, its pieces open. Everything else (components,
            supplementary ones, distances) is then measured on the pieces, and each open
            component's ``ends`` are its end points. A sample's spacing along a curve is
            ``2 r_8 / 8`` (``r_8`` the distance to its 8th nearest neighbour; the median
            over it and those neighbours), exactly the step of evenly spaced samples.
        rim: with ``trim``, the spacings a curve may run past the end of the data
            (where the samples lie to one side): True (default) ``DEFAULT_RIM`` (1), a
            number >= 0, None or False the distance rule alone; see
            [`trim_curves`][jurs.levelset.trim_curves].

    Returns:
        [`LevelSetReport`][jurs.levelset.LevelSetReport].

    Raises:
        ValueError: a ``trim`` that is not positive and finite, a ``rim`` that is
            negative or not finite, or ``points`` with fewer than 2 distinct rows when
            trimming.
    """
    check_trim(trim, points)  # before the grid is sampled
    check_rim(rim)
    xs, ys, _ = sampling_grid(*_box(spline, box), resolution)
    values, zero_area = _sampled(spline, xs, ys, zero_tol)
    return _measure(
        xs,
        ys,
        values,
        zero_area,
        points,
        offset=offset,
        threshold=threshold,
        fit_cell=_fit_cell(spline),
        reference=reference,
        tiny_cells=tiny_cells,
        trim=trim,
        rim=rim,
    )


@functools.singledispatch
def _fit_cell(spline) -> float:
    """The width of the spline's cells (its box over its knot spans), 0 for a function that
    is not a [`jurs.ImplicitSpline`][]."""
    return 0.0


@_fit_cell.register
def _(spline: ImplicitSpline) -> float:
    return spline.cell_width


def analyze_grid(
    xs: Float[npt.ArrayLike, " nx"],
    ys: Float[npt.ArrayLike, " ny"],
    values: Float[npt.ArrayLike, "ny nx"],
    points: Float[npt.ArrayLike, "m 2"],
    *,
    offset: float = 0.1,
    threshold: float | None = None,
    fit_cell: float = 0.0,
    reference: Float[npt.ArrayLike, "k 2"] | None = None,
    tiny_cells: float = DEFAULT_TINY_CELLS,
    zero_tol: float = 1e-12,
    trim: float | bool | None = None,
    rim: float | bool | None = True,
) -> LevelSetReport:
    """[`analyze`][jurs.levelset.analyze] for a function already sampled on a grid:
    ``values[j, i]`` at ``(xs[i], ys[j])``, with ``xs``/``ys`` from
    [`sampling_grid`][jurs.levelset.sampling_grid] (any implicit function can be measured
    this way, so other methods are compared on equal terms). The cell size is the spacing
    along the longer side; ``fit_cell``, the width of the fitted function's own cells (0:
    none), raises the default threshold to ``FIT_CELL_FRACTION`` of it; other arguments as
    in [`analyze`][jurs.levelset.analyze]."""
    values = np.asarray(values, float)
    return _measure(
        xs,
        ys,
        values,
        _zero_area(values, zero_tol),
        points,
        offset=offset,
        threshold=threshold,
        fit_cell=fit_cell,
        reference=reference,
        tiny_cells=tiny_cells,
        trim=trim,
        rim=rim,
    )


def _measure(
    xs,
    ys,
    values: np.ndarray,
    zero_area: float,
    points,
    *,
    offset: float,
    threshold: float | None,
    fit_cell: float,
    reference,
    tiny_cells: float,
    trim: float | bool | None,
    rim: float | bool | None,
) -> LevelSetReport:
    """``analyze_grid`` given the zero-area fraction (NaN values: no line there)."""
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) == 0:
        raise ValueError(f"points must have shape (m, 2) with m >= 1, got {points.shape}")
    if threshold is None:
        if not offset > 0:
            raise ValueError(f"offset must be positive, got {offset}")
        threshold = max(
            DEFAULT_THRESHOLD_FACTOR * float(offset), FIT_CELL_FRACTION * float(fit_cell)
        )
    if not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    xs, ys, values = np.asarray(xs, float), np.asarray(ys, float), np.asarray(values, float)
    if values.shape != (len(ys), len(xs)):
        raise ValueError(
            f"values must have shape (len(ys), len(xs)) = {(len(ys), len(xs))}, got {values.shape}"
        )
    h = float(max(xs[-1] - xs[0], ys[-1] - ys[0]) / (max(len(xs), len(ys)) - 1))
    lines = contour_lines(xs, ys, values)
    spacings = check_trim(trim, points)
    if spacings is not None:
        lines = trim_curves(lines, points, spacings, rim)
    components = classify(
        lines, points, threshold=float(threshold), cell_size=h, tiny_cells=tiny_cells
    )
    target = points if reference is None else np.asarray(reference, float).reshape(-1, 2)
    zero = [resample(c.polyline, h / 2) for c in components]
    zero = np.concatenate(zero) if zero else np.empty((0, 2))
    chamfer, hausdorff = chamfer_hausdorff(zero, target)
    return LevelSetReport(
        tuple(components),
        float(threshold),
        h,
        max(len(xs), len(ys)),
        float(tiny_cells),
        zero_area,
        chamfer,
        hausdorff,
        "data points" if reference is None else "reference curve",
        spacings,
    )


def polylines_table(components: Sequence[Component]) -> Float[np.ndarray, "rows 5"]:
    """Rows ``(component, closed, supplementary, x, y)`` for every vertex, components
    numbered from 0 in the order given (as written to the CLI's CSV)."""
    rows = [
        np.column_stack(
            [
                np.full(len(c.polyline), k),
                np.full(len(c.polyline), c.closed),
                np.full(len(c.polyline), c.supplementary),
                c.polyline,
            ]
        )
        for k, c in enumerate(components)
    ]
    return np.concatenate(rows) if rows else np.empty((0, 5))
