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
* **One-sidedness** ``u(x)`` of a point x: take its ``k = RIM_NEIGHBOURS`` nearest
  samples (48 on a surface, 8 along a curve), their centroid c and their least principal
  axis (the data's normal there); u is the length of ``x - c`` along the other axes (the
  tangent plane, or line) over the distance to the k-th sample, between 0 and 1. Amid the
  samples they surround x and u is noise: its spread is ``1 / (2 sqrt(k))`` per axis, 0.07
  on a surface, so 0.25 is 3.5 of it. At a straight rim they fill a half-disc, whose
  centroid lies ``4 / (3 pi) = 0.42`` of its radius inside (along a curve, past an end,
  about 0.5), and past the rim u grows towards 1. An interior gap of random samples, seen
  from inside, still has samples all round: it reads low.
* **Trim**: a point is kept where its distance is within its tolerance, ``trim``
  (default ``DEFAULT_TRIM``, 2.5) amid the samples and ``rim`` (default ``DEFAULT_RIM``,
  1) where they lie to one side: ``level = distance - (trim - (trim - rim) w)``, ``w``
  rising linearly from 0 at ``u = 0.25`` to 1 at ``u = 0.4`` (``ONE_SIDED``), and the parts
  of the zero set where the level is positive are cut off (the level taken as linear
  between mesh vertices or polyline points). Past the rim the nearest sample is a rim
  sample, so the cut lies ``rim`` of its spacings past it: the distance decides where, the
  one-sidedness only which tolerance. ``rim=None`` (or a rim at least the trim) is the
  distance rule alone, ``trim`` spacings everywhere.
* **Holes and islands** (surfaces, with the rim test): a gap of random samples near the
  rim, or a large one, can read one-sided from its edge and open a hole. So a set of cut
  vertices (joined by edges) that kept vertices ring, that touches no border of the mesh,
  and whose faces cover under ``HOLE_AREA`` (20) squared spacings is kept: random samples
  leave empty patches up to about 13 squared spacings among 20000 (``m a e^-a ~ 1``).
  And open pieces of the trimmed mesh under ``ISLAND_AREA`` (4) squared spacings, slivers
  the cut leaves beside a ragged rim, are dropped. Along a curve the same: a cut between
  two kept stretches whose kept ends lie under ``GAP_LENGTH`` (5) spacings apart is kept
  (among 100 random samples of an arc the distance rule alone split the trimmed curve on
  25 of 40 draws, the rim test with this on none).

Where the zero set runs on past the data's rim, the trimmed surface (or curve) stops about
``rim`` rim spacings past the last samples (1.2 times the median spacing there), and its
boundary follows the rim. On the scans of ``benchmarks/open_scans.py`` (20000 random
samples each) the trimmed mesh's farthest point from the scanned part lay 1.2-1.8
spacings from it on four of five (on the three-view bunny 3.7, across patches hidden from
every viewpoint), where the distance rule alone (``rim=None``) ran on 3.5-4.3.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from ._faces import boundary_edges, face_areas, face_components, face_edges, unique_edges

#: Default trim amid the samples, in local spacings of the data. Random samples leave
#: gaps: on a sphere sampled uniformly at random by area (1e3, 1e4, 1e5 points) 99.9 % of
#: the sphere lay within 1.6-2.0 spacings of the data and all of it (2e5 random surface
#: points) within 2.4-2.6; the meshes of sphere fits (1500 and 5000 points, grid 12) were
#: left whole by trims of 2, 2.5 and 3. By the distance alone it stops an open surface
#: about 3 spacings past the data's rim (the rim's spacing reads about 1.2x), hence the
#: rim test and ``DEFAULT_RIM``.
DEFAULT_TRIM = 2.5
#: Default tolerance past the data's rim (where the samples lie to one side), in local
#: spacings. Measured on the five scans of ``benchmarks/open_scans.py`` (20000 random
#: samples each) at 0.5, 0.75 and 1: the Chamfer distance to the scanned part was up to a
#: quarter lower below 1 (the band past the rim is thin at all three), but only at 1 did
#: every scan's boundary loops match its true rims (below, a supported sliver of the
#: three-view bunny went as an island); the Hausdorff distance was 1.2-3.6 spacings at 1.
DEFAULT_RIM = 1.0
#: Nearest samples whose centroid gives a point's one-sidedness, by dimension. 48 on a
#: surface: the noise amid random samples (``1 / (2 sqrt(k))`` per axis) is a sixth of the
#: rim's 0.42; at 16 and 32 more interior gaps read one-sided (more holes in the scans).
RIM_NEIGHBOURS = {2: 8, 3: 48}
#: One-sidedness at which the tolerance starts to fall from the trim, and where it reaches
#: the rim's (module docstring).
ONE_SIDED = (0.25, 0.4)
#: Cut regions ringed by kept surface and smaller than this many squared spacings are
#: holes random sampling leaves, closed (surfaces, with the rim test).
HOLE_AREA = 20.0
#: Open pieces of a trimmed surface smaller than this many squared spacings are dropped:
#: slivers the cut leaves beside a ragged rim (about 0.2 squared spacings on the scans),
#: below the smallest scanned piece a scan can show.
ISLAND_AREA = 4.0
#: Cuts of a curve between kept stretches shorter than this many spacings are gaps random
#: sampling leaves, kept (curves, with the rim test): among m random samples along a curve
#: the largest gap is about ln(m) spacings, 4.6 among 100.
GAP_LENGTH = 5.0
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
    value = _spacings_option(trim, "trim", DEFAULT_TRIM, "a positive, finite", lambda v: v > 0)
    if value is not None and points is None:
        raise ValueError("trim needs the data points: pass points=, the cloud that was fitted")
    return value


