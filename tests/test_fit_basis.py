"""``jurs.fit``'s choice of basis: the adaptive (THB) basis where the data ask for finer
cells than the automatic uniform grid affords, the uniform grid otherwise or when asked."""

import dataclasses
import json

import jax
import numpy as np
import pytest

import jurs
from jurs import cli
from jurs._fit.adaptive import (
    AUTO_MAX_FINEST_3D,
    AUTO_MAX_SURFACE_POINTS,
    AUTO_REFINEMENT,
    NOISY_SPACINGS,
    UNIFORM_RESIDUAL_SPACINGS,
    auto_finest,
    hierarchy_stride,
    noise_decides,
    uniform_residual,
    wants_adaptive,
)
from jurs._fit.settings import data_cell


def _ellipse(m: int):
    t = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
    points = np.c_[np.cos(t), 0.5 * np.sin(t)]
    normals = np.c_[np.cos(t), 2.0 * np.sin(t)]
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _wiggly_circle(m: int, waves: int = 60, amplitude: float = 0.01):
    """A unit circle with ``waves`` bumps of ``amplitude`` along it: detail about three
    cells of the capped uniform grid wide."""
    t = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
    r = 1.0 + amplitude * np.sin(waves * t)
    dr = amplitude * waves * np.cos(waves * t)
    points = np.c_[r * np.cos(t), r * np.sin(t)]
    tangents = np.c_[dr * np.cos(t) - r * np.sin(t), dr * np.sin(t) + r * np.cos(t)]
    normals = np.c_[tangents[:, 1], -tangents[:, 0]]
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def dense():
    """An ellipse sampled densely enough that its uniform grid is capped."""
    return _ellipse(1000)


@pytest.fixture(scope="module")
def detailed():
    """A circle with fine bumps, sampled densely enough that its uniform grid is capped."""
    return _wiggly_circle(1500)


def test_detailed_dense_cloud_is_fitted_on_the_adaptive_basis(detailed):
    """Cells of the capped grid wider than the data ask for, and its fit leaves the bumps:
    the default fit is the adaptive one (the same spline as fit_adaptive with those
    settings), and basis='uniform' or a grid given keeps the uniform grid. The bumps
    scatter the points about local quadratics by more than ``NOISY_SPACINGS``, so the
    default goes to the hierarchy without the grid's trial fit."""
    points, normals = detailed
    sol = jurs.fit(points, normals)
    assert isinstance(sol.spline, jurs.AdaptiveSpline) and sol.succeeded
    settings = sol.settings
    assert settings.cell_width >= AUTO_REFINEMENT * settings.data_cell
    assert noise_decides(settings)
    assert sol.stats["noise_spacings"] >= NOISY_SPACINGS
    assert "uniform_residual" not in sol.stats  # no trial fit
    assert max(sol.stats["finest"]) > max(settings.grid)
    direct = jurs.fit_adaptive(points, normals, settings=settings)
    np.testing.assert_array_equal(np.asarray(sol.spline.control), direct.spline.control)
    uniform = jurs.fit(points, normals, basis="uniform")
    assert isinstance(uniform.spline, jurs.ImplicitSpline)
    assert uniform.settings.grid == settings.grid
    # The finer basis follows the bumps closer than the capped grid: the residual that
    # chose it, measured again on both fits.
    cloud = jurs.Cloud(points, normals)
    far = [uniform_residual(s.spline, cloud, settings) for s in (sol, uniform)]
    assert far[0] < UNIFORM_RESIDUAL_SPACINGS < far[1]
    given = jurs.fit(points, normals, grid=(16, 12))
    assert isinstance(given.spline, jurs.ImplicitSpline)
    assert jurs.auto_settings(points, normals, grid=(16, 12)).data_cell is None


