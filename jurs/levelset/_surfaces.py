"""Triangle meshes of the zero set of a 3D spline, and what to measure on them.

[`mesh`][jurs.levelset.mesh] samples g on a lattice slab by slab
(``jurs._model.lattice.lattice_values``), runs marching cubes (scikit-image) on each slab,
stitches the slabs and moves the vertices onto {g = 0} by Newton steps.
[`analyze_mesh`][jurs.levelset.analyze_mesh] splits a mesh into connected components and
measures each (area, closed or open, genus, distance to the data), flagging the supplementary
ones ("bubbles" away from the data); [`mesh_distances`][jurs.levelset.mesh_distances] compares
a mesh with a reference cloud (Chamfer, Hausdorff, normal consistency). Everything is
host-side NumPy/SciPy; see docs/surfaces.md for the definitions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from .._model.lattice import lattice_values, spline_fields, values_and_gradients
from ..datasets import sample_mesh

#: Lattice nodes per spline cell along the finest axis for the default resolution: g is a
#: cubic in each cell, and marching cubes sees at most one zero crossing per lattice edge,
#: so a feature one cell wide needs two or three nodes across it to show up at all. The
#: Newton steps afterwards put the vertices on the zero set, but the flat triangles between
#: them cut the curved surface short by about ``kappa e^2 / 8`` (curvature kappa, edge e),
#: which on clean fits was most of the mesh's error at 3 nodes a cell; at 5 the mesh of a
#: clean sphere fit is within about 1.3x of the fit's own distance to the sphere, for 5x
#: the meshing time of 3 (docs/performance.md, "Measurements behind the level-set and
#: plotting defaults"). Five a cell makes the default mesh of a 48^3 fit about 230 nodes a
#: side.
SAMPLES_PER_CELL = 5
#: Bounds of the default resolution (nodes along the longest side of the box). 256 keeps a
#: default mesh at a few hundred thousand triangles, meshed in a couple of seconds
#: (docs/performance.md); pass ``resolution`` for more.
MIN_RESOLUTION, MAX_RESOLUTION = 32, 256
#: Default lattice nodes per slab of [`mesh`][jurs.levelset.mesh]: 8 MiB of float64
#: values, which bounds the memory of a mesh; larger slabs mesh no faster
#: (docs/performance.md).
SLAB_NODES = 1 << 20
#: Lattice values closer to the level than this fraction of the largest value difference
#: along a lattice edge (estimated by ``_slope_bound``) are moved to that distance
#: above it. Marching cubes computes in float32: a node this close to the level would get
#: the vertices of all its crossing edges on itself (a vertex ``t`` of an edge from a node
#: at index ~1000 rounds onto it below t ~ 6e-5), and two such nodes in one cube, welded,
#: leave an edge shared by four faces (seen on spheres through lattice nodes). The shift
#: moves the surface by at most this fraction of a lattice spacing where g is steepest, and
#: the Newton steps take it back.
NUDGE = 1e-3
#: Default supplementary threshold: this many median nearest-neighbour spacings of the
#: data, and at least ``THRESHOLD_DIAGONAL`` of the data's bounding-box diagonal.
THRESHOLD_SPACINGS = 3.0
THRESHOLD_DIAGONAL = 0.01
#: Default number of mesh samples of
#: [`mesh_distances`][jurs.levelset.mesh_distances]: at least this many, and
#: ``SAMPLES_PER_REFERENCE`` per reference point, at most ``MAX_SAMPLES``.
MIN_SAMPLES, SAMPLES_PER_REFERENCE, MAX_SAMPLES = 10_000, 4, 1_000_000

_EMPTY = (np.empty((0, 3)), np.empty((0, 3), dtype=np.int64))


def _marching_cubes():
    try:
        from skimage.measure import marching_cubes
    except ImportError:
        raise ImportError('meshing needs scikit-image: pip install "jurs[surfaces]"') from None
    return marching_cubes


def lattice_axes(
    lower: Float[np.ndarray, " 3"], upper: Float[np.ndarray, " 3"], resolution: int
) -> list[Float[np.ndarray, " n"]]:
    """Lattice node coordinates over the box: ``resolution`` nodes along its longest side,
    about the same spacing along the others (at least 2 nodes). Returns three 1D arrays."""
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
        raise TypeError(f"resolution must be an int, got {resolution!r}")
    if int(resolution) < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    extent = upper - lower
    counts = np.maximum(2, np.round((int(resolution) - 1) * extent / extent.max()).astype(int) + 1)
    return [np.linspace(lo, hi, c) for lo, hi, c in zip(lower, upper, counts)]


def default_resolution(
    spline, lower: Float[np.ndarray, " 3"], upper: Float[np.ndarray, " 3"]
) -> int:
    """``SAMPLES_PER_CELL`` lattice nodes per spline cell (the finest axis's) along the
    longest side of the box, within [``MIN_RESOLUTION``, ``MAX_RESOLUTION``]."""
    control, _, s_lower, s_upper = spline_fields(spline, dims=(3,))
    cell = np.min((s_upper - s_lower) / (np.asarray(control.shape) - 3.0))
    nodes = int(np.ceil(SAMPLES_PER_CELL * np.max(upper - lower) / cell)) + 1
    return int(np.clip(nodes, MIN_RESOLUTION, MAX_RESOLUTION))


def mesh(
    spline,
    resolution: int | None = None,
    *,
    box=None,
    level: float = 0.0,
    newton_steps: int = 2,
    chunk: int = SLAB_NODES,
) -> tuple[Float[np.ndarray, "V 3"], Int[np.ndarray, "F 3"]]:
    """Triangle mesh of ``{g = level}`` of a 3D spline over ``box``.

    Args:
        spline: any object with fields ``control`` and ``weights`` (``(N, M, K)``, weights
            positive), ``lower`` and ``upper`` (``(3,)``), such as a 3D
            [`jurs.ImplicitSpline`][].
        resolution: lattice nodes along the longest side of the box (the other sides get
            the same spacing). Default: 5 per spline cell, between 32 and 256.
        box: ``(lower, upper)`` to mesh; default the spline's own box.
        level: the level set to mesh.
        newton_steps: Newton steps ``x <- x - (g - level) grad g / |grad g|^2`` per vertex
            after marching cubes. A step longer than one lattice spacing is not taken
            (near a critical point of g the linearisation says nothing; the vertex keeps
            its marching-cubes position).
        chunk: lattice nodes per slab (at least two planes of the first axis per slab).

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)``; every face's normal (right-hand
        rule) points towards ``g > level``, outward for a spline negative inside. Empty
        arrays when the level set misses the box. Where the surface leaves the box the mesh
        is open.

    Memory: g is never held on the whole lattice. One slab of at most
    ``max(chunk, 2 * ny * nz)`` nodes is evaluated, meshed and dropped at a time. Measured
    peak (tracemalloc): about 16 bytes per node of a slab (its values and the contraction
    intermediates) plus about 450 bytes per vertex of the mesh (the result itself takes 72:
    a vertex and about two faces; the rest is the slabs' marching-cubes output and the
    sort that welds it); at resolution 400 with 333 000 vertices, 140 MiB where the values
    of the whole lattice alone would take 490 MiB.
    """
    lower, upper = _box(spline, box)
    if resolution is None:
        resolution = default_resolution(spline, lower, upper)
    if int(newton_steps) < 0:
        raise ValueError(f"newton_steps must be >= 0, got {newton_steps}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    axes = lattice_axes(lower, upper, resolution)
    spacing = np.array([(a[-1] - a[0]) / (len(a) - 1) for a in axes])
    nudge = NUDGE * float(np.max(spacing * _slope_bound(spline)))
    vertices, faces = _march_in_slabs(spline, axes, float(level), nudge, int(chunk))
    if len(faces) == 0:
        return _EMPTY
    vertices = lower + vertices * spacing
    return _newton(spline, vertices, float(level), int(newton_steps), spacing.max()), faces


def _box(spline, box):
    """``(lower, upper)`` of the box to mesh as float64 ``(3,)`` arrays, checked."""
    _, _, s_lower, s_upper = spline_fields(spline, dims=(3,))
    if box is None:
        return s_lower, s_upper
    lower, upper = (np.asarray(b, dtype=np.float64) for b in box)
    if lower.shape != (3,) or upper.shape != (3,):
        raise ValueError(
            f"box must be (lower, upper) with 3 coordinates each, got shapes "
            f"{lower.shape} and {upper.shape}"
        )
    if not (np.isfinite(lower).all() and np.isfinite(upper).all() and (upper > lower).all()):
        raise ValueError(f"box must be finite with lower < upper, got {lower}, {upper}")
    return lower, upper


def _slope_bound(spline) -> np.ndarray:
    """A scale of ``|dg/dx_a|`` per axis: ``(max w / min w) max |C_(i+1) - C_i| / h_a``
    (for weights 1 a bound: the derivative is a quadratic spline with those coefficients)."""
    control, weights, lower, upper = spline_fields(spline, dims=(3,))
    h = (upper - lower) / (np.asarray(control.shape) - 3.0)
    steps = np.array([np.abs(np.diff(control, axis=a)).max() for a in range(3)])
    return weights.max() / weights.min() * steps / h


def _march_in_slabs(spline, axes, level: float, nudge: float, chunk: int):
    """Marching cubes over the lattice, slab by slab along the first axis; vertices in
    lattice index units.

    Consecutive slabs share one plane of nodes, evaluated once and handed on, so the
    vertices marching cubes puts on that plane come out bitwise equal in both slabs (the
    same values on the same edges); ``_weld`` merges them. Values within ``nudge`` of
    the level are set to ``level + nudge`` first (see ``NUDGE``).
    """
    marching_cubes = _marching_cubes()
    xs, ys, zs = axes
    planes = max(2, chunk // (len(ys) * len(zs)))
    vertex_parts, face_parts = [], []
    count = 0
    carried = None  # previous slab's last plane of values
    for start in range(0, len(xs) - 1, planes - 1):
        stop = min(start + planes, len(xs))  # nodes start .. stop - 1
        fresh = lattice_values(spline, (xs[start + (carried is not None) : stop], ys, zs))
        near = np.abs(fresh - level) < nudge
        fresh[near] = level + nudge
        values = fresh if carried is None else np.concatenate([carried, fresh])
        carried = values[-1:]
        if not values.min() <= level <= values.max():
            continue
        # "descent": scikit-image's default orientation, whose faces (right-hand rule) face
        # the larger values, i.e. g > level. It computes in float32.
        verts, tris, _, _ = marching_cubes(values, level, gradient_direction="descent")
        verts = verts.astype(np.float64)
        verts[:, 0] += start
        vertex_parts.append(verts)
        face_parts.append(tris.astype(np.int64) + count)
        count += len(verts)
    if not face_parts:
        return _EMPTY
    return _weld(np.concatenate(vertex_parts), np.concatenate(face_parts))


def _weld(vertices, faces):
    """Merge vertices at bitwise equal positions, drop the faces that collapse, and the
    vertices no face uses any more.

    Marching cubes puts one vertex on each lattice edge the level set crosses, so two
    vertices coincide as the same edge's vertex seen from two slabs, or (should the nudge
    of ``NUDGE`` fall short) at a node where g is at the level to float32, where every
    crossing edge has its vertex on the node and the triangles between them have no area.
    Merged, each point is one vertex.
    """
    vertices, inverse = np.unique(vertices, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    faces = faces[(faces != np.roll(faces, 1, axis=1)).all(axis=1)]
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[used], faces.reshape(-1, 3)


def _newton(spline, vertices, level: float, steps: int, longest: float):
    """``steps`` Newton steps onto ``{g = level}`` along the gradient, each no longer than
    ``longest`` (see [`mesh`][jurs.levelset.mesh]); points with a zero or non-finite
    gradient stay put."""
    x = vertices.copy()
    for _ in range(steps):
        value, gradient = values_and_gradients(spline, x)
        norm2 = np.sum(gradient * gradient, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            move = -((value - level) / norm2)[:, None] * gradient
        ok = np.isfinite(move).all(axis=1) & (np.sum(move * move, axis=1) <= longest**2)
        x[ok] += move[ok]
    return x


def _check_mesh(vertices, faces):
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
    return vertices, faces.astype(np.int64)


def face_areas(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"]
) -> Float[np.ndarray, " F"]:
    """Area of each triangle; ``(F,)``."""
    vertices, faces = _check_mesh(vertices, faces)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def mesh_components(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"]
) -> tuple[int, Int[np.ndarray, " F"]]:
    """Connected components of a triangle mesh (faces sharing a vertex are connected).

    Returns ``(count, labels)``: ``labels (F,)`` numbers each face's component from 0, the
    components ordered by face count, largest first (ties by first face).
    """
    vertices, faces = _check_mesh(vertices, faces)
    return _face_components(faces, len(vertices))


def _face_components(faces, num_vertices: int):
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


def _topology(faces, labels, count):
    """Per component: vertices, edges, faces and boundary edges (edges of one face);
    four ``(count,)`` int arrays."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edge_label = np.repeat(labels, 3)
    _, where, uses = np.unique(edges, axis=0, return_index=True, return_counts=True)
    owner = edge_label[where]
    vertex_owner = np.zeros(faces.max() + 1, dtype=np.int64)
    vertex_owner[faces.reshape(-1)] = np.repeat(labels, 3)
    used = np.zeros(faces.max() + 1, dtype=bool)
    used[faces.reshape(-1)] = True
    return (
        np.bincount(vertex_owner[used], minlength=count),
        np.bincount(owner, minlength=count),
        np.bincount(labels, minlength=count),
        np.bincount(owner[uses == 1], minlength=count),
    )


