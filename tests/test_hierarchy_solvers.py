"""The hierarchy takes the exact solve, its reweighting and its held-out choice of lambda
as solvers: jurs.fit(..., basis="adaptive", solver=LeastSquares / RobustLeastSquares /
HeldOutLeastSquares), and refuses the others with the reason."""

import numpy as np
import pytest

import jurs
from jurs._fit import adaptive as adaptive_fit
from jurs._problem.adaptive import assemble_adaptive_problem


@pytest.fixture(scope="module")
def flipped():
    """Example 1 with the normals of 20 of its 400 points turned inward: gross errors
    that a robust fit weighs down on any basis. ``(points, flipped normals, flipped rows,
    the clean fit's lambda, the clean normals)``."""
    points, normals = jurs.datasets.example1(400)
    bad = np.random.default_rng(0).choice(len(points), 20, replace=False)
    wrong = np.array(normals)
    wrong[bad] *= -1
    clean = jurs.fit(points, normals, basis="adaptive")
    return points, wrong, bad, float(clean.metrics["lam"]), normals


def _mean_distance(spline, points) -> float:
    g = np.asarray(spline(points))
    slope = np.linalg.norm(np.asarray(spline.grad(points)), axis=1)
    return float(np.mean(np.abs(g) / slope))


def test_least_squares_on_the_hierarchy_is_the_default_solve(flipped):
    points, _, _, lam, normals = flipped
    default = jurs.fit_adaptive(points, normals, lam=lam, checks=False)
    given = jurs.fit(points, normals, basis="adaptive", solver=jurs.LeastSquares(lam=lam))
    assert isinstance(given.spline, jurs.AdaptiveSpline)
    np.testing.assert_array_equal(given.spline.control, default.spline.control)
    assert float(given.metrics["lam"]) == lam


def test_robust_least_squares_fits_a_hierarchy(flipped):
    points, normals, bad, lam, _ = flipped
    plain = jurs.fit(points, normals, basis="adaptive", checks=False, throw=False)
    solver = jurs.RobustLeastSquares(lam=lam, loss="huber", rtol=1e-6)
    sol = jurs.fit(points, normals, basis="adaptive", solver=solver, checks=False, throw=False)
    assert isinstance(sol.spline, jurs.AdaptiveSpline)
    assert sol.status == "successful"
    weights = np.asarray(sol.state.point_weights)
    assert weights.shape == (len(points),)
    good = np.setdiff1d(np.arange(len(points)), bad)
    assert weights[bad].max() < 0.1  # the flipped normals are set aside
    assert np.median(weights[good]) > 0.9
    # The zero set follows the data closer than the plain fit of the same cloud.
    assert _mean_distance(sol.spline, points) < 0.8 * _mean_distance(plain.spline, points)


@pytest.mark.parametrize(
    "method", ["host_cg", "host_cg_assembled", "multigrid", "host_multigrid", "cg"]
)
def test_row_weighted_solves_agree_with_the_factorisation(method, monkeypatch):
    if method == "host_cg_assembled":  # CG on the assembled normal matrix, whatever the sizes
        monkeypatch.setattr(adaptive_fit, "ASSEMBLED_SAMPLES_PER_FUNCTION", 0.0)
        method = "host_cg"
    points, normals = jurs.datasets.example1(150)
    cloud = jurs.Cloud(points, normals)
    settings = jurs.auto_settings(cloud)
    layout = adaptive_fit.hierarchy_layout(settings, 2, None, None, None, None, None)
    problem, matrices = assemble_adaptive_problem(points, normals, **layout)
    weights = np.random.default_rng(1).uniform(0.1, 1.0, len(problem.targets))
    lam = 1e-3
    exact, _ = adaptive_fit.solve_direct(problem, lam, matrices, weights)
    solve = adaptive_fit.exact_solve(method, problem, matrices, lam, 1e-12, 10_000, float)
    control, steps, residual = solve(weights, start=exact * 0.5)
    assert steps > 0 and residual <= 1e-12
    np.testing.assert_allclose(control, exact, atol=1e-8 * np.abs(exact).max())
    unweighted, _ = adaptive_fit.solve_direct(problem, lam, matrices)
    assert np.abs(unweighted - exact).max() > 1e-6  # the weights took part


