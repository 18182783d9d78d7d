"""Carrying a normal's sign along a spanning forest: the one routine behind the orientation
of estimated normals (``jurs._cloud.normals``) and the check of given ones
(``jurs._cloud.orientation``)."""

from __future__ import annotations

import numpy as np


def forest_signs(forest, normals: np.ndarray) -> np.ndarray:
    """Signs (+1/-1) that make ``normals`` consistent along every edge of ``forest`` (a
    SciPy sparse graph whose edges form a forest), relative to an arbitrary sign per tree.

    Each edge says "same" or "opposite" (the sign of ``n_i . n_j``); in the doubled graph
    (nodes i+ and i-, joined straight for "same" and crosswise for "opposite") every tree
    becomes two components, and a node is + when its i+ copy lies in the lower-labelled
    one. One connected-components pass, no traversal order to keep."""
    from scipy import sparse  # lazily: import jurs loads no SciPy sparse
    from scipy.sparse import csgraph

    m = len(normals)
    coo = sparse.coo_matrix(forest)
    i, j = coo.row, coo.col
    same = np.sum(normals[i] * normals[j], axis=1) >= 0
    rows = np.concatenate([i, i + m])
    cols = np.concatenate([np.where(same, j, j + m), np.where(same, j + m, j)])
    doubled = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * m, 2 * m))
    _, labels = csgraph.connected_components(doubled, directed=False)
    return np.where(labels[:m] < labels[m:], 1.0, -1.0)
