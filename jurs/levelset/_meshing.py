"""Triangle meshes of the zero set of a 3D spline.

[`mesh`][jurs.levelset.mesh] samples g on a lattice slab by slab
(``jurs._model.lattice.lattice_values``), runs marching cubes (scikit-image) on each slab,
stitches the slabs and moves the vertices onto {g = 0} by Newton steps; with a face budget
(``faces=``) fast-simplification decimates the mesh and the same Newton steps put the kept
vertices back on {g = 0}. An adaptive spline
([`jurs.AdaptiveSpline`][]) is marched only in the blocks of the lattice where g may reach
the level (``jurs/_model/band.py``; docs/design.md section 8). What to measure on
a mesh (components, genus, distances) is in ``jurs/levelset/_mesh_analysis.py``. Everything
is host-side NumPy/SciPy; see docs/surfaces.md for the definitions.
"""

from __future__ import annotations

import functools

import numpy as np
from jaxtyping import Float, Int

from .._model.adaptive import AdaptiveSpline, finest_slope_bound
from .._model.band import BATCH_BLOCKS, BLOCK_CELLS, BandPlan, BlockGrid, plan_band
from .._model.function import AbstractSpline
from .._model.lattice import FinestSpline, lattice_values
from .._model.spline import grid_spline
from .._problem.memory import check_memory
from ._trimming import Support, check_points, check_rim, check_trim, near_support, trim_to_support

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
#: The same for an adaptive spline, per finest cell, where the mesh is not trimmed. Its
#: finest cells are chosen from the data (three point spacings on a surface), narrow beside
#: the shape's curvature, so the flat triangles' error is far below the fit's at fewer
#: nodes: on four 1e5-point clouds, 2.5 nodes a finest cell gave the Chamfer distance of 5
#: within 2 % and the Hausdorff within 3 %, with a quarter of the faces. A trimmed mesh
#: keeps ``SAMPLES_PER_CELL``: the trim clips along the faces, and at 2.5 a scan's rim
#: left up to 5.3 spacings of surface past the data instead of 4.1 (docs/performance.md,
#: "A hierarchy's default mesh").
ADAPTIVE_SAMPLES_PER_CELL = 2.5
#: Bounds of the default resolution (nodes along the longest side of the box). 256 keeps a
#: default mesh at a few hundred thousand triangles, quick to mesh (docs/performance.md,
#: "Mesh lattice density"); pass ``resolution`` for more.
MIN_RESOLUTION, MAX_RESOLUTION = 32, 256
#: Bound of the default resolution of an adaptive spline, whose mesh marches only the
#: blocks where g may reach the level (``jurs._model.band``): 2.5 nodes a finest cell
#: up to a 1025^3-equivalent lattice, within ``max_nodes`` of marched nodes.
MAX_ADAPTIVE_RESOLUTION = 1025
#: Default lattice nodes per slab of [`mesh`][jurs.levelset.mesh]: 8 MiB of float64
#: values, which bounds the memory of a mesh; larger slabs mesh no faster
#: (docs/performance.md).
SLAB_NODES = 1 << 20
#: Lattice values closer to the level than this fraction of the largest value difference
#: along a lattice edge (estimated by ``AbstractSpline.slope_bound``) are moved to that distance
#: above it. Marching cubes computes in float32: a node this close to the level would get
#: the vertices of all its crossing edges on itself (a vertex ``t`` of an edge from a node
#: at index ~1000 rounds onto it below t ~ 6e-5), and two such nodes in one cube, welded,
#: leave an edge shared by four faces (seen on spheres through lattice nodes). The shift
#: moves the surface by at most this fraction of a lattice spacing where g is steepest, and
#: the Newton steps take it back.
NUDGE = 1e-3
#: Lattice nodes a mesh samples at most unless ``max_nodes`` says otherwise: 2^27, a
#: lattice of 512^3, eight times the default cap's nodes. The time grows with the
#: cube of the resolution while the memory (bounded by the slabs) grows with its square, so
#: a resolution of 1200-2000 fits in memory and runs for many minutes; it is refused in
#: milliseconds instead (docs/robustness.md, "Meshing").
MAX_NODES = 1 << 27
#: Lattice nodes meshed a second, for the estimate in the refusal's message: measured on
#: the default cap's 256^3 lattice (docs/performance.md, "Mesh lattice density").
NODES_PER_SECOND = 1e7
#: Peak bytes per lattice node of a slab, and per vertex of the mesh (measured about 16
#: and 450: see [`mesh`][jurs.levelset.mesh], *Memory*), and the vertices a mesh has per
#: node of a lattice plane (resolution^2) assumed by the memory estimate: a sphere filling
#: its box has about 2 (docs/surfaces.md, "Meshing a spline"); four times that leaves room
#: for folded surfaces.
BYTES_PER_SLAB_NODE, BYTES_PER_VERTEX, VERTICES_PER_PLANE_NODE = 16, 450, 8
#: Fewest faces a face budget may ask for: a closed surface needs four (a tetrahedron).
MIN_FACES = 4
#: Longest side of the box a mesh is scaled into before fast-simplification decimates it.
#: The library collapses edges in up to 100 passes, each taking the edges whose quadric
#: error (a sum of squared distances to the planes of the faces merged into a vertex) is
#: under ``1e-9 (pass + 3)^7``: an absolute schedule, so the result depends on the
#: mesh's units. Measured on an icosphere of 82 000 faces: scaled into a box of side 1,
#: its vertices ended up to 2.2 % of the radius off the sphere at 500 faces; of side 10,
#: 0.9 % (equal at 5000 faces and more); of side 1e4, the target was not reached (1056
#: faces for 500). At 1.3 M faces even side 10 stops short of the smallest budgets (24
#: faces for 8), so a result above the budget is decimated once more in a box of side 1.
DECIMATION_BOX = 10.0