def check_rim(rim) -> float | None:
    """``rim`` as a float number of spacings (True: ``DEFAULT_RIM``), or None for the
    distance alone (None or False); ValueError for a rim that is negative or not finite."""
    return _spacings_option(rim, "rim", DEFAULT_RIM, "a finite", lambda v: v >= 0, ">= 0")


def _spacings_option(value, name, default, kind, valid, bound="") -> float | None:
    """A trim-like option as a float number of spacings: None or False is None, True the
    ``default``; TypeError for anything but a number, ValueError for one not finite and
    ``valid``."""
    if value is None or value is False:
        return None
    if value is True:
        return float(default)
    if not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be None, True or a number of spacings, got {value!r}")
    number = float(value)
    if not (np.isfinite(number) and valid(number)):
        bound = f" {bound}" if bound else ""
        raise ValueError(f"{name} must be {kind} number of spacings{bound}, got {value!r}")
    return number


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
        self.points = unique

    def one_sidedness(
        self, x: Float[npt.ArrayLike, "n d"], neighbours: int | None = None
    ) -> Float[np.ndarray, " n"]:
        """How far the data around each row of ``x`` lie to one side of it, from 0 (x
        amid its samples) to 1 (all of them off to one side, far away): the offset of x
        from the centroid of its ``neighbours`` nearest samples, along the data's tangent
        plane (tangent line on a curve: the principal axes of those samples, less the
        least one), over the distance to the farthest of them (module docstring)."""
        x = np.asarray(x, dtype=np.float64)
        if len(x) == 0:
            return np.empty(0)
        dim = x.shape[1]
        k = RIM_NEIGHBOURS[dim] if neighbours is None else int(neighbours)
        k = min(k, len(self.points))
        distance, index = self.tree.query(x, k=k, workers=-1)
        distance, index = distance.reshape(len(x), k), index.reshape(len(x), k)
        near = self.points[index]
        centre = near.mean(axis=1)
        spread = near - centre[:, None]
        # The least principal axis of the neighbours: the data's normal there.
        _, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))
        normal = axes[:, :, 0]
        offset = x - centre
        offset -= np.sum(offset * normal, axis=1, keepdims=True) * normal
        reach = np.maximum(distance[:, -1], 1e-300)
        return np.minimum(np.linalg.norm(offset, axis=1) / reach, 1.0)

    def spacings(
        self, x: Float[npt.ArrayLike, "n d"], beyond: float = np.inf
    ) -> Float[np.ndarray, " n"]:
        """Distance of each row of ``x`` to its nearest sample, in that sample's spacings;
        ``inf`` for rows farther than ``beyond`` from every sample (the tree then stops
        searching early)."""
        x = np.asarray(x, dtype=np.float64)
        if len(x) == 0:
            return np.empty(0)
        distance, nearest = self.nearest(x, beyond)
        out = np.full(len(x), np.inf)
        found = nearest < len(self.points)
        out[found] = distance[found] / self.spacing[nearest[found]]
        return out

    def nearest(self, x, beyond: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """``(distance, index)`` of each row's nearest sample (``inf`` and
        ``len(points)`` past ``beyond``), the queries over the host's cores."""
        x = np.asarray(x, dtype=np.float64)
        return self.tree.query(x, distance_upper_bound=beyond, workers=-1)


def trim_mesh(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    points: Float[npt.ArrayLike, "m 3"],
    trim: float | bool | None = True,
    rim: float | bool | None = True,
) -> tuple[Float[np.ndarray, "V2 3"], Int[np.ndarray, "F2 3"]]:
    """The part of a mesh the data ``points`` support: within ``trim`` local spacings of
    them amid the samples, within ``rim`` past the data's rim.

    The rule (module docstring; docs/surfaces.md, "Open scans"): a sample's *local
    spacing* is ``1 / sqrt(density)`` around it, ``r_8 sqrt(pi / 8)`` with ``r_8`` the
    distance to its 8th nearest neighbour, then the median of that over the sample and
    its 8 neighbours (the median keeps samples at the rim, whose neighbours lie on one
    side, from reading twice as sparse). A point's distance in spacings is its distance to
    the nearest sample over that sample's spacing. Its tolerance is ``trim`` where its 48
    nearest samples surround it and ``rim`` where they lie to one side (the offset of
    their centroid along the tangent plane over their reach, 0.25 to 0.4: between, a mix).
    ``trim`` 2.5 (``DEFAULT_TRIM``) bridges the gaps random samples leave (a sphere's
    random samples leave all of it within 2.4-2.6 spacings, 99.9 % within 1.6-2.0);
    ``rim`` 1 (``DEFAULT_RIM``) stops an open surface about a rim spacing past its last
    samples, where the distance alone stopped it about 3 spacings out.

    The level (distance less tolerance) is measured at every vertex and taken as linear
    along each edge. Faces wholly beyond are dropped, faces wholly within kept, and faces
    that cross it are **clipped**: a new vertex on each crossing edge (shared by the two
    faces of that edge, so the result stays one connected surface), one triangle where
    one corner is within, two where two are. The boundary of the result is that contour,
    a polyline that follows the data's rim. With the rim test, cut regions that kept
    surface rings (no border of the mesh) under ``HOLE_AREA`` (20) squared spacings are
    kept whole, holes random sampling leaves, and open pieces under ``ISLAND_AREA`` (4)
    squared spacings are dropped. Vertices no face uses are removed; face orientation is
    kept.

    Args:
        vertices, faces: a triangle mesh (as from [`mesh`][jurs.levelset.mesh]).
        points: ``(m, 3)`` data points, at least 2 distinct.
        trim: spacings to keep amid the samples (positive); True for ``DEFAULT_TRIM``;
            None or False returns the mesh as given.
        rim: spacings to keep past the data's rim (>= 0; a rim above ``trim`` is
            ``trim``); True for ``DEFAULT_RIM``; None or False for the distance rule
            alone (``trim`` everywhere, no holes closed or islands dropped).

    Returns:
        ``(vertices (V2, 3) float64, faces (F2, 3) int64)``; empty arrays when nothing is
        kept.

    Raises:
        ValueError: bad ``vertices``, ``faces``, ``points``, ``trim`` or ``rim`` (named).
        TypeError: a ``trim`` or ``rim`` that is not None, a bool or a number.
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
    return trim_to_support(vertices, faces, Support(points), value, check_rim(rim))


def trim_to_support(vertices, faces, support: Support, trim: float, rim: float | None):
    """``trim_mesh`` of checked arrays (``(V, 3)`` float64, ``(F, 3)`` int64, at least one
    face) against the data's ``support``, with a checked ``trim`` and ``rim``."""
    # A vertex an edge away from a kept one has its level exactly (a crossing edge's
    # clip reads it); one farther is cut, whatever its level, and reads inf.
    corners = vertices[faces]
    reach = float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1).max())
    level = trim_levels(support, vertices, trim, rim, reach)
    if rim is not None and rim < trim:
        level = fill_holes(vertices, faces, level, support, HOLE_AREA)
        return drop_islands(*clip_mesh(vertices, faces, level), support, ISLAND_AREA)
    return clip_mesh(vertices, faces, level)


