"""Points that stand alone: outliers away from the curve or surface the others sample, and
small stray groups of them, which [`jurs.fit`][] sets aside."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .measure import kd_tree, query_all

if TYPE_CHECKING:
    from scipy.spatial import KDTree as cKDTree


#: A point stands alone (``isolated_points``) when its ``ISOLATION_RANK``-th
#: nearest other point is farther than this many times the same distance typical around it.
ISOLATION_RATIO = 3.0


#: The sparsest sampling around a point, relative to the cloud's median spacing, that
#: ``isolated_points`` takes as the shape's: far from the shape, the points around
#: an outlier are other outliers, as sparse as it is. With a larger ratio and cap, many
#: outliers uniform in the box stayed in; with these, noisy outlines lose only their most
#: displaced points, and clean or unevenly sampled ones, gaps and separate small
#: components none (docs/performance.md, "Measurements behind the defaults").
SPARSE_SPACING = 1.5


#: Where more points than this fraction stand alone, the cloud has no dense shape for them
#: to stand apart from (a sparse sampling), and none is set aside.
MAX_SET_ASIDE = 0.2


#: Which neighbour's distance says how far a point is from the rest: the third, so that
#: outliers in pairs and threes stand alone too.
ISOLATION_RANK = 3


#: Neighbours whose own such distances say what is typical around a point.
ISOLATION_NEIGHBOURS = 8


#: A group of at most this many points apart from the rest (``stray_clusters``) is
#: set aside unless its normals agree on a side of it: a closed outline sampled by more
#: points is left to the fit (a small far ring of 12 points is kept).
STRAY_CLUSTER = 8


#: The fraction of a small group's normals that must point away from its centroid (or
#: all towards it) for it to count as a ring or shell of its own.
RING_AGREEMENT = 0.8


#: A point whose nearest ``ISOLATION_RANK`` points all lie along its tangent line or
#: plane, their normals within this angle's cosine of its own (45 degrees), samples the
#: shape where it is sparse (``on_the_shape``): no density test sets it aside.
SHAPE_NORMAL_AGREEMENT = 0.7


#: ... and "along the tangent": the sine of the angle between the tangent and the step to
#: a neighbour at most this, plus what the curvature explains (``on_the_shape``).
SHAPE_LEAN = 0.25


def on_the_shape(points, normals, near, index) -> np.ndarray:
    """``(len(index),)`` booleans: whether each point ``index`` samples a smooth curve
    or surface with its nearest ``ISOLATION_RANK`` points (``near``: each point's nearest,
    itself first). It does where each of them has a normal within
    ``SHAPE_NORMAL_AGREEMENT`` of its own and lies along its tangent: the sine of the
    step's angle out of the tangent at most ``SHAPE_LEAN`` plus half the two normals'
    difference (on a circle the step leans by exactly that).

    Why: density alone cannot tell a sparsely sampled part of the shape from outliers (a
    circle with 120 points on one half and 600 on the other lost 117 of the 120). The
    points of a part agree with their neighbours on the tangent and the side; outliers
    with random normals, or normals estimated from a scatter of other outliers, agree
    with three neighbours one time in a thousand in 2D and less in 3D."""
    k = min(ISOLATION_RANK, near.shape[1] - 1)
    nbr = near[index, 1 : k + 1]
    step = points[nbr] - points[index, None, :]
    length = np.maximum(np.linalg.norm(step, axis=-1), 1e-300)
    lean = np.abs((step * normals[index, None, :]).sum(-1)) / length
    turn = np.linalg.norm(normals[nbr] - normals[index, None, :], axis=-1)
    agree = (normals[nbr] * normals[index, None, :]).sum(-1) >= SHAPE_NORMAL_AGREEMENT
    return (agree & (lean <= SHAPE_LEAN + 0.5 * turn)).all(axis=1)


def isolated_points(
    points: np.ndarray, tree: cKDTree | None = None, normals: np.ndarray | None = None
) -> np.ndarray:
    """``(m,)`` booleans: the points that stand alone, away from the curve or surface the
    others sample. Point i stands alone when its ``ISOLATION_RANK``-th nearest other
    point is more than ``ISOLATION_RATIO`` times farther than is typical around it: the
    median of the same distance over its ``ISOLATION_NEIGHBOURS`` nearest points,
    taken as at most ``SPARSE_SPACING`` times the cloud's median. With ``normals``, so
    do the points of a small stray cluster (``stray_clusters``), but never a point that
    samples the shape with its neighbours (``on_the_shape``): a sparse part stays.

    Why this test: an outlier far from the shape has no neighbours at the sampling's
    spacing, while its nearest points (on the shape) do; a fit through it grows a loop
    around it (docs/design.md section 6; docs/performance.md, "Measurements behind the
    defaults"). The k-th neighbour, not the first, finds outliers in pairs and threes too;
    comparing with the point's own neighbours, not the cloud's median spacing, keeps
    uneven sampling (5x density changes), gap ends and small separate components in:
    their neighbours are as sparse as they are. Outliers within a few spacings of the
    shape are not found here (the robust reweighting of [`jurs.fit`][] weighs the near
    ones down).
    """
    tree = kd_tree(points) if tree is None else tree
    m = len(points)
    k = min(m - 1, ISOLATION_RANK)
    count = min(m, max(ISOLATION_RANK, ISOLATION_NEIGHBOURS) + 1)
    dist, near = query_all(tree, points, count)  # reach, neighbours, clusters
    reach = dist[:, k]  # the k-th nearest other point
    typical = float(np.median(reach))
    isolated = np.zeros(m, bool)
    candidates = np.flatnonzero(reach > ISOLATION_RATIO * typical)
    if candidates.size:
        around = near[candidates, 1 : ISOLATION_NEIGHBOURS + 1]
        # Capped: the points around an outlier far from the shape can be other outliers.
        local = np.minimum(np.median(reach[around], axis=1), SPARSE_SPACING * typical)
        isolated[candidates[reach[candidates] > ISOLATION_RATIO * local]] = True
    if normals is not None and m > STRAY_CLUSTER:
        link = ISOLATION_RATIO * SPARSE_SPACING * typical
        isolated |= stray_clusters(points, normals, dist, near, link)
    if normals is not None and isolated.any():
        found = np.flatnonzero(isolated)
        isolated[found[on_the_shape(points, normals, near, found)]] = False
    return isolated


def stray_clusters(points, normals, dist, near, link: float) -> np.ndarray:
    """``(m,)`` booleans: the points of the small groups that stand apart from the rest and
    do not sample a closed curve or surface of their own.

    The groups are the connected components of the nearest-neighbour graph (``near``,
    ``dist``: each point's nearest points, itself first) cut at ``link`` (the farthest
    spacing ``isolated_points`` takes as the shape's). A component of at most
    ``STRAY_CLUSTER`` points is stray unless its normals agree on a side of it: at
    least ``RING_AGREEMENT`` of them pointing away from its centroid (a small ring or
    shell of its own) or towards it (a small hole).

    Why: outliers uniform in the box fall in groups of four or five points a few spacings
    apart now and then; each one's third neighbour is then near, so the test of
    ``isolated_points`` keeps them, and the fit loops around the group (an extra
    component on traced outlines: docs/design.md section 6). A real small component
    samples its outline with outward normals; random normals agree that well on 5 points
    one time in 2.7."""
    from scipy import sparse  # lazily: import jurs loads no SciPy sparse
    from scipy.sparse import csgraph

    m = len(points)
    # Only a point with a neighbour beyond the link among its nearest can belong to a
    # group small enough (its nearest points would all be in its group otherwise); a
    # group holding one point linked to any other point is not small.
    link_ok = (dist[:, 1:] <= link) & (near[:, 1:] < m)
    candidate = ~link_ok.all(axis=1) if near.shape[1] > STRAY_CLUSTER else np.ones(m, bool)
    small = np.zeros(m, bool)
    if not candidate.any():
        return small
    index = np.flatnonzero(candidate)
    where = np.full(m, -1)
    where[index] = np.arange(index.size)
    nbr, ok = near[index, 1:], link_ok[index]
    linked_candidate = candidate[np.where(ok, nbr, 0)]
    anchored = (ok & ~linked_candidate).any(axis=1)
    inner = ok & linked_candidate
    rows = np.repeat(np.arange(index.size), nbr.shape[1])[inner.ravel()]
    cols = where[nbr.ravel()[inner.ravel()]]
    graph = sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(index.size,) * 2)
    _, label = csgraph.connected_components(graph, directed=False)
    size = np.bincount(label)
    stray = (size[label] <= STRAY_CLUSTER) & ~(np.bincount(label, weights=anchored) > 0)[label]
    if not stray.any():
        return small
    pts, nrm = points[index], normals[index]
    centroid = np.stack(
        [np.bincount(label, weights=pts[:, a]) / size for a in range(points.shape[1])], 1
    )
    facing = np.sign(np.einsum("ij,ij->i", pts - centroid[label], nrm))
    agreement = np.abs(np.bincount(label, weights=facing) / size)  # |2 f - 1|
    small[index] = stray & (agreement[label] < 2.0 * RING_AGREEMENT - 1.0)
    return small