_EMPTY = (np.empty((0, 3)), np.empty((0, 3), dtype=np.int64))


def skimage_marching_cubes():
    try:
        from skimage.measure import marching_cubes
    except ImportError:
        raise ImportError(
            "meshing needs scikit-image: from the jurs checkout, pip install -e '.[surfaces]'"
        ) from None
    return marching_cubes


def fast_simplification_simplify():
    """fast-simplification's ``simplify``, imported when a face budget is asked for."""
    try:
        from fast_simplification import simplify
    except ImportError:
        raise ImportError(
            "mesh(..., faces=) decimates with fast-simplification: from the jurs checkout, "
            "pip install -e '.[surfaces]'"
        ) from None
    return simplify


def check_faces(faces) -> int | None:
    """``faces`` (a face budget of [`mesh`][jurs.levelset.mesh]) as an int, or None; a
    ValueError for anything but None or an integer >= ``MIN_FACES``."""
    if faces is None:
        return None
    if isinstance(faces, bool) or not isinstance(faces, (int, np.integer)):
        raise ValueError(f"faces must be an integer (a face count) or None, got {faces!r}")
    if int(faces) < MIN_FACES:
        raise ValueError(
            f"faces must be at least {MIN_FACES} (a closed surface has at least 4), got {faces}"
        )
    return int(faces)


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
    spline, lower: Float[np.ndarray, " 3"], upper: Float[np.ndarray, " 3"], trimmed: bool = False
) -> int:
    """``SAMPLES_PER_CELL`` lattice nodes per spline cell (the finest axis's) along the
    longest side of the box, within [``MIN_RESOLUTION``, ``MAX_RESOLUTION``]; for an
    adaptive spline, per *finest* cell (``ADAPTIVE_SAMPLES_PER_CELL``, or
    ``SAMPLES_PER_CELL`` for a ``trimmed`` mesh) within [``MIN_RESOLUTION``,
    ``MAX_ADAPTIVE_RESOLUTION``] (only the band is marched, and
    [`mesh`][jurs.levelset.mesh] lowers it further when the marched nodes exceed
    ``max_nodes``)."""
    spline = grid_spline(spline, dims=(3,))
    cell = float(np.min(spline.cell_widths))
    per_cell, largest = _default_density(spline, trimmed)
    nodes = int(np.ceil(per_cell * np.max(upper - lower) / cell)) + 1
    return int(np.clip(nodes, MIN_RESOLUTION, largest))


@functools.singledispatch
def _default_density(spline: AbstractSpline, trimmed: bool) -> tuple[float, int]:
    """``(nodes per cell, largest resolution)`` of the default lattice: the whole lattice
    is marched."""
    return SAMPLES_PER_CELL, MAX_RESOLUTION


@_default_density.register
def _(spline: AdaptiveSpline, trimmed: bool) -> tuple[float, int]:
    # Only the band is marched (and mesh lowers the resolution to fit max_nodes).
    per_cell = SAMPLES_PER_CELL if trimmed else ADAPTIVE_SAMPLES_PER_CELL
    return per_cell, MAX_ADAPTIVE_RESOLUTION


