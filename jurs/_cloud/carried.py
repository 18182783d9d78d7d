"""The data a zero set carries: which of a cloud's points each component of a sampled zero
set accounts for. One rule for the supplementary components of curves
(``jurs.levelset.analyze``) and meshes (``jurs.levelset.analyze_mesh``) and for the fit's
own extra-components doubt (``jurs._solution.verdicts``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from jaxtyping import Float

if TYPE_CHECKING:  # SciPy's spatial module loads when first used, not on import jurs
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

#: A closed component is supplementary where less than this share of it (length, area)
#: lies by data it carries (``carried_samples``): a loop or bubble beside the data whose
#: points another part of the zero set passes through is as spurious as one away from
#: them (a small loop at a traced horse's tail; a bubble inside a CAD part's solid).
MIN_CARRIED_FRACTION = 0.5


def carried_samples(
    samples: Float[npt.ArrayLike, "k d"],
    labels: npt.ArrayLike,
    tree: cKDTree,
    threshold: float,
    tolerance: float | Float[npt.ArrayLike, " k"] = 0.0,
) -> tuple[Float[np.ndarray, " k"], np.ndarray]:
    """``(distance, carried)`` for zero-set ``samples (k, d)`` of the components
    ``labels (k,)``: each sample's distance to the nearest data point of ``tree`` (a
    KD-tree of the data), and whether that point lies within ``threshold`` and is
    *carried* by the sample's own component: no sample of another component lies
    nearer to it, or, with a ``tolerance`` (one, or one a sample), none nearer by more
    than that: the step of the lattice the zero set was sampled on, where a thin part
    pinched below that step splits its zero set into pieces side by side, both beside
    the data and a step apart at most (a glyph's inner corner at 256 nodes a side). A
    component's share of carried samples is how much of it the data account for; a loop
    beside data that another part passes through carries none. Curves (polyline
    segments' midpoints) and surfaces (face centroids, lattice crossings) alike."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

    samples = np.asarray(samples, float)
    labels = np.asarray(labels).reshape(-1)
    if len(samples) == 0:
        return np.empty(0), np.zeros(0, bool)
    distance, nearest = tree.query(samples)
    used, back = np.unique(nearest, return_inverse=True)
    back = back.reshape(-1)
    # The component each data point near a sample lies nearest to (its owner), and how
    # near.
    closest, at = cKDTree(samples).query(np.asarray(tree.data)[used])
    owned = (labels[at][back] == labels) | (distance <= closest[back] + tolerance)
    return distance, (distance <= threshold) & owned


#: A closed component is a *shell on the surface* where more than this share of it
#: (samples, or their weights) lies within reach of another component
#: (``surface_shells``).
SHELL_FRACTION = 0.5
#: The reach of the fit's verdict, in diagonals of its lattice of half-cells (about a
#: cell and a half): a bubble left by a tunnel or pit narrower than a cell lies within
#: about a cell of the true surface.
SHELL_REACH = 2.0
#: The reach of a mesh's analysis, in the longest edges of the shell's faces: the default
#: mesh has three to five lattice nodes a finest cell, so four edges are about the same
#: cell and a half.
SHELL_EDGES = 4.0
#: A shell's sample stands off the data where its nearest data point is farther than this
#: share of the reach (half a lattice diagonal in the verdict, one edge in a mesh).
OFF_DATA = 0.25


def surface_shells(
    samples: Float[npt.ArrayLike, "k d"],
    labels: npt.ArrayLike,
    closed: npt.ArrayLike,
    reach: float | Float[npt.ArrayLike, " k"],
    weights: Float[npt.ArrayLike, " k"] | None = None,
    tree: cKDTree | None = None,
) -> np.ndarray:
    """Which components of a sampled zero set are closed shells lying on another one:
    ``(c,)`` bool for the ``c = len(closed)`` components of ``labels (k,)``, true where
    the component is ``closed``, is not the largest (by samples), and more than
    ``SHELL_FRACTION`` of it (by ``weights``, default one a sample) lies within ``reach``
    (one, or one a sample: ``SHELL_REACH`` lattice diagonals, ``SHELL_EDGES`` of a face's
    longest edges) of a sample of another component and, given the data's KD-``tree``,
    of which the nearest data point lies nearer to another component than to it, or
    farther from it than ``OFF_DATA`` of the reach (the data are not its own: a small
    sphere sampled beside the surface passes through its data and is data). Such a
    shell carries the data the surface beside it passes through, so the carried rule
    lets it by; it is where g dips across the surface and back, as it does over a tunnel
    or pit narrower than a cell that the fit filled in: the genus there may be wrong. One
    rule for meshes
    (``jurs.levelset.analyze_mesh``) and the fit's verdict
    (``jurs._solution.verdicts``)."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

    samples = np.asarray(samples, float)
    labels = np.asarray(labels, np.int64).reshape(-1)
    closed = np.asarray(closed, bool).reshape(-1)
    count = len(closed)
    shells = np.zeros(count, bool)
    if count < 2 or len(samples) == 0:
        return shells
    weights = np.ones(len(samples)) if weights is None else np.asarray(weights, float)
    reach = np.broadcast_to(np.asarray(reach, float), (len(samples),))
    sizes = np.bincount(labels, minlength=count)
    # The largest component is what a shell lies on, never a shell itself (and querying
    # it would cost a query for most of the samples).
    candidates = np.flatnonzero(closed & (np.arange(count) != np.argmax(sizes)) & (sizes > 0))
    if len(candidates) == 0:
        return shells
    tree_of_samples = cKDTree(samples)
    for c in candidates:
        mine = np.flatnonzero(labels == c)
        near = tree_of_samples.query_ball_point(samples[mine], reach[mine], return_sorted=False)
        lengths = np.fromiter((len(n) for n in near), np.int64, len(mine))
        found = np.concatenate([np.asarray(n, np.int64) for n in near])
        owner = np.repeat(np.arange(len(mine)), lengths)
        other = np.bincount(owner, weights=labels[found] != c, minlength=len(mine)) > 0
        if tree is not None:
            gap, at = tree.query(samples[mine])
            nearest = np.asarray(tree.data)[at]
            # Data of its own: the nearest data point is nearer to it than to the others
            # and it passes through them (a small sphere sampled beside a surface). A
            # component standing off the data it seems to carry is g's pocket beside
            # them, whichever component they are nearer to.
            off = gap > OFF_DATA * reach[mine]
            other &= (labels[tree_of_samples.query(nearest)[1]] != c) | off
        total = weights[mine].sum()
        shells[c] = total > 0 and weights[mine][other].sum() > SHELL_FRACTION * total
    return shells
