"""The rims of an open scan, one by one: which of the scanned part's true rims a trimmed
mesh's boundary loops follow, which it misses and why, and what its extra loops bound.

``open_scans.py`` counts boundary loops against true rims; a count can be right while one
rim is missed and an extra loop stands in for it, or wrong by a rim the samples cannot
show. So each true rim is described by what a scan of it shows:

* its **gap**: the least distance from it to another rim, in the median local spacing (an
  island beside the main part, a hole beside the rim). Random samples leave gaps of about
  2.5 spacings amid the data (``jurs.levelset.DEFAULT_TRIM``), so two rims nearer than that
  read as random sampling;
* its **depth**, for a hole: how far the hole reaches from the data, the largest distance
  in local spacings of its faces' corners and centroids to the nearest sample (the trim's
  measure), and the area of it beyond the default trim. The scanned part's own random
  gaps reach some spacings too (``truth_stray_max``), and the trim closes a cut region
  under ``jurs.levelset._trimming.HOLE_AREA`` as one: a hole no deeper, or with less than
  that beyond the trim, reads the same as a random gap.

A boundary loop of the mesh *follows* the true rim that most of its vertices lie nearest
to, within ``FOLLOW_SPACINGS``; a true rim no loop follows is *missed* (closed over, or
merged into another rim's loop), and a loop following none is *extra*.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

#: A loop follows a true rim when the median distance of its vertices to it is within this
#: many median spacings (the default trim stops 1-2.5 spacings from the data).
FOLLOW_SPACINGS = 3.0


def rim_loops(vertices, faces) -> list[tuple[float, np.ndarray]]:
    """The boundary loops of a mesh as ``(length, vertex indices)``, longest first (a loop:
    boundary edges joined at vertices, as ``jurs.levelset.boundary_loops`` counts them)."""
    faces = np.asarray(faces)
    if len(faces) == 0:
        return []
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    unique, count = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[count == 1]
    if len(boundary) == 0:
        return []
    n = len(vertices)
    graph = sparse.coo_matrix(
        (np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n)
    )
    _, labels = connected_components(graph, directed=False)
    lengths = np.linalg.norm(vertices[boundary[:, 0]] - vertices[boundary[:, 1]], axis=1)
    edge_label = labels[boundary[:, 0]]
    used = np.unique(boundary)
    loops = [
        (float(lengths[edge_label == k].sum()), used[labels[used] == k])
        for k in np.unique(edge_label)
    ]
    return sorted(loops, key=lambda loop: -loop[0])


def describe_rims(vertices, faces, seen, support, spacing: float) -> list[dict]:
    """Each true rim of the scanned part (``faces[seen]``, holes and islands already
    cleaned): ``length`` and ``gap`` in median spacings (``gap`` None for a lone rim),
    ``kind`` ("hole" where it rings an unseen region other than the largest, the far side;
    else "rim"), a hole's ``depth`` in local spacings and the area of it ``beyond`` the
    default trim (faces whose centroid lies farther; squared median spacings)."""
    from jurs.levelset import DEFAULT_TRIM, face_areas, mesh_components

    loops = rim_loops(vertices, faces[seen])
    if not loops:
        return []
    unseen = faces[~seen]
    count, labels = (0, np.empty(0, dtype=np.int64))
    if len(unseen):  # a heightfield seen whole has none
        count, labels = mesh_components(vertices, unseen)
    areas = np.bincount(labels, weights=face_areas(vertices, unseen), minlength=count)
    region_of_vertex = np.full(len(vertices), -1)
    for k in range(count):  # a rim's vertices are corners of the unseen faces beside it
        if k != np.argmax(areas):  # the largest unseen region is the far side, no hole
            region_of_vertex[np.unique(unseen[labels == k])] = k
    regions = [set(region_of_vertex[ids][region_of_vertex[ids] >= 0].tolist()) for _, ids in loops]
    trees = [cKDTree(vertices[ids]) for _, ids in loops]
    out = []
    for i, (length, ids) in enumerate(loops):
        others = [trees[j].query(vertices[ids])[0].min() for j in range(len(loops)) if j != i]
        entry = {
            "length": length / spacing,
            "gap": float(min(others)) / spacing if others else None,  # the one rim
            "kind": "rim",
            "depth": None,
        }
        if len(regions[i]) == 1:  # an unseen region ringed by this rim: a hole
            region = unseen[labels == next(iter(regions[i]))]
            corners = np.concatenate([vertices[np.unique(region)], vertices[region].mean(1)])
            beyond = support.spacings(vertices[region].mean(1)) > DEFAULT_TRIM
            entry.update(
                kind="hole",
                depth=float(support.spacings(corners).max()),
                beyond=float(face_areas(vertices, region[beyond]).sum()) / spacing**2,
            )
        out.append(entry)
    return out


def follow_rims(
    true_vertices, true_faces, mesh_vertices, mesh_faces, support, spacing: float
) -> dict:
    """Which true rims (of ``true_faces``) the loops of a trimmed mesh follow: ``missed``
    (indices into the true rims, longest first), and ``extra`` loops, each with its
    ``length`` (median spacings), its piece's ``area`` (squared median spacings) and the
    ``samples`` (of ``support``, a ``jurs.levelset._trimming.Support``) within one local
    spacing of that piece."""
    from jurs.levelset import face_areas, mesh_components

    rims = rim_loops(true_vertices, true_faces)
    loops = rim_loops(mesh_vertices, mesh_faces)
    followed = set()
    extra = []
    if rims:
        trees = [cKDTree(true_vertices[ids]) for _, ids in rims]
    for length, ids in loops:
        if not rims:
            nearest, distance = np.zeros(len(ids), int), np.full(len(ids), np.inf)
        else:
            d = np.stack([t.query(mesh_vertices[ids])[0] for t in trees])
            nearest, distance = d.argmin(0), d.min(0)
        if np.median(distance) <= FOLLOW_SPACINGS * spacing:
            followed.add(int(np.bincount(nearest).argmax()))
            continue
        _, labels = mesh_components(mesh_vertices, mesh_faces)
        piece_of_vertex = np.full(len(mesh_vertices), -1)
        piece_of_vertex[mesh_faces.ravel()] = np.repeat(labels, 3)
        piece = mesh_faces[labels == piece_of_vertex[ids[0]]]
        near = cKDTree(mesh_vertices[np.unique(piece)]).query(support.points)[0] <= support.spacing
        extra.append(
            {
                "length": length / spacing,
                "area": float(face_areas(mesh_vertices, piece).sum()) / spacing**2,
                "samples": int(near.sum()),
            }
        )
    return {"missed": [i for i in range(len(rims)) if i not in followed], "extra": extra}
