"""Automatic settings: what they measure, that they move with the data, and that the default
fit gives a clean zero set."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jurs
import jurs.levelset as ls
import jurs.shapes
from jurs._cloud import measure as _measure
from jurs._fit import settings as _defaults

ROT90 = np.array([[0.0, -1.0], [1.0, 0.0]])


def reference(name):
    return np.concatenate(
        [ls.resample(np.vstack([c, c[:1]]), 0.01) for c in jurs.shapes.outline(name)]
    )


def diagonal(points):
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def zero_set(sol, resolution=400):
    lines = ls.zero_level_set(sol.spline, resolution)
    return np.concatenate([ls.resample(p, 0.005) for p, _ in lines])


@pytest.fixture(scope="module")
def lobes():
    return jurs.shapes.get("lobes", 300)


@pytest.fixture(scope="module")
def lobes_fit(lobes):
    return jurs.fit(*lobes)


def test_noise_estimate():
    p, n = jurs.shapes.get("ellipse", 800)
    assert _measure.estimate_noise(p, n) < 1e-4  # the quadratic absorbs the curvature
    for sigma in (0.02, 0.05):
        noisy, noisy_n = jurs.datasets.add_noise(p, n, sigma=sigma, seed=2)
        assert abs(_measure.estimate_noise(noisy, noisy_n) / sigma - 1.0) < 0.25


def test_settings_scale_and_rotate_with_the_data(lobes):
    p, n = lobes
    base = jurs.auto_settings(p, n)
    scaled = jurs.auto_settings(3.0 * p + 7.0, n)
    np.testing.assert_allclose(
        [scaled.spacing, scaled.offset, scaled.eps],
        [3 * base.spacing, 3 * base.offset, 3 * base.eps],
        rtol=1e-9,
    )
    assert scaled.grid == base.grid
    np.testing.assert_allclose(
        [scaled.lam, scaled.smoothing], [base.lam, base.smoothing], rtol=1e-9
    )
    np.testing.assert_allclose(
        np.asarray(scaled.domain), 3 * np.asarray(base.domain) + 7, rtol=1e-9, atol=1e-9
    )
    turned = jurs.auto_settings(p @ ROT90.T, n @ ROT90.T)
    assert turned.grid == base.grid[::-1]
    np.testing.assert_allclose([turned.offset, turned.lam], [base.offset, base.lam], rtol=1e-9)


def test_lam_is_scale_free_in_m_and_grid():
    """Same shape, density and grid doubled: lambda grows with the samples and nothing else
    (R does not grow with the grid)."""
    p, n = jurs.shapes.get("ellipse", 100)
    a = jurs.auto_settings(p, n, offset=0.05, smoothing=1e-4)
    p2, n2 = jurs.shapes.get("ellipse", 200)
    b = jurs.auto_settings(p2, n2, offset=0.05, smoothing=1e-4)
    assert b.grid[0] > a.grid[0] + 10
    np.testing.assert_allclose(b.lam / a.lam, 2.0, rtol=1e-2)


def test_offset_does_not_cross_thin_parts():
    """A strip 0.2 wide, with an offset asked for of 0.4 (as noise of 0.2 would ask): the
    inner offsets would cross to the far side; the chosen one does not."""
    t = np.linspace(0, 1, 40, endpoint=False)
    length, width = 6.0, 0.2
    top = np.stack([length * t, np.full_like(t, width / 2)], 1)
    bottom = np.stack([length * t, np.full_like(t, -width / 2)], 1)
    points = np.concatenate([top, bottom])
    normals = np.concatenate([np.tile([0.0, 1.0], (40, 1)), np.tile([0.0, -1.0], (40, 1))])
    spacing = _measure.point_spacing(points)
    assert _measure.offset_agreement(points, normals, 0.4) < 0.6  # crosses
    d = _defaults.choose_offset(points, normals, spacing, noise=0.2)
    assert d < width
    assert _measure.offset_agreement(points, normals, d) == 1.0
    # The whole ladder in one query gives what one offset at a time gives.
    ladder = np.array([0.4, 0.28, 0.1, 0.05])
    batched = _measure.offset_agreement(points, normals, ladder)
    assert batched.shape == (4,)
    np.testing.assert_array_equal(
        batched, [_measure.offset_agreement(points, normals, x) for x in ladder]
    )


@pytest.mark.slow
def test_overrides_are_kept(lobes):
    p, n = lobes
    s = jurs.auto_settings(p, n, grid=(12, 14), offset=0.2, smoothing=1e-3)
    assert s.grid == (12, 14) and s.offset == 0.2 and s.eps == 0.2 and s.smoothing == 1e-3
    sol = jurs.fit(p, n, grid=12, solver=jurs.LeastSquares(lam=0.5))
    assert sol.settings.grid == (12, 12) and float(sol.metrics["lam"]) == 0.5
    assert (
        jurs.fit(p, n, grid=12, offset=0.1, eps=0.01, solver=jurs.IPIA(max_steps=2)).settings
        is None
    )


@pytest.mark.slow
def test_fit_takes_the_smoothing_of_its_default_solver(lobes):
    p, n = lobes
    chosen = jurs.auto_settings(p, n, grid=12, smoothing=1e-4)
    sol = jurs.fit(p, n, grid=12, smoothing=1e-4)
    assert sol.settings == chosen
    assert float(sol.metrics["lam"]) == pytest.approx(chosen.lam, rel=1e-12)
    assert sol.settings.lam != jurs.auto_settings(p, n, grid=12).lam
    with pytest.raises(ValueError, match="solver given"):
        jurs.fit(p, n, smoothing=1e-4, solver=jurs.LeastSquares(lam=0.1))
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="smoothing must be"):
            jurs.fit(p, n, smoothing=bad)


def test_traced_points_need_explicit_settings(lobes):
    p, n = lobes
    with pytest.raises(ValueError, match="concrete points"):
        jax.jit(lambda q: jurs.fit(q, n).metrics["E"])(jnp.asarray(p))


@pytest.mark.slow
def test_default_fit_is_clean_and_accurate(lobes, lobes_fit):
    p, _ = lobes
    sol = lobes_fit
    assert isinstance(sol.settings, jurs.Settings)
    assert sol.succeeded
    report = ls.analyze(sol.spline, p, offset=sol.settings.offset, reference=reference("lobes"))
    assert report.num_supplementary == 0 and report.num_tiny_loops == 0
    assert report.num_components == 1
    assert report.chamfer < 1e-3 * diagonal(p)


@pytest.mark.slow
def test_default_fit_on_noisy_data():
    p, n = jurs.shapes.get("glyph_8", 600)
    diag = diagonal(p)
    noisy, noisy_n = jurs.datasets.add_noise(p, n, sigma=0.005 * diag, seed=4)
    sol = jurs.fit(noisy, noisy_n)
    assert sol.settings.noise > 0.5 * 0.005 * diag
    report = ls.analyze(
        sol.spline, noisy, offset=sol.settings.offset, reference=reference("glyph_8")
    )
    assert report.num_supplementary == 0 and report.num_tiny_loops == 0
    assert report.num_components == 3  # the outline and the two counters
    assert report.chamfer < 0.5 * 0.005 * diag  # closer to the clean curve than the noise


@pytest.mark.parametrize("motion", ["translate", "rotate", "scale"])
@pytest.mark.slow
def test_default_zero_set_moves_with_the_data(lobes, lobes_fit, motion):
    p, n = lobes
    shift, scale = np.array([13.0, -4.0]), 2.5
    forward = {
        "translate": lambda x: x + shift,
        "rotate": lambda x: x @ ROT90.T,
        "scale": lambda x: scale * x,
    }[motion]
    back = {
        "translate": lambda x: x - shift,
        "rotate": lambda x: x @ ROT90,
        "scale": lambda x: x / scale,
    }[motion]
    moved = jurs.fit(forward(p), n @ ROT90.T if motion == "rotate" else n)
    chamfer, _ = ls.chamfer_hausdorff(back(zero_set(moved)), zero_set(lobes_fit))
    assert chamfer < 1e-3 * diagonal(p)


@pytest.mark.slow
def test_doubling_the_density_changes_little(lobes, lobes_fit):
    p, _ = lobes
    dense = jurs.fit(*jurs.shapes.get("lobes", 600))
    assert dense.settings.grid != lobes_fit.settings.grid
    chamfer, _ = ls.chamfer_hausdorff(zero_set(dense), zero_set(lobes_fit))
    assert chamfer < 1e-3 * diagonal(p)