@pytest.mark.parametrize("method", ["direct", "host_cg"])
def test_a_search_over_lambda_keeps_the_weights_system(method, monkeypatch):
    """``exact_solve`` keeps the assembled normal equations of the last row weights and
    moves them by ``(lam' - lam) R`` for a new lambda: the solve equals a fresh one's."""
    monkeypatch.setattr(adaptive_fit, "ASSEMBLED_SAMPLES_PER_FUNCTION", 0.0)
    points, normals = jurs.datasets.example1(150)
    settings = jurs.auto_settings(jurs.Cloud(points, normals))
    layout = adaptive_fit.hierarchy_layout(settings, 2, None, None, None, None, None)
    problem, matrices = assemble_adaptive_problem(points, normals, **layout)
    weights = np.random.default_rng(2).uniform(0.1, 1.0, len(problem.targets))
    solve = adaptive_fit.exact_solve(method, problem, matrices, 1e-3, 1e-12, 10_000, float)
    solve(weights)
    moved, _, residual = solve(weights, lam=1e-1)
    fresh, _ = adaptive_fit.solve_direct(problem, 1e-1, matrices, weights)
    assert residual <= 1e-10
    np.testing.assert_allclose(moved, fresh, atol=1e-8 * np.abs(fresh).max())


def test_other_solvers_are_refused_with_the_reason():
    points, normals = jurs.datasets.example1(100)
    iurs = jurs.IURS(tau=1e-2, lam=0.0, max_steps=5)
    with pytest.raises(ValueError, match="paper's iterations .* basis='uniform'"):
        jurs.fit(points, normals, basis="adaptive", solver=iurs)
    with pytest.raises(ValueError, match="JointLevenbergMarquardt runs on the uniform grid"):
        jurs.fit(points, normals, basis="adaptive", solver=jurs.JointLevenbergMarquardt())
    with pytest.raises(TypeError, match="jurs solver"):
        jurs.fit_adaptive(points, normals, solver="cauchy")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="lam or a solver, not both"):
        jurs.fit_adaptive(points, normals, lam=1e-3, solver=jurs.LeastSquares(lam=1e-3))


def _held_out_fit(points, normals, candidates, **kwargs):
    solver = jurs.HeldOutLeastSquares(lam=candidates, **kwargs)
    return jurs.fit(points, normals, basis="adaptive", solver=solver, checks=False, throw=False)


def test_held_out_lambda_on_the_hierarchy_tells_noise_from_structure(flipped):
    """HeldOutLeastSquares runs its search on the hierarchy: around the default lambda of
    the clean outline, the clean cloud keeps a small one and the same cloud with noise a
    far larger one; the fit is the exact solve of all points at the lambda it reports."""
    points, _, _, lam, normals = flipped
    candidates = tuple(lam * 10.0**k for k in range(-3, 4))
    clean = _held_out_fit(points, normals, candidates)
    noisy_points = points + np.random.default_rng(1).normal(0, 0.01, points.shape)
    noisy = _held_out_fit(noisy_points, normals, candidates)
    for sol in (clean, noisy):
        assert isinstance(sol.spline, jurs.AdaptiveSpline)
        assert sol.status == "successful"
        chosen = float(sol.state.lam)
        assert chosen in candidates and float(sol.metrics["lam"]) == chosen
        scores = np.asarray(sol.state.scores)
        assert np.nanargmin(scores) == candidates.index(chosen)
    assert float(noisy.state.lam) >= 100 * float(clean.state.lam)
    exact = jurs.fit(
        points, normals, basis="adaptive", checks=False,
        solver=jurs.LeastSquares(lam=float(clean.state.lam)),
    )  # fmt: skip
    np.testing.assert_allclose(clean.spline.control, exact.spline.control, rtol=1e-9, atol=1e-12)


def test_held_out_search_on_the_hierarchy_stops_early_as_on_the_grid(flipped):
    """Past the first rise of more than 5 % the candidates are not tried (NaN), unless
    ``early_stop=False``."""
    points, _, _, lam, normals = flipped
    candidates = tuple(lam * 10.0**k for k in range(0, 7))
    stopped = np.asarray(_held_out_fit(points, normals, candidates).state.scores)
    tried = ~np.isnan(stopped)
    assert tried[0] and not tried[-1]
    last = np.flatnonzero(tried)[-1]
    assert stopped[last] > 1.05 * stopped[last - 1]
    every = np.asarray(_held_out_fit(points, normals, candidates, early_stop=False).state.scores)
    assert not np.isnan(every).any()
    np.testing.assert_allclose(every[tried], stopped[tried], rtol=1e-6)
