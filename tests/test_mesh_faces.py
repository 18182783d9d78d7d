"""Face budgets: ``jurs.levelset.mesh(..., faces=F)`` decimates the marching-cubes mesh with
fast-simplification and moves the kept vertices back onto the zero set."""

import sys

import numpy as np
import pytest
from test_mesh import exact_sphere, face_normals, hemisphere_points, sampled_spline

import jurs
from jurs import levelset
from jurs._model.spline import grid_spline
from jurs.levelset import _meshing

pytest.importorskip("skimage")
pytest.importorskip("fast_simplification")


def distances_to_zero_set(spline, points):
    """``|g| / |grad g|`` at ``points``: their distance to {g = 0} to first order."""
    value, gradient = grid_spline(spline, dims=(3,)).values_and_gradients(points)
    return np.abs(np.asarray(value)) / np.linalg.norm(np.asarray(gradient), axis=1)


def outward(spline, vertices, faces):
    """Whether every face's normal points along grad g at its centroid (towards g > 0)."""
    centroids = vertices[faces].mean(axis=1)
    _, gradient = grid_spline(spline, dims=(3,)).values_and_gradients(centroids)
    return bool((np.sum(face_normals(vertices, faces) * np.asarray(gradient), axis=1) > 0).all())


@pytest.fixture(scope="module")
def torus_fit():
    """A torus fitted on an 8^3 grid, and its dense mesh."""
    spline = jurs.fit(*jurs.datasets.torus(1000, seed=0), grid=8).spline
    return spline, levelset.mesh(spline)


@pytest.mark.slow  # the fit: about 15 s on a loaded 2-core machine, most of it compiling
def test_decimated_torus_fit_is_closed_outward_on_the_zero_set_and_near_the_dense_mesh(
    torus_fit,
):
    spline, (dense_vertices, dense_faces) = torus_fit
    cell = float(np.min(grid_spline(spline, dims=(3,)).cell_widths))
    dense = levelset.analyze_mesh(dense_vertices, dense_faces)
    assert [(c.closed, c.genus) for c in dense.components] == [(True, 1)]
    assert len(dense_faces) > 10_000
    for budget in (2000, 300):
        vertices, faces = levelset.mesh(spline, faces=budget)
        # The library stops at the budget or one face below it (a collapse removes two).
        assert budget - 1 <= len(faces) <= budget
        assert vertices.dtype == np.float64 and faces.dtype == np.int64
        report = levelset.analyze_mesh(vertices, faces)
        assert [(c.closed, c.genus) for c in report.components] == [(True, 1)]
        assert report.num_boundary_loops == 0
        assert len(np.unique(faces)) == len(vertices)  # no unused vertex
        # Newton steps put the vertices back on the zero set ...
        assert distances_to_zero_set(spline, vertices).max() < 1e-6 * cell
        # ... and the faces still point outward, as the dense mesh's.
        assert outward(spline, vertices, faces) and outward(spline, dense_vertices, dense_faces)
        # Against the dense mesh's vertices: near it relative to the fit's cell.
        near = levelset.mesh_distances(vertices, faces, dense_vertices)
        assert near["chamfer"] < 0.1 * cell and near["hausdorff"] < 0.5 * cell
    # Without the Newton steps the decimated vertices lie off the zero set.
    rough, faces = levelset.mesh(spline, faces=300, newton_steps=0)
    assert distances_to_zero_set(spline, rough).max() > 1e-3 * cell


def test_no_budget_or_a_large_one_leaves_the_mesh_as_it_was():
    spline = exact_sphere(radius=1.0, n=10)
    vertices, faces = levelset.mesh(spline, 24)
    for budget in (None, len(faces), 10 * len(faces)):
        again = levelset.mesh(spline, 24, faces=budget)
        np.testing.assert_array_equal(again[0], vertices)
        np.testing.assert_array_equal(again[1], faces)


