"""What to measure on a triangle mesh of a 3D spline's zero set.

[`analyze_mesh`][jurs.levelset.analyze_mesh] splits a mesh into connected components and
measures each (area, closed or open, genus, distance to the data), flagging the supplementary
ones ("bubbles" away from the data); [`mesh_distances`][jurs.levelset.mesh_distances] compares
a mesh with a reference cloud (Chamfer, Hausdorff, normal consistency). The meshes come from
[`mesh`][jurs.levelset.mesh] (``jurs/levelset/_meshing.py``). Everything is host-side
NumPy/SciPy; see docs/surfaces.md for the definitions.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from .._cloud.carried import (
    MIN_CARRIED_FRACTION,
    SHELL_EDGES,
    carried_samples,
    surface_shells,
)
from .._solution.verdicts import describe_shell
from ..datasets import sample_mesh
from ._faces import boundary_edges, check_mesh, face_areas, face_components
from ._trimming import DEFAULT_TRIM, UNSUPPORTED_FRACTION, Support, check_points

#: Default supplementary threshold: this many median nearest-neighbour spacings of the
#: data, and at least ``THRESHOLD_DIAGONAL`` of the data's bounding-box diagonal.
THRESHOLD_SPACINGS = 3.0
THRESHOLD_DIAGONAL = 0.01
#: Default number of mesh samples of
#: [`mesh_distances`][jurs.levelset.mesh_distances]: at least this many, and
#: ``SAMPLES_PER_REFERENCE`` per reference point, at most ``MAX_SAMPLES``.
MIN_SAMPLES, SAMPLES_PER_REFERENCE, MAX_SAMPLES = 10_000, 4, 1_000_000


def _check_points(points, name: str, minimum: int = 1) -> np.ndarray:
    """``points`` as float64 ``(m, 3)``, m >= ``minimum``, finite; ValueError naming ``name``."""
    return check_points(points, 3, name, minimum)


def clean_faces(faces: Int[np.ndarray, "F 3"]) -> tuple[Int[np.ndarray, " K"], tuple[str, ...]]:
    """``(kept, notes)``: the indices of the faces that make a mesh's surface, ascending,
    and a note for each kind dropped. Dropped are faces that name one vertex twice (no
    triangle: an edge or a point) and every repeat of a face already seen, in either
    orientation (the same three vertices). Either kind counts its edges and its face again
    in the Euler characteristic, so left in it gives a false genus (a sphere's faces given
    twice read as genus -n) and false boundary or non-manifold edges."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return np.arange(0), ()
    proper = (
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    )
    notes = []
    if not proper.all():
        notes.append(f"dropped {int(np.sum(~proper))} degenerate faces (a vertex named twice)")
    candidates = np.flatnonzero(proper)
    _, first = np.unique(np.sort(faces[candidates], axis=1), axis=0, return_index=True)
    kept = np.sort(candidates[first])
    if len(kept) < len(candidates):
        notes.append(f"dropped {len(candidates) - len(kept)} duplicated faces (a repeat of a face)")
    return kept, tuple(notes)


def mesh_components(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"]
) -> tuple[int, Int[np.ndarray, " F"]]:
    """Connected components of a triangle mesh (faces sharing a vertex are connected).

    Returns ``(count, labels)``: ``labels (F,)`` numbers each face's component from 0, the
    components ordered by face count, largest first (ties by first face).
    """
    vertices, faces = check_mesh(vertices, faces)
    return face_components(faces, len(vertices))