def genus(faces: Int[npt.ArrayLike, "F 3"]) -> int:
    """Genus of a closed, connected, orientable triangle mesh from its Euler characteristic
    ``V - E + F = 2 - 2 genus`` (V counts only the vertices the faces use).

    Raises ValueError for a mesh with boundary edges (open), more than one component, or
    an odd Euler characteristic (not an orientable closed surface).
    """
    faces = np.asarray(faces)
    if (
        faces.ndim != 2
        or faces.shape[1] != 3
        or len(faces) == 0
        or faces.min() < 0
        or not np.issubdtype(faces.dtype, np.integer)
    ):
        raise ValueError(
            f"faces must be a non-empty (F, 3) array of vertex indices, got "
            f"shape {faces.shape} {faces.dtype}"
        )
    faces = faces.astype(np.int64)
    count, labels = _face_components(faces, int(faces.max()) + 1)
    if count != 1:
        raise ValueError(f"genus needs one connected component, got {count}")
    v, e, f, boundary = (int(x[0]) for x in _topology(faces, labels, 1))
    if boundary:
        raise ValueError(f"genus needs a closed mesh; this one has {boundary} boundary edges")
    euler = v - e + f
    if euler % 2:
        raise ValueError(f"Euler characteristic {euler} is odd: not a closed orientable surface")
    return (2 - euler) // 2