def test_a_large_cloud_fits_a_strided_subsample_on_the_hierarchy(detailed, monkeypatch):
    """Above the point limit (``hierarchy_stride`` > 1: surfaces only, here forced on a
    curve) the automatic hierarchy fits every k-th point with settings chosen for them, the
    same spline as ``fit_adaptive`` of that subsample with those settings; whether the
    grid is capped is asked with the subsample's ``data_cell``."""
    from jurs._fit import fit as _fit

    points, normals = _wiggly_circle(3000)
    monkeypatch.setattr(_fit, "hierarchy_stride", lambda count, ndim: 2)
    sol = jurs.fit(points, normals)
    assert isinstance(sol.spline, jurs.AdaptiveSpline) and sol.succeeded
    assert sol.stats["hierarchy_stride"] == 2 and sol.stats["hierarchy_points"] == 1500
    whole = jurs.auto_settings(points, normals)
    assert sol.settings.spacing > 1.5 * whole.spacing  # the subsample's own settings
    sub = jurs.fit_adaptive(points[::2], normals[::2], settings=sol.settings)
    # To rounding: the fit reads the cloud's unit normals, normalised once more here.
    np.testing.assert_allclose(sol.spline.control, sub.spline.control, rtol=0, atol=1e-12)
    # basis="adaptive" fits every point, as asked.
    assert "hierarchy_points" not in jurs.fit(points, normals, basis="adaptive").stats
    # The 1500-point cloud's subsample of 750 asks for cells its grid's cap allows: the
    # whole cloud's grid is fitted, though the whole cloud's own ask is capped.
    points, normals = detailed
    assert wants_adaptive(jurs.auto_settings(points, normals))
    kept = jurs.fit(points, normals)
    assert isinstance(kept.spline, jurs.ImplicitSpline) and "hierarchy_points" not in kept.stats
    assert kept.settings == jurs.auto_settings(points, normals)


def test_smooth_dense_cloud_keeps_the_capped_grid(dense):
    """A capped grid whose fit follows a smooth shape closely is kept: the hierarchy would
    cost more for the same zero set."""
    points, normals = dense
    sol = jurs.fit(points, normals)
    assert isinstance(sol.spline, jurs.ImplicitSpline) and sol.succeeded
    assert sol.settings.cell_width >= AUTO_REFINEMENT * sol.settings.data_cell
    assert not noise_decides(sol.settings)
    assert sol.stats["uniform_residual"] <= UNIFORM_RESIDUAL_SPACINGS
    uniform = jurs.fit(points, normals, basis="uniform")
    np.testing.assert_array_equal(
        np.asarray(sol.spline.control), np.asarray(uniform.spline.control)
    )
    adaptive = jurs.fit(points, normals, basis="adaptive")
    assert isinstance(adaptive.spline, jurs.AdaptiveSpline)
    # Both zero sets lie within the residual bound of the data.
    for fit in (sol, adaptive):
        residual = uniform_residual(fit.spline, jurs.Cloud(points, normals), sol.settings)
        assert residual <= UNIFORM_RESIDUAL_SPACINGS


def test_sparse_cloud_keeps_the_uniform_grid():
    """A grid that gives the cells the data ask for: the uniform fit, as before."""
    points, normals = _ellipse(120)
    sol = jurs.fit(points, normals)
    assert isinstance(sol.spline, jurs.ImplicitSpline)
    assert sol.settings.cell_width < AUTO_REFINEMENT * sol.settings.data_cell
    adaptive = jurs.fit(points, normals, basis="adaptive")
    assert isinstance(adaptive.spline, jurs.AdaptiveSpline)
    assert adaptive.settings == sol.settings


def test_basis_arguments_are_checked(dense):
    points, normals = dense
    with pytest.raises(ValueError, match="basis must be one of"):
        jurs.fit(points, normals, basis="octree")
    extras: tuple[tuple[dict, str], ...] = (
        (dict(grid=(16, 12)), "grid"),
        (dict(bucket_size=4), "bucket_size"),
    )
    for extra, name in extras:
        with pytest.raises(ValueError, match=f"takes no {name}"):
            jurs.fit(points, normals, basis="adaptive", **extra)
    # The hierarchy takes LeastSquares and RobustLeastSquares (tests/test_hierarchy_solvers.py)
    # and refuses the grid's other solvers with the reason.
    with pytest.raises(ValueError, match="paper's iterations"):
        jurs.fit(points, normals, basis="adaptive", solver=jurs.IPIA(max_steps=3))
    # A callback (a chunked run) keeps the uniform grid.
    calls = []
    sol = jurs.fit(points, normals, callback=lambda done, total: calls.append(done))
    assert isinstance(sol.spline, jurs.ImplicitSpline) and calls


