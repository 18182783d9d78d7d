"""The defaults on real data: lambda by held-out points, points set aside, finer grids for
thin features, and the doubt verdict (docs/guide/settings.md, docs/design.md section 6)."""

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs._cloud.measure import feature_width
from jurs._cloud.outliers import isolated_points
from jurs._fit.adaptive import UNIFORM_RESIDUAL_SPACINGS
from jurs._fit.settings import CLEAN_SMOOTHING, MAX_FEATURE_COEFFICIENTS, SMOOTHING_CANDIDATES
from jurs._solution.verdicts import crossed_features
from jurs.solvers._held_out import held_out_distance, held_out_points, select_lam


def _circle(m, radius=1.0, centre=(0.0, 0.0)):
    t = 2.0 * np.pi * (np.arange(m) + 0.5) / m
    n = np.stack([np.cos(t), np.sin(t)], axis=1)
    return np.asarray(centre) + radius * n, n


def _staircase(m=1500, seed=None):
    """A disc of radius 40 pixels traced as a new user would: marching squares on the
    binary image, no blur (pixel-edge kinks), sampled finer than a pixel; with ``seed``,
    the same outline with independent noise of 0.5 % of its diagonal on the points."""
    from skimage import measure

    yy, xx = np.mgrid[0:100, 0:100]
    image = ((xx - 50.0) ** 2 + (yy - 50.0) ** 2 < 40.0**2).astype(float)
    contour = max(measure.find_contours(image, 0.5), key=len)
    outline = jurs.shapes.orient([np.stack([contour[:-1, 1], -contour[:-1, 0]], axis=1)])
    p, n = jurs.shapes.sample_outline(outline, m)
    if seed is not None:
        diag = np.linalg.norm(np.ptp(p, axis=0))
        p, n = jurs.datasets.add_noise(p, n, sigma=0.005 * diag, normal_sigma=0.1, seed=seed)
    return p, n


# --------------------------------------------------------------------------- held-out lambda


def test_held_out_points_spread_evenly():
    held = np.asarray(held_out_points(1000, 0.2))
    assert abs(held.mean() - 0.2) < 0.01
    # Every stretch of 50 points of the order holds close to its share.
    assert all(abs(held[k : k + 50].mean() - 0.2) <= 0.04 for k in range(0, 950, 50))


@pytest.mark.slow
def test_held_out_distance_known_answer():
    """g(x, y) = x, which cubic B-splines reproduce exactly (coefficients at the Greville
    abscissae): each held-out point's distance is |x|, capped at d."""
    rng = np.random.default_rng(0)
    p = rng.uniform(-1.0, 1.0, (200, 2))
    n = np.tile([1.0, 0.0], (200, 1))
    d = 0.3
    problem = jurs.make_problem(p, n, grid=(12, 12), offset=d, eps=d, domain=((-2, -2), (2, 2)))
    h = 4.0 / 9.0
    control = jnp.asarray(np.repeat((-2.0 + (np.arange(12) - 1.0) * h)[:, None], 12, axis=1))
    spline = jurs.ImplicitSpline(control, jnp.ones_like(control), problem.lower, problem.upper)
    assert np.allclose(spline(jnp.asarray(p)), p[:, 0], atol=1e-12)
    values = jurs.internal.bspline_values(problem.local, control[None])
    held = held_out_points(200, 0.2)
    score = float(held_out_distance(problem, values, held)[0])
    expected = np.mean(np.minimum(np.abs(p[np.asarray(held), 0]), d) ** 2)
    assert score == pytest.approx(expected, rel=1e-10)


@pytest.mark.slow
def test_select_lam_known_optimum():
    """Exact samples of a circle: the fit that follows the data (the small candidate)
    predicts held-out points best; with noise of 2 % of the radius, following the noise
    on a fine grid loses to averaging it."""
    p, n = _circle(400)
    kw = dict(grid=(40, 40), offset=0.05, eps=0.05)
    clean = jurs.make_problem(p, n, **kw)
    lam, scores = select_lam(clean, jnp.asarray([1e-6, 10.0]))
    assert float(lam) == 1e-6 and scores[0] < scores[1]
    noisy, _ = jurs.datasets.add_noise(p, n, sigma=0.02, normal_sigma=0.0, seed=1)
    problem = jurs.make_problem(noisy, n, grid=(40, 40), offset=0.05, eps=0.05)
    lam, scores = select_lam(problem, jnp.asarray([1e-9, 0.3]))
    assert float(lam) == 0.3 and scores[1] < scores[0]


