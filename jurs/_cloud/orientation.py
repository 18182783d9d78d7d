"""Whether given normals are consistently oriented: the fractions of normals flipped
against their neighbours along the curve or surface, and of normals lying along it."""

from __future__ import annotations

import numpy as np

from .._problem.validate import unit_normals
from .measure import PROBES, kd_tree, strided_probes
from .signs import forest_signs

#: Neighbours per point in ``flipped_normal_fraction``'s graph.
ORIENTATION_NEIGHBOURS = 8


def orientation_sample(points, normals, tree=None):
    """``(p, n, dist, idx)`` that ``flipped_normal_fraction`` and
    ``tangential_normal_fraction`` read: the points (at most
    ``jurs._cloud.measure.PROBES``, evenly strided), their unit normals, and each
    point's ``ORIENTATION_NEIGHBOURS`` + 1 nearest (itself first) from one KD-tree
    query, so a caller of both builds the tree once. ``tree``: a KD-tree of ``points``
    already built (used where no subsample is taken)."""
    p = np.asarray(points, float)
    n = unit_normals(np.asarray(normals, float))
    at = strided_probes(len(p), PROBES)
    if at is not None:  # the neighbours among the probes: a graph over the probes
        p, n, tree = p[at], n[at], None
    tree = kd_tree(p) if tree is None else tree
    dist, idx = tree.query(p, k=min(ORIENTATION_NEIGHBOURS + 1, len(p)))
    return p, n, np.asarray(dist), np.asarray(idx)


def flipped_normal_fraction(points, normals, sample=None) -> float:
    """Fraction of the points whose normal is flipped against its neighbours along the
    curve, after Hoppe et al. (1992): the sign is carried along a minimum spanning tree of
    the neighbour graph (weights ``1 - |n_i . n_j|``) and, in each connected part, the
    smaller of the two sign classes counts. 0 for consistently oriented normals; about 1/2
    when half the cloud is flipped, however large the cloud.

    Only *tangential* neighbours are edges (the displacement within 72.5 degrees of both
    tangents, within two median spacings): the two sides of a thin part, or a ring and its
    hole, face opposite ways legitimately, and lie across, not along, each other. Where
    noise scrambles the displacement's direction the graph falls apart into small parts
    and the check turns blind, not wrong. Consistent clouds read 0, also with normal
    noise and positional outliers, and a little more where the sampling is coarser than
    the parts (legs thinner than the spacing); half or every other normal flipped reads
    0.5 (docs/robustness.md, "Verdicts, after the fit", lists the clouds measured).
    Runs on the host (SciPy), on concrete inputs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

    p, n, dist, idx = orientation_sample(points, normals) if sample is None else sample
    m = len(p)
    k = dist.shape[1] - 1
    dist, idx = dist[:, 1:], idx[:, 1:]
    nearest = dist[:, 0][dist[:, 0] > 0]
    if nearest.size == 0:
        return 0.0
    spacing = float(np.median(nearest))
    i, j, d = np.repeat(np.arange(m), k), idx.ravel(), dist.ravel()
    u = (p[j] - p[i]) / np.where(d > 0, d, 1.0)[:, None]
    dot = np.sum(n[i] * n[j], axis=1)
    edge = (
        (d > 0)
        & (d <= 2.0 * spacing)
        & (np.abs(np.sum(u * n[i], axis=1)) < 0.3)
        & (np.abs(np.sum(u * n[j], axis=1)) < 0.3)
    )
    graph = coo_matrix((1.0 - np.abs(dot[edge]) + 1e-3, (i[edge], j[edge])), shape=(m, m))
    forest = minimum_spanning_tree(graph.tocsr().maximum(graph.T.tocsr()))
    count, labels = connected_components(forest, directed=False)
    # Per part, the points whose sign the forest flips against the part's reference.
    flip = forest_signs(forest, n) < 0
    flipped = np.bincount(labels, weights=flip, minlength=count)
    size = np.bincount(labels, minlength=count)
    smaller = np.minimum(flipped, size - flipped)
    smaller[_touching_parts(p, i[edge], j[edge], labels, flip, smaller, spacing)] = 0
    return float(smaller.sum() / m)


#: ``flipped_normal_fraction``: two sign classes of one part, each of at least this many
#: points, that meet only within ``TOUCH_SPACINGS`` median spacings of one place are two
#: parts that touch (rings or spheres tangent at a point), not a flipped half.
TOUCH_POINTS = 25
TOUCH_SPACINGS = 4.0


def _touching_parts(p, i, j, labels, flip, smaller, spacing) -> np.ndarray:
    """Labels of the parts whose two sign classes meet at one place only (within
    ``TOUCH_SPACINGS`` spacings of the seam's centre) and hold ``TOUCH_POINTS`` points each.
    Two rings tangent at a point are joined there by neighbours along the common tangent
    whose outward normals face each other, and the carried sign flipped a whole ring (0.5
    flipped). A flipped half of a closed curve meets the rest at both its ends, and of a
    surface along a whole loop; a small flipped patch holds few points."""
    seam = (labels[i] == labels[j]) & (flip[i] != flip[j])
    parts = np.unique(labels[i[seam]])
    touching = []
    for part in parts[smaller[parts] >= TOUCH_POINTS]:
        at = seam & (labels[i] == part)
        ends = np.concatenate([p[i[at]], p[j[at]]])
        reach = np.max(np.linalg.norm(ends - ends.mean(axis=0), axis=1))
        if reach <= TOUCH_SPACINGS * spacing:
            touching.append(part)
    return np.asarray(touching, dtype=int)


def tangential_normal_fraction(points, normals, sample=None) -> float:
    """Fraction of the points whose normal lies within 45 degrees of the curve's tangent
    (of a surface's tangent plane), spanned by the principal directions of the point and
    its ``ORIENTATION_NEIGHBOURS`` nearest neighbours (counted only where the direction
    across is clear, the variance along each tangent direction at least 4 times its: not
    at corners, not in clouds sampled coarser than their features).
    About 1/2 for random normals, which ``flipped_normal_fraction`` cannot see (its
    graph falls apart) and a fine grid fits "successfully"; near 0 on the consistent
    clouds listed there (docs/robustness.md, "Verdicts, after the fit";
    docs/performance.md, "Measurements behind the defaults"). Host side."""
    p, n, _, idx = orientation_sample(points, normals) if sample is None else sample
    near = p[idx] - p[idx].mean(axis=1, keepdims=True)
    variance, axes = np.linalg.eigh(np.einsum("mki,mkj->mij", near, near))
    clear = variance[:, 1] > 4.0 * variance[:, 0]
    # Within 45 degrees of the tangent: at most cos 45 degrees along the direction across
    # (the smallest variance's).
    along = np.abs(np.sum(axes[:, :, 0] * n, axis=1)) < np.sqrt(0.5)
    return float(np.mean(clear & along))