def mesh(
    spline,
    resolution: int | None = None,
    *,
    box=None,
    level: float = 0.0,
    newton_steps: int = 2,
    chunk: int = SLAB_NODES,
    max_nodes: int | None = MAX_NODES,
    points: Float[np.ndarray, "m 3"] | None = None,
    trim: float | bool | None = None,
    rim: float | bool | None = True,
    faces: int | None = None,
) -> tuple[Float[np.ndarray, "V 3"], Int[np.ndarray, "F 3"]]:
    """Triangle mesh of ``{g = level}`` of a 3D spline over ``box``.

    Args:
        spline: any object with fields ``control`` and ``weights`` (``(N, M, K)``, weights
            positive), ``lower`` and ``upper`` (``(3,)``), such as a 3D
            [`jurs.ImplicitSpline`][]; or a 3D [`jurs.AdaptiveSpline`][], which is
            marched only in the blocks of ``BLOCK_CELLS`` (16) lattice cells where g may
            reach the level (over the finest cells, or where the convex hull of its
            coefficients straddles the level: surface far from the data is meshed too).
            The result is the full lattice's mesh at the same resolution, bit for bit,
            without evaluating the full lattice.
        resolution: lattice nodes along the longest side of the box (the other sides get
            the same spacing). Default: 5 per spline cell, between 32 and 256; for an
            adaptive spline 2.5 per finest cell (5 when trimmed), between 32 and 1025,
            lowered until the marched nodes fit in ``max_nodes``.
        box: ``(lower, upper)`` to mesh; default the spline's own box.
        level: the level set to mesh.
        newton_steps: Newton steps ``x <- x - (g - level) grad g / |grad g|^2`` per vertex
            after marching cubes. A step longer than one lattice spacing is not taken
            (near a critical point of g the linearisation says nothing; the vertex keeps
            its marching-cubes position).
        chunk: lattice nodes per slab (at least two planes of the first axis per slab).
            It bounds memory only: the mesh is the same, bit for bit, for any ``chunk``
            (``_march_in_slabs``). An adaptive spline's blocks do not use it.
        max_nodes: lattice nodes above which the mesh is refused before any is sampled
            (default ``MAX_NODES``, 2^27: a 512^3 lattice); None, or a larger
            number, meshes anyway. For an adaptive spline the nodes counted are those of
            the marched blocks. The memory is checked too, against the host's
            available memory, and that check cannot be lifted.
        points: ``(m, 3)`` data points the spline was fitted to; needed by ``trim``,
            unused without it.
        trim: keep only the surface the data support (an open scan): None (default) or
            False meshes the whole zero set over the box; a positive number keeps the
            part within that many local spacings of the data amid the samples (across
            the gaps random samples leave); True keeps ``DEFAULT_TRIM`` (2.5) spacings.
            A sample's local spacing is ``1 / sqrt(density)`` around it, from the
            distance to its 8th nearest neighbour (the median over it and those
            neighbours), and a point's distance is measured to its nearest sample in
            that sample's spacings. Faces that cross the trim are clipped at it (not
            dropped whole), so the boundary of the result is a clean polyline following
            the data's rim; the rule and its measurements:
            [`trim_mesh`][jurs.levelset.trim_mesh] and docs/surfaces.md, "Open scans".
        rim: with ``trim``, the spacings the surface may run past the data's rim,
            where the samples lie to one side of it: True (default) ``DEFAULT_RIM``
            (1), a number >= 0 that many (at most ``trim``), None or False the
            distance rule alone (``trim`` spacings everywhere). See
            [`trim_mesh`][jurs.levelset.trim_mesh].
        faces: a face budget: None (default) keeps every face marching cubes gives (about
            two a vertex; 1.19 M on a default fit of the 1e5-point bunny); an integer >=
            ``MIN_FACES`` (4) decimates the mesh (after any trim) to that many faces, and
            then the same ``newton_steps`` move its vertices back onto the level set, each
            step no longer than the vertex's longest edge (or a lattice spacing, where
            that is longer). A mesh with no more faces is returned as it is. The
            decimation is fast-simplification's (pyvista's wrapper of Fast Quadric Mesh
            Simplification, the library trimesh's ``simplify_quadric_decimation`` calls;
            optional extra ``surfaces``), chosen because its quadric error metric
            collapses first the edges whose removal moves the surface least, so the faces
            that remain go where it curves and flat parts take few; it keeps the faces'
            orientation (a collapse that would turn a face over is not made); and it is a
            small compiled wheel taking and returning NumPy arrays. It stops at ``faces``
            faces (or one fewer), or short of them where no collapse is left that keeps
            every face's orientation, so the result can have more faces than asked on a
            small budget: an edge from an open mesh's boundary inwards is never collapsed
            (the boundary itself is decimated, along itself), so a trimmed mesh keeps a
            ring of faces along its rim. The library stops on a face count, not on a
            distance, so there is no error tolerance to ask for; the distances measured
            at several budgets are in docs/surfaces.md, "Face budgets".

    Raises:
        ValueError: a spline with non-finite control points or weights, a weight <= 0
            (g = sum w C B / sum w B is then undefined or changes meaning where the
            denominator vanishes), or one whose control points all equal ``level`` (g is
            that level everywhere: its level set is the whole box, not a surface); a
            lattice of more than ``max_nodes`` nodes (the message gives the estimated time
            and memory) or one whose estimated memory exceeds what is available; a
            ``trim`` that is not positive and finite, or given without ``points``; a
            ``rim`` that is negative or not finite;
            ``points`` not ``(m, 3)``, not finite, or with fewer than 2 distinct rows;
            ``faces`` not None nor an integer >= 4 (before anything is sampled).
        ImportError: ``faces`` given without fast-simplification installed (before
            anything is sampled).

    Returns:
        ``(vertices (V, 3) float64, faces (F, 3) int64)``; every face's normal (right-hand
        rule) points towards ``g > level``, outward for a spline negative inside. Empty
        arrays when the level set misses the box (or, trimmed, lies wholly away from the
        data). Where the surface leaves the box, or is trimmed, the mesh is open.

    Memory: g is never held on the whole lattice. One slab of at most
    ``max(chunk, 2 * ny * nz)`` nodes is evaluated, meshed and dropped at a time. Measured
    peak (tracemalloc): about 16 bytes per node of a slab (its values and the contraction
    intermediates) plus about 450 bytes per vertex of the mesh (the result itself takes 72:
    a vertex and about two faces; the rest is the slabs' marching-cubes output and the
    sort that welds it); at resolution 400 with 333 000 vertices, 140 MiB where the values
    of the whole lattice alone would take 490 MiB. An adaptive spline's blocks are
    evaluated ``BATCH_BLOCKS`` (256) at a time, about 20 MiB of values.
    """
    budget = check_faces(faces)
    simplify = None if budget is None else fast_simplification_simplify()
    spline = grid_spline(spline, dims=(3,))
    lower, upper = _box(spline, box)
    _check_values(spline, float(level))
    spacings = check_trim(trim, points)  # before the lattice: a bad trim fails at once
    rim_spacings = check_rim(rim)
    if int(newton_steps) < 0:
        raise ValueError(f"newton_steps must be >= 0, got {newton_steps}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    support = near = None
    if spacings is not None:
        support = Support(check_points(points, 3))
        # A trimmed mesh of an adaptive spline skips the blocks the trim would cut whole.
        near = near_support(support, spacings, int(newton_steps))
    chosen = resolution is None
    if resolution is None:
        resolution = default_resolution(spline, lower, upper, trimmed=spacings is not None)
    spacing, vertices, triangles = _march(
        spline, lower, upper, int(resolution), float(level), max_nodes, chosen, int(chunk), near
    )
    if len(triangles) == 0:
        return _EMPTY
    vertices = lower + vertices * spacing
    vertices = _newton(spline, vertices, float(level), int(newton_steps), spacing.max())
    if spacings is not None and support is not None:
        vertices, triangles = trim_to_support(vertices, triangles, support, spacings, rim_spacings)
        if len(triangles) == 0:
            return _EMPTY
    if simplify is None or budget is None or len(triangles) <= budget:
        return vertices, triangles
    vertices, triangles = _decimate(simplify, vertices, triangles, budget)
    # Decimation places a vertex where it best fits the planes of the faces merged into it,
    # off the level set by up to the sagitta of its edges: the same Newton steps take it
    # back, each no longer than its longest edge (a lattice spacing at least).
    reach = np.maximum(spacing.max(), _longest_edges(vertices, triangles))
    return _newton(spline, vertices, float(level), int(newton_steps), reach), triangles


def _decimate(simplify, vertices, faces, budget: int):
    """fast-simplification's decimation of a mesh to ``budget`` faces, in a box of side
    ``DECIMATION_BOX`` (see there), and once more in a box of side 1 where its schedule
    stopped above the budget. ``(vertices, faces int64)``; orientation kept."""
    lowest, highest = vertices.min(axis=0), vertices.max(axis=0)
    centre, size = (lowest + highest) / 2, float(np.max(highest - lowest))
    scaled = (vertices - centre) * (DECIMATION_BOX / size)
    points, triangles = simplify(scaled, faces, target_count=budget)[:2]
    if len(triangles) > budget:
        points = np.asarray(points) / DECIMATION_BOX
        points, triangles = simplify(points, triangles, target_count=budget)[:2]
        points = np.asarray(points) * DECIMATION_BOX
    points = centre + np.asarray(points, np.float64) * (size / DECIMATION_BOX)
    return points, np.asarray(triangles, np.int64).reshape(-1, 3)


def _longest_edges(vertices, faces) -> np.ndarray:
    """The length of each vertex's longest edge ``(V,)`` (0 for a vertex no face uses)."""
    ends = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lengths = np.linalg.norm(vertices[ends[:, 0]] - vertices[ends[:, 1]], axis=1)
    longest = np.zeros(len(vertices))
    np.maximum.at(longest, ends[:, 0], lengths)
    np.maximum.at(longest, ends[:, 1], lengths)
    return longest


def _check_values(spline, level: float) -> None:
    """ValueError, in jurs's words, for a spline whose level set is no surface: non-finite
    control points or weights, a weight <= 0, or every control point at ``level``.

    Without it a NaN spline gave an empty mesh (read as "the level set misses the box") and
    a zero spline scikit-image's "No surface found"."""
    control, weights = spline.coefficients()
    if not np.isfinite(level):
        raise ValueError(f"level must be finite, got {level}")
    for name, values in (("control points", control), ("weights", weights)):
        bad = ~np.isfinite(values)
        if bad.any():
            raise ValueError(
                f"the spline's {name} are not all finite ({int(bad.sum())} of {values.size} "
                "are NaN or infinite): it has no level set to mesh"
            )
    if not (weights > 0).all():
        raise ValueError(
            f"the spline's weights must be positive; {int(np.sum(weights <= 0))} of "
            f"{weights.size} are <= 0 (smallest {weights.min():.3g}), where "
            "g = sum w C B / sum w B is undefined"
        )
    if (control == level).all():
        raise ValueError(
            f"every control point of the spline equals the level {level:g}: g is that level "
            "everywhere in the box, so its level set is the whole box, not a surface"
        )


def check_lattice_size(
    counts, resolution: int, chunk: int = SLAB_NODES, max_nodes: int | None = MAX_NODES
) -> None:
    """ValueError before meshing a lattice of ``counts`` nodes a side when it has more than
    ``max_nodes`` nodes (None: no limit; the message estimates the time at
    ``NODES_PER_SECOND``) or when its estimated peak memory (``BYTES_PER_SLAB_NODE`` a
    node of a slab, ``BYTES_PER_VERTEX`` a vertex, ``VERTICES_PER_PLANE_NODE`` vertices
    a node of a plane) exceeds the host's available memory
    (``jurs._problem.memory.check_memory``, named ``resolution=...`` as in 2D)."""
    nodes = float(np.prod(np.asarray(counts, dtype=np.float64)))
    plane = nodes / max(counts)
    # A slab holds at most the whole lattice, however large the chunk asked.
    slab = min(max(chunk, 2 * plane), nodes)
    memory = BYTES_PER_SLAB_NODE * slab + (BYTES_PER_VERTEX * VERTICES_PER_PLANE_NODE * plane)
    if max_nodes is not None:
        if isinstance(max_nodes, bool) or not isinstance(max_nodes, (int, np.integer)):
            raise TypeError(f"max_nodes must be an int or None, got {max_nodes!r}")
        if nodes > max_nodes:
            seconds = nodes / NODES_PER_SECOND
            raise ValueError(
                f"resolution={resolution} samples g at {nodes:.3g} lattice nodes, more than "
                f"max_nodes={int(max_nodes)}: about {_duration(seconds)} of meshing and up "
                f"to {memory / 2**30:.2g} GiB; pass a larger max_nodes (or None) to mesh "
                "anyway, or choose a smaller resolution"
            )
    check_memory(f"resolution={resolution}", memory, device=False)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} minutes"
    return f"{seconds / 3600:.1f} hours"


