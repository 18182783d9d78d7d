"""Trimming a zero set to the data: the part of a surface (3D) or curve (2D) the samples
support.

A fit's zero set is closed over its box, so on an open scan (one side of an object, a
terrain, a coastline) it runs on past the data wherever the regulariser carries it. The
rule here keeps what lies near the data, measured in the data's own *local spacing*:

* **Local spacing** ``s_i`` of sample i: ``1 / sqrt(density)`` on a surface (3D), ``1 /
  density`` along a curve (2D), the density estimated from the distance ``r_k`` to the
  ``k = TRIM_NEIGHBOURS`` (8) nearest other samples: ``r_k sqrt(pi / k)`` (k samples in a
  disk of radius ``r_k``) or ``2 r_k / k`` (k samples in a segment of length ``2 r_k``),
  and then ``s_i`` is the median of that estimate over sample i and its k neighbours. On a
  square grid of step a this reads 0.89 a, along a curve of step a exactly a; unlike the
  nearest-neighbour distance it does not depend on how regular the sampling is (on random
  samples the nearest neighbour is about half the spacing). The median: at the data's rim
  a sample's neighbours lie on one side, which made its own estimate up to 2x too large
  (1.33x at the median rim sample of a random hemisphere scan); the neighbourhood's median
  reads 1.2x there, at most 1.5x. Repeated samples are counted once.
* **Distance in spacings** of a point x: ``|x - p| / s_p`` with p the sample nearest to x
  (a KD-tree query).
* **Trim**: the parts of the zero set farther than ``trim`` spacings are cut off, at
  ``trim`` spacings (the distance taken as linear between mesh vertices or polyline
  points). Default ``DEFAULT_TRIM``, 2.5 spacings.

Where the zero set runs on past the data's rim, the trimmed surface (or curve) stops about
``1.2 trim`` rim spacings past the last samples, and its boundary follows the rim.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

#: Default trim, in local spacings of the data. Random samples leave gaps: on a sphere
#: sampled uniformly at random by area (1e3, 1e4, 1e5 points) 99.9 % of the sphere lay
#: within 1.6-2.0 spacings of the data and all of it (2e5 random surface points) within
#: 2.4-2.6; the meshes of sphere fits (1500 and 5000 points, grid 12) were left whole by
#: trims of 2, 2.5 and 3. 2.5 keeps a closed surface whole and stops an open one about 3
#: spacings past the data's rim (the rim's spacing reads about 1.2x; docs/surfaces.md,
#: "Open scans").
DEFAULT_TRIM = 2.5
#: Neighbours whose distance gives a sample's local spacing.
TRIM_NEIGHBOURS = 8
#: Fraction of a mesh's area farther than ``DEFAULT_TRIM`` spacings from the data above
#: which [`analyze_mesh`][jurs.levelset.analyze_mesh] notes that most of the surface is
#: unsupported.
UNSUPPORTED_FRACTION = 0.5


def check_trim(trim, points) -> float | None:
    """``trim`` as a float number of spacings (True: ``DEFAULT_TRIM``), or None for no
    trim (None or False); ValueError for a trim that is not positive and finite, or a trim
    without ``points``."""
    if trim is None or trim is False:
        return None
    if trim is True:
        value = DEFAULT_TRIM
    else:
        if not isinstance(trim, (int, float, np.integer, np.floating)):
            raise TypeError(f"trim must be None, True or a number of spacings, got {trim!r}")
        value = float(trim)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"trim must be a positive, finite number of spacings, got {trim!r}")
    if points is None:
        raise ValueError("trim needs the data points: pass points=, the cloud that was fitted")
    return value


def check_points(points, dim: int, name: str = "points", minimum: int = 2) -> np.ndarray:
    """``points`` as float64 ``(m, dim)`` with finite rows, at least ``minimum`` of them;
    ValueError naming ``name`` otherwise."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != dim or len(points) < minimum:
        raise ValueError(
            f"{name} must have shape (m, {dim}) with m >= {minimum}, got {points.shape}"
        )
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{name} must be finite; {int(bad.sum())} of {len(points)} hold NaN or infinite "
            f"coordinates (the first is row {int(np.flatnonzero(bad)[0])})"
        )
    return points