def near_support(support: Support, trim: float, steps: int):
    """A ``jurs._model.band.plan_band`` filter for a mesh to be trimmed: the lattice
    blocks that may hold a vertex of the trimmed mesh, those within ``trim`` of the
    largest spacing, a hole's inradius (``HOLE_AREA``: a hole closed whole lies that near
    its ring) and ``steps + 2`` lattice diagonals (how far ``steps`` Newton steps move a
    vertex, and an edge to a kept one) of a sample. What the filter leaves out the trim
    would cut whole, so the trimmed mesh is the same."""
    reach = (float(trim) + math.sqrt(HOLE_AREA / math.pi)) * float(support.spacing.max())

    def near(lower, upper, step):
        slack = reach + (int(steps) + 2) * float(np.linalg.norm(step))
        half = 0.5 * np.linalg.norm(np.asarray(upper) - np.asarray(lower), axis=1)
        centre = 0.5 * (np.asarray(lower) + np.asarray(upper))
        distance, _ = support.nearest(centre, slack + float(half.max(initial=0.0)))
        return distance <= slack + half

    return near


def trim_levels(
    support: Support, x, trim: float, rim: float | None, reach: float = np.inf
) -> np.ndarray:
    """Per-point trim level (negative: kept): the distance in spacings less the tolerance,
    ``trim`` amid the data and ``rim`` where the data lie to one side (module docstring).
    Points farther than ``reach`` beyond the largest tolerance of any sample (``trim``
    of the largest spacing) read ``inf``: cut, and ``reach`` from anything kept."""
    distance = support.spacings(x, float(trim) * float(support.spacing.max()) + reach)
    tolerance = np.full(len(distance), float(trim))
    if rim is None or rim >= trim:
        return distance - tolerance
    # Within ``rim`` everything is kept and beyond twice the trim nothing is, whatever the
    # tolerance; between, it is read from the one-sidedness.
    between = np.flatnonzero((distance > rim) & (distance < 2.0 * trim))
    sidedness = np.ones(len(distance))
    sidedness[between] = support.one_sidedness(np.asarray(x, dtype=np.float64)[between])
    low, high = ONE_SIDED
    weight = np.clip((sidedness - low) / (high - low), 0.0, 1.0)
    return distance - (trim - (trim - rim) * weight)