@dataclasses.dataclass(frozen=True)
class MeshComponent:
    """One connected component of a mesh.

    Attributes:
        faces: indices of its faces in the mesh's face array.
        area: its surface area.
        closed: no boundary edge (every edge shared by two or more faces).
        genus: from the Euler characteristic for a closed component, None for an open one
            (or a closed one with an odd Euler characteristic: not an orientable surface).
        median_distance: area-weighted median of the distance from its face centroids to
            the nearest data point (NaN without data).
        supplementary: ``median_distance > threshold``: more than half of its area lies
            farther than the threshold from the data.
    """

    faces: np.ndarray
    area: float
    closed: bool
    genus: int | None
    median_distance: float
    supplementary: bool

    @property
    def num_faces(self) -> int:
        return len(self.faces)


@dataclasses.dataclass(frozen=True)
class MeshReport:
    """What [`analyze_mesh`][jurs.levelset.analyze_mesh] measured.

    Attributes:
        components: every [`MeshComponent`][jurs.levelset.MeshComponent],
            largest area first.
        threshold: the supplementary threshold (None without data points).
    """

    components: tuple
    threshold: float | None

    @property
    def num_components(self) -> int:
        return len(self.components)

    @property
    def supplementary(self) -> list:
        """The supplementary components."""
        return [c for c in self.components if c.supplementary]

    @property
    def total_area(self) -> float:
        return float(sum(c.area for c in self.components))

    @property
    def supplementary_area(self) -> float:
        return float(sum(c.area for c in self.supplementary))

    def as_dict(self) -> dict:
        """The summary numbers (JSON-ready): ``num_components``, ``num_closed``,
        ``num_supplementary``, ``total_area``, ``supplementary_area``, ``genera`` (per
        component, None for open ones) and ``threshold``."""
        return {
            "num_components": self.num_components,
            "num_closed": sum(c.closed for c in self.components),
            "num_supplementary": len(self.supplementary),
            "total_area": self.total_area,
            "supplementary_area": self.supplementary_area,
            "genera": [c.genus for c in self.components],
            "threshold": self.threshold,
        }