def test_held_out_search_stops_only_where_the_score_clearly_rises():
    """A rise within ``EARLY_STOP_RISE`` (a flat start, as noisy clouds score) goes on to
    the next candidate; a clear rise (a structured cloud's) stops the search."""
    from jurs.solvers._held_out import EARLY_STOP_RISE, stops_search

    horse = (0.016798587707113937, 0.01682314586444228)  # 1 % noise: 1e-6, then 1e-5
    assert not bool(stops_search(horse[1], horse[0]))
    assert bool(stops_search(1.08, 1.0))  # the smallest first rise of a structured cloud
    assert not bool(stops_search(1.0 + 0.99 * EARLY_STOP_RISE, 1.0))


@pytest.mark.slow
def test_held_out_solver_reports_its_choice():
    p, n = _circle(300)
    solver = jurs.HeldOutLeastSquares(lam=jnp.asarray([1e-4, 1e-2, 10.0]))
    sol = jurs.fit(p, n, grid=(20, 20), offset=0.05, eps=0.05, solver=solver)
    assert sol.status == "successful"
    assert float(sol.state.lam) == 1e-4 == float(sol.metrics["lam"])
    # The search stopped where the score rose (at 1e-2): 10 was never tried.
    scores = np.asarray(sol.state.scores)
    assert scores.shape == (3,) and np.all(np.isfinite(scores[:2])) and np.isnan(scores[2])
    assert scores[1] > scores[0]
    every = dataclasses.replace(solver, early_stop=False)
    full = jurs.fit(p, n, grid=(20, 20), offset=0.05, eps=0.05, solver=every)
    assert np.all(np.isfinite(full.state.scores)) and float(full.state.lam) == 1e-4
    assert np.allclose(full.state.scores[:2], scores[:2], rtol=1e-10)
    assert np.allclose(full.spline.control, sol.spline.control, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="ascend"):
        jurs.HeldOutLeastSquares(lam=jnp.asarray([1e-2, 1e-4]))
    jurs.HeldOutLeastSquares(lam=jnp.asarray([1e-2, 1e-4]), early_stop=False)
    with pytest.raises(ValueError, match="lam"):
        jurs.HeldOutLeastSquares(lam=jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="holdout"):
        jurs.HeldOutLeastSquares(lam=jnp.asarray([1.0, 2.0]), holdout=0.7)


@pytest.mark.slow
def test_staircase_is_structure_noise_is_noise():
    """The noise estimate reads a pixel staircase as noise; the held-out choice does not:
    the traced disc gets the clean smoothing, the same disc with 0.5 % noise more."""
    stairs = jurs.auto_settings(*_staircase())
    assert 2.0 * stairs.noise / stairs.offset > 0.1  # the staircase measures as noise ...
    assert stairs.held_out is not None  # ... so the data chose
    assert stairs.smoothing == CLEAN_SMOOTHING
    noisy = jurs.auto_settings(*_staircase(seed=3))
    assert noisy.held_out is not None and noisy.smoothing > CLEAN_SMOOTHING
    assert [c for c, _ in noisy.held_out] == list(SMOOTHING_CANDIDATES)
    clean = jurs.auto_settings(*_circle(500))
    assert clean.held_out is None and clean.smoothing == CLEAN_SMOOTHING


# --------------------------------------------------------------------------- outliers


def _with_outliers(p, n, count, seed=0):
    """``count`` points moved uniformly into the box, at least 10 % of its diagonal from
    every clean point, with random normals; and their indices."""
    rng = np.random.default_rng(seed)
    lo, hi = p.min(axis=0) - 0.5, p.max(axis=0) + 0.5
    far = []
    while len(far) < count:
        x = rng.uniform(lo, hi)
        if np.min(np.linalg.norm(p - x, axis=1)) > 0.1 * np.linalg.norm(hi - lo):
            far.append(x)
    index = rng.choice(len(p), count, replace=False)
    po, no = p.copy(), n.copy()
    po[index] = far
    angle = rng.uniform(0.0, 2.0 * np.pi, count)
    no[index] = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return po, no, np.sort(index)


