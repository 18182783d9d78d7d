"""A triangle mesh's faces: the check of a mesh given, the faces' areas, their connected
components and the boundary edges; what the mesh analysis (``_mesh_analysis.py``) and the
trimming of open scans (``_trimming.py``) both read. Host-side NumPy/SciPy."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int
from scipy import sparse
from scipy.sparse import csgraph


def check_mesh(vertices, faces):
    """``(vertices float64 (V, 3), faces int64 (F, 3))``, checked: shapes, finite vertices,
    face indices in range. ValueError naming the input otherwise."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if (
        faces.ndim != 2
        or faces.shape[1] != 3
        or (faces.size and not np.issubdtype(faces.dtype, np.integer))
    ):
        raise ValueError(
            f"faces must be an integer array of shape (F, 3), got {faces.shape} {faces.dtype}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(
            f"faces index vertices 0..{len(vertices) - 1}, got indices {faces.min()}..{faces.max()}"
        )
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise ValueError(
            f"vertices must be finite; {int(bad.sum())} of {len(vertices)} hold NaN or "
            f"infinite coordinates (the first is vertex {int(np.flatnonzero(bad)[0])})"
        )
    return vertices, faces.astype(np.int64)


def face_areas(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"]
) -> Float[np.ndarray, " F"]:
    """Area of each triangle; ``(F,)``."""
    vertices, faces = check_mesh(vertices, faces)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def face_components(faces, num_vertices: int):
    """[`mesh_components`][jurs.levelset.mesh_components] of checked int64 ``faces`` over
    ``num_vertices`` vertices."""
    if len(faces) == 0:
        return 0, np.empty(0, dtype=np.int64)
    # Each face links its first vertex to the other two: enough to connect all three.
    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].reshape(-1)
    graph = sparse.coo_matrix(
        (np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(num_vertices, num_vertices)
    )
    _, vertex_label = csgraph.connected_components(graph, directed=False)
    raw = vertex_label[faces[:, 0]]
    used, first, inverse, sizes = np.unique(
        raw, return_index=True, return_inverse=True, return_counts=True
    )
    order = np.lexsort((first, -sizes))  # largest first, then by first face
    rank = np.empty(len(used), dtype=np.int64)
    rank[order] = np.arange(len(used))
    return len(used), rank[inverse.reshape(-1)]


def face_edges(faces) -> np.ndarray:
    """The ``(3F, 2)`` edges of ``faces``, each as its sorted vertex pair, face by face."""
    return np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)


def unique_edges(edges, **options):
    """``np.unique(edges, axis=0, **options)`` of sorted ``(E, 2)`` vertex pairs: the
    same pairs, order and optional outputs, by one int64 key a pair (its lexicographic
    order is the pairs'), a sort of numbers instead of a sort of records."""
    edges = np.asarray(edges, dtype=np.int64)
    span = int(edges.max()) + 1 if edges.size else 1
    out = np.unique(edges[:, 0] * span + edges[:, 1], **options)
    first, rest = (out[0], out[1:]) if isinstance(out, tuple) else (out, ())
    pairs = np.stack(np.divmod(first, span), axis=1)
    return (pairs, *rest) if rest else pairs


def boundary_edges(faces, labels):
    """The boundary edges (edges of one face) as ``(B, 2)`` vertex pairs, and the
    component label of each."""
    edge_label = np.repeat(labels, 3)
    unique, where, uses = unique_edges(face_edges(faces), return_index=True, return_counts=True)
    return unique[uses == 1], edge_label[where][uses == 1]