class Support:
    """The data's local spacings and a KD-tree of its distinct samples, for measuring
    distances in spacings (module docstring). ``points``: ``(m, 2)`` samples of a curve or
    ``(m, 3)`` samples of a surface."""

    def __init__(self, points: Float[npt.ArrayLike, "m d"], neighbours: int = TRIM_NEIGHBOURS):
        points = np.asarray(points, dtype=np.float64)
        unique = np.unique(points, axis=0)
        if len(unique) < 2:
            raise ValueError("trimming needs at least 2 distinct data points")
        self.tree = cKDTree(unique)
        k = min(int(neighbours), len(unique) - 1)
        distance, index = self.tree.query(unique, k=k + 1)  # column 0: the sample itself
        radius = distance[:, k]
        raw = radius * np.sqrt(np.pi / k) if points.shape[1] == 3 else 2.0 * radius / k
        # The median over the neighbourhood: at the rim a sample's own estimate reads up
        # to twice too large (its neighbours on one side), its neighbours' less so.
        self.spacing = np.median(raw[index], axis=1)

    def spacings(self, x: Float[npt.ArrayLike, "n d"]) -> Float[np.ndarray, " n"]:
        """Distance of each row of ``x`` to its nearest sample, in that sample's spacings."""
        x = np.asarray(x, dtype=np.float64)
        if len(x) == 0:
            return np.empty(0)
        distance, nearest = self.tree.query(x)
        return distance / self.spacing[nearest]


