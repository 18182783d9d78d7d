"""Every verdict a fit can get beyond the solver's own, and its thresholds, in one place.

The driver's loop ([`jurs.solve`][]) sets ``successful``, ``max_steps_reached``,
``failed``, ``nonfinite`` and ``weights_at_floor`` from the run, and
``inconsistent_normals`` where the fit reads its offsets the wrong way round
(``offset_sign_disagreement``, traced with the fit). [`jurs.fit`][] then judges a
fit made at top level against its cloud on the host (``judge``): normals flipped or
lying along the shape, or all pointing inward (a closed zero set with g negative on the
box's border), make it ``inconsistent_normals`` (``check_orientation``); with
automatic settings, parts cut, gaps bridged or points left far from the zero set make it
``doubtful`` (``check_doubts``). The reasoning behind each threshold is in
docs/robustness.md; the measurements in ``benchmarks/results/quality.md`` and
``benchmarks/results/surfaces.md``.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._cloud.carried import (
    MIN_CARRIED_FRACTION,
    SHELL_REACH,
    carried_samples,
    surface_shells,
)
from .._cloud.measure import PROBES, feature_width, strided_probes
from .._model.adaptive import AdaptiveSpline
from .._model.band import band_regions, plan_band
from .._model.function import AbstractSpline
from .._model.spline import ImplicitSpline
from .._problem.energy import layout_residuals
from .._problem.problem import Problem, values_by_point
from .._problem.validate import unit_normals
from .solution import RESULTS

#: A fit whose stop rule was met but whose own sign is wrong at more than this fraction of
#: the offset samples (g <= 0 outside, g >= 0 inside) is reported as
#: ``RESULTS.inconsistent_normals``. With the automatic settings, clean and noisy clouds
#: stay well below it and random or alternately flipped normals mostly above it
#: (docs/robustness.md, "Verdicts, after the fit"; docs/performance.md, "Measurements
#: behind the defaults").
MAX_OFFSET_SIGN_DISAGREEMENT = 0.2


#: The check reads every k-th point, at most this many: its per-point sums are arrays of
#: the points' length, which a sharded fit all-reduces to every device (a 1e7-point cloud:
#: 240 MB a device, more than its share of the samples on 8 devices). 65536 points estimate
#: the fraction within about 0.4 % (two standard errors at the threshold).
SIGN_CHECK_POINTS = 1 << 16


def offset_sign_disagreement(problem: Problem, spline: ImplicitSpline):
    """Fraction of the points whose two offset samples the fit reads the wrong way round:
    ``g(P + d n) <= g(P - d n)``, the fit rising inward across the point.

    The two samples are compared with each other, not with 0: where the grid's cells are
    much wider than d (a dense cloud on a capped grid) the zero set lies farther than d
    from the data, so an offset can sit on the wrong side of it while the fit still
    rises outward through the point (1e6 points of a circle: a third of the offsets on the
    wrong side of an accurate fit). Above ``SIGN_CHECK_POINTS`` points, an evenly
    strided subset of them is read (``offset_sign_counts``)."""
    wrong, counted = offset_sign_counts(problem, spline, sign_check_stride(problem.num_points))
    return wrong / jnp.maximum(counted, 1)


def sign_check_stride(num_points: int) -> int:
    """The stride of ``offset_sign_disagreement`` over ``num_points`` points: every
    point up to ``SIGN_CHECK_POINTS``."""
    return -(-num_points // SIGN_CHECK_POINTS)


def offset_sign_counts(problem: Problem, spline: ImplicitSpline, stride, first=0):
    """``(wrong, counted)`` of ``offset_sign_disagreement`` (``sign_counts`` of the
    spline's residuals)."""
    local = problem.local
    mask, targets = local.to_layout(problem.mask), local.to_layout(problem.targets)
    r, _, _ = layout_residuals(local, mask, targets, spline.control, spline.weights)
    return sign_counts(problem, r, stride, first)


def sign_counts(problem: Problem, r: Array, stride, first=0, in_order: bool = False):
    """``(wrong, counted)`` of ``offset_sign_disagreement`` from the residuals ``r`` in
    the kernels' layout, reading the points whose index ``first + i`` (``i`` the point's
    own in ``problem``, ``first`` that of its first point in a larger cloud taken in
    parts) is a multiple of ``stride``: the counts of a cloud's parts add up to the whole
    cloud's. ``stride`` and ``first`` may be traced. ``in_order``: the problem's slots are
    the paper's order, one sample a slot (as [`jurs.make_problem`][] lays out traced
    points with ``bucket_size=1``), read as they are instead of gathered by point."""
    local = problem.local
    mask, targets = local.to_layout(problem.mask), local.to_layout(problem.targets)
    m = problem.num_points
    if in_order:
        g = (r + targets).reshape(3, m)  # r = g - b where real
        read = (mask.reshape(3, m)[1] > 0) & ((first + jnp.arange(m)) % stride == 0)
        return jnp.sum(read & (g[1] <= g[2])), jnp.sum(read)
    # (The table form, for small problems only, carries it as floats: exact there.)
    index = local.to_layout(problem.sample_index).astype(jnp.int32)
    point, kind = index % m, index // m
    real = (mask > 0) & ((first + point) % stride == 0)
    # The points read have distinct ``point // stride``: m // stride + 1 slots each kind.
    size = m // stride + 1 if isinstance(stride, int) else m
    index = kind * size + point // stride
    _, g_out, g_in = values_by_point(r + targets, index, real, size)  # r = g - b where real
    counted = values_by_point(jnp.ones_like(r), index, real, size)[1] > 0
    wrong = counted & (g_out <= g_in)
    return jnp.sum(wrong), jnp.sum(counted)


#: More than this fraction of the points with normals flipped against their neighbours
#: (``jurs._problem.problem.flipped_normal_fraction``), or with normals along the curve
#: (``jurs._problem.problem.tangential_normal_fraction``), makes a fit
#: ``inconsistent_normals``: consistent clouds read near 0 (a little more where sampled
#: coarser than their parts), half or every other normal flipped and random normals
#: about 0.5 (docs/robustness.md, "Verdicts, after the fit").
MAX_FLIPPED_FRACTION = 0.2


MAX_TANGENTIAL_FRACTION = 0.2


#: The inside-out check samples g on the box's border on a lattice of half-cells (two
#: nodes a knot span), at most this many nodes (coarser beyond): a few planes of the grid,
#: cheap beside the fit.
BORDER_CHECK_NODES = 1 << 18


def border_negative_fraction(spline: AbstractSpline) -> float:
    """The fraction of the box's border where ``g < 0``: 0 for a closed shape fitted as the
    contract says (negative inside, positive outside, so positive on the border), 1 for the
    same shape fitted inside out (every normal pointing inward: the fit follows its
    offsets, and is positive inside), in between where the zero set reaches the border (an
    open scan, a trimmed surface: no inside to check). NaN where g is not finite there.

    g is sampled at the nodes of a lattice of half-cells over each face (edge in 2D) of the
    box, at most ``BORDER_CHECK_NODES`` nodes, as scattered points (``AbstractSpline.on_host``'s
    ``values``, float64 on the host): a hierarchy evaluates each at its own leaf, where a
    lattice would refine its coarse border cells to the finest level."""
    box = (
        tuple(np.asarray(spline.lower, float).tolist()),
        tuple(np.asarray(spline.upper, float).tolist()),
    )
    nodes = _border_nodes(*box, tuple(int(c) for c in spline.finest_cells))
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.asarray(spline.on_host().values(nodes))
    if not np.isfinite(values).all():
        return float("nan")
    return float(np.mean(values < 0))


@functools.lru_cache(maxsize=2)
def _border_nodes(lower: tuple, upper: tuple, cells: tuple) -> np.ndarray:
    """``border_negative_fraction``'s nodes ``(n, d)`` on the box ``lower``-``upper`` with
    ``cells`` finest cells a side; kept for the next fit in the same box (read-only; two
    boxes kept, at most ``BORDER_CHECK_NODES`` nodes each: a surface's take 6 MB)."""
    lower_, upper_ = np.asarray(lower), np.asarray(upper)
    steps = 2.0 * np.asarray(cells, float)
    d = len(steps)
    # Each of the 2 d faces holds the lattice of the other d - 1 axes.
    count = 2 * d * float(np.prod(steps + 1)) / float(np.min(steps + 1))
    if count > BORDER_CHECK_NODES:
        scale = (BORDER_CHECK_NODES / count) ** (1.0 / max(d - 1, 1))
        steps = np.maximum(2.0, np.floor(steps * scale))
    axes = [np.linspace(lo, hi, int(n) + 1) for lo, hi, n in zip(lower_, upper_, steps)]
    nodes = []
    for axis in range(d):  # both faces across ``axis``
        faces = [*axes[:axis], np.array([lower_[axis], upper_[axis]]), *axes[axis + 1 :]]
        nodes.append(np.stack(np.meshgrid(*faces, indexing="ij"), -1).reshape(-1, d))
    joined = np.concatenate(nodes)
    joined.flags.writeable = False
    return joined


def _inward_doubt(cloud) -> str:
    what = "curve" if cloud.ndim == 2 else "surface"
    return (
        f"the fit is negative all along the box's border, outside the closed {what}: every "
        "normal points inward, and g is positive inside, the opposite of the contract "
        "(negative inside, positive outside). Pass -normals (normals pointing outward) "
        "and fit again"
    )


def check_orientation(sol, cloud):
    """``sol`` with ``metrics["flipped_normal_fraction"]`` and
    ``metrics["tangential_normal_fraction"]`` (measured once per ``cloud``,
    ``jurs._cloud.cloud.Cloud.orientation``) and, where more than
    ``MAX_FLIPPED_FRACTION`` of the normals are flipped against their neighbours or
    more than ``MAX_TANGENTIAL_FRACTION`` lie along the curve, the verdict
    ``RESULTS.inconsistent_normals`` in place of success or max_steps (half-flipped or
    random normals fitted "successfully" into 2 or 20 loops). Host side. Unlike an input
    error this is a verdict, as optimistix reports a failed solve in ``sol.result``: the
    fit ran; [`jurs.fit`][] raises it with ``throw=True`` and returns it otherwise.

    Normals that all point inward agree with each other, so the checks above and the
    driver's offset-sign check pass them, and the fit, following its offsets, is positive
    inside. Where g is negative on the whole border of the box
    (``metrics["border_negative_fraction"]`` 1, ``border_negative_fraction``) the zero set
    is closed and the fit inside out: ``RESULTS.inconsistent_normals`` too, with
    ``stats["doubts"]`` saying so (and to pass ``-normals``). A zero set that reaches the
    border (an open scan) has no inside, and is not judged by it."""
    flipped, along = cloud.orientation
    negative = border_negative_fraction(sol.spline)
    metrics = dict(
        sol.metrics,
        flipped_normal_fraction=np.asarray(flipped),
        tangential_normal_fraction=np.asarray(along),
        border_negative_fraction=np.asarray(negative),
    )
    stats = dict(sol.stats)
    result = sol.result
    inward = negative == 1.0
    if inward:
        stats["doubts"] = (_inward_doubt(cloud),)
    bad = flipped > MAX_FLIPPED_FRACTION or along > MAX_TANGENTIAL_FRACTION or inward
    if bad and sol.status in ("successful", "max_steps_reached"):
        result = RESULTS.inconsistent_normals
    return dataclasses.replace(sol, metrics=metrics, stats=stats, result=result)


#: A fit is ``doubtful`` where more than this fraction of its points (and more than 2)
#: sit across a thin part or a narrow gap (less than a cell wide) from a point whose side
#: the fit gets wrong (``crossed_features``): a neck pinched, two parts fused, a tip
#: cut short. Clean shapes stay below it (their few such points are the wedges of
#: glyphs' sharp inner corners, rounded off within a cell), while very elongated
#: ellipses and noisy surfaces with parts thinner than the noise (the bunny's ears, the
#: airplane's wings) go above it (docs/design.md section 6; docs/surfaces.md,
#: "Accuracy, speed and limits").
MAX_CROSSED_FRACTION = 0.005


#: ... or where more than this fraction of the points (those set aside excepted) lie
#: farther from the zero set than the fit resolves (``far_point_fraction``): good fits
#: of noisy clouds, also with displaced points, stay below it (docs/performance.md,
#: "Measurements behind the defaults").
MAX_FAR_FRACTION = 0.02


#: Far points lie beyond this many times the spread of the points' distances to the zero
#: set (``far_point_fraction``): 6e-5 of Gaussian noise does; 2 d alone is not enough,
#: since d is set from an estimate of the noise below the true one and good noisy fits
#: leave a share of their points beyond it (docs/design.md section 6).
FAR_SPREAD = 4.0


def values_and_distances(spline: AbstractSpline, points) -> tuple[np.ndarray, np.ndarray]:
    """``(g(p), |g(p)| / |grad g(p)|)`` at the host's ``(n, d)`` ``points``: the value and
    the first-order distance to the zero set, float64 NumPy, for either basis. One host
    evaluation (the spline's ``values_and_gradients``) serves both checks of a fit (the
    distances of ``far_point_fraction``, the signs of ``crossed_features``). Evaluated on
    the host, not compiled: a compiled evaluation took a program per grid and per count
    of points, which a new cloud paid in compilation, where the host's evaluation of a
    check's points is about as fast (docs/startup.md, "Shape-stable compiled fits")."""
    points = np.asarray(points, float)
    if len(points) == 0:
        return np.empty(0), np.empty(0)
    value, gradient = spline.values_and_gradients(points)
    return value, np.abs(value) / np.maximum(np.linalg.norm(gradient, axis=1), 1e-300)


def far_point_fraction(spline: ImplicitSpline, points, offset: float) -> tuple[float, float]:
    """``(fraction, threshold)``: the fraction of ``points`` (at most ``PROBES``,
    evenly strided) whose distance to the zero set (``values_and_distances``) exceeds
    the largest of 2 d, half a cell, and ``FAR_SPREAD`` times the distances' own robust
    spread (1.4826 times their median): the distance within which a fit's zero set lies
    of its data where it follows them (the offsets reach d; a grid's cell bounds what its
    zero set can follow; noisy points scatter about it by their noise, which d may
    underestimate)."""
    p = np.asarray(points, float)
    at = strided_probes(len(p), PROBES)
    p = p if at is None else p[at]
    cell = spline.cell_width
    _, distance = values_and_distances(spline, p)
    spread = 1.4826 * float(np.nanmedian(distance)) if np.isfinite(distance).any() else 0.0
    threshold = max(2.0 * float(offset), 0.5 * cell, FAR_SPREAD * spread)
    return float(np.mean(~(distance <= threshold))), threshold


#: A pair of points whose normals face away from each other counts as lying *along* the
#: surface (flipped neighbours, not the two sides of a thin part or a gap) where the line
#: between them makes more than 60 degrees with the first's normal: across a thin part or
#: a gap it runs along the normals (at a wedge's tip up to its half-angle away).
ALONG_COSINE = 0.5


#: A surface's fit is ``doubtful`` where more than this fraction of its points face
#: another sheet (the far side of a thin part or of a gap) less than a cell away
#: (``crossed_pairs``' ``sheets``). A surface's grid is never refined for such features
#: (a curve's is, down to ``jurs._fit.settings.FEATURE_CELLS`` cells), and its cells are
#: three spacings wide: a plate whose two sheets lie 1-2 spacings apart was fitted with
#: its midpoints inside but stray sheets between and beside the two, so the crossed-pairs
#: count saw nothing wrong and the fit was ``successful``. A sphere, torus or double torus
#: has no such points (docs/robustness.md, "Verdicts, after the fit").
MAX_SHEET_FRACTION = 0.02


def crossed_pairs(
    spline: ImplicitSpline, points, normals, spacing: float, tree=None
) -> tuple[int, int, float, float]:
    """``(across, along, sheets, width)``: how many of ``points`` (at most ``PROBES``,
    evenly strided) face a point less than a cell away whose normal points the other way
    (``jurs._cloud.measure.feature_width``) while the fit puts the midpoint between the
    two on the wrong side: outside where the normals point away from each other (a thin
    part), inside where they point towards each other (a gap). ``across`` counts the pairs
    that lie across the part or gap (the line between the two within 60 degrees of the
    normal, ``ALONG_COSINE``): a part cut or a gap bridged by the zero set. ``along``
    counts those that lie side by side along the surface: neighbours with opposite
    normals, a cloud whose normals are flipped in part (a sphere with one half's normals
    flipped read as thin parts along the seam). ``sheets`` is the fraction of the points
    read that face a point across (not along) less than a cell away, whatever the fit
    does there: two sheets of a thin part or the two sides of a gap closer than a cell,
    and ``width`` the median distance across (NaN where there is none). ``tree``: a
    KD-tree of ``points``, where the caller has one."""
    p, n = np.asarray(points, float), unit_normals(np.asarray(normals, float), np)
    at = strided_probes(len(p), PROBES)
    own = np.arange(len(p)) if at is None else at
    width, partner = feature_width(p, n, spline.cell_width, spacing, own, tree)
    paired = partner >= 0
    if not paired.any():
        return 0, 0, 0.0, float("nan")
    a, b, normal = p[own[paired]], p[partner[paired]], n[own[paired]]
    offset = np.sum((b - a) * normal, axis=1)
    inside = offset < 0  # a thin part, not a gap
    value, _ = values_and_distances(spline, 0.5 * (a + b))
    wrong = np.where(inside, value > 0, value < 0)
    along = np.abs(offset) < ALONG_COSINE * np.linalg.norm(b - a, axis=1)
    across = width[paired][~along]
    sheets = float(len(across)) / len(own)
    middle = float(np.median(across)) if len(across) else float("nan")
    return int(np.sum(wrong & ~along)), int(np.sum(wrong & along)), sheets, middle


def crossed_features(spline: ImplicitSpline, points, normals, spacing: float) -> int:
    """How many of ``points`` (at most ``PROBES``, evenly strided) face a point less than
    a cell away across a thin part or a narrow gap while the fit puts the midpoint between
    the two on the wrong side, or side by side with the opposite normal: the sum of
    ``crossed_pairs``."""
    return sum(crossed_pairs(spline, points, normals, spacing)[:2])


#: The zero-set check samples g on a lattice of half-cells (two lattice steps a knot span),
#: at most this many nodes (coarser beyond): under a second on the host, small beside a fit
#: of a grid that large (docs/robustness.md, "Verdicts, after the fit").
EXTRA_CHECK_NODES = 1 << 20
#: On a hierarchy the check labels the same half-cell lattice of its finest level, but
#: evaluates and labels only the band's blocks (``jurs._model.band.band_regions``), at
#: most this many nodes (coarser beyond): the work grows with the surface, not the box,
#: and a shell one finest cell wide still holds lattice nodes.
EXTRA_BAND_NODES = 1 << 24


def _lattice_axes(lower, upper, steps) -> list[np.ndarray]:
    return [np.linspace(lo, hi, int(n) + 1) for lo, hi, n in zip(lower, upper, steps)]


@functools.singledispatch
def sign_interfaces(
    spline: AbstractSpline,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The lattice edges of the zero-set check where g changes sign: ``(low, high, at,
    steps)``, each edge's regions at its two ends (ids), its midpoint ``(k, d)`` in
    lattice index units, and the lattice's steps per axis. Regions: the nodes of one sign
    that touch, across faces where g > 0, across faces, edges and corners where g <= 0, so
    that the two never cross each other. The grid labels its whole lattice of half-cells
    (at most ``EXTRA_CHECK_NODES`` nodes); the hierarchy only its band's blocks."""
    from scipy import ndimage

    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    steps = 2.0 * np.asarray(spline.finest_cells, float)
    d = len(steps)
    scale = (EXTRA_CHECK_NODES / float(np.prod(steps + 1))) ** (1.0 / d)
    if scale < 1.0:
        steps = np.maximum(2.0, np.floor(steps * scale))
    with np.errstate(invalid="ignore", divide="ignore"):
        positive = spline.band_lattice(_lattice_axes(lower, upper, steps), 0.0)[0] > 0
    empty = np.zeros(0, np.int64)
    if positive.all() or not positive.any():
        return empty, empty, np.zeros((0, d)), steps
    faces_only = ndimage.generate_binary_structure(d, 1)
    # (SciPy's stub types label's result as an int too: it is a tuple without output=.)
    region, count = cast("tuple[np.ndarray, int]", ndimage.label(positive, structure=faces_only))
    negative = cast(
        "tuple[np.ndarray, int]", ndimage.label(~positive, structure=np.ones((3,) * d, bool))
    )[0]
    region = np.where(positive, region, negative + count).astype(np.int64)
    lows, highs, where = [], [], []
    for axis in range(d):
        head = tuple(slice(0, -1) if a == axis else slice(None) for a in range(d))
        tail = tuple(slice(1, None) if a == axis else slice(None) for a in range(d))
        index = np.nonzero(positive[head] != positive[tail])
        a, b = region[head][index], region[tail][index]
        first_above = positive[head][index]
        lows.append(np.where(first_above, b, a))
        highs.append(np.where(first_above, a, b))
        at = np.stack(index, axis=1).astype(float)
        at[:, axis] += 0.5
        where.append(at)
    return np.concatenate(lows), np.concatenate(highs), np.concatenate(where), steps


@sign_interfaces.register
def _(spline: AdaptiveSpline) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if spline.ndim == 2:
        # A curve's whole lattice stays cheap to label, and its band's blocks cost more
        # to plan than they save: the grid's path, which evaluates only the band anyway.
        return sign_interfaces.dispatch(AbstractSpline)(spline)
    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    steps = 2.0 * np.asarray(spline.finest_cells, float)
    evaluator = spline.on_host()
    axes = _lattice_axes(lower, upper, steps)
    with np.errstate(invalid="ignore", divide="ignore"):
        plan = plan_band(evaluator, axes, 0.0, 0.0)
        if plan.nodes > EXTRA_BAND_NODES:
            # The band's nodes grow with the square of the lattice's density.
            steps = np.maximum(2.0, np.floor(steps * np.sqrt(EXTRA_BAND_NODES / plan.nodes)))
            axes = _lattice_axes(lower, upper, steps)
            plan = plan_band(evaluator, axes, 0.0, 0.0)
        low, high, at = band_regions(evaluator, axes, 0.0, plan=plan)
    return low, high, at, steps


def extra_components(spline: ImplicitSpline, tree, threshold: float) -> list[dict]:
    """The closed components of the zero set away from the data, or lying on another
    component: each a dict with its ``centre``, bounding box (``lower``, ``upper``),
    ``area_share`` and ``distance``.

    g is sampled on a lattice of half-cells over the spline's box (``sign_interfaces``:
    the grid's whole lattice, at most ``EXTRA_CHECK_NODES`` nodes; the hierarchy's
    finest half-cells over the band's blocks, at most ``EXTRA_BAND_NODES``). The nodes of
    one sign that touch make a region (across faces where g > 0, across faces, edges and
    corners where g <= 0, so that the two never cross each other), and the lattice edges
    from one region to another hold that interface's piece of the zero set: each pair of
    regions that meet is one component. (Labelling the cells the zero set crosses
    instead merged nested shells a few cells apart into one.) A component is *closed*
    when none of its edges lies on the box's border, and counted when less than half of
    its edges' midpoints (``MIN_CARRIED_FRACTION``) lie by data it *carries*
    (``jurs._cloud.carried.carried_samples``, jurs.levelset's supplementary rule): the
    nearest point of ``tree`` (the data the fit keeps) within ``threshold``
    (``far_point_fraction``'s: at least half a knot span) plus half a lattice step (how
    far a midpoint sits from the zero set at most), and nearer to this component than to
    any other. A component away from the data carries none, and neither does a small loop
    beside data that the true zero set passes through. A closed component that carries
    its data but lies on another one (``jurs._cloud.carried.surface_shells``: most of it
    within two lattice diagonals) is counted too, with ``shell`` true: g dips across the
    surface and back there, over a tunnel or pit narrower than a cell. ``area_share`` is
    the component's share of all the zero set's lattice edges (about its share of the
    area, or of the length in 2D); ``distance`` the median distance from its midpoints to
    the data, ``carried_share`` its share carried, ``away`` whether that median exceeds
    the limit. One path for curves and surfaces: the same lattice, regions and
    interfaces in 2D and 3D."""
    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    low, high, at, steps = sign_interfaces(spline)
    if len(at) == 0:
        return []
    shape = steps + 1
    key = np.minimum(low, high) * (int(max(low.max(), high.max())) + 1) + np.maximum(low, high)
    # An edge lies on the box's border where one of its whole coordinates is an end.
    whole = at == np.floor(at)
    border = (whole & ((at == 0) | (at == shape - 1))).any(axis=1)
    step = (upper - lower) / steps
    points = lower + at * step
    pairs, group, sizes = np.unique(key, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    limit = threshold + 0.5 * float(np.linalg.norm(step))
    # Within a lattice diagonal of the nearest: a thin part pinched below the lattice's
    # step splits its zero set into pieces side by side, not a loop beside the data.
    diagonal = float(np.linalg.norm(step))
    distance, carried = carried_samples(points, group, tree, limit, diagonal)
    open_ = np.bincount(group, weights=border, minlength=len(pairs)) > 0
    share = np.bincount(group, weights=carried, minlength=len(pairs)) / sizes
    order = np.lexsort((distance, group))
    first = np.cumsum(sizes) - sizes
    median = distance[order][first + sizes // 2]
    shells = surface_shells(points, group, ~open_, SHELL_REACH * diagonal, tree=tree)
    found = []
    # Less than half carried: away from the data (the median beyond the limit) or beside
    # data that another component passes through (jurs.levelset's supplementary rule);
    # or carried but lying on another component.
    counted = ~open_ & ((share < MIN_CARRIED_FRACTION) | shells)
    for k in np.flatnonzero(counted):
        mine = points[order[first[k] : first[k] + sizes[k]]]
        shell = bool(share[k] >= MIN_CARRIED_FRACTION)
        found.append(
            {
                "centre": mine.mean(axis=0).tolist(),
                "lower": (mine.min(axis=0) - 0.5 * step).tolist(),
                "upper": (mine.max(axis=0) + 0.5 * step).tolist(),
                "area_share": float(sizes[k]) / len(key),
                "distance": float(median[k]),
                "carried_share": float(share[k]),
                "away": bool(median[k] > limit) and not shell,
                "shell": shell,
                "cell": float(spline.cell_width),
                "finest": int(np.max(np.asarray(spline.finest_cells))),
            }
        )
    return sorted(found, key=lambda c: -c["area_share"])


#: Places are printed to this fraction of the extent they are compared with: a part
#: centred at (5.97e+05, ...) in a cloud 30 m wide said nothing of where, at 3 digits.
PLACE_RESOLUTION = 1e-3


def format_place(coordinates, extent: float) -> str:
    """``coordinates`` as ``"(x, y[, z])"`` with the decimals that resolve
    ``PLACE_RESOLUTION`` of ``extent`` (the box's diagonal, say), however far from the
    origin they lie: ``(597312.41, 5405123.87)`` for a part of a scan 30 m wide, not
    ``(5.97e+05, 5.41e+06)``."""
    coordinates = [float(x) for x in coordinates]
    resolution = PLACE_RESOLUTION * float(extent)
    if not (np.isfinite(resolution) and resolution > 0):
        return "(" + ", ".join(f"{x:.6g}" for x in coordinates) + ")"
    decimals = max(0, int(np.ceil(-np.log10(resolution))))
    return "(" + ", ".join(f"{x:.{decimals}f}" for x in coordinates) + ")"


def _share(fraction: float) -> str:
    """A share in percent, with the digits a small one needs ("0.004%", not "0.0%")."""
    percent = 100.0 * float(fraction)
    return f"{percent:.1f}%" if percent >= 1.0 else f"{percent:.2g}%"


def describe_shell(centre, lower, upper, extent: float, share=None, cell=None, finest=None) -> str:
    """The words for a shell lying on the surface (``jurs._cloud.carried.surface_shells``),
    the fit's doubt and ``analyze_mesh``'s note alike: its place and box (``format_place``
    to the digits ``extent`` needs), its ``share`` of the zero set where known, what it
    means and the fix (with the fit's ``cell`` width and ``finest`` cells where known)."""
    where = (
        f"centred at {format_place(centre, extent)} within {format_place(lower, extent)} .. "
        f"{format_place(upper, extent)}"
    )
    if share is not None:
        where += f", {_share(share)} of the zero set"
    width = "a cell" if cell is None else f"a cell ({float(cell):.3g})"
    finer = (
        "A finer fit (finest=, grid=)"
        if finest is None
        else f"A finer grid (finest= above {int(finest)} cells along the longest side on the "
        "hierarchy, grid= on a uniform one)"
    )
    return (
        f"a closed zero-set shell lying on the surface, {where}: g dips across the surface "
        f"and back there, as over a tunnel, handle or pit narrower than {width} that the fit "
        "filled in, so the surface's genus and components may be wrong there (the data "
        f"beside it seem carried, lying within a step of it). {finer} or denser samples "
        "there resolve it"
    )


def describe_extra(component: dict, extent: float) -> str:
    """The doubt for one of ``extra_components``' components, its place and box printed
    to the digits ``extent`` (the spline's box diagonal) needs (``format_place``)."""
    centre = format_place(component["centre"], extent)
    lower = format_place(component["lower"], extent)
    upper = format_place(component["upper"], extent)
    if component.get("shell", False):
        return describe_shell(
            component["centre"],
            component["lower"],
            component["upper"],
            extent,
            share=component["area_share"],
            cell=component.get("cell"),
            finest=component.get("finest"),
        )
    where = (
        "away from the data"
        if component.get("away", True)
        else "beside data that another part of the zero set passes through"
    )
    return (
        f"a closed zero-set component {where}, centred at {centre} within {lower} .. "
        f"{upper}, {_share(component['area_share'])} of the zero set, its median distance to "
        f"the points kept {component['distance']:.3g}, "
        f"{component.get('carried_share', 0.0):.0%} of it by points it carries: a shape "
        "the data do not have (points set aside or with inconsistent normals leave such "
        "shells, fits without normals small loops; jurs.levelset marks them supplementary)"
    )


def judged_points(cloud, settings) -> np.ndarray:
    """Mask of ``cloud.points`` a fit is judged on: the cloud's kept points, less those
    the ``settings`` (None: none) set aside."""
    keep = np.zeros(len(cloud), bool)
    keep[cloud.kept] = True
    if settings is not None and settings.set_aside:
        keep[list(settings.set_aside)] = False
    return keep


def check_doubts(sol, cloud, settings, offset):
    """``sol`` with ``metrics["far_point_fraction"]``, ``metrics["crossed_features"]``,
    ``stats["doubts"]`` (the reasons to doubt the zero set, in words; one for each closed
    component away from the data, saying where it is), ``stats["extra_components"]``
    (those components, ``extra_components``) and, where there is a doubt, the verdict
    ``RESULTS.doubtful`` in place of success, and a warning. Host side;
    ``settings`` (None: a fit with settings given) says which points were set aside and
    the cloud's spacing, without which the thin-part check is not made."""
    keep = judged_points(cloud, settings)
    p = cloud.points
    aside = () if settings is None else settings.set_aside
    tree = cloud.tree_without(aside)  # of p[keep]
    far, threshold = far_point_fraction(sol.spline, p[keep], offset)
    crossed, along, thin = 0, 0, 0.0 if settings is None else settings.thin_fraction
    sheets, width = 0.0, float("nan")
    if settings is not None:
        crossed, along, sheets, width = crossed_pairs(
            sol.spline, p[keep], cloud.normals[keep], settings.spacing, tree
        )
    doubts = list(sol.stats.get("doubts", ()))  # check_orientation's, where it found one
    if cloud.ndim == 3 and sheets > MAX_SHEET_FRACTION:
        doubts.append(
            f"{sheets:.1%} of the points face another sheet less than a cell "
            f"({sol.spline.cell_width:.3g}) away, {width:.3g} apart at the median: a thin "
            "plate or shell, or a narrow gap, that this grid cannot place both sides of "
            "(the zero set there is a rough slab). A finer grid= (cells about as wide as "
            "the sheets are apart) resolves it"
        )
    most = max(2, MAX_CROSSED_FRACTION * min(int(keep.sum()), PROBES))
    flipped = along > most and along > crossed
    if flipped:
        doubts.append(
            f"{along} points sit beside a neighbour (less than a cell away, along the "
            "surface) whose normal points the other way, and the zero set follows the "
            "flipped ones: the normals are not consistently oriented there (part of the "
            "cloud flipped). Orient them all outward (jurs.estimate_normals) and fit again"
        )
    if crossed > most:
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
    extra = extra_components(sol.spline, tree, threshold)
    extent = float(np.linalg.norm(np.asarray(sol.spline.upper) - np.asarray(sol.spline.lower)))
    doubts.extend(describe_extra(c, extent) for c in extra)
    # device_put, not jnp.asarray: a Python number through jnp.asarray compiles a small
    # program of its own in each new process.
    metrics = dict(
        sol.metrics,
        far_point_fraction=jax.device_put(np.asarray(far)),
        crossed_features=jax.device_put(np.asarray(crossed + along)),
        flipped_pairs=jax.device_put(np.asarray(along)),
    )
    stats = dict(sol.stats, doubts=tuple(doubts), extra_components=tuple(extra))
    result = sol.result
    # Compared by name on the host: comparing the result's items dispatches (and, in a
    # new process, compiles) a JAX program for each comparison.
    status = sol.status
    usable = status in ("successful", "max_steps_reached")
    if flipped and usable:
        # The cause has its own verdict (raised with throw=True, as check_orientation's).
        result = RESULTS.inconsistent_normals
    elif doubts and status == "successful":
        result = RESULTS.doubtful
        warnings.warn("jurs.fit: doubtful fit: " + "; ".join(doubts), stacklevel=4)
    return dataclasses.replace(sol, metrics=metrics, stats=stats, result=result)


def check_components(sol, cloud, offset):
    """``sol`` judged by its closed components away from the data alone
    (``extra_components``, ``describe_extra``): ``doubtful`` in place of success, and a
    warning, where there are any. What a fit by a robust solver with every setting given
    is judged by: outliers the solve did not weigh down leave such loops (half a cloud of
    outliers at a clean cloud's settings drew one around each), the check needs no
    settings, and the points such a fit does weigh down may rightly lie far from its
    zero set, so ``check_doubts``' far-point rule does not apply."""
    tree = cloud.tree_without(())
    _, threshold = far_point_fraction(sol.spline, cloud.points[cloud.kept], offset)
    extra = extra_components(sol.spline, tree, threshold)
    extent = float(np.linalg.norm(np.asarray(sol.spline.upper) - np.asarray(sol.spline.lower)))
    found = [describe_extra(c, extent) for c in extra]
    stats = dict(sol.stats, extra_components=tuple(extra))
    if not found:
        return dataclasses.replace(sol, stats=stats)
    doubts = (*sol.stats.get("doubts", ()), *found)
    result = sol.result
    if sol.status == "successful":
        result = RESULTS.doubtful
        warnings.warn("jurs.fit: doubtful fit: " + "; ".join(found), stacklevel=4)
    return dataclasses.replace(sol, stats=dict(stats, doubts=doubts), result=result)


def judge(sol, cloud, settings, offset, components: bool = False):
    """The host's verdicts on a fit of ``cloud`` made at top level: the orientation of the
    normals (``check_orientation``) and, where the settings were chosen automatically
    (the data were not looked at by a person), the doubts (``check_doubts``); with
    settings given, its closed components away from the data (``check_components``)
    where ``components`` (a fit by a solver that expects outliers, which can draw loops
    around them)."""
    sol = check_orientation(sol, cloud)
    if settings is not None:
        return check_doubts(sol, cloud, settings, offset)
    return check_components(sol, cloud, offset) if components else sol
