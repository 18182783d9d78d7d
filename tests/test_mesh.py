"""Surfaces of 3D splines: lattice evaluation, meshing, mesh metrics, 3D clouds and files.

The splines here are plain records of the four fields the meshing code reads (control,
weights, lower, upper), built from implicit functions sampled at the Greville points
``lo + (i - 1) h`` of the uniform cubic basis. For a quadratic such as ``|x|^2 - r^2``
Marsden's identity gives exact coefficients (``x^2`` has coefficients ``tau_i^2 - h^2 / 3``),
so that spline's zero set *is* the sphere and vertices can be checked to rounding.
"""

from collections import namedtuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs import datasets
from jurs import levelset as _mesh  # levelset._meshing and levelset._mesh_analysis
from jurs._model import lattice as _lattice
from jurs.levelset._trimming import Support

pytest.importorskip("skimage")
pytest.importorskip("trimesh")

Spline = namedtuple("Spline", "control weights lower upper")


def test_missing_scikit_image_says_to_install_from_the_checkout(monkeypatch):
    """jurs is not published: the hint installs the extra from the checkout."""
    import sys

    from jurs.levelset._meshing import skimage_marching_cubes

    monkeypatch.setitem(sys.modules, "skimage.measure", None)
    with pytest.raises(ImportError, match=r"pip install -e '\.\[surfaces\]'"):
        skimage_marching_cubes()


def greville_nodes(lower, upper, shape):
    """The coefficient sites of each axis, ``(axes, h)``."""
    h = [(hi - lo) / (n - 3) for lo, hi, n in zip(lower, upper, shape)]
    return [lo + (np.arange(n) - 1.0) * hh for lo, hh, n in zip(lower, h, shape)], h


def sampled_spline(fn, lower, upper, shape, weights=None):
    """Spline whose coefficients are ``fn`` (on ``(n, 3)`` points) at the Greville points."""
    axes, _ = greville_nodes(lower, upper, shape)
    sites = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    control = fn(sites.reshape(-1, 3)).reshape(shape)
    weights = np.ones(shape) if weights is None else weights
    return Spline(control, weights, np.asarray(lower, float), np.asarray(upper, float))


def exact_sphere(radius=1.0, n=12, half=1.5):
    """The spline that equals ``|x|^2 - radius^2`` everywhere (Marsden's identity)."""
    lower, upper = np.full(3, -half), np.full(3, half)
    _, h = greville_nodes(lower, upper, (n, n, n))
    shift = sum(hh * hh for hh in h) / 3.0
    return sampled_spline(
        lambda p: np.sum(p * p, axis=1) - radius**2 - shift, lower, upper, (n, n, n)
    )


def torus_distance(p, major=1.0, minor=0.35):
    return np.hypot(np.hypot(p[:, 0], p[:, 1]) - major, p[:, 2]) - minor