def test_isolated_points_finds_planted_outliers_only():
    p, n = jurs.shapes.get("lobes", 1000, nonuniform=0.6)  # density varying 4x
    assert not isolated_points(p).any()
    p2, _ = jurs.shapes.get("rose", 800, gap=0.08)  # gap ends
    assert not isolated_points(p2).any()
    small = np.concatenate([p, _circle(12, 0.05, (9.0, 9.0))[0]])  # a small far component
    assert not isolated_points(small).any()
    po, _, index = _with_outliers(p, n, 15)
    pair = np.concatenate([po, po[index[:1]] + 0.01])  # an outlier with a close partner
    assert set(np.flatnonzero(isolated_points(pair))) == set(index) | {len(po)}


def test_stray_groups_are_set_aside_small_rings_kept():
    """A group of five outliers a few spacings apart (each one's third neighbour near) with
    random normals is set aside with normals given; six points on a small far ring, with
    outward normals or inward ones (a hole), are kept."""
    p, n = _circle(600)  # spacing about 0.01
    rng = np.random.default_rng(4)
    group = np.array([3.0, 3.0]) + 0.03 * rng.standard_normal((5, 2))
    angle = rng.uniform(0.0, 2.0 * np.pi, 5)
    random_normals = np.stack([np.cos(angle), np.sin(angle)], 1)
    # Chosen to disagree: three of five facing away from the group's centre.
    facing = np.einsum("ij,ij->i", group - group.mean(0), random_normals) > 0
    assert 1 < facing.sum() < 4
    ring, ring_n = _circle(6, 0.03, (-3.0, 3.0))
    points = np.concatenate([p, group, ring, ring + [0.0, -6.0]])
    normals = np.concatenate([n, random_normals, ring_n, -ring_n])
    assert not isolated_points(points)[600:605].all()  # the rank test alone keeps them
    found = np.flatnonzero(isolated_points(points, None, normals))
    assert set(found) == set(range(600, 605))


@pytest.mark.slow
def test_default_fit_sets_outliers_aside():
    """1.5 % outliers: set aside, a robust fit of the rest (Huber) on the uniform grid,
    their weights 0, no loop around any of them (and none on the adaptive basis, which
    leaves them out); the clean cloud keeps every point and the plain exact solve."""
    p, n = _circle(600)
    po, no, index = _with_outliers(p, n, 9)
    sol = jurs.fit(po, no, basis="uniform")
    assert sol.settings.set_aside == tuple(index)
    assert isinstance(sol.state, jurs.solvers.RobustLeastSquaresState)
    w = np.asarray(sol.state.point_weights)[: len(po)]
    assert np.all(w[index] == 0) and np.all(np.delete(w, index) > 0.5)
    report = jurs.levelset.analyze(sol.spline, p, offset=sol.settings.offset)
    assert report.num_components == 1 and report.num_supplementary == 0
    # Dense enough that the uniform grid is capped, but its fit follows the circle: the
    # default keeps it, as fitted above.
    auto = jurs.fit(po, no)
    assert isinstance(auto.spline, jurs.ImplicitSpline) and auto.settings == sol.settings
    assert auto.stats["uniform_residual"] <= UNIFORM_RESIDUAL_SPACINGS
    np.testing.assert_array_equal(np.asarray(auto.spline.control), np.asarray(sol.spline.control))
    # The adaptive basis fits without the points set aside.
    adaptive = jurs.fit(po, no, basis="adaptive")
    assert isinstance(adaptive.spline, jurs.AdaptiveSpline)
    report = jurs.levelset.analyze(adaptive.spline, p, offset=adaptive.settings.offset)
    assert report.num_components == 1 and report.num_supplementary == 0
    clean = jurs.fit(p, n, basis="uniform")
    assert clean.settings.set_aside == () and isinstance(
        clean.state, jurs.solvers.LeastSquaresState
    )