def _box(spline: AbstractSpline, box):
    """``(lower, upper)`` of the box to mesh as float64 ``(3,)`` arrays, checked."""
    s_lower = np.asarray(spline.lower, np.float64)
    s_upper = np.asarray(spline.upper, np.float64)
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


@functools.singledispatch
def _march(spline: AbstractSpline, lower, upper, resolution, level, max_nodes, chosen, chunk, near):
    """``(spacing, vertices in index units, faces)``: marching cubes over the whole lattice
    of ``resolution`` nodes along the longest side, in slabs of ``chunk`` nodes (``near``,
    an adaptive spline's filter of blocks, is not read)."""
    axes = lattice_axes(lower, upper, resolution)
    check_lattice_size([len(a) for a in axes], resolution, chunk, max_nodes)
    spacing = _spacing(axes)
    nudge = NUDGE * float(np.max(spacing * spline.slope_bound()))
    vertices, faces = _march_in_slabs(spline, axes, level, nudge, chunk)
    return spacing, vertices, faces


@_march.register
def _(spline: AdaptiveSpline, lower, upper, resolution, level, max_nodes, chosen, chunk, near):
    # Only the blocks where g may reach the level (jurs._model.band), and near the data.
    _, spacing, vertices, faces = _mesh_band(
        spline, lower, upper, resolution, level, max_nodes, chosen, near
    )
    return spacing, vertices, faces


