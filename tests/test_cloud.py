"""jurs.Cloud: a cloud checked and measured once, reused across fits."""

import sys

import jax
import numpy as np
import pytest

import jurs
from jurs._cloud import cloud as cloud_module
from jurs._problem import memory, validate

PAPER = dict(grid=(9, 9), offset=0.1, eps=0.01)


def _count_calls(monkeypatch, function) -> list:
    """Counts the calls of ``function`` from every jurs module that imported it."""
    calls = []

    def counting(*args, **kwargs):
        calls.append(1)
        return function(*args, **kwargs)

    for name, module in list(sys.modules.items()):
        if name == "jurs" or name.startswith("jurs."):
            for attribute, value in list(vars(module).items()):
                if value is function:
                    monkeypatch.setattr(module, attribute, counting)
    return calls


@pytest.mark.parametrize("automatic", [True, False])
def test_checks_run_once_per_fit(monkeypatch, automatic):
    """Validation of the points, normalisation of the grid and the memory check run once
    each in a fit, automatic or fully specified (they ran two or three times)."""
    points, normals = jurs.datasets.example1(300)
    validated = _count_calls(monkeypatch, validate.validate_points)
    normalised = _count_calls(monkeypatch, validate.normalise_grid)
    memory_checked = _count_calls(monkeypatch, memory.check_memory)
    kwargs = {} if automatic else dict(PAPER, solver=jurs.LeastSquares(lam=1e-6))
    sol = jurs.fit(points, normals, grid=12, **{k: v for k, v in kwargs.items() if k != "grid"})
    assert sol.status in ("successful", "doubtful")
    assert len(validated) == 1
    assert len(normalised) == 1
    assert len(memory_checked) == 1


def test_a_cloud_is_measured_once_and_fits_as_arrays_do(monkeypatch):
    """A Cloud passed to several fits is validated and orientation-checked once, and each
    fit equals the fit of the arrays."""
    points, normals = jurs.datasets.example1(120)
    solver = jurs.LeastSquares(lam=1e-6)
    cloud = jurs.Cloud(points, normals)
    orientation = _count_calls(monkeypatch, cloud_module.flipped_normal_fraction)
    validated = _count_calls(monkeypatch, validate.validate_points)
    first = jurs.fit(cloud, solver=solver, **PAPER)
    second = jurs.fit(cloud, solver=jurs.LeastSquares(lam=1e-4), **PAPER)
    assert len(orientation) == 1 and len(validated) == 0
    plain = jurs.fit(points, normals, solver=solver, **PAPER)
    np.testing.assert_allclose(first.spline.control, plain.spline.control, rtol=1e-12)
    assert float(first.metrics["flipped_normal_fraction"]) == 0.0
    assert not np.allclose(first.spline.control, second.spline.control)
    assert "Cloud(120 points in 2D, with normals)" == repr(cloud)


def test_a_cloud_with_automatic_settings_matches_the_arrays():
    points, normals = jurs.datasets.example1(200)
    cloud = jurs.Cloud(points, normals)
    settings = jurs.auto_settings(cloud)
    assert settings == jurs.auto_settings(points, normals)
    from_cloud = jurs.fit(cloud)
    from_arrays = jurs.fit(points, normals)
    assert from_cloud.settings == from_arrays.settings
    np.testing.assert_allclose(from_cloud.spline.control, from_arrays.spline.control, rtol=1e-10)
    # Settings chosen before give the same fit without choosing again.
    again = jurs.fit(cloud, settings=settings)
    np.testing.assert_allclose(again.spline.control, from_arrays.spline.control, rtol=1e-10)
    assert "far_point_fraction" in again.metrics  # the doubt checks of automatic settings


def test_checks_false_skips_the_verdicts_of_the_host():
    """checks=False returns the solver's verdict: half-flipped normals fit without
    inconsistent_normals from the host check (the caller said the data are fine)."""
    points, normals = jurs.datasets.example1(120)
    half = normals.copy()
    half[:60] *= -1
    solver = jurs.LeastSquares(lam=1e-6)
    checked = jurs.fit(points, half, solver=solver, throw=False, **PAPER)
    assert checked.status == "inconsistent_normals"
    assert "flipped_normal_fraction" in checked.metrics
    unchecked = jurs.fit(points, half, solver=solver, throw=False, checks=False, **PAPER)
    assert "flipped_normal_fraction" not in unchecked.metrics
    np.testing.assert_allclose(unchecked.spline.control, checked.spline.control, rtol=1e-12)


def test_cloud_refuses_bad_input_and_traced_points():
    with pytest.raises(ValueError, match="NaN"):
        jurs.Cloud(np.array([[0.0, 0.0], [1.0, np.nan], [0.0, 1.0]]), np.ones((3, 2)))
    with pytest.raises(ValueError, match="shape"):
        jurs.Cloud(np.zeros((5, 4)), np.ones((5, 4)))
    points, normals = jurs.datasets.example1(60)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda p: jurs.Cloud(p, normals).ndim)(points)
    cloud = jurs.Cloud(points, normals)
    with pytest.raises(ValueError, match="holds its normals"):
        jurs.fit(cloud, normals, **PAPER)
    with pytest.raises(ValueError, match="holds its normals"):
        jurs.auto_settings(cloud, normals)