# --------------------------------------------------------------------------- thin features


def test_feature_width_measures_thin_parts_and_gaps():
    inner, ni = _circle(400, 1.0)
    outer, no = _circle(400, 1.1)
    p = np.concatenate([inner, outer])
    n = np.concatenate([-ni, no])  # an annulus 0.1 wide: inner ring faces inward
    width, partner = feature_width(p, n, radius=0.5, spacing=0.016)
    assert np.allclose(width, 0.1, atol=2e-3)
    assert np.all((partner < 400) != (np.arange(800) < 400))  # across, never the same ring
    far, _ = feature_width(p, n, radius=0.05, spacing=0.016)
    assert np.all(np.isinf(far))


def test_thin_features_refine_the_grid_within_budget():
    """A band 60 long and 0.2 wide (a quarter of the cell 96 functions would give): beyond
    96 functions along it, within the budget."""
    x = np.linspace(-30, 30, 3000)
    top = np.stack([x, np.full_like(x, 0.1)], axis=1)
    bottom = np.stack([x, np.full_like(x, -0.1)], axis=1)
    p = np.concatenate([top, bottom])
    n = np.concatenate([np.tile([0.0, 1.0], (3000, 1)), np.tile([0.0, -1.0], (3000, 1))])
    s = jurs.auto_settings(p, n)
    assert max(s.grid) > 96 and np.prod(s.grid) <= MAX_FEATURE_COEFFICIENTS
    cell = np.max(np.subtract(s.domain[1], s.domain[0]) / (np.asarray(s.grid) - 3))
    assert cell <= 2 * 0.2 and s.thin_fraction == 0.0


# --------------------------------------------------------------------------- doubt


@pytest.mark.slow
def test_crossed_features_counts_fused_rings():
    """Two rings 0.05 apart fused by a coarse fit: the points facing each other across
    the gap are counted; well apart, none."""
    a, na = _circle(300, 1.0, (-1.025, 0.0))
    b, nb = _circle(300, 1.0, (1.025, 0.0))
    p, n = np.concatenate([a, b]), np.concatenate([na, nb])
    coarse = jurs.fit(p, n, grid=(10, 8), offset=0.02, eps=0.02, solver=jurs.LeastSquares(1e-3))
    assert crossed_features(coarse.spline, p, n, spacing=0.02) > 5
    fine = jurs.fit(p, n, grid=(120, 64), offset=0.01, eps=0.01, solver=jurs.LeastSquares(1e-6))
    assert crossed_features(fine.spline, p, n, spacing=0.02) == 0


@pytest.mark.slow
def test_elongated_shape_is_doubtful_with_a_reason():
    p, n = jurs.datasets.ellipse(4000, a=1000.0, b=1.0)
    with pytest.warns(UserWarning, match="doubtful"):
        sol = jurs.fit(p, n)
    assert sol.status == "doubtful" and sol.stats["doubts"]
    assert "thin part" in sol.stats["doubts"][0] and "grid=" in sol.stats["doubts"][0]
    assert sol.result == jurs.RESULTS.doubtful and "doubt" in sol.message


@pytest.mark.slow
def test_clean_fit_has_no_doubt():
    p, n = _circle(400)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sol = jurs.fit(p, n)
    assert sol.status == "successful" and sol.stats["doubts"] == ()
    assert float(sol.metrics["far_point_fraction"]) == 0.0


def test_levelset_threshold_follows_the_fit_cell():
    """A dense cloud on a coarse grid: the zero set 0.01 off the data is the curve, not a
    supplementary component, once the fit's cell (0.1) sets the threshold (an eighth)."""
    xs = ys = np.linspace(-1.5, 1.5, 301)
    gx, gy = np.meshgrid(xs, ys)
    values = np.hypot(gx, gy) - 1.01
    p, _ = _circle(20000)
    plain = jurs.levelset.analyze_grid(xs, ys, values, p, offset=1e-4)
    assert plain.num_supplementary == 1
    report = jurs.levelset.analyze_grid(xs, ys, values, p, offset=1e-4, fit_cell=0.1)
    assert report.num_supplementary == 0 and report.threshold == pytest.approx(0.0125)