def _march_in_slabs(spline, axes, level: float, nudge: float, chunk: int):
    """Marching cubes over the lattice, slab by slab along the first axis; vertices in
    lattice index units.

    Consecutive slabs share one plane of nodes, evaluated once and handed on, so the
    vertices marching cubes puts on that plane come out bitwise equal in both slabs (the
    same values on the same edges); ``_weld`` merges them. Values within ``nudge`` of
    the level are set to ``level + nudge`` first (see ``NUDGE``). A node's value does not
    depend on the slab that holds it (``jurs._model.lattice.grid_lattice_values``;
    ``FinestSpline``), and ``lattice_vertices`` puts each vertex where marching cubes over
    the whole lattice at once puts it, so the mesh is the same, bit for bit, for any
    ``chunk``.
    """
    marching_cubes = skimage_marching_cubes()
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
        vertex_parts.append(lattice_vertices(verts, values, level, (start, 0, 0)))
        face_parts.append(tris.astype(np.int64) + count)
        count += len(verts)
    if not face_parts:
        return _EMPTY
    return _weld(np.concatenate(vertex_parts), np.concatenate(face_parts))


#: scikit-image's marching cubes (``_marching_cubes_lewiner_cy``) weighs a cube corner of
#: value ``v`` (level subtracted) by ``1 / (FLT_EPSILON + |v|)``, its FLT_EPSILON being
#: float64's epsilon.
MC_EPSILON = float(np.spacing(1.0))
#: The corners of a cube in scikit-image's order (its ``v0`` .. ``v7``), as offsets along
#: the array's axes (0, 1, 2), which it calls (z, y, x).
MC_CORNERS = np.array(
    [[0, 0, 0], [0, 0, 1], [0, 1, 1], [0, 1, 0], [1, 0, 0], [1, 0, 1], [1, 1, 1], [1, 1, 0]]
)