def fill_holes(vertices, faces, level, support: Support, area: float) -> np.ndarray:
    """``level`` with the small holes closed: every connected set of cut vertices (level >=
    0, joined by edges) that is ringed by kept vertices, touches no border edge of the
    mesh, and whose faces cover less than ``area`` squared local spacings is set to kept."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    out = level >= 0
    if not out.any() or out[faces].all():
        return level
    unique, uses = unique_edges(face_edges(faces), return_counts=True)
    border = np.zeros(len(vertices), dtype=bool)
    border[unique[uses == 1].reshape(-1)] = True
    both = unique[out[unique].all(axis=1)]
    n = len(vertices)
    graph = coo_matrix((np.ones(len(both)), (both[:, 0], both[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    outside = np.flatnonzero(out)
    groups, group = np.unique(label[outside], return_inverse=True)
    g = np.full(n, -1)
    g[outside] = group
    count = len(groups)
    # Each face that holds a cut vertex belongs to that vertex's set (a face's cut
    # vertices share an edge, hence a set).
    touched = out[faces].any(axis=1)
    owner = g[faces[touched]].max(axis=1)
    size = np.bincount(owner, weights=face_areas(vertices, faces[touched]), minlength=count)
    ringed = np.bincount(owner, weights=(~out[faces[touched]]).any(axis=1), minlength=count) > 0
    bordered = np.bincount(group, weights=border[outside], minlength=count) > 0
    hole = small_groups(support, area, size, ringed & ~bordered, vertices, outside, group)
    if not hole.any():
        return level
    level = level.copy()
    level[outside[hole[group]]] = -1.0
    return level


def small_groups(support: Support, area: float, size, candidate, points, members, group):
    """Which of ``count`` groups of points cover less than ``area`` squared local
    spacings: ``size`` ``(count,)`` their areas, ``candidate`` ``(count,)`` those that
    may, ``points[members]`` their points and ``group`` the group of each member; a
    group's spacing is the largest of its points' nearest samples'. A group of at least
    ``area`` of the largest spacing anywhere is none, so only the others' points are
    looked up."""
    small = candidate & (size < area * support.spacing.max() ** 2)
    asked = small[group]
    _, nearest = support.nearest(points[members[asked]])
    scale = np.zeros(len(size))
    np.maximum.at(scale, group[asked], support.spacing[nearest] ** 2)
    return small & (size < area * scale)


def drop_islands(vertices, faces, support: Support, area: float):
    """The mesh without its open connected pieces (a border edge) that cover less than
    ``area`` squared local spacings: slivers the clip leaves beside the rim."""
    if len(faces) == 0:
        return vertices, faces
    faces = np.asarray(faces, dtype=np.int64)
    count, owner = face_components(faces, len(vertices))
    if count == 1:
        return vertices, faces
    size = np.bincount(owner, weights=face_areas(vertices, faces), minlength=count)
    open_piece = np.zeros(count, dtype=bool)
    open_piece[boundary_edges(faces, owner)[1]] = True
    # Each used vertex lies in one piece: its faces'.
    piece = np.full(len(vertices), -1)
    piece[faces] = owner[:, None]
    used = np.flatnonzero(piece >= 0)
    drop = small_groups(support, area, size, open_piece, vertices, used, piece[used])
    if not drop.any():
        return vertices, faces
    return _compact(vertices, faces[~drop[owner]])


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
    unique, index = unique_edges(keys, return_inverse=True)
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
    rim: float | bool | None = True,
) -> list[tuple[Float[np.ndarray, "k 2"], bool]]:
    """The parts of 2D polylines the data ``points`` support: within ``trim`` local
    spacings of them amid the samples, within ``rim`` past the end of the data.

    The level (distance in spacings less the tolerance: ``trim`` where the 8 nearest
    samples surround a point, ``rim`` where they lie to one side; module docstring) is
    measured at every vertex and taken as linear along each segment; a polyline is cut
    where it crosses 0 (a new end point there) and split into one piece per stretch
    within it. With the rim test a cut between two kept stretches whose kept ends lie
    under ``GAP_LENGTH`` (5) spacings apart is kept (a gap random sampling leaves). A
    closed polyline wholly within stays closed; one that leaves the data becomes open
    pieces (the piece across its start is joined up). Pieces of fewer than 2 points are dropped.

    Args:
        lines: ``(polyline (k, 2), closed)`` pairs, as from
            [`zero_level_set`][jurs.levelset.zero_level_set] (closed polylines repeat
            their first point at the end).
        points: ``(m, 2)`` data points, at least 2 distinct.
        trim: spacings to keep amid the samples (positive); True for
            ``DEFAULT_TRIM``; None or False returns the polylines as given.
        rim: spacings to keep past the end of the data (>= 0; at most ``trim``); True
            for ``DEFAULT_RIM``; None or False for the distance rule alone.

    Returns:
        ``(polyline, closed)`` pairs: the pieces, in the order of the input.
    """
    points = check_points(points, 2)
    value = check_trim(trim, points)
    if value is None:  # None or False: no trim
        return [(np.asarray(p, dtype=np.float64).reshape(-1, 2), bool(c)) for p, c in lines]
    rim_value = check_rim(rim)
    support = Support(points)
    out = []
    for polyline, closed in lines:
        polyline = np.asarray(polyline, dtype=np.float64).reshape(-1, 2)
        if len(polyline) == 0:
            continue
        level = trim_levels(support, polyline, value, rim_value)
        if rim_value is not None and rim_value < value:
            level = bridge_gaps(polyline, level, bool(closed), support, GAP_LENGTH)
        out.extend(_clip_polyline(polyline, level, bool(closed)))
    return out


def bridge_gaps(polyline, level, closed: bool, support: Support, length: float) -> np.ndarray:
    """``level`` with the short cuts of a polyline kept: a run of cut points (level >= 0)
    with kept points on both sides (an open polyline's ends do not count), the two kept
    points less than ``length`` local spacings apart along it, is set to kept."""
    out = level >= 0
    n = len(polyline)
    if not out.any() or out.all():
        return level
    ring = closed and n > 2 and np.array_equal(polyline[0], polyline[-1])
    m = n - 1 if ring else n  # a closed polyline repeats its first point at the end
    step = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(step)])
    total = along[-1]
    _, nearest = support.tree.query(polyline)
    scale = support.spacing[nearest]
    level = level.copy()
    kept = np.flatnonzero(~out[:m])
    if not ring:
        pairs = [(a, b) for a, b in zip(kept[:-1], kept[1:]) if b > a + 1]
    else:
        pairs = [(a, b) for a, b in zip(kept, np.append(kept[1:], kept[0] + m)) if b > a + 1]
    for a, b in pairs:
        run = np.arange(a + 1, b) % m
        span = along[b % m] - along[a] if b < m or not ring else total - along[a] + along[b - m]
        if span < length * scale[run].max():
            level[run] = -1.0
    if ring:
        level[-1] = level[0]
    return level


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