def face_normals(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


# --- lattice evaluation ---------------------------------------------------------------------


def test_axis_basis_is_a_partition_of_unity_with_the_right_slopes():
    x = np.linspace(-0.5, 2.5, 41)  # beyond the box [0, 2] too
    values = _lattice.axis_basis(x, 0.0, 2.0, 7)
    assert values.shape == (41, 7)
    np.testing.assert_allclose(values.sum(axis=1), 1.0, atol=1e-14)
    inside = (x >= 0) & (x <= 2)
    assert (values[inside] >= 0).all() and ((values[inside] > 0).sum(axis=1) <= 4).all()
    step = 1e-6
    slopes = _lattice.axis_basis(x, 0.0, 2.0, 7, derivative=True)
    numeric = (
        _lattice.axis_basis(x + step, 0.0, 2.0, 7) - _lattice.axis_basis(x - step, 0.0, 2.0, 7)
    ) / (2 * step)
    interior = np.abs((x / (2 / 4)) - np.round(x / (2 / 4))) > 1e-3  # not on a knot
    np.testing.assert_allclose(slopes[interior], numeric[interior], atol=1e-8)


def test_lattice_values_match_the_2d_spline_and_its_gradient():
    rng = np.random.default_rng(0)
    control, weights = rng.normal(size=(7, 9)), rng.uniform(0.5, 2.0, (7, 9))
    spline = jurs.ImplicitSpline(
        jnp.asarray(control), jnp.asarray(weights), jnp.array([-1.0, 0.0]), jnp.array([2.0, 1.5])
    )
    xs, ys = np.linspace(-1.2, 2.1, 13), np.linspace(-0.1, 1.6, 11)
    grid = _lattice.lattice_values(spline, (xs, ys))
    xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    # One jitted call: op by op, JAX took 4 s here.
    direct, direct_grad = eqx.filter_jit(lambda s, p: (s(p), s.grad(p)))(spline, jnp.asarray(xy))
    np.testing.assert_allclose(grid.ravel(), direct, atol=1e-13)
    value, gradient = _lattice.values_and_gradients(spline, xy, chunk=17)
    np.testing.assert_allclose(value, direct, atol=1e-13)
    np.testing.assert_allclose(gradient, direct_grad, atol=1e-12)
    np.testing.assert_allclose(_lattice.lattice_values(spline, (xs, ys), xp=jnp), grid, atol=1e-13)


def test_lattice_values_match_pointwise_evaluation_in_3d():
    rng = np.random.default_rng(1)
    shape = (5, 6, 7)
    spline = Spline(
        rng.normal(size=shape),
        rng.uniform(0.5, 2.0, shape),
        np.array([0.0, -1.0, 2.0]),
        np.array([1.0, 1.0, 5.0]),
    )
    axes = (np.linspace(-0.1, 1.1, 6), np.linspace(-1, 1, 5), np.linspace(2, 5, 4))
    grid = _lattice.lattice_values(spline, axes)
    assert grid.shape == (6, 5, 4)
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # Independent reference: the dense basis of each axis at each point, summed in full.
    b = [
        _lattice.axis_basis(points[:, k], spline.lower[k], spline.upper[k], shape[k])
        for k in range(3)
    ]
    num = np.einsum("ni,nj,nk,ijk->n", *b, spline.weights * spline.control)
    den = np.einsum("ni,nj,nk,ijk->n", *b, spline.weights)
    np.testing.assert_allclose(grid.ravel(), num / den, atol=1e-13)
    value, gradient = _lattice.values_and_gradients(spline, points)
    np.testing.assert_allclose(value, num / den, atol=1e-13)
    step = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = step
        numeric = (
            _lattice.values_and_gradients(spline, points + e)[0]
            - _lattice.values_and_gradients(spline, points - e)[0]
        ) / (2 * step)
        np.testing.assert_allclose(gradient[:, k], numeric, atol=1e-6)


def test_a_node_has_the_same_value_in_every_lattice_that_holds_it():
    """The slabs of a mesh evaluate the lattice piece by piece: a node's value must not
    depend on the piece (a BLAS product's summation order does, in the last bits)."""
    from jurs.levelset._meshing import lattice_axes

    rng = np.random.default_rng(1)
    shape = (27, 27, 27)
    spline = Spline(rng.normal(size=shape), rng.uniform(0.5, 2.0, shape), -np.ones(3), np.ones(3))
    xs, ys, zs = lattice_axes(spline.lower, spline.upper, 131)
    whole = _lattice.lattice_values(spline, (xs, ys, zs))
    for planes in (1, 2, 7):
        pieces = [
            _lattice.lattice_values(spline, (xs[a : a + planes], ys, zs))
            for a in range(0, len(xs), planes)
        ]
        np.testing.assert_array_equal(np.concatenate(pieces), whole)
    sub = _lattice.lattice_values(spline, (xs[40:47], ys[3:90], zs[60:61]))
    np.testing.assert_array_equal(sub, whole[40:47, 3:90, 60:61])


def test_lattice_checks_its_input():
    spline = exact_sphere()
    with pytest.raises(ValueError, match="needs 3 lattice axes"):
        _lattice.lattice_values(spline, (np.zeros(2), np.zeros(2)))
    with pytest.raises(ValueError, match="same shape"):
        _lattice.lattice_values(spline._replace(weights=np.ones((3, 3, 3))), [np.zeros(2)] * 3)
    with pytest.raises(ValueError, match=r"points must have shape \(n, 3\)"):
        _lattice.values_and_gradients(spline, np.zeros((4, 2)))


# --- meshing --------------------------------------------------------------------------------


def test_sphere_mesh_is_one_closed_outward_genus_0_surface_on_the_zero_set():
    spline = exact_sphere(radius=1.0)
    vertices, faces = _mesh.mesh(spline)
    assert vertices.dtype == np.float64 and faces.dtype == np.int64
    np.testing.assert_allclose(np.linalg.norm(vertices, axis=1), 1.0, atol=1e-8)
    rough = _mesh.mesh(spline, newton_steps=0)[0]
    assert np.abs(np.linalg.norm(rough, axis=1) - 1.0).max() > 1e-4  # Newton did the work
    report = _mesh.analyze_mesh(vertices, faces)
    assert report.num_components == 1
    (component,) = report.components
    assert component.closed and component.genus == 0
    assert _mesh.genus(faces) == 0
    assert abs(component.area - 4 * np.pi) < 0.02 * 4 * np.pi
    centroids = vertices[faces].mean(axis=1)
    assert (np.sum(face_normals(vertices, faces) * centroids, axis=1) > 0).all()  # outward


def test_torus_has_genus_1_and_double_torus_genus_2():
    torus = sampled_spline(torus_distance, [-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], (19, 19, 9))
    vertices, faces = _mesh.mesh(torus)
    assert _mesh.genus(faces) == 1
    # The Greville-sampled distance is a close approximation, not the torus itself.
    assert np.abs(torus_distance(vertices)).max() < 0.05
    double = sampled_spline(
        lambda p: datasets.genus2_function(p)[0], [-2.6, -1.6, -0.7], [2.6, 1.6, 0.7], (40, 26, 14)
    )
    report = _mesh.analyze_mesh(*_mesh.mesh(double))
    assert [(c.closed, c.genus) for c in report.components] == [(True, 2)]


def test_slabs_give_the_same_mesh_as_one_slab():
    spline = sampled_spline(torus_distance, [-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], (19, 19, 9))
    whole = _mesh.mesh(spline, 40, chunk=1 << 30)
    slabs = _mesh.mesh(spline, 40, chunk=1)  # two planes a slab: every plane is a seam
    # Bit for bit: the same lattice values and vertex coordinates in any slab
    # (_meshing.lattice_vertices), so the same welded vertices in the same order.
    np.testing.assert_array_equal(slabs[0], whole[0])
    np.testing.assert_array_equal(slabs[1], whole[1])
    assert _mesh.analyze_mesh(*slabs).components[0].closed


def test_mesh_does_not_depend_on_the_slab_size():
    """Issue 54, item 13: random control points on a 10^3 grid (several components, open
    at the box). With the default slab this lattice is one slab; with smaller ones
    marching cubes rounded a vertex to float32 counted from its slab's first plane: the
    vertices moved by ~1e-7, which reordered some of them, so the arrays returned
    differed by up to 1.8 on a box of side 2 (and their faces' indices)."""
    rng = np.random.default_rng(8)
    spline = Spline(rng.normal(size=(10, 10, 10)), np.ones((10, 10, 10)), -np.ones(3), np.ones(3))
    whole = _mesh.mesh(spline)
    assert _mesh.analyze_mesh(*whole).num_components > 1
    for chunk in (5000, 2000, 1):
        vertices, faces = _mesh.mesh(spline, chunk=chunk)
        np.testing.assert_array_equal(vertices, whole[0])
        np.testing.assert_array_equal(faces, whole[1])
    # Without Newton steps: the vertices marching cubes gives, at a finer lattice.
    whole = _mesh.mesh(spline, 90, newton_steps=0)
    for chunk in (30_000, 1):
        np.testing.assert_array_equal(
            _mesh.mesh(spline, 90, newton_steps=0, chunk=chunk)[0], whole[0]
        )


def test_slab_vertices_are_those_of_marching_cubes_over_the_whole_volume():
    """``lattice_vertices`` reproduces scikit-image's own coordinates at the whole
    volume's indices, centre vertices of ambiguous cubes included (white noise is full of
    them), so a volume marched in slabs of any thickness gives the whole volume's mesh."""
    from skimage.measure import marching_cubes

    from jurs.levelset import _meshing

    values = np.random.default_rng(0).normal(size=(30, 20, 15))
    level = 0.1
    verts, faces, _, _ = marching_cubes(values, level, gradient_direction="descent")
    inside = (verts != np.floor(verts)).sum(axis=1) >= 2
    assert inside.sum() > 100  # centre vertices
    np.testing.assert_array_equal(
        _meshing.lattice_vertices(verts, values, level, (0, 0, 0)), verts.astype(np.float64)
    )
    whole = _meshing._weld(verts.astype(np.float64), faces.astype(np.int64))
    for planes in (2, 3, 8):
        parts, part_faces, count = [], [], 0
        for start in range(0, len(values) - 1, planes - 1):
            slab = values[start : start + planes]
            v, f, _, _ = marching_cubes(slab, level, gradient_direction="descent")
            parts.append(_meshing.lattice_vertices(v, slab, level, (start, 0, 0)))
            part_faces.append(f.astype(np.int64) + count)
            count += len(v)
        slabs = _meshing._weld(np.concatenate(parts), np.concatenate(part_faces))
        np.testing.assert_array_equal(slabs[0], whole[0])
        np.testing.assert_array_equal(slabs[1], whole[1])


def test_empty_level_set_and_bad_input():
    spline = exact_sphere(radius=1.0)
    vertices, faces = _mesh.mesh(spline, 16, level=50.0)
    assert vertices.shape == (0, 3) and faces.shape == (0, 3)
    assert _mesh.analyze_mesh(vertices, faces).num_components == 0
    assert _mesh.mesh_distances(vertices, faces, np.ones((3, 3)))["chamfer"] == np.inf
    flat = Spline(np.zeros((5, 5)), np.ones((5, 5)), np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="dimension 3"):
        _mesh.mesh(flat)
    with pytest.raises(ValueError, match="box"):
        _mesh.mesh(spline, box=(np.zeros(2), np.ones(2)))
    with pytest.raises(ValueError, match="resolution"):
        _mesh.mesh(spline, 1)
    with pytest.raises(ValueError, match="faces"):
        _mesh.analyze_mesh(np.zeros((3, 3)), np.array([[0, 1, 5]]))


def test_box_cuts_the_surface_open():
    spline = exact_sphere(radius=1.0)
    vertices, faces = _mesh.mesh(spline, 24, box=(np.array([-1.5, -1.5, 0.0]), np.full(3, 1.5)))
    (component,) = _mesh.analyze_mesh(vertices, faces).components
    assert not component.closed and component.genus is None
    with pytest.raises(ValueError, match="boundary edges"):
        _mesh.genus(faces)


def test_mesh_refuses_splines_without_a_surface():
    sphere = exact_sphere(radius=1.0, n=8)
    nan_control = sphere.control.copy()
    nan_control[2, 3, 4] = np.nan
    inf_weights = sphere.weights.copy()
    inf_weights[0, 0, 0] = np.inf
    cases = [
        (sphere._replace(control=nan_control), "control points are not all finite"),
        (sphere._replace(weights=inf_weights), "weights are not all finite"),
        (sphere._replace(weights=np.zeros_like(sphere.weights)), "weights must be positive"),
        (sphere._replace(weights=-sphere.weights), "weights must be positive"),
        (sphere._replace(control=np.zeros_like(sphere.control)), "whole box, not a surface"),
    ]
    for spline, message in cases:
        with pytest.raises(ValueError, match=message):
            _mesh.mesh(spline, 16)
    # A constant spline away from the level has an honest empty mesh; at it, none.
    constant = sphere._replace(control=np.full_like(sphere.control, 2.0))
    assert len(_mesh.mesh(constant, 16)[1]) == 0
    with pytest.raises(ValueError, match="equals the level 2"):
        _mesh.mesh(constant, 16, level=2.0)
    with pytest.raises(ValueError, match="level must be finite"):
        _mesh.mesh(sphere, 16, level=np.nan)


def test_mesh_refuses_a_lattice_too_large_unless_lifted(monkeypatch):
    sphere = exact_sphere(radius=1.0, n=8)
    with pytest.raises(ValueError, match=r"resolution=1200 samples g at 1\.73e\+09 .*minutes"):
        _mesh.mesh(sphere, 1200)
    with pytest.raises(ValueError, match="max_nodes=1000.*larger max_nodes"):
        _mesh.mesh(sphere, 16, max_nodes=1000)
    with pytest.raises(TypeError, match="max_nodes"):
        _mesh.mesh(sphere, 16, max_nodes=1e6)  # pyright: ignore[reportArgumentType]
    lifted = _mesh.mesh(sphere, 16, max_nodes=16**3)
    assert len(lifted[1]) and len(_mesh.mesh(sphere, 16, max_nodes=None)[1]) == len(lifted[1])
    # The memory estimate is checked against the host's memory, and cannot be lifted.
    from jurs._problem import memory

    monkeypatch.setattr(memory, "available_memory", lambda device=True: 1 << 20)
    with pytest.raises(ValueError, match="resolution=200 needs about .* GiB of memory"):
        _mesh.mesh(sphere, 200, max_nodes=None)


# --- mesh analysis and distances ------------------------------------------------------------


def test_analyze_mesh_drops_duplicated_and_degenerate_faces():
    vertices, faces = _mesh.mesh(exact_sphere(radius=1.0, n=8), 16)
    clean = _mesh.analyze_mesh(vertices, faces)
    assert clean.notes == () and clean.components[0].genus == 0
    flipped = faces[:, ::-1]  # the same triangles, the other way round
    degenerate = np.array([[0, 0, 1], [2, 3, 3]])
    messy = np.concatenate([faces, faces, flipped, degenerate])
    report = _mesh.analyze_mesh(vertices, messy)
    (component,) = report.components
    assert component.closed and component.genus == 0
    assert component.area == pytest.approx(clean.components[0].area, rel=1e-12)
    np.testing.assert_array_equal(np.sort(component.faces), np.arange(len(faces)))
    assert report.notes == (
        "dropped 2 degenerate faces (a vertex named twice)",
        f"dropped {2 * len(faces)} duplicated faces (a repeat of a face)",
    )
    assert _mesh.genus(messy) == 0
    distances = _mesh.mesh_distances(vertices, messy, vertices, vertices, samples=2000)
    assert distances == _mesh.mesh_distances(vertices, faces, vertices, vertices, samples=2000)


def test_mesh_analysis_refuses_non_finite_input():
    vertices, faces = _mesh.mesh(exact_sphere(radius=1.0, n=8), 16)
    bad = vertices.copy()
    bad[5] = np.nan
    for fn in (_mesh.analyze_mesh, _mesh.face_areas, _mesh.mesh_components):
        with pytest.raises(ValueError, match="vertices must be finite; 1 of .* vertex 5"):
            fn(bad, faces)
    points = vertices[:50].copy()
    points[7, 1] = np.inf
    with pytest.raises(ValueError, match="points must be finite; 1 of 50 .* row 7"):
        _mesh.analyze_mesh(vertices, faces, points)
    with pytest.raises(ValueError, match="reference_points must be finite"):
        _mesh.mesh_distances(vertices, faces, points)
    with pytest.raises(ValueError, match="reference_normals must be finite"):
        _mesh.mesh_distances(vertices, faces, vertices[:50], np.full((50, 3), np.nan))
    with pytest.raises(ValueError, match="faces index vertices"):
        _mesh.analyze_mesh(vertices, faces - 1)


def test_far_small_bubble_is_supplementary():
    def shapes(p):  # a sphere of radius 0.8 and a small one in the corner
        return np.minimum(
            np.linalg.norm(p, axis=1) - 0.8, np.linalg.norm(p - [1.0, 1.0, 1.0], axis=1) - 0.15
        )

    spline = sampled_spline(shapes, np.full(3, -1.3), np.full(3, 1.35), (30, 30, 30))
    vertices, faces = _mesh.mesh(spline)
    points, _ = datasets.sphere3d(2000, radius=0.8)
    report = _mesh.analyze_mesh(vertices, faces, points)
    assert report.num_components == 2
    sphere, bubble = report.components  # largest area first
    assert not sphere.supplementary and sphere.median_distance < 0.05
    assert bubble.supplementary and bubble.median_distance > report.threshold
    assert bubble.closed and bubble.genus == 0 and bubble.area < 0.1 * sphere.area
    assert report.as_dict()["num_supplementary"] == 1
    assert report.as_dict()["genera"] == [0, 0]
    count, labels = _mesh.mesh_components(vertices, faces)
    assert count == 2 and np.bincount(labels)[0] == sphere.num_faces
    assert bubble.carried_fraction == 0.0 and sphere.carried_fraction > 0.99
    # A threshold above the bubble's distance puts it near the data, but they lie on the
    # sphere: the bubble carries none of them and stays supplementary (it was kept).
    (near,) = _mesh.analyze_mesh(vertices, faces, points, threshold=2.0).supplementary
    assert near.median_distance < 2.0 and near.carried_fraction == 0.0


# --- open scans: trimming and boundary loops ------------------------------------------------


def hemisphere_points(m=1500, seed=0):
    """The upper half (z > 0) of m random samples of the unit sphere."""
    points, _ = datasets.sphere3d(m, seed=seed)
    return points[points[:, 2] > 0]


def test_trimmed_mesh_of_a_hemisphere_scan_is_open_with_one_loop_at_the_rim():
    """The distance rule alone (``rim=None``): the surface within 2.5 spacings."""
    spline = exact_sphere(radius=1.0, n=10)  # the whole sphere: a fit that closed the scan
    points = hemisphere_points()
    whole = _mesh.mesh(spline, 24)
    assert _mesh.analyze_mesh(*whole).components[0].closed
    vertices, faces = _mesh.mesh(spline, 24, points=points, trim=True, rim=None)
    report = _mesh.analyze_mesh(vertices, faces, points)
    assert report.num_components == 1
    (part,) = report.components
    assert not part.closed and part.num_boundary_loops == report.num_boundary_loops == 1
    # The rim of the data is the equator (length 2 pi); the trimmed mesh stops a few
    # spacings below it, and keeps no face beyond the trim.
    spacing = np.median(Support(points).spacing)
    assert -4 * spacing < vertices[:, 2].min() < 0
    rim = np.unique(_boundary_vertices(faces))
    assert np.abs(vertices[rim, 2] - np.median(vertices[rim, 2])).max() < 2 * spacing
    radius = np.hypot(vertices[rim, 0], vertices[rim, 1]).mean()
    # About the circle there, a little longer: the rim of random samples is ragged.
    assert 2 * np.pi * radius < part.boundary_length < 1.15 * 2 * np.pi * radius
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 0.01  # still on the sphere
    assert len(np.unique(faces)) == len(vertices)  # no unused vertex
    # Beyond the trim only slivers at the rim, where the distance between two vertices is
    # not quite linear (another sample is nearest midway).
    fraction = report.unsupported_fraction
    assert fraction is not None and fraction < 0.01 and not report.mostly_unsupported
    # Clipped faces keep their orientation: outward, as the whole mesh's.
    centroids = vertices[faces].mean(axis=1)
    assert (np.sum(face_normals(vertices, faces) * centroids, axis=1) > 0).all()
    # A wider trim keeps more; the same trim through trim_mesh gives the same mesh.
    wider = _mesh.mesh(spline, 24, points=points, trim=5.0, rim=None)[0]
    assert wider[:, 2].min() < vertices[:, 2].min()
    again = _mesh.trim_mesh(*whole, points, _mesh.DEFAULT_TRIM, rim=None)
    np.testing.assert_array_equal(again[1], faces)
    np.testing.assert_allclose(again[0], vertices)


def test_default_trim_stops_at_the_rim_of_a_hemisphere_scan():
    """The rim test: where the samples lie to one side the surface stops ``DEFAULT_RIM``
    spacings past them, not ``DEFAULT_TRIM``; still one piece with one boundary loop."""
    spline = exact_sphere(radius=1.0, n=10)
    points = hemisphere_points()
    spacing = np.median(Support(points).spacing)
    whole = _mesh.mesh(spline, 24)
    vertices, faces = _mesh.mesh(spline, 24, points=points, trim=True)
    report = _mesh.analyze_mesh(vertices, faces, points)
    assert report.num_components == 1 and report.num_boundary_loops == 1
    # The true rim is the equator: the farthest point past it is under 2 spacings (the
    # distance rule alone: about 3.7).
    assert -2 * spacing < vertices[:, 2].min() < 0
    distance_only = _mesh.trim_mesh(*whole, points, True, rim=None)[0]
    assert distance_only[:, 2].min() < -3 * spacing
    # The boundary lies about DEFAULT_RIM spacings from the data (linear along edges).
    rim = np.unique(_boundary_vertices(faces))
    reach = Support(points).spacings(vertices[rim])
    assert 0.8 * _mesh.DEFAULT_RIM < np.median(reach) < 1.2 * _mesh.DEFAULT_RIM
    # The same through trim_mesh; a wider rim keeps more; a rim above the trim is the trim.
    again = _mesh.trim_mesh(*whole, points, True, rim=True)
    np.testing.assert_array_equal(again[1], faces)
    wider = _mesh.trim_mesh(*whole, points, True, rim=2.0)[0]
    assert wider[:, 2].min() < vertices[:, 2].min() - 0.5 * spacing
    capped = _mesh.trim_mesh(*whole, points, 2.0, rim=4.0)
    np.testing.assert_array_equal(capped[1], _mesh.trim_mesh(*whole, points, 2.0, rim=None)[1])


def _grid_sheet(n=21):
    """A flat square sheet of (n - 1)^2 pairs of triangles, unit cells."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def test_small_holes_are_closed_and_small_islands_dropped():
    """On a sheet sampled at every node (spacing 0.89): a cut disc of 2 cells radius
    inside is a hole under ``HOLE_AREA`` squared spacings (closed), one of 5 is not; a cut
    region touching the sheet's border is never closed; a kept piece of one cell is an
    island under ``ISLAND_AREA`` (dropped)."""
    from jurs.levelset import _trimming

    vertices, faces = _grid_sheet()
    support = Support(vertices)
    r = np.linalg.norm(vertices[:, :2] - 10.0, axis=1)
    for radius, closed in ((2.0, True), (5.0, False)):
        level = np.where(r < radius, 1.0, -1.0)
        filled = _trimming.fill_holes(vertices, faces, level, support, _trimming.HOLE_AREA)
        assert (filled < 0).all() == closed
        assert ((filled >= 0) == (level >= 0)).all() != closed
    corner = np.where(np.linalg.norm(vertices[:, :2], axis=1) < 2.0, 1.0, -1.0)
    same = _trimming.fill_holes(vertices, faces, corner, support, _trimming.HOLE_AREA)
    np.testing.assert_array_equal(same, corner)
    kept = (r > 6.0) | (np.abs(vertices[:, :2] - 10.0).max(axis=1) < 0.6)  # a ring, a dot
    v, f = _trimming.clip_mesh(vertices, faces, np.where(kept, -1.0, 1.0))
    assert _mesh.mesh_components(v, f)[0] == 2
    v2, f2 = _trimming.drop_islands(v, f, support, _trimming.ISLAND_AREA)
    assert _mesh.mesh_components(v2, f2)[0] == 1 and len(f2) < len(f)


def _boundary_vertices(faces):
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, uses = np.unique(edges, axis=0, return_counts=True)
    return unique[uses == 1].reshape(-1)


def test_trim_leaves_a_closed_sphere_scan_unchanged():
    spline = exact_sphere(radius=1.0, n=10)
    points, _ = datasets.sphere3d(1500, seed=0)
    vertices, faces = _mesh.mesh(spline, 24)
    trimmed = _mesh.mesh(spline, 24, points=points, trim=True)
    np.testing.assert_array_equal(trimmed[1], faces)
    np.testing.assert_array_equal(trimmed[0], vertices)
    # Whole even with no rim at all: amid the samples the tolerance is the trim's.
    np.testing.assert_array_equal(_mesh.trim_mesh(vertices, faces, points, True, rim=0.0)[1], faces)
    report = _mesh.analyze_mesh(vertices, faces, points)
    assert report.num_boundary_loops == 0 and report.components[0].boundary_lengths == ()
    assert report.unsupported_fraction == 0.0


def test_untrimmed_open_scan_is_noted_as_mostly_unsupported():
    vertices, faces = _mesh.mesh(exact_sphere(radius=1.0, n=10), 24)
    points, _ = datasets.sphere3d(3000, seed=0)
    cap = points[points[:, 2] > 0.5]  # a quarter of the sphere's area
    report = _mesh.analyze_mesh(vertices, faces, cap)
    assert report.unsupported_fraction == pytest.approx(0.75, abs=0.08)
    assert report.mostly_unsupported
    assert any("most of the surface is unsupported" in n and "trim" in n for n in report.notes)
    assert report.as_dict()["unsupported_fraction"] == report.unsupported_fraction
    # Trimmed, the note goes.
    trimmed = _mesh.mesh(exact_sphere(radius=1.0, n=10), 24, points=cap, trim=True)
    assert not _mesh.analyze_mesh(*trimmed, cap).notes


def test_boundary_loops_of_a_square_and_a_square_with_a_hole():
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    report = _mesh.analyze_mesh(square, faces)
    (part,) = report.components
    assert part.num_boundary_loops == 1 and part.boundary_length == pytest.approx(4.0)
    d = report.as_dict()
    assert d["num_boundary_loops"] == 1 and d["boundary_length"] == pytest.approx(4.0)
    assert d["boundary_loops"] == [1] and d["boundary_lengths"] == [[pytest.approx(4.0)]]
    owner, length = _mesh.boundary_loops(square, faces)
    assert owner.tolist() == [0] and length == pytest.approx([4.0])
    # A 3 x 3 square of side 3 without its middle cell: two loops, 12 and 4 long, in one
    # component; a second, separate square adds a loop of its own.
    grid = np.array([[x, y, 0.0] for y in range(4) for x in range(4)])
    cells = [(x, y) for y in range(3) for x in range(3) if (x, y) != (1, 1)]
    quads = [(4 * y + x, 4 * y + x + 1, 4 * y + x + 5, 4 * y + x + 4) for x, y in cells]
    holed = np.array([f for a, b, c, e in quads for f in ((a, b, c), (a, c, e))])
    vertices = np.concatenate([grid, square + [10, 0, 0]])
    faces2 = np.concatenate([holed, faces + len(grid)])
    report = _mesh.analyze_mesh(vertices, faces2)
    big, small = report.components
    assert big.boundary_lengths == (pytest.approx(12.0), pytest.approx(4.0))
    assert small.boundary_lengths == (pytest.approx(4.0),)
    assert report.num_boundary_loops == 3 and report.boundary_length == pytest.approx(20.0)


def test_trim_checks_its_input():
    spline = exact_sphere(radius=1.0, n=8)
    points = hemisphere_points(200)
    with pytest.raises(ValueError, match="trim needs the data points"):
        _mesh.mesh(spline, 16, trim=True)
    for bad in (-1.0, 0.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="trim must be a positive, finite number"):
            _mesh.mesh(spline, 16, points=points, trim=bad)
    with pytest.raises(TypeError, match="trim must be None, True or a number"):
        _mesh.mesh(spline, 16, points=points, trim="2")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match=r"points must have shape \(m, 3\)"):
        _mesh.mesh(spline, 16, points=points[:, :2], trim=True)
    with pytest.raises(ValueError, match="points must be finite"):
        _mesh.mesh(spline, 16, points=np.full((5, 3), np.nan), trim=True)
    with pytest.raises(ValueError, match="at least 2 distinct data points"):
        _mesh.mesh(spline, 16, points=np.zeros((5, 3)), trim=True)
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    with pytest.raises(ValueError, match="vertices must be a finite"):
        _mesh.trim_mesh(square * np.nan, [[0, 1, 2]], points)
    with pytest.raises(ValueError, match="faces must be an integer"):
        _mesh.trim_mesh(square, [[0, 1, 4]], points)
    # No trim: points are not needed, and False is no trim.
    whole = _mesh.mesh(spline, 16)
    np.testing.assert_array_equal(_mesh.mesh(spline, 16, points=points, trim=False)[1], whole[1])
    np.testing.assert_array_equal(_mesh.trim_mesh(*whole, points, None)[1], whole[1])
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="rim must be a finite number of spacings >= 0"):
            _mesh.mesh(spline, 16, points=points, trim=True, rim=bad)
        with pytest.raises(ValueError, match="rim must be a finite number"):
            _mesh.trim_mesh(*whole, points, True, rim=bad)
    with pytest.raises(TypeError, match="rim must be None, True or a number"):
        _mesh.mesh(spline, 16, points=points, trim=True, rim="1")  # pyright: ignore[reportArgumentType]


def test_distances_of_a_mesh_to_its_own_samples_are_tiny():
    vertices, faces = _mesh.mesh(exact_sphere(radius=1.0), 48)
    points, normals = datasets.sample_mesh(vertices, faces, 20000, seed=1)
    own = _mesh.mesh_distances(vertices, faces, points, normals)
    assert own["chamfer"] < 0.01 and own["hausdorff"] < 0.05
    assert own["normal_consistency"] > 0.999
    moved = _mesh.mesh_distances(vertices + [0.1, 0.0, 0.0], faces, points, normals)
    assert moved["chamfer"] > 3 * own["chamfer"] and moved["hausdorff"] > 0.09
    exact = _mesh.mesh_distances(vertices, faces, *datasets.sphere3d(20000, seed=2))
    assert exact["chamfer"] < 0.01 and exact["normal_consistency"] > 0.999
    assert np.isnan(_mesh.mesh_distances(vertices, faces, points)["normal_consistency"])


# --- 3D clouds ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["sphere3d", "torus", "genus2"])
def test_3d_clouds_lie_on_their_surface_with_unit_outward_normals(name):
    implicit = {
        "sphere3d": lambda p: np.linalg.norm(p, axis=1) - 1.0,
        "torus": torus_distance,
        "genus2": lambda p: datasets.genus2_function(p)[0],
    }[name]
    points, normals = getattr(datasets, name)(3000, seed=3)
    assert points.shape == normals.shape == (3000, 3) and points.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    assert np.abs(implicit(points)).max() < 1e-10
    assert (implicit(points + 0.02 * normals) > 0).all()
    assert (implicit(points - 0.02 * normals) < 0).all()
    again = getattr(datasets, name)(3000, seed=3)[0]
    np.testing.assert_array_equal(points, again)


def test_torus_is_uniform_by_area():
    points, normals = datasets.torus(40000, major=1.0, minor=0.35, seed=0)
    # Area on the outer half (cos v > 0) is (pi R + 2 r) / (2 pi R) of the whole.
    outer = np.mean(np.hypot(points[:, 0], points[:, 1]) > 1.0)
    assert abs(outer - (np.pi + 0.7) / (2 * np.pi)) < 0.01


def test_sample_mesh_is_uniform_by_area_with_face_normals():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [3, 2, 0], [5, 0, 0]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 2, normals +z and -z
    points, normals = datasets.sample_mesh(vertices, faces, 20000, seed=0)
    on_big = points[:, 0] >= 3
    assert abs(on_big.mean() - 0.8) < 0.01
    np.testing.assert_array_equal(normals[on_big], [[0, 0, -1]] * on_big.sum())
    np.testing.assert_array_equal(normals[~on_big], [[0, 0, 1]] * (~on_big).sum())
    with pytest.raises(ValueError, match="no area"):
        datasets.sample_mesh(vertices, np.array([[0, 0, 0]]), 5)


# --- files ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "suffix, tol", [(".ply", 1e-6), (".obj", 1e-15), (".xyz", 0.0), (".pts", 0.0)]
)
def test_cloud_round_trip(tmp_path, suffix, tol):
    points, normals = datasets.torus(50)
    path = tmp_path / f"cloud{suffix}"
    datasets.save_points(path, points, normals)
    p2, n2 = datasets.load_points(path)
    np.testing.assert_allclose(p2, points, atol=tol)
    np.testing.assert_allclose(n2, normals, atol=tol)
    datasets.save_points(path, points)
    p3, n3 = datasets.load_points(path)
    assert n3 is None and p3.shape == (50, 3)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".off"])
def test_mesh_round_trip(tmp_path, suffix):
    vertices, faces = _mesh.mesh(exact_sphere(), 16)
    path = tmp_path / f"surface{suffix}"
    datasets.save_mesh(path, vertices, faces)
    v2, f2 = datasets.load_mesh(path)
    assert v2.shape == vertices.shape and f2.shape == faces.shape
    # STL stores triangles apart and is re-indexed on loading: compare the triangles.
    np.testing.assert_allclose(v2[f2], vertices[faces], atol=1e-6)


def test_points_of_a_mesh_file(tmp_path):
    """A mesh file gives points drawn on its faces, with outward face normals (not its
    vertices, without normals), and says so."""
    vertices, faces = _mesh.mesh(exact_sphere(), 16)
    path = tmp_path / "surface.ply"
    datasets.save_mesh(path, vertices, faces)
    with pytest.warns(UserWarning, match="drawn uniformly by area"):
        points, normals = datasets.load_points(path)
    assert normals is not None and len(points) == datasets.MESH_SAMPLES
    radius = np.linalg.norm(vertices, axis=1).mean()
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), radius, rtol=0.05)
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("bad.ply", "not a ply\n", r"not a readable PLY file"),
        ("bad.xyz", "0 0 0\n1 1\n", r"row 2: expected 3 columns"),
        ("bad.xyz", "0 0 0 1\n", r"row 1: expected 3 columns x y z or 6"),
        ("bad.pts", "0 0 0\n1 x 1\n", r"row 2: not all numbers"),
        ("bad.xyz", "0 0 0 0 0 0\n", r"row 1 has a zero-length normal"),
        ("bad.xyz", "# only a comment\n", r"no data rows"),
    ],
)
def test_bad_cloud_files(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        datasets.load_points(path)
    assert str(path) in str(info.value)


def test_bad_mesh_files(tmp_path):
    cloud = tmp_path / "cloud.ply"
    datasets.save_points(cloud, *datasets.sphere3d(10))
    with pytest.raises(ValueError, match="no triangle faces"):
        datasets.load_mesh(cloud)
    with pytest.raises(ValueError, match="mesh files are"):
        datasets.load_mesh(tmp_path / "surface.xyz")
    with pytest.raises(FileNotFoundError):
        datasets.load_mesh(tmp_path / "missing.obj")
    with pytest.raises(ValueError, match=r"3D points go to"):
        datasets.save_points(tmp_path / "cloud.csv", np.zeros((4, 3)))


# --- properties of the mesh analysis (hypothesis) -------------------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# derandomize: the same examples every run (see tests/test_properties.py).
PROPERTY = settings(
    max_examples=25,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
_SPHERE_MESH = _mesh.mesh(exact_sphere(radius=1.0, n=8), 12)
_TORUS_MESH = _mesh.mesh(
    sampled_spline(torus_distance, [-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], (12, 12, 7)), 20
)


def _summary(report):
    return sorted((c.num_faces, c.closed, c.genus, round(c.area, 9)) for c in report.components)


@PROPERTY
@given(
    which=st.sampled_from([0, 1, 2]),
    seed=st.integers(0, 2**32 - 1),
    repeats=st.integers(0, 3),
    degenerate=st.integers(0, 5),
)
def test_components_and_genus_survive_shuffles_repeats_and_degenerate_faces(
    which, seed, repeats, degenerate
):
    """Renumbering the vertices, reordering the faces (and their corners, orientation kept),
    repeating faces in either orientation and adding degenerate ones change no component,
    genus or area."""
    if which == 2:  # both shapes in one mesh: two components
        v0, f0 = _SPHERE_MESH
        v1, f1 = _TORUS_MESH
        vertices, faces = np.concatenate([v0, v1 + 5.0]), np.concatenate([f0, f1 + len(v0)])
    else:
        vertices, faces = (_SPHERE_MESH, _TORUS_MESH)[which]
    expected = _summary(_mesh.analyze_mesh(vertices, faces))
    rng = np.random.default_rng(seed)
    renumber = rng.permutation(len(vertices))
    moved = np.empty_like(vertices)
    moved[renumber] = vertices
    shuffled = renumber[faces][rng.permutation(len(faces))]
    shuffled = np.roll(shuffled, rng.integers(3), axis=1)  # a rotation keeps the orientation
    extra = shuffled[rng.integers(0, len(shuffled), repeats * 50)]
    flip = rng.random(len(extra)) < 0.5
    extra[flip] = extra[flip][:, ::-1]
    bad = shuffled[rng.integers(0, len(shuffled), degenerate)]  # collapsed faces
    bad[:, 1] = bad[:, 0]
    messy = np.concatenate([shuffled, extra, bad])
    messy = messy[rng.permutation(len(messy))]
    report = _mesh.analyze_mesh(moved, messy)
    assert _summary(report) == expected
    assert len(report.notes) == bool(len(extra)) + bool(degenerate)
    count, labels = _mesh.mesh_components(moved, messy)
    assert count == len(expected) and labels.shape == (len(messy),)
    if which < 2:
        assert _mesh.genus(messy) == (0, 1)[which]


@PROPERTY
@given(
    num_vertices=st.integers(1, 30),
    faces=st.lists(st.tuples(*[st.integers(-3, 33)] * 3), max_size=60),
    coordinate=st.sampled_from([0.0, 1e-300, 1e300, np.nan, np.inf, -np.inf]),
    seed=st.integers(0, 2**32 - 1),
)
def test_random_meshes_are_analysed_or_refused_by_name(num_vertices, faces, coordinate, seed):
    """Any (V, 3) vertices and (F, 3) indices: a report whose components cover every
    proper face once, or a ValueError naming the vertices or the faces."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(num_vertices, 3))
    vertices[rng.integers(num_vertices)] = coordinate
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    try:
        report = _mesh.analyze_mesh(vertices, faces, vertices + 0.1)
    except ValueError as exc:
        assert "vertices" in str(exc) or "faces" in str(exc) or "points" in str(exc)
        return
    assert np.isfinite(vertices).all() and (faces.size == 0 or faces.min() >= 0)
    covered = np.sort(np.concatenate([c.faces for c in report.components] + [np.arange(0)]))
    assert len(np.unique(covered)) == len(covered)
    proper = faces[
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    ]
    assert len(covered) == len(np.unique(np.sort(proper, axis=1), axis=0))
    for c in report.components:
        assert c.area >= 0 and (c.genus is None or c.closed)


def test_unique_rows_are_numpy_s():
    """The weld's row sort gives ``np.unique(axis=0)``'s rows, order and inverse, with
    repeated rows, ties in the first columns and -0.0 beside 0.0."""
    from jurs.levelset import _meshing

    rng = np.random.default_rng(3)
    rows = np.round(rng.normal(size=(2000, 3)), 1)
    rows = np.concatenate(
        [rows, rows[rng.permutation(2000)[:700]], [[0.0, -0.0, 1.0]], [[-0.0, 0.0, 1.0]]]
    )
    got, inverse = _meshing._unique_rows(rows)
    want, want_inverse = np.unique(rows, axis=0, return_inverse=True)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(inverse, want_inverse.reshape(-1))


def test_unique_edges_is_numpys_unique_of_the_pairs():
    """The one-key unique of sorted vertex pairs: the same pairs, order, first indices,
    inverse and counts as ``np.unique(axis=0)``."""
    from jurs.levelset._faces import face_edges, unique_edges

    faces = np.random.default_rng(0).integers(0, 50, (400, 3))
    edges = face_edges(faces)
    mine = unique_edges(edges, return_index=True, return_inverse=True, return_counts=True)
    numpys = np.unique(edges, axis=0, return_index=True, return_inverse=True, return_counts=True)
    for a, b in zip(mine, numpys):
        np.testing.assert_array_equal(np.asarray(a).reshape(-1), np.asarray(b).reshape(-1))
    np.testing.assert_array_equal(unique_edges(edges), np.unique(edges, axis=0))
