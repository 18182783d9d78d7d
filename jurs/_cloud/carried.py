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