def lattice_vertices(verts, values, level: float, first) -> np.ndarray:
    """Marching cubes' vertices ``verts (V, 3)`` (float32, index units of ``values``, a
    part of the lattice whose node 0 is the lattice's node ``first``) in the whole
    lattice's index units, float64: where scikit-image's marching cubes puts them when it
    marches the whole lattice at once, bit for bit.

    It places a vertex at ``i + f`` in float64 (``i`` a corner's index in the array it
    marches, ``f`` in [0, 1] from the corner values rounded to float32, weighted as
    ``MC_EPSILON`` says) and rounds that to float32, whose spacing grows with ``i``.
    Shifted by ``first`` after the rounding, a vertex of a slab starting at plane ``s``
    was ``fl32(i - s + f) + s``, not ``fl32(i + f)``: meshes of one spline with two slab
    sizes differed by about 1e-7 on a box of side 2, which reordered some of the welded
    vertices (sorted by position), so the arrays returned differed far more (issue 54).
    So each coordinate off the lattice's planes is computed again from the corner values
    with ``i`` counted from the whole lattice's first node: the one coordinate of a vertex
    on a lattice edge (the other two are integers), all three of a vertex inside a cube
    (Lewiner's centre vertex, every coordinate off the planes). A coordinate on a plane is
    an integer, exact in both.

    A vertex stays off the planes by at least a fraction of a spacing that ``NUDGE``
    bounds (about 3e-4 of a spacing inside a cube, 1e-3 on an edge), so a coordinate
    integral in float32 is on a plane, and the floor of the others is the cube's, for
    lattices below several thousand nodes a side (float32 rounds ``i + f`` by up to 6e-8
    times ``i``)."""
    local = verts.astype(np.float64)
    out = local + np.asarray(first, np.float64)
    off = local != np.floor(local)
    along = off.sum(axis=1)
    corner = np.floor(local).astype(np.int64)
    level = float(level)

    def weights(nodes):
        # scikit-image's arithmetic: the float32 value, the level subtracted in float64.
        v = values[nodes[:, 0], nodes[:, 1], nodes[:, 2]].astype(np.float32).astype(np.float64)
        return 1.0 / (MC_EPSILON + np.abs(v - level))

    # On an edge along `axis`: i + w1 / (w0 + w1), w1 the weight of the node at i + 1.
    for axis in range(3):
        rows = np.flatnonzero((along == 1) & off[:, axis])
        if not len(rows):
            continue
        step = np.zeros(3, np.int64)
        step[axis] = 1
        w0, w1 = weights(corner[rows]), weights(corner[rows] + step)
        index = (corner[rows, axis] + int(first[axis])).astype(np.float64)
        out[rows, axis] = (index + w1 / (w0 + w1)).astype(np.float32)
    # Inside a cube: i + (sum of the weights of the corners at i + 1) / (sum of all eight),
    # each sum added one by one in scikit-image's corner order.
    rows = np.flatnonzero(along >= 2)
    if len(rows):
        cube = np.minimum(corner[rows], np.array(values.shape) - 2)
        w = [weights(cube + offset) for offset in MC_CORNERS]
        total = w[0]
        for term in w[1:]:
            total = total + term
        for axis in range(3):
            upper = [term for term, offset in zip(w, MC_CORNERS) if offset[axis]]
            part = upper[0]
            for term in upper[1:]:
                part = part + term
            index = (cube[:, axis] + int(first[axis])).astype(np.float64)
            out[rows, axis] = (index + part / total).astype(np.float32)
    return out


