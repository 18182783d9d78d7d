"""I-PIA and IURS (paper Sections II-IV, Algorithm 1) tied to the maths they implement."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import PAPER, dense_collocation

import jurs

# Every test here takes several seconds (compiles and long iterations): make test-fast skips them.
pytestmark = pytest.mark.slow


def dense_laplacian(shape):
    n = shape[0] * shape[1]
    return np.asarray(
        jax.jacfwd(lambda c: jurs.internal.grid_laplacian(c.reshape(shape)).ravel())(jnp.zeros(n))
    )


@pytest.fixture(scope="module")
def box_problem():
    """Points filling a unit box with random normals: every basis function sees data."""
    g = np.linspace(0.0, 1.0, 15)
    points = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    angle = np.random.default_rng(0).random(len(points)) * 2 * np.pi
    normals = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    return jurs.make_problem(points, normals, grid=(4, 4), offset=0.02, margin=0.0)


def test_ipia_is_eq11(box_problem):
    """50 steps of jurs.IPIA equal 50 steps of C <- C + mu D^T (b - D C), dense."""
    d = dense_collocation(box_problem, np.ones(box_problem.shape))
    b = np.asarray(box_problem.targets)
    mu = 2.0 / np.abs(d.T @ d).sum(axis=1).max()
    c = np.zeros(d.shape[1])
    for _ in range(50):
        c = c + mu * d.T @ (b - d @ c)
    sol = jurs.solve(jurs.IPIA(max_steps=50, tol=0.0), box_problem)
    np.testing.assert_allclose(np.asarray(sol.spline.control).ravel(), c, rtol=1e-11, atol=1e-15)
    assert np.all(np.asarray(sol.spline.weights) == 1.0)


def test_ipia_converges_to_least_squares_minimiser(box_problem):
    """D^T D is badly conditioned (corner B-splines peak at 1/6), so I-PIA's coefficients
    creep; its energy converges, at least as fast as gradient descent's O(1/k) bound:
    E_k - E* <= ||C* - C_0||^2 / (mu k) (step mu/2 on a 2 lambda_max-smooth quadratic).
    E_k - E* is also ||D (C_k - C*)||^2, the squared error of the fitted values."""
    d = dense_collocation(box_problem, np.ones(box_problem.shape))
    b = np.asarray(box_problem.targets)
    c_star = np.linalg.lstsq(d, b, rcond=None)[0]
    e_star = np.sum((d @ c_star - b) ** 2)
    steps = 20000
    sol = jurs.solve(jurs.IPIA(max_steps=steps, tol=0.0), box_problem)
    history = np.asarray(sol.stats["energy_history"])
    assert np.all(np.diff(history) <= 1e-15 * history[:-1]), "I-PIA energy never increases"
    gap = float(sol.metrics["E_d"]) - e_star
    mu = float(sol.metrics["mu"])
    assert 0 <= gap <= np.sum(c_star**2) / (mu * steps)
    assert gap <= 1e-3 * e_star
    fitted = d @ np.asarray(sol.spline.control).ravel()
    np.testing.assert_allclose(np.sum((fitted - d @ c_star) ** 2), gap, rtol=1e-3)


@pytest.mark.parametrize("lam", [0.002, 0.02])
def test_regularised_fixed_point(lam):
    """With weights fixed (tau = 0) the fixed point of eq. 33 minimises E_d + (2 lam / mu) R,
    i.e. solves (D^T D + 2 (2 lam / mu) L) C = D^T b (docs/design.md section 3)."""
    problem = jurs.make_problem(*jurs.datasets.example1(40), grid=(6, 6))
    d = dense_collocation(problem, np.ones(problem.shape))
    b = np.asarray(problem.targets)
    sol = jurs.solve(jurs.IURS(tau=0.0, lam=lam, max_steps=20000, tol=0.0), problem)
    mu = float(sol.metrics["mu"])
    lam_objective = float(jurs.objective_lam(lam, mu))
    expected = np.linalg.solve(
        d.T @ d + 2 * lam_objective * dense_laplacian(problem.shape), d.T @ b
    )
    np.testing.assert_allclose(
        np.asarray(sol.spline.control).ravel(), expected, rtol=1e-9, atol=1e-12
    )
    # ... and it is the minimiser: the gradient of that objective vanishes there.
    grad = jax.grad(jurs.objective, argnums=1)(
        problem, sol.spline.control, sol.spline.weights, lam_objective
    )
    assert float(jnp.max(jnp.abs(grad))) < 1e-10


def test_iurs_with_tau_zero_is_ipia():
    problem = jurs.make_problem(*jurs.datasets.example1(60), grid=(8, 8))
    ipia = jurs.solve(jurs.IPIA(max_steps=60, tol=0.0), problem)
    iurs = jurs.solve(jurs.IURS(tau=0.0, lam=0.0, max_steps=60, tol=0.0), problem)
    np.testing.assert_allclose(
        np.asarray(iurs.spline.control), np.asarray(ipia.spline.control), rtol=1e-12, atol=1e-16
    )
    np.testing.assert_array_equal(np.asarray(iurs.spline.weights), 1.0)
    np.testing.assert_allclose(
        np.asarray(iurs.stats["energy_history"]),
        np.asarray(ipia.stats["energy_history"]),
        rtol=1e-12,
    )


def test_iurs_step_is_algorithm1(rng):
    """One IURS step by hand: eq. 20, rebuild D, eq. 25, eq. 33, eq. 35."""
    problem = jurs.make_problem(*jurs.datasets.example1(50), grid=(7, 7))
    control = jnp.asarray(0.01 * rng.standard_normal((7, 7)))
    weights = jnp.asarray(0.8 + 0.4 * rng.random((7, 7)))
    tau, lam = 0.05, 0.01
    solver = jurs.IURS(tau=tau, lam=lam)
    state, _ = solver.init(
        problem, jurs.ImplicitSpline(control, weights, problem.lower, problem.upper)
    )
    new_state, energy = solver.step(problem, state)
    grad_w = jax.grad(jurs.internal.data_energy, argnums=2)(problem, control, weights)
    w1 = np.maximum(np.asarray(weights - tau * grad_w), solver.min_weight)
    d = dense_collocation(problem, w1)
    b = np.asarray(problem.targets)
    c0 = np.asarray(control).ravel()
    mu = 2.0 / np.abs(d.T @ d).sum(axis=1).max()
    c1 = c0 + mu * d.T @ (b - d @ c0) - lam * 4 * dense_laplacian((7, 7)) @ c0
    np.testing.assert_allclose(np.asarray(new_state.weights), w1, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(new_state.control).ravel(), c1, rtol=1e-10, atol=1e-15)
    e1 = np.sum((d @ c1 - b) ** 2) + lam * float(
        jurs.internal.regulariser(jnp.asarray(c1.reshape(7, 7)))
    )
    np.testing.assert_allclose(float(energy), e1, rtol=1e-10)


def test_weights_stay_positive():
    points, normals = jurs.datasets.example1(80)
    sol = jurs.fit(
        points,
        normals,
        solver=jurs.IURS(tau=50.0, max_steps=100, min_weight=1e-3),
        throw=False,
        **PAPER,
    )
    weights = np.asarray(sol.spline.weights)
    assert weights.min() >= 1e-3
    assert np.isfinite(weights).all()


def test_example1_paper_settings():
    """Example 1 as in the paper: 120 points, 9 x 9, d = 0.1, eps = 0.01, tau = 1e-2, 200 steps."""
    points, normals = jurs.datasets.example1(120)
    ipia = jurs.fit(points, normals, solver=jurs.IPIA(max_steps=200, tol=0.0), **PAPER)
    iurs = jurs.fit(points, normals, solver=jurs.IURS(tau=1e-2, max_steps=200, tol=0.0), **PAPER)
    assert int(ipia.stats["num_steps"]) == int(iurs.stats["num_steps"]) == 200
    assert float(ipia.metrics["E_ave"]) <= 2e-6  # paper: 1.27e-6
    assert float(ipia.metrics["E_max"]) <= 5e-3  # paper: 2.19e-3
    # IURS minimises E over (C, w) and ends no higher; E_ave and E_max, which it does not
    # target, stay within 0.1 % of I-PIA's (the paper's tau moves the weights very little).
    assert float(iurs.metrics["E"]) <= float(ipia.metrics["E"])
    assert float(iurs.metrics["E_ave"]) <= 1.001 * float(ipia.metrics["E_ave"])
    assert float(iurs.metrics["E_max"]) <= 1.001 * float(ipia.metrics["E_max"])
    assert not np.allclose(np.asarray(iurs.spline.weights), 1.0), "IURS moved the weights"


def test_results_and_stop_rule():
    points, normals = jurs.datasets.example1(60)
    capped = jurs.fit(points, normals, solver=jurs.IPIA(max_steps=30, tol=0.0), **PAPER)
    assert capped.result == jurs.RESULTS.max_steps_reached
    assert int(capped.stats["num_steps"]) == 30
    assert "max_steps" in capped.message
    converged = jurs.fit(points, normals, solver=jurs.IPIA(max_steps=500, tol=1e-5), **PAPER)
    assert converged.result == jurs.RESULTS.successful and converged.succeeded
    k = int(converged.stats["num_steps"])
    history = np.asarray(converged.stats["energy_history"])
    assert k < 500
    assert abs(history[k] - history[k - 1]) < 1e-5 <= abs(history[k - 1] - history[k - 2])  # eq. 38
    assert np.isnan(history[k + 1 :]).all()
    np.testing.assert_allclose(history[k], float(converged.metrics["E"]), rtol=1e-12)


def test_divergence_keeps_last_finite_iterate():
    """lam far above the stability bound of eq. 33 diverges: the run stops, says so, and
    keeps the last finite iterate; with throw=True it raises."""
    points, normals = jurs.datasets.example1(60)
    solver = jurs.IURS(tau=1e-2, lam=2.0, max_steps=2000, tol=0.0)
    sol = jurs.fit(points, normals, solver=solver, throw=False, **PAPER)
    assert sol.result == jurs.RESULTS.nonfinite
    assert int(sol.stats["num_steps"]) < 2000
    assert np.isfinite(np.asarray(sol.spline.control)).all()
    assert all(np.isfinite(float(v)) for v in sol.metrics.values())
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or Inf"):
        jax.block_until_ready(jurs.fit(points, normals, solver=solver, throw=True, **PAPER))


def test_float32_still_behaves():
    points, normals = jurs.datasets.example1(120)
    with jax.enable_x64(False):
        sol = jurs.fit(points, normals, solver=jurs.IURS(max_steps=200, tol=0.0), **PAPER)
        assert sol.spline.control.dtype == jnp.float32
        e_ave32 = float(sol.metrics["E_ave"])
    sol64 = jurs.fit(points, normals, solver=jurs.IURS(max_steps=200, tol=0.0), **PAPER)
    assert sol.result == jurs.RESULTS.max_steps_reached
    np.testing.assert_allclose(e_ave32, float(sol64.metrics["E_ave"]), rtol=1e-2)


def test_fit_is_differentiable_and_batchable():
    points, normals = jurs.datasets.example1(40)
    points = points + 0.01 * np.random.default_rng(3).standard_normal(
        points.shape
    )  # no ties in mu's max
    held_out = jnp.asarray(jurs.datasets.example1(17)[0])
    domain = ((-5.0, -9.0), (5.0, 1.5))

    def loss(pts):
        sol = jurs.fit(pts, normals, solver=jurs.IURS(max_steps=5, tol=0.0), domain=domain, **PAPER)
        return jnp.mean(sol.spline(held_out) ** 2)

    # One compilation for the gradient and the four differences (the value is the same
    # forward computation; a jit of the loss alone would compile the fit again).
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    grad = np.asarray(value_and_grad(jnp.asarray(points))[1])
    h = 1e-6
    for row, col in [(0, 0), (7, 1)]:
        e = np.zeros_like(points)
        e[row, col] = h
        fd = (
            value_and_grad(jnp.asarray(points + e))[0] - value_and_grad(jnp.asarray(points - e))[0]
        ) / (2 * h)
        np.testing.assert_allclose(grad[row, col], float(fd), rtol=1e-5)
    batch = jnp.stack([jnp.asarray(points), jnp.asarray(points) * 1.1])
    fit_one = lambda p: jurs.fit(
        p, normals, solver=jurs.IPIA(max_steps=5, tol=0.0), **PAPER
    ).metrics["E_d"]
    batched = jax.vmap(fit_one)(batch)
    np.testing.assert_allclose(np.asarray(batched), [float(fit_one(p)) for p in batch], rtol=1e-12)


@pytest.mark.parametrize("bucket_size", [1, 16])
def test_normal_form_ipia_follows_ipia(bucket_size):
    """The normal-equation form gives I-PIA's iterates and energies, on either layout."""
    points, normals = jurs.datasets.example1(700)
    problem = jurs.make_problem(points, normals, grid=(12, 12), bucket_size=bucket_size)
    per_sample = jurs.solve(jurs.IPIA(max_steps=80, tol=0.0), problem)
    normal_form = jurs.solve(jurs.NormalIPIA(max_steps=80, tol=0.0), problem)
    np.testing.assert_allclose(
        np.asarray(normal_form.spline.control),
        np.asarray(per_sample.spline.control),
        rtol=1e-10,
        atol=1e-14,
    )
    np.testing.assert_allclose(
        np.asarray(normal_form.stats["energy_history"]),
        np.asarray(per_sample.stats["energy_history"]),
        rtol=1e-10,
    )
    np.testing.assert_allclose(
        float(normal_form.state.mu), float(per_sample.metrics["mu"]), rtol=1e-12
    )
    # The carried product is D^T D C at the final C (one stencil product a step).
    state = normal_form.state
    np.testing.assert_allclose(
        np.asarray(state.product),
        np.asarray(state.normal.matvec(state.control)),
        rtol=1e-12,
        atol=1e-14,
    )