def test_rule_on_settings():
    """``wants_adaptive``: grid given (no data cell) never; ``auto_finest`` caps a
    surface's finest level only; ``hierarchy_stride`` keeps at most the point limit of a
    surface, every point of a curve."""
    settings = jurs.Settings(
        grid=(99, 99),
        offset=0.01,
        eps=0.01,
        lam=1e-6,
        smoothing=1e-6,
        domain=((0.0, 0.0), (96.0, 96.0)),
        spacing=0.1,
        noise=0.0,
        data_cell=data_cell(2, 0.1, 0.0),
    )
    assert wants_adaptive(settings)
    assert not wants_adaptive(dataclasses.replace(settings, data_cell=None))
    assert not wants_adaptive(dataclasses.replace(settings, data_cell=1.01 / AUTO_REFINEMENT))
    assert auto_finest(settings) is None
    surface = dataclasses.replace(
        settings, grid=(51, 51, 51), domain=((0.0,) * 3, (48.0,) * 3), data_cell=0.3
    )
    assert auto_finest(surface) is None  # 48 / 0.3 = 160 cells asked for: not capped
    surface = dataclasses.replace(surface, spacing=0.03, data_cell=0.09)
    assert wants_adaptive(surface)
    # The data's ask measured elsewhere (a large surface's subsample) decides instead.
    assert not wants_adaptive(surface, data_cell=1.01 / AUTO_REFINEMENT)
    assert wants_adaptive(dataclasses.replace(surface, data_cell=1.0), data_cell=0.09)
    assert hierarchy_stride(AUTO_MAX_SURFACE_POINTS, 3) == 1
    assert hierarchy_stride(AUTO_MAX_SURFACE_POINTS + 1, 3) == 2
    assert hierarchy_stride(10**6, 3) == 7  # 142 858 points kept
    assert hierarchy_stride(10**6, 2) == 1
    assert auto_finest(surface) == AUTO_MAX_FINEST_3D  # 48 / 0.09 = 533 cells asked for


def test_command_line_follows_the_same_rule(dense, detailed, tmp_path):
    for name, cloud, args, basis in (
        ("ellipse", dense, [], None),
        ("wiggly", detailed, [], "adaptive"),
        ("wiggly", detailed, ["--basis", "uniform"], None),
    ):
        path = tmp_path / f"{name}.csv"
        jurs.datasets.save_points(path, *cloud)
        out = tmp_path / f"out_{name}{len(args)}"
        assert cli.main(["fit", str(path), "-o", str(out), "-q", *args]) == 0
        settings = json.loads((out / "metrics.json").read_text())["settings"]
        assert settings.get("basis") == basis
        assert (settings["grid"] is None) == (basis == "adaptive")


def test_new_dense_clouds_compile_nothing(detailed):
    """After one default fit of a detailed dense cloud, detailed clouds of other sizes
    with the same capped grid compile nothing: the uniform fit they try first shares its
    compiled solve, and the hierarchy is built, solved and checked on the host (a compiled
    check per new hierarchy cost seconds)."""
    jurs.fit(*detailed)
    counts = []

    def count(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            counts.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        sols = [jurs.fit(*_wiggly_circle(m, waves)) for m, waves in ((1400, 50), (1600, 70))]
    finally:
        jax.monitoring.unregister_event_duration_listener(count)
    assert counts == []
    assert all(isinstance(sol.spline, jurs.AdaptiveSpline) and sol.succeeded for sol in sols)


def test_an_offset_given_beside_settings_reaches_the_hierarchy():
    """``jurs.fit(..., basis="adaptive", settings=s, offset=o)`` fitted with ``s.offset``
    on the hierarchy, where the grid takes ``o``: the hierarchy now takes it too, as
    ``jurs.fit_adaptive(..., settings=s, offset=o)`` does."""
    points, normals = jurs.datasets.example1(300)
    settings = jurs.auto_settings(jurs.Cloud(points, normals))
    offset = 2.0 * settings.offset
    given = jurs.fit(points, normals, basis="adaptive", settings=settings, offset=offset)
    alone = jurs.fit(points, normals, basis="adaptive", settings=settings)
    direct = jurs.fit_adaptive(
        points, normals, settings=settings, offset=offset, finest=auto_finest(settings)
    )
    np.testing.assert_allclose(
        np.asarray(given.spline.control), np.asarray(direct.spline.control), rtol=0, atol=1e-12
    )
    probe = points + 0.5 * settings.offset * normals  # g there follows the offset's target
    assert np.abs(np.asarray(given.spline(probe)) - np.asarray(alone.spline(probe))).max() > 1e-6