def _weld(vertices, faces):
    """Merge vertices at bitwise equal positions, drop the faces that collapse, and the
    vertices no face uses any more.

    Marching cubes puts one vertex on each lattice edge the level set crosses, so two
    vertices coincide as the same edge's vertex seen from two slabs, or (should the nudge
    of ``NUDGE`` fall short) at a node where g is at the level to float32, where every
    crossing edge has its vertex on the node and the triangles between them have no area.
    Merged, each point is one vertex.
    """
    vertices, inverse = _unique_rows(vertices)
    faces = inverse[faces]
    faces = faces[(faces != np.roll(faces, 1, axis=1)).all(axis=1)]
    # The vertices the faces use, in their order, renumbered (np.unique's result, by a
    # mark and a running count instead of a sort).
    used = np.zeros(len(vertices), bool)
    used[faces] = True
    number = np.cumsum(used) - 1
    return vertices[used], number[faces].reshape(-1, 3)


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_inverse=True)``, the same rows in the same
    (lexicographic) order: by ``np.lexsort`` of the columns, where ``np.unique`` sorts
    the rows as records, several times slower on a mesh's millions of vertices."""
    order = np.lexsort(rows.T[::-1])
    ordered = rows[order]
    new = np.ones(len(rows), bool)
    np.any(ordered[1:] != ordered[:-1], axis=1, out=new[1:])
    inverse = np.empty(len(rows), np.int64)
    inverse[order] = np.cumsum(new) - 1
    return ordered[new], inverse