def test_a_cloud_without_normals_is_fitted_as_points_alone():
    points, _ = jurs.datasets.example1(150)
    from_cloud = jurs.fit(jurs.Cloud(points), **PAPER, solver=jurs.LeastSquares(lam=1e-6))
    from_points = jurs.fit(points, **PAPER, solver=jurs.LeastSquares(lam=1e-6))
    assert "estimated_normals" in from_cloud.stats
    np.testing.assert_allclose(from_cloud.spline.control, from_points.spline.control, rtol=1e-12)
    masked = jurs.Cloud(points, mask=np.arange(150) < 140)
    with pytest.raises(ValueError, match="takes no mask"):
        jurs.fit(masked, **PAPER, solver=jurs.LeastSquares(lam=1e-6))


def test_a_cloud_keeps_its_own_copy():
    """Editing the arrays after building the Cloud changes neither its measurements nor
    its fits."""
    points, normals = jurs.datasets.example1(120)
    points, normals = points.copy(), normals.copy()
    cloud = jurs.Cloud(points, normals)
    before = jurs.fit(cloud, solver=jurs.LeastSquares(lam=1e-6), **PAPER)
    points += 5.0
    normals *= -1.0
    after = jurs.fit(cloud, solver=jurs.LeastSquares(lam=1e-6), **PAPER)
    np.testing.assert_array_equal(before.spline.control, after.spline.control)
    assert after.status == "successful"


def _circle(m, centre=0.0):
    t = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
    unit = np.stack([np.cos(t), np.sin(t)], axis=1)
    return unit + centre, unit


def test_repeated_points_are_kept_once_with_a_warning():
    """A cloud with every point given four times was refused as "all points coincide"
    (its nearest other points were its own copies); with normals estimated it read as
    inconsistent. Repeats are kept once, with a warning that counts them."""
    points, normals = _circle(150)
    repeated = np.repeat(points, 4, axis=0)
    with pytest.warns(UserWarning, match="450 of the 600 points repeat"):
        cloud = jurs.Cloud(repeated, np.repeat(normals, 4, axis=0))
    assert len(cloud) == 150 and cloud.repeated == 450
    np.testing.assert_array_equal(cloud.points, points)
    for given in ((repeated, np.repeat(normals, 4, axis=0)), (repeated,)):
        with pytest.warns(UserWarning, match="repeat others exactly"):
            sol = jurs.fit(*given)
        assert sol.status == "successful"


def test_repeats_with_opposed_normals_keep_the_first():
    points, normals = _circle(40)
    flipped = np.concatenate([points, points[:1]]), np.concatenate([normals, -normals[:1]])
    with pytest.warns(UserWarning, match="1 of the 41 points"):
        cloud = jurs.Cloud(*flipped)
    assert cloud.normals is not None
    np.testing.assert_allclose(cloud.normals[0], normals[0])


@pytest.mark.parametrize("estimated", [False, True])
def test_float32_rounding_that_merges_points_is_named(estimated):
    """Float32 coordinates 1e7 from the origin collapse onto a few distinct points; the
    error blamed "coincident points", not the precision."""
    points, normals = _circle(200, centre=1e7)
    given = (points.astype(np.float32),) + (() if estimated else (normals,))
    with pytest.raises(ValueError, match="float32, which at .* resolves only steps of 1"):
        jurs.fit(*given)


@pytest.mark.parametrize("estimated", [False, True])
@pytest.mark.parametrize(
    "points, where",
    [
        (np.c_[np.random.default_rng(0).uniform(-1, 1, (300, 2)), np.zeros(300)], "in a plane"),
        (np.c_[np.linspace(0, 1, 60), 2 * np.linspace(0, 1, 60), np.full(60, 5.0)], "on a line"),
        (np.c_[np.linspace(0, 1, 60), 2 * np.linspace(0, 1, 60)], "on a line"),
    ],
)
def test_clouds_that_enclose_nothing_are_refused(points, where, estimated):
    """A planar XYZ cloud with normals estimated was fitted as a "surface" (or crashed
    in ARPACK); a collinear one likewise."""
    normals = np.zeros_like(points)
    normals[:, -1] = 1.0
    if points.shape[1] == 2:
        normals = np.tile([-2.0, 1.0], (len(points), 1))
    given = (points,) if estimated else (points, normals)
    with pytest.raises(ValueError, match=f"points lie {where}"):
        jurs.fit(*given)


def test_a_flat_but_closed_cloud_is_not_refused():
    """An ellipse 50 times longer than wide encloses an area: its width is many spacings."""
    t = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    points = np.stack([50.0 * np.cos(t), np.sin(t)], axis=1)
    normals = np.stack([np.cos(t) / 50.0, np.sin(t)], axis=1)
    assert len(jurs.Cloud(points, normals)) == 400
