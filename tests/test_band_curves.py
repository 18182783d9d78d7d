"""Contouring an adaptive curve over the blocks where g may reach the level: the lines of
the full grid, pieces far from the data kept, nothing compiled."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from test_band_mesh import _quasi_interpolant  # one helper for 2D and 3D

import jurs
from jurs._model.adaptive import AdaptiveSpline
from jurs._model.hierarchy import build_hierarchy, refine_near
from jurs._model.lattice import values_and_gradients
from jurs.levelset import _curves


def _circle_with_far_piece():
    """A circle's distance on a hierarchy refined around it, with one level-0 coefficient
    far from the data set to -2: a small loop of g < 0 where no fine cell is."""
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    centre = np.array([0.5, 0.5])
    samples = centre + 0.35 * np.stack([np.cos(t), np.sin(t)], 1)
    spline = _quasi_interpolant(
        lambda x: np.linalg.norm(x - centre, axis=1) - 0.35,
        [-1.0, -1.0],
        [2.0, 2.0],
        (6, 6),
        3,
        samples,
    )
    hierarchy = spline.hierarchy
    keys = np.asarray(hierarchy.function_keys[0])[np.asarray(hierarchy.active[0])]
    multi = np.stack(np.unravel_index(keys, hierarchy.functions(0)), -1)
    far = int(np.flatnonzero(np.all(multi == 6, axis=1))[0])  # centred at (1.5, 1.5)
    return AdaptiveSpline(hierarchy, spline.control.at[far].set(-2.0), spline.weights)


def _assert_same_lines(a, b):
    assert len(a) == len(b)
    for (pa, ca), (pb, cb) in zip(a, b):
        assert ca == cb and pa.shape == pb.shape
        np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-12)


def test_band_contours_are_the_full_grids_far_piece_included():
    spline = _circle_with_far_piece()
    xs, ys, _ = _curves.sampling_grid(spline.lower, spline.upper, 301)
    full = _curves.evaluate_grid(spline, xs, ys)
    band, evaluated, plan = _curves._band_values(spline, xs, ys, 0.0)
    # The band's nodes hold the full grid's values; far fewer of them were evaluated.
    assert np.array_equal(band[evaluated], full[evaluated])
    assert plan.nodes < 0.5 * plan.lattice_nodes
    # The nodes left out carry a value from their own side of the level.
    assert np.array_equal(np.sign(band), np.sign(full))
    lines = jurs.levelset.zero_level_set(spline, 301)
    _assert_same_lines(lines, _curves.contour_lines(xs, ys, full))
    assert len(lines) == 2 and all(closed for _, closed in lines)
    assert any(np.all(p > 1.1) for p, _ in lines)  # the far piece is there
    # analyze reports what the full grid gives, the zero-area fraction included.
    points = np.concatenate([p for p, _ in lines])
    report = jurs.levelset.analyze(spline, points, resolution=301)
    expected = jurs.levelset.analyze_grid(xs, ys, full, points, fit_cell=spline.cell_width)
    assert report.as_dict() == expected.as_dict()


def test_band_zero_area_fraction_falls_back_to_the_full_grid():
    """A zero_tol the band cannot decide (above the hull's tolerance) is measured on the
    full grid: g is nearly 0 on a plateau far from the data, which the band leaves out
    (its values clear the hull's tolerance), but ``zero_tol = 1e-7`` counts."""
    spline = _circle_with_far_piece()
    hierarchy = spline.hierarchy
    # Level-0 coefficients around (1.5, 1.5) set to 1e-8: a plateau of tiny g.
    keys = np.asarray(hierarchy.function_keys[0])[np.asarray(hierarchy.active[0])]
    multi = np.stack(np.unravel_index(keys, hierarchy.functions(0)), -1)
    near = np.flatnonzero(np.all(np.abs(multi - 6) <= 2, axis=1))
    spline = AdaptiveSpline(hierarchy, spline.control.at[near].set(1e-8), spline.weights)
    xs, ys, _ = _curves.sampling_grid(spline.lower, spline.upper, 201)
    full = _curves.evaluate_grid(spline, xs, ys)
    points = np.array([[0.85, 0.5], [0.15, 0.5]])
    band, evaluated, _ = _curves._band_values(spline, xs, ys, 0.0)
    for zero_tol in (1e-12, 1e-7):
        report = jurs.levelset.analyze(spline, points, resolution=201, zero_tol=zero_tol)
        expected = _curves._zero_area(full, zero_tol)
        assert report.zero_area_fraction == expected
    # At 1e-7 the plateau counts, and lies outside the band: the band alone falls short.
    assert expected > 0.05
    assert np.mean(evaluated & (np.abs(band) <= 1e-7 * np.abs(full).max())) < 0.5 * expected


def test_analyze_of_an_adaptive_fit_matches_the_full_grid_and_compiles_nothing():
    """A fitted outline: the band's report is the full grid's, and taking it compiles no
    program (the spline is evaluated on the host)."""
    from test_compile import _CompileCounter

    t = np.linspace(0, 2 * np.pi, 160, endpoint=False)
    circle = np.stack([np.cos(t), 0.6 * np.sin(t)], 1)
    normals = np.stack([0.6 * np.cos(t), np.sin(t)], 1)
    spline = jurs.fit_adaptive(circle, normals / np.linalg.norm(normals, axis=1)[:, None]).spline
    assert isinstance(spline, AdaptiveSpline)
    with _CompileCounter("") as counter:
        report = jurs.levelset.analyze(spline, circle, resolution=257)
    assert counter.count == 0
    xs, ys, _ = _curves.sampling_grid(spline.lower, spline.upper, 257)
    full = _curves.evaluate_grid(spline, xs, ys)
    expected = jurs.levelset.analyze_grid(xs, ys, full, circle, fit_cell=spline.cell_width)
    assert report.as_dict() == expected.as_dict() and report.num_components == 1


def test_host_evaluation_of_a_2d_adaptive_spline_is_its_own():
    """``evaluate_grid`` and the scattered values of a rational 2D adaptive spline (on the
    host, ``FinestSpline``) agree with its JAX evaluation, its gradients with central
    differences of the host values."""
    rng = np.random.default_rng(5)
    lower, upper = np.zeros(2), np.array([2.5, 2.0])
    refine = refine_near(lower, upper, (5, 4), 2, rng.uniform(0.3, 1.2, (6, 2)), 1)
    hierarchy = build_hierarchy(lower, upper, (5, 4), refine)
    spline = AdaptiveSpline(
        hierarchy,
        jnp.asarray(rng.normal(size=hierarchy.num_active)),
        jnp.asarray(rng.uniform(0.5, 2.0, hierarchy.num_active)),
    )
    xs, ys = np.linspace(-0.1, 2.6, 31), np.linspace(-0.1, 2.1, 23)
    gx, gy = np.meshgrid(xs, ys)
    xy = np.stack([gx.ravel(), gy.ravel()], 1)
    own = np.asarray(eqx.filter_jit(lambda s, p: s(p))(spline, jnp.asarray(xy)))
    grid = _curves.evaluate_grid(spline, xs, ys)
    np.testing.assert_allclose(grid.ravel(), own, rtol=1e-12, atol=1e-13)
    value, gradient = values_and_gradients(spline, xy)
    np.testing.assert_allclose(value, own, rtol=1e-12, atol=1e-13)
    step = 1e-6
    for k in range(2):
        shift = np.zeros(2)
        shift[k] = step
        plus, _ = values_and_gradients(spline, xy + shift)
        minus, _ = values_and_gradients(spline, xy - shift)
        np.testing.assert_allclose(gradient[:, k], (plus - minus) / (2 * step), atol=1e-6)