def default_threshold(points: Float[npt.ArrayLike, "m 3"]) -> float:
    """``THRESHOLD_SPACINGS`` median nearest-neighbour spacings of ``points``, and at
    least ``THRESHOLD_DIAGONAL`` of their bounding-box diagonal.

    A surface through the data lies, at most of its area, within a fraction of the spacing
    of the nearest point; the floor on the diagonal keeps dense clouds, finer than what a
    fit on a coarse grid follows, from flagging the surface itself.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        raise ValueError("the default threshold needs at least 2 data points; pass threshold")
    spacing = np.median(cKDTree(points).query(points, k=2)[0][:, 1])
    diagonal = np.linalg.norm(np.ptp(points, axis=0))
    return float(max(THRESHOLD_SPACINGS * spacing, THRESHOLD_DIAGONAL * diagonal))


def analyze_mesh(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    points: Float[npt.ArrayLike, "m 3"] | None = None,
    *,
    threshold: float | None = None,
) -> MeshReport:
    """Components of a mesh and, given the data ``points (m, 3)``, which are supplementary.

    Args:
        vertices, faces: the mesh (as from [`mesh`][jurs.levelset.mesh]).
        points: the data the surface was fitted to; without them no distances are measured
            and nothing is supplementary.
        threshold: distance beyond which a component is supplementary (its area-weighted
            median distance to the data exceeds it); default ``default_threshold``.
            Unused without ``points``.

    Returns:
        [`MeshReport`][jurs.levelset.MeshReport].
    """
    vertices, faces = _check_mesh(vertices, faces)
    if points is not None:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise ValueError(f"points must have shape (m, 3) with m >= 1, got {points.shape}")
        threshold = default_threshold(points) if threshold is None else float(threshold)
        if not threshold > 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
    if len(faces) == 0:
        return MeshReport((), threshold if points is not None else None)
    count, labels = _face_components(faces, len(vertices))
    num_v, num_e, num_f, boundary = _topology(faces, labels, count)
    area = face_areas(vertices, faces)
    component_area = np.bincount(labels, weights=area, minlength=count)
    median = np.full(count, np.nan)
    if points is not None:
        distance = cKDTree(points).query(vertices[faces].mean(axis=1))[0]
        median = _weighted_medians(distance, area, labels, component_area)
    euler = num_v - num_e + num_f
    order = np.argsort(-component_area, kind="stable")
    face_order = np.argsort(labels, kind="stable")
    split = np.split(face_order, np.cumsum(num_f)[:-1])
    components = tuple(
        MeshComponent(
            faces=split[c],
            area=float(component_area[c]),
            closed=bool(boundary[c] == 0),
            genus=int((2 - euler[c]) // 2) if boundary[c] == 0 and euler[c] % 2 == 0 else None,
            median_distance=float(median[c]),
            supplementary=bool(points is not None and median[c] > threshold),
        )
        for c in order
    )
    return MeshReport(components, threshold if points is not None else None)


def _weighted_medians(values, weights, labels, totals):
    """Per label, the smallest value at which the cumulative weight of that label's values
    (ascending) reaches half its total."""
    order = np.lexsort((values, labels))
    label, weight = labels[order], weights[order]
    before = (np.cumsum(totals) - totals)[label]  # weight of the labels sorted earlier
    reached = np.cumsum(weight) - before >= 0.5 * totals[label]
    hits = np.flatnonzero(reached)
    first = hits[np.unique(label[hits], return_index=True)[1]]
    out = np.full(len(totals), np.nan)
    out[label[first]] = values[order][first]
    return out


def mesh_distances(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    reference_points: Float[npt.ArrayLike, "m 3"],
    reference_normals: Float[npt.ArrayLike, "m 3"] | None = None,
    *,
    samples: int | None = None,
    seed: int = 0,
) -> dict:
    """Chamfer and Hausdorff distances and normal consistency between a mesh and a
    reference cloud.

    The mesh is sampled by area (``samples`` points, default 4 per reference point, between
    10 000 and 1 000 000; reproducible by ``seed``). With ``Z`` the samples, ``Y`` the
    reference points and ``d(a, B) = min_b |a - b|``, as [`jurs.levelset.chamfer_hausdorff`][]
    defines them in 2D:

    * ``chamfer = (mean_{z in Z} d(z, Y) + mean_{y in Y} d(y, Z)) / 2`` (mean of unsquared
      distances, symmetric);
    * ``hausdorff = max(max_z d(z, Y), max_y d(y, Z))``;
    * ``normal_consistency``: mean over the samples of ``|cos|`` of the angle between the
      sampled face's normal and the normal of the nearest reference point (1 for parallel
      normals; orientation is not compared). NaN without ``reference_normals``.

    Both distances have a floor of about half the spacing of the sparser of ``Z`` and ``Y``
    (point sets, not surfaces, are compared). An empty mesh (or one without area) gives
    ``inf`` distances and NaN consistency.

    Returns:
        ``{"chamfer", "hausdorff", "normal_consistency", "samples"}``.
    """
    vertices, faces = _check_mesh(vertices, faces)
    reference = np.asarray(reference_points, dtype=np.float64)
    if reference.ndim != 2 or reference.shape[1] != 3 or len(reference) == 0:
        raise ValueError(
            f"reference_points must have shape (m, 3) with m >= 1, got {reference.shape}"
        )
    if reference_normals is not None:
        reference_normals = np.asarray(reference_normals, dtype=np.float64)
        if reference_normals.shape != reference.shape:
            raise ValueError(
                f"reference_normals must have the shape of reference_points "
                f"{reference.shape}, got {reference_normals.shape}"
            )
    if samples is None:
        samples = int(np.clip(SAMPLES_PER_REFERENCE * len(reference), MIN_SAMPLES, MAX_SAMPLES))
    if int(samples) < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if len(faces) == 0 or not face_areas(vertices, faces).sum() > 0:
        return {
            "chamfer": float("inf"),
            "hausdorff": float("inf"),
            "normal_consistency": float("nan"),
            "samples": 0,
        }
    z, z_normals = sample_mesh(vertices, faces, int(samples), seed=seed)
    d_zy, nearest = cKDTree(reference).query(z)
    d_yz = cKDTree(z).query(reference)[0]
    consistency = float("nan")
    if reference_normals is not None:
        n = reference_normals[nearest]
        length = np.linalg.norm(n, axis=1)
        if not (length > 0).all():
            raise ValueError("reference_normals has zero-length normals")
        consistency = float(np.mean(np.abs(np.sum(z_normals * n, axis=1)) / length))
    return {
        "chamfer": float(0.5 * (d_zy.mean() + d_yz.mean())),
        "hausdorff": float(max(d_zy.max(), d_yz.max())),
        "normal_consistency": consistency,
        "samples": int(samples),
    }