def test_decimated_sphere_down_to_a_tetrahedron():
    spline = exact_sphere(radius=1.0)
    # Two Newton steps from farther off the coarser the mesh (quadratic convergence).
    for budget, tolerance in ((500, 1e-8), (50, 1e-4), (4, 1e-2)):
        vertices, faces = levelset.mesh(spline, faces=budget)
        assert budget - 1 <= len(faces) <= budget
        (component,) = levelset.analyze_mesh(vertices, faces).components
        assert component.closed and component.genus == 0
        assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < tolerance
        assert outward(spline, vertices, faces)


def test_decimation_does_not_depend_on_the_units():
    """fast-simplification's collapse schedule is in absolute units: the mesh is scaled
    into a box of ``DECIMATION_BOX`` first, so a sphere of radius 1000 decimates as one of
    radius 1."""
    simplify = _meshing.fast_simplification_simplify()
    vertices, faces = levelset.mesh(exact_sphere(radius=1.0))
    small = _meshing._decimate(simplify, vertices, faces, 300)
    large = _meshing._decimate(simplify, 1000.0 * vertices + 5000.0, faces, 300)
    np.testing.assert_array_equal(small[1], large[1])
    np.testing.assert_allclose((large[0] - 5000.0) / 1000.0, small[0], atol=1e-9)


def test_trimmed_scan_is_decimated_after_the_trim_and_stays_open():
    spline = exact_sphere(radius=1.0, n=10)
    points = hemisphere_points()
    whole = levelset.mesh(spline, 24, points=points, trim=True)
    vertices, faces = levelset.mesh(spline, 24, points=points, trim=True, faces=500)
    assert 499 <= len(faces) <= 500 < len(whole[1])
    report = levelset.analyze_mesh(vertices, faces, points)
    assert report.num_components == 1 and report.num_boundary_loops == 1
    assert not report.components[0].closed
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 1e-6
    assert outward(spline, vertices, faces)
    # The boundary is decimated along itself: the rim stays where the trim put it.
    assert abs(vertices[:, 2].min() - whole[0][:, 2].min()) < 0.05
    # An edge from the boundary inwards is never collapsed, so a small budget stops above.
    assert len(levelset.mesh(spline, 24, points=points, trim=True, faces=20)[1]) > 20


def test_torus_with_two_budgets_has_genus_1():
    torus = sampled_spline(
        lambda p: np.hypot(np.hypot(p[:, 0], p[:, 1]) - 1.0, p[:, 2]) - 0.35,
        [-1.6, -1.6, -0.6],
        [1.6, 1.6, 0.6],
        (19, 19, 9),
    )
    for budget in (3000, 200):
        vertices, faces = levelset.mesh(torus, faces=budget)
        assert len(faces) <= budget and levelset.genus(faces) == 1
        assert outward(torus, vertices, faces)


@pytest.mark.parametrize(
    "faces, match",
    [
        (3, "at least 4"),
        (0, "at least 4"),
        (-10, "at least 4"),
        (2.5, "integer"),
        (1000.0, "integer"),
        ("1000", "integer"),
        (True, "integer"),
    ],
)
def test_bad_budgets_are_refused_before_the_lattice(faces, match):
    # A lattice of 1e18 nodes would be refused too, by its size: the budget comes first.
    with pytest.raises(ValueError, match=f"faces must .*{match}"):
        levelset.mesh(exact_sphere(), 10**6, faces=faces)


def test_missing_fast_simplification_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "fast_simplification", None)
    spline = exact_sphere(radius=1.0, n=8)
    with pytest.raises(ImportError, match=r"fast-simplification.*pip install -e '\.\[surfaces\]'"):
        levelset.mesh(spline, 10**6, faces=100)  # before the lattice's size is checked
    assert len(levelset.mesh(spline, 16)[1]) > 0  # without a budget it is not needed


def test_fast_simplification_is_imported_only_for_a_budget():
    import subprocess

    code = (
        "import sys, jurs.levelset as ls; from jurs.levelset import _meshing; "
        "print('fast_simplification' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-1] == "False"