def _newton(spline, vertices, level: float, steps: int, longest):
    """``steps`` Newton steps onto ``{g = level}`` along the gradient, each no longer than
    ``longest`` (a length, or one per vertex; see [`mesh`][jurs.levelset.mesh]); points
    with a zero or non-finite gradient stay put."""
    x = vertices.copy()
    for _ in range(steps):
        value, gradient = spline.values_and_gradients(x)
        norm2 = np.sum(gradient * gradient, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            move = -((value - level) / norm2)[:, None] * gradient
        ok = np.isfinite(move).all(axis=1) & (np.sum(move * move, axis=1) <= longest**2)
        x[ok] += move[ok]
    return x


def _spacing(axes) -> np.ndarray:
    return np.array([(a[-1] - a[0]) / (len(a) - 1) for a in axes])


def _mesh_band(
    spline, lower, upper, resolution: int, level: float, max_nodes, chosen: bool, near=None
):
    """Marching cubes over the blocks of the lattice where an adaptive spline may reach
    the level (``jurs._model.band``), those ``near`` keeps (``plan_band``'s filter; None:
    all); ``(axes, spacing, vertices in index units, faces)``. A default resolution
    (``chosen``) is lowered until the marched nodes fit in ``max_nodes``; a given one is
    refused past it (``check_band_size``)."""
    evaluator = spline.on_host()
    marching_cubes = skimage_marching_cubes()
    slope = finest_slope_bound(spline, evaluator)
    while True:
        axes = lattice_axes(lower, upper, int(resolution))
        spacing = _spacing(axes)
        nudge = NUDGE * float(np.max(spacing * slope))
        plan = plan_band(evaluator, axes, level, nudge, near=near)
        fits = max_nodes is None or plan.nodes <= max_nodes
        if fits or not chosen or resolution <= MIN_RESOLUTION:
            break
        # A surface's band grows as the square of the resolution.
        shrink = 0.95 * np.sqrt(max_nodes / plan.nodes)
        resolution = max(MIN_RESOLUTION, int((resolution - 1) * shrink) + 1)
    check_band_size(plan, [len(a) for a in axes], int(resolution), max_nodes)
    vertices, faces = march_band(evaluator, axes, plan, level, nudge, marching_cubes)
    if len(faces):
        vertices, faces = _weld(vertices, faces)
    return axes, spacing, vertices, faces


def check_band_size(plan: BandPlan, counts, resolution: int, max_nodes: int | None) -> None:
    """``check_lattice_size`` for the band of an adaptive spline: the nodes counted are
    those of the marched blocks (``plan.nodes``), the memory one batch of blocks'
    values and the vertices of a lattice plane, as on the full lattice."""
    plane = float(np.prod(np.asarray(counts, np.float64))) / max(counts)
    batch = min(plan.nodes, BATCH_BLOCKS * (BLOCK_CELLS + 1) ** 3)
    memory = BYTES_PER_SLAB_NODE * batch + BYTES_PER_VERTEX * VERTICES_PER_PLANE_NODE * plane
    if max_nodes is not None:
        if isinstance(max_nodes, bool) or not isinstance(max_nodes, (int, np.integer)):
            raise TypeError(f"max_nodes must be an int or None, got {max_nodes!r}")
        if plan.nodes > max_nodes:
            seconds = plan.nodes / NODES_PER_SECOND
            raise ValueError(
                f"resolution={resolution} samples g at {plan.nodes:.3g} lattice nodes in the "
                f"blocks where it may reach the level (of {plan.lattice_nodes:.3g} over the "
                f"box), more than max_nodes={int(max_nodes)}: about {_duration(seconds)} of "
                f"meshing and up to {memory / 2**30:.2g} GiB; pass a larger max_nodes (or "
                "None) to mesh anyway, or choose a smaller resolution"
            )
    check_memory(f"resolution={resolution}", memory, device=False)


def march_band(
    evaluator: FinestSpline,
    axes,
    plan: BandPlan,
    level: float,
    nudge: float,
    marching_cubes,
    block: int = BLOCK_CELLS,
):
    """Marching cubes over ``plan``'s blocks; ``(vertices in lattice index units, faces)``
    before welding. Values within ``nudge`` of the level are set to ``level + nudge``
    first, as on the full lattice."""
    grid = BlockGrid(evaluator, axes, block)
    vertex_parts, face_parts = [], []
    count = 0
    for batch, values, real in grid.batch_values(evaluator, plan.blocks):
        for b, where in enumerate(batch):
            block_values = values[b, : real[b, 0], : real[b, 1], : real[b, 2]]
            block_values = np.where(
                np.abs(block_values - level) < nudge, level + nudge, block_values
            )
            if not block_values.min() <= level <= block_values.max():
                continue
            # "descent": faces (right-hand rule) towards g > level, as on the full lattice.
            verts, tris, _, _ = marching_cubes(block_values, level, gradient_direction="descent")
            first = [int(grid.first[k][where[k]]) for k in range(grid.ndim)]
            vertex_parts.append(lattice_vertices(verts, block_values, level, first))
            face_parts.append(tris.astype(np.int64) + count)
            count += len(verts)
    if not face_parts:
        return np.empty((0, 3)), np.empty((0, 3), np.int64)
    return np.concatenate(vertex_parts), np.concatenate(face_parts)