def trim_mesh(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    points: Float[npt.ArrayLike, "m 3"],
    trim: float | bool | None = True,
) -> tuple[Float[np.ndarray, "V2 3"], Int[np.ndarray, "F2 3"]]:
    """The part of a mesh within ``trim`` local spacings of the data ``points``.

    The rule (docs/surfaces.md, "Open scans"): a sample's *local spacing* is ``1 /
    sqrt(density)`` around it, ``r_8 sqrt(pi / 8)`` with ``r_8`` the distance to its 8th
    nearest neighbour, then the median of that over the sample and its 8 neighbours (the
    median keeps samples at the rim, whose neighbours lie on one side, from reading
    twice as sparse). A point's distance in spacings is its distance to the nearest
    sample over that sample's spacing. The default of 2.5 (``DEFAULT_TRIM``) was measured:
    random samples of a sphere leave all of it within 2.4-2.6 spacings and 99.9 % within
    1.6-2.0, and the meshes of sphere fits stayed whole at 2; the trimmed surface stops
    about 3 spacings past the data's rim.

    The distance in spacings is measured at every vertex and taken as
    linear along each edge. Faces wholly beyond ``trim`` are dropped, faces wholly within
    kept, and faces that cross it are **clipped** at ``trim``: a new vertex on each crossing
    edge (shared by the two faces of that edge, so the result stays one connected
    surface), one triangle where one corner is within, two where two are. The boundary of
    the result is that contour, a polyline that follows the data's rim ``trim`` spacings out.
    Vertices no face uses are removed; face orientation is kept.

    Args:
        vertices, faces: a triangle mesh (as from [`mesh`][jurs.levelset.mesh]).
        points: ``(m, 3)`` data points, at least 2 distinct.
        trim: spacings to keep (positive); True for ``DEFAULT_TRIM``; None or False
            returns the mesh as given.

    Returns:
        ``(vertices (V2, 3) float64, faces (F2, 3) int64)``; empty arrays when nothing is
        within ``trim``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise ValueError(f"vertices must be a finite (V, 3) array, got shape {vertices.shape}")
    if faces.size == 0:
        faces = np.empty((0, 3), dtype=np.int64)
    elif (
        faces.ndim != 2
        or faces.shape[1] != 3
        or not np.issubdtype(faces.dtype, np.integer)
        or faces.min() < 0
        or faces.max() >= len(vertices)
    ):
        raise ValueError(
            f"faces must be an integer (F, 3) array of indices into the {len(vertices)} "
            f"vertices, got shape {faces.shape} {faces.dtype}"
        )
    faces = faces.astype(np.int64)
    points = check_points(points, 3)
    value = check_trim(trim, points)
    if value is None:  # None or False: no trim
        return vertices, faces
    if len(faces) == 0:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    return clip_mesh(vertices, faces, Support(points).spacings(vertices) - value)


def clip_mesh(vertices, faces, level):
    """The part of a mesh where the per-vertex ``level`` (linear along edges) is below 0;
    see [`trim_mesh`][jurs.levelset.trim_mesh]."""
    # A vertex exactly at the contour would put the crossing point on itself and leave a
    # face of no area; counted as outside, its edges cross just beside it instead.
    inside = level < 0
    count = inside[faces].sum(axis=1)
    keep = faces[count == 3]
    cut = faces[(count == 1) | (count == 2)]
    if len(cut) == 0:
        return _compact(vertices, keep)
    # Roll each cut face so that its odd corner (the lone inside one, or the lone outside
    # one) comes first; rolling keeps the orientation.
    inner = inside[cut]
    odd = np.where(inner.sum(axis=1)[:, None] == 1, inner, ~inner).argmax(axis=1)
    rows = np.arange(len(cut))[:, None]
    cut = cut[rows, (odd[:, None] + np.arange(3)) % 3]
    a, b, c = cut[:, 0], cut[:, 1], cut[:, 2]
    # New vertices on the crossing edges a-b and a-c, one per edge (keyed by its sorted
    # ends) so that the two faces of an edge share it.
    edges = np.concatenate([np.stack([a, b], 1), np.stack([a, c], 1)])
    keys = np.sort(edges, axis=1)
    unique, index = np.unique(keys, axis=0, return_inverse=True)
    index = index.reshape(-1)
    lo, hi = unique[:, 0], unique[:, 1]
    t = level[lo] / (level[lo] - level[hi])
    new = vertices[lo] + t[:, None] * (vertices[hi] - vertices[lo])
    ab = len(vertices) + index[: len(cut)]
    ac = len(vertices) + index[len(cut) :]
    lone_inside = inside[a]
    # One corner inside: the triangle (a, ab, ac). Two inside (b, c): the quad
    # (ab, b, c, ac), as two triangles.
    one = np.stack([a, ab, ac], 1)[lone_inside]
    two = ~lone_inside
    quads = np.concatenate([np.stack([ab, b, c], 1)[two], np.stack([ab, c, ac], 1)[two]], axis=0)
    all_faces = np.concatenate([keep, one, quads])
    return _compact(np.concatenate([vertices, new]), all_faces)


def _compact(vertices, faces):
    """Drop the vertices no face uses and renumber the faces."""
    if len(faces) == 0:
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[used], faces.reshape(-1, 3).astype(np.int64)


def trim_curves(
    lines,
    points: Float[npt.ArrayLike, "m 2"],
    trim: float | bool | None = True,
) -> list[tuple[Float[np.ndarray, "k 2"], bool]]:
    """The parts of 2D polylines within ``trim`` local spacings of the data ``points``.

    The distance in spacings (module docstring) is measured at every vertex and taken as
    linear along each segment; a polyline is cut where it crosses ``trim`` (a new end point
    there) and split into one piece per stretch within it. A closed polyline wholly within
    stays closed; one that leaves the data becomes open pieces (the piece across its start
    is joined up). Pieces of fewer than 2 points are dropped.

    Args:
        lines: ``(polyline (k, 2), closed)`` pairs, as from
            [`zero_level_set`][jurs.levelset.zero_level_set] (closed polylines repeat
            their first point at the end).
        points: ``(m, 2)`` data points, at least 2 distinct.
        trim: spacings to keep (positive); True for ``DEFAULT_TRIM``; None or False
            returns the polylines as given.

    Returns:
        ``(polyline, closed)`` pairs: the pieces, in the order of the input.
    """
    points = check_points(points, 2)
    value = check_trim(trim, points)
    if value is None:  # None or False: no trim
        return [(np.asarray(p, dtype=np.float64).reshape(-1, 2), bool(c)) for p, c in lines]
    support = Support(points)
    out = []
    for polyline, closed in lines:
        polyline = np.asarray(polyline, dtype=np.float64).reshape(-1, 2)
        if len(polyline) == 0:
            continue
        level = support.spacings(polyline) - value
        out.extend(_clip_polyline(polyline, level, bool(closed)))
    return out


def _clip_polyline(polyline, level, closed):
    """Pieces of ``polyline`` where ``level < 0`` (linear along segments)."""
    inside = level < 0
    if inside.all():
        return [(polyline, closed)]
    if not inside.any():
        return []
    if closed:
        # Start at an outside vertex, so that no piece runs across the start; a closed
        # polyline repeats its first point at the end, dropped and re-added here.
        ring = polyline[:-1] if np.array_equal(polyline[0], polyline[-1]) else polyline
        ring_level = level[: len(ring)]
        start = int(np.flatnonzero(ring_level >= 0)[0])
        polyline = np.concatenate([np.roll(ring, -start, axis=0), ring[start : start + 1]])
        level = np.concatenate([np.roll(ring_level, -start), ring_level[start : start + 1]])
        inside = level < 0
    pieces, current = [], []
    for i in range(len(polyline)):
        if i > 0 and inside[i] != inside[i - 1]:
            t = level[i - 1] / (level[i - 1] - level[i])
            current.append(polyline[i - 1] + t * (polyline[i] - polyline[i - 1]))
            if not inside[i]:
                pieces.append(current)
                current = []
        if inside[i]:
            current.append(polyline[i])
    if current:
        pieces.append(current)
    return [(np.asarray(p), False) for p in pieces if len(p) >= 2]