def boundary_loops(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"]
) -> tuple[Int[np.ndarray, " L"], Float[np.ndarray, " L"]]:
    """The boundary loops of a triangle mesh: ``(component, length)``, one entry per
    loop, longest first. ``component`` numbers the mesh component (as
    [`mesh_components`][jurs.levelset.mesh_components]) the loop bounds.

    A boundary edge is an edge of one face; a *loop* is a connected set of boundary edges
    (edges sharing a vertex), its length the sum of theirs. On a manifold mesh each is a
    closed polyline, the rim of a hole or of an open surface; two rims that touch at a
    vertex count as one loop. Degenerate and repeated faces are left out first
    (``clean_faces``).
    """
    vertices, faces = check_mesh(vertices, faces)
    faces = faces[clean_faces(faces)[0]]
    if len(faces) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0)
    _, labels = face_components(faces, len(vertices))
    return _loops(vertices, faces, labels)


def _loops(vertices, faces, labels):
    """[`boundary_loops`][jurs.levelset.boundary_loops] of checked, cleaned faces with
    their component ``labels``."""
    edges, owner = boundary_edges(faces, labels)
    if len(edges) == 0:
        return np.empty(0, dtype=np.int64), np.empty(0)
    n = len(vertices)
    graph = sparse.coo_matrix(
        (np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n)
    )
    _, vertex_loop = csgraph.connected_components(graph, directed=False)
    loop = np.unique(vertex_loop[edges[:, 0]], return_inverse=True)[1].reshape(-1)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    lengths = np.bincount(loop, weights=length)
    components = np.zeros(len(lengths), dtype=np.int64)
    components[loop] = owner
    order = np.argsort(-lengths, kind="stable")
    return components[order], lengths[order]


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

    Degenerate and duplicated faces are left out first (``clean_faces``). Raises
    ValueError for a mesh with boundary edges (open), more than one component, or an odd
    Euler characteristic (not an orientable closed surface).
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
    faces = faces[clean_faces(faces)[0]]
    if len(faces) == 0:
        raise ValueError("faces holds no proper triangle (every face names a vertex twice)")
    count, labels = face_components(faces, int(faces.max()) + 1)
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
            farther than the threshold from the data; or, for a closed component,
            ``carried_fraction`` below ``MIN_CARRIED_FRACTION`` (a half): a bubble the data
            do not account for, also beside them (a closed bubble inside a CAD part's
            solid, near both its faces, read 0 supplementary before); or a closed shell
            lying on another component (``jurs._cloud.carried.surface_shells``: most of
            its area within four of its longest edges of another component), which the
            data beside it seem to carry: g dips across the surface and back there, over
            a tunnel or pit narrower than a cell that the fit filled in, and ``notes``
            names its place.
        boundary_lengths: the length of each of its boundary loops, longest first
            (empty for a closed component); see
            [`boundary_loops`][jurs.levelset.boundary_loops].
        carried_fraction: the share of its area (at face centroids) whose nearest data
            point lies within the threshold and nearer to this component than to any
            other (``jurs._cloud.carried.carried_samples``); NaN without data.
    """

    faces: np.ndarray
    area: float
    closed: bool
    genus: int | None
    median_distance: float
    supplementary: bool
    boundary_lengths: tuple = ()
    carried_fraction: float = float("nan")

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def num_boundary_loops(self) -> int:
        return len(self.boundary_lengths)

    @property
    def boundary_length(self) -> float:
        return float(sum(self.boundary_lengths))


@dataclasses.dataclass(frozen=True)
class MeshReport:
    """What [`analyze_mesh`][jurs.levelset.analyze_mesh] measured.

    Attributes:
        components: every [`MeshComponent`][jurs.levelset.MeshComponent],
            largest area first.
        threshold: the supplementary threshold (None without data points).
        notes: what was dropped from the input before measuring (degenerate and
            duplicated faces, ``clean_faces``), and a note when most of the surface is
            unsupported (below), in words; empty for a clean, supported mesh.
        unsupported_fraction: the fraction of the area farther than ``DEFAULT_TRIM``
            (2.5) local spacings from the data (the rule of
            [`trim_mesh`][jurs.levelset.trim_mesh]), measured at face centroids; None
            without data points. Above ``UNSUPPORTED_FRACTION`` (a half) most of the
            surface runs on where there are no data, as an untrimmed fit of an open scan
            does, and ``notes`` says so.
    """

    components: tuple
    threshold: float | None
    notes: tuple = ()
    unsupported_fraction: float | None = None

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

    @property
    def num_boundary_loops(self) -> int:
        """Boundary loops of all components together."""
        return sum(c.num_boundary_loops for c in self.components)

    @property
    def boundary_length(self) -> float:
        """Length of all boundary loops together."""
        return float(sum(c.boundary_length for c in self.components))

    @property
    def mostly_unsupported(self) -> bool:
        """More than ``UNSUPPORTED_FRACTION`` of the area lies away from the data."""
        return self.unsupported_fraction is not None and (
            self.unsupported_fraction > UNSUPPORTED_FRACTION
        )

    def as_dict(self) -> dict:
        """The summary numbers (JSON-ready): ``num_components``, ``num_closed``,
        ``num_supplementary``, ``total_area``, ``supplementary_area``, ``genera`` (per
        component, None for open ones), ``num_boundary_loops`` and ``boundary_length``
        (in total), ``boundary_loops`` and ``boundary_lengths`` (per component: the
        count, and the length of each loop), ``unsupported_fraction``, ``threshold`` and
        ``notes``."""
        return {
            "num_components": self.num_components,
            "num_closed": sum(c.closed for c in self.components),
            "num_supplementary": len(self.supplementary),
            "total_area": self.total_area,
            "supplementary_area": self.supplementary_area,
            "genera": [c.genus for c in self.components],
            "num_boundary_loops": self.num_boundary_loops,
            "boundary_length": self.boundary_length,
            "boundary_loops": [c.num_boundary_loops for c in self.components],
            "boundary_lengths": [list(c.boundary_lengths) for c in self.components],
            "unsupported_fraction": self.unsupported_fraction,
            "threshold": self.threshold,
            "notes": list(self.notes),
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
        [`MeshReport`][jurs.levelset.MeshReport]. Each component's ``faces`` index the
        ``faces`` given. Each component carries its boundary loops (count and lengths).
        With ``points``, the report's ``unsupported_fraction`` is the share of the area
        farther than ``DEFAULT_TRIM`` local spacings from the data; above a half,
        ``notes`` says that most of the surface is unsupported and suggests trimming
        ([`mesh`][jurs.levelset.mesh]'s ``trim``, ``jurs fit --trim``). Closed fits
        are judged by ``supplementary`` as before; the note only flags open ones.

    Input: vertices must be finite and faces must index them (ValueError otherwise, as
    for non-finite ``points``). Faces that name a vertex twice and repeats of a face (the
    same three vertices, in either orientation) are dropped before anything is measured,
    and ``MeshReport.notes`` says how many: they add no surface, and counted they made
    the genus false (a mesh with every face given twice read as genus -n).
    """
    vertices, faces = check_mesh(vertices, faces)
    if points is not None:
        points = _check_points(points, "points")
        threshold = default_threshold(points) if threshold is None else float(threshold)
        if not threshold > 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
    kept, notes = clean_faces(faces)
    faces = faces[kept]
    if len(faces) == 0:
        return MeshReport((), threshold if points is not None else None, notes)
    count, labels = face_components(faces, len(vertices))
    num_v, num_e, num_f, boundary = _topology(faces, labels, count)
    area = face_areas(vertices, faces)
    component_area = np.bincount(labels, weights=area, minlength=count)
    median, share = np.full(count, np.nan), np.full(count, np.nan)
    unsupported = None
    if points is not None:
        assert threshold is not None  # set above with the points
        centroids = vertices[faces].mean(axis=1)
        # Each face's longest edge: the step of the lattice it was marched on, below which
        # a pinch splits the surface into pieces side by side (carried_samples).
        corners = vertices[faces]
        edge = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
        data = cKDTree(points)
        distance, carried = carried_samples(centroids, labels, data, threshold, edge)
        median = _weighted_medians(distance, area, labels, component_area)
        carried_area = np.bincount(labels, weights=area * carried, minlength=count)
        share = carried_area / np.maximum(component_area, 1e-300)
        unsupported = _unsupported_fraction(points, centroids, area)
        if unsupported is not None and unsupported > UNSUPPORTED_FRACTION:
            notes = (
                *notes,
                f"most of the surface is unsupported: {100 * unsupported:.0f} % of its area "
                f"lies farther than {DEFAULT_TRIM:g} local point spacings from the data, as "
                "where an open scan was fitted; trim the mesh to the data "
                "(levelset.mesh(..., points=, trim=True), jurs fit --trim)",
            )
        # A shell on the surface: the carried rule lets it by, the data beside it
        # being carried within a step; it marks a feature the fit did not resolve.
        shells = surface_shells(
            centroids, labels, boundary == 0, SHELL_EDGES * edge, weights=area, tree=data
        )
        extent = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        for c in np.flatnonzero(shells):
            mine = labels == c
            box = vertices[faces[mine].ravel()]
            centre = np.average(centroids[mine], axis=0, weights=area[mine])
            shell = describe_shell(centre, box.min(axis=0), box.max(axis=0), extent)
            notes = (*notes, f"{shell} (marked supplementary)")
    else:
        shells = np.zeros(count, bool)
    loop_owner, loop_length = _loops(vertices, faces, labels)
    euler = num_v - num_e + num_f
    order = np.argsort(-component_area, kind="stable")
    face_order = np.argsort(labels, kind="stable")
    split = np.split(face_order, np.cumsum(num_f)[:-1])
    components = tuple(
        MeshComponent(
            faces=kept[split[c]],
            area=float(component_area[c]),
            closed=bool(boundary[c] == 0),
            genus=int((2 - euler[c]) // 2) if boundary[c] == 0 and euler[c] % 2 == 0 else None,
            median_distance=float(median[c]),
            supplementary=bool(
                points is not None
                and (
                    median[c] > threshold
                    or (boundary[c] == 0 and share[c] < MIN_CARRIED_FRACTION)
                    or shells[c]
                )
            ),
            boundary_lengths=tuple(float(x) for x in loop_length[loop_owner == c]),
            carried_fraction=float(share[c]),
        )
        for c in order
    )
    return MeshReport(components, threshold if points is not None else None, notes, unsupported)


def _unsupported_fraction(points, centroids, area) -> float | None:
    """The share of ``area`` whose centroids lie farther than ``DEFAULT_TRIM`` local
    spacings from ``points``; None where the spacing cannot be measured (fewer than 2
    distinct points) or the mesh has no area."""
    total = float(area.sum())
    if not total > 0 or len(np.unique(points, axis=0)) < 2:
        return None
    far = Support(points).spacings(centroids) > DEFAULT_TRIM
    return float(area[far].sum() / total)


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
    ``inf`` distances and NaN consistency. The input is checked as by
    [`analyze_mesh`][jurs.levelset.analyze_mesh] (degenerate and repeated faces are left
    out: a face given twice would be sampled twice as often).

    Returns:
        ``{"chamfer", "hausdorff", "normal_consistency", "samples"}``.
    """
    vertices, faces = check_mesh(vertices, faces)
    faces = faces[clean_faces(faces)[0]]  # a repeated face would be sampled twice as often
    reference = _check_points(reference_points, "reference_points")
    if reference_normals is not None:
        reference_normals = np.asarray(reference_normals, dtype=np.float64)
        if reference_normals.shape != reference.shape:
            raise ValueError(
                f"reference_normals must have the shape of reference_points "
                f"{reference.shape}, got {reference_normals.shape}"
            )
        if not np.isfinite(reference_normals).all():
            raise ValueError("reference_normals must be finite")
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
