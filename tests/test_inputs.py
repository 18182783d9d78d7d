"""Bad inputs raise ValueError naming the problem, and nothing the caller passed is changed."""

import numpy as np
import pytest

import jurs


@pytest.fixture
def cloud():
    return jurs.datasets.example1(30)


def fit_small(points, normals, **kw):
    kw.setdefault("solver", jurs.IPIA(max_steps=2))
    kw.setdefault("grid", (6, 6))
    kw.setdefault("offset", 0.1)
    kw.setdefault("eps", 0.01)
    return jurs.fit(points, normals, **kw)


@pytest.mark.parametrize("where", ["points", "normals"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite(cloud, where, bad):
    points, normals = (a.copy() for a in cloud)
    (points if where == "points" else normals)[4, 1] = bad
    with pytest.raises(ValueError, match=rf"{where} contain NaN or Inf \(first at row 4\)"):
        fit_small(points, normals)


def test_shapes(cloud):
    points, normals = cloud
    with pytest.raises(ValueError, match=r"points must have shape \(m, 2\)"):
        fit_small(np.ones((30, 4)), np.ones((30, 4)))
    with pytest.raises(ValueError, match="normals must have the same shape"):
        fit_small(points, normals[:-1])
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_small(points[:2], normals[:2])
    with pytest.raises(ValueError, match=r"mask must have shape \(30,\)"):
        fit_small(points, normals, mask=np.ones(29, bool))


def test_zero_length_normal(cloud):
    points, normals = (a.copy() for a in cloud)
    normals[7] = 0.0
    with pytest.raises(ValueError, match=r"zero-length normal at row 7"):
        fit_small(points, normals)


@pytest.mark.parametrize("grid", [3, (4, 3), (2, 9), 0])
def test_grid_too_small(cloud, grid):
    with pytest.raises(ValueError, match="at least 4 x 4"):
        fit_small(*cloud, grid=grid)


@pytest.mark.parametrize("grid", [(9,), (9, 9, 9), "nine", (9.5, 9)])
def test_grid_malformed(cloud, grid):
    with pytest.raises(ValueError, match="grid"):
        fit_small(*cloud, grid=grid)


@pytest.mark.parametrize("name", ["offset", "eps"])
@pytest.mark.parametrize("value", [-0.1, 0.0, np.nan])
def test_offset_and_eps(cloud, name, value):
    with pytest.raises(ValueError, match=name):
        fit_small(*cloud, **{name: value})


@pytest.mark.parametrize("field", ["tau", "lam", "tol"])
def test_negative_solver_parameters(field):
    with pytest.raises(ValueError, match=rf"{field} must be non-negative"):
        jurs.IURS(**{field: -1e-3})
    with pytest.raises(ValueError, match="min_weight must be positive"):
        jurs.IURS(min_weight=0.0)
    with pytest.raises(ValueError, match="tol must be non-negative"):
        jurs.IPIA(tol=-1.0)


def test_domain(cloud):
    points, normals = cloud
    with pytest.raises(ValueError, match=r"points outside the given domain \(first at row"):
        fit_small(points, normals, domain=((-1.0, -1.0), (1.0, 1.0)))
    # Data inside, but the offsets P +/- d n poke out.
    lo, hi = points.min(axis=0), points.max(axis=0)
    with pytest.raises(ValueError, match="offset samples"):
        fit_small(points, normals, domain=(tuple(lo), tuple(hi)), offset=0.1)
    with pytest.raises(ValueError, match="min < max"):
        fit_small(points, normals, domain=((5.0, -9.0), (-5.0, 1.0)))
    with pytest.raises(ValueError, match="domain must be"):
        fit_small(points, normals, domain=(0.0, 1.0))


def test_solver_type(cloud):
    with pytest.raises(TypeError, match="jurs solver"):
        jurs.fit(*cloud, solver="IURS")


def test_inputs_are_not_modified(cloud):
    points, normals = cloud
    normals = 3.0 * normals  # not unit length: normalised inside, not in place
    before = points.copy(), normals.copy()
    sol = fit_small(points, normals)
    np.testing.assert_array_equal(points, before[0])
    np.testing.assert_array_equal(normals, before[1])
    # Scaling the normals does not change the fit (they are normalised).
    unit = fit_small(points, normals / 3.0)
    np.testing.assert_allclose(
        np.asarray(sol.spline.control), np.asarray(unit.spline.control), rtol=1e-12
    )


def test_bucket_size(cloud):
    with pytest.raises(ValueError, match="bucket_size must be a positive int"):
        jurs.make_problem(*cloud, grid=6, bucket_size=0)
    problem = jurs.make_problem(*cloud, grid=6, bucket_size=4)
    assert problem.local.bucket_size == 4
    slots = problem.samples.shape[0]
    assert slots % 4 == 0 and slots > 90, "30 points give 90 samples, padded into full buckets"
    assert float(problem.mask.sum()) == 90.0
