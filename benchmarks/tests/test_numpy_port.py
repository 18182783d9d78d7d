"""The NumPy baseline of benchmarks/speed.py (``benchmarks/_numpy_port.py``, a dense port of
the paper's Algorithm 1) takes the same iterates as ``jurs.IURS``, so its timings compare
like with like."""

import jax
import numpy as np
import pytest

import jurs

from .. import _numpy_port as port

STEPS = 5
GRID = (9, 9)


def _run_both(control, weights, tau, lam):
    """STEPS steps of jurs.IURS and of the port on Example 1 (120 points) on one box,
    compared after every step; returns the port's last state."""
    points, normals = jurs.datasets.example1(120)
    problem = jurs.make_problem(points, normals, grid=GRID, bucket_size=1)
    domain = (np.asarray(problem.lower), np.asarray(problem.upper))
    dense = port.Problem(points, normals, grid=GRID, domain=domain)

    solver = jurs.IURS(tau=tau, lam=lam)
    spline = jurs.ImplicitSpline(control, weights, problem.lower, problem.upper)
    state, energy = solver.init(problem, spline)
    ours = port.init(dense, lam, control, weights)
    np.testing.assert_allclose(ours["E"], energy, rtol=1e-12)
    step = jax.jit(solver.step)
    for _ in range(STEPS):
        state, energy = step(problem, state)
        ours = port.step(dense, ours, tau=tau, lam=lam)
        np.testing.assert_allclose(ours["E"], energy, rtol=1e-10)
        np.testing.assert_allclose(ours["mu"], state.mu, rtol=1e-12)
        np.testing.assert_allclose(ours["w"].reshape(GRID), state.weights, rtol=1e-10)
        np.testing.assert_allclose(ours["C"].reshape(GRID), state.control, rtol=1e-9, atol=1e-12)
    return ours


@pytest.mark.parametrize("lam", [1e-3, 0.0])
def test_port_matches_jurs_from_algorithm_1_start(lam):
    """C = 0, w = 1, tau = 1e-2 as in the paper's Example 1."""
    _run_both(np.zeros(GRID), np.ones(GRID), 1e-2, lam)


def test_port_matches_jurs_with_moving_weights():
    """From a random start the weight step (eq. 20) moves w visibly, so the rational
    collocation and the weight gradient are exercised, not just the PIA step."""
    rng = np.random.default_rng(0)
    weights = 1.0 + 0.3 * rng.random(GRID)
    control = 0.05 * rng.standard_normal(GRID)
    ours = _run_both(control, weights, 1e-1, 1e-3)
    assert np.max(np.abs(ours["w"] - weights.ravel())) > 1e-3


def test_port_auto_box_is_jurs_box():
    points, normals = jurs.datasets.example1(50)
    problem = jurs.make_problem(points, normals, grid=(8, 8), bucket_size=1)
    dense = port.Problem(points, normals, grid=8)
    np.testing.assert_allclose(dense.lower, problem.lower, rtol=1e-14)
    np.testing.assert_allclose(dense.upper, problem.upper, rtol=1e-14)
    # Partition of unity: the dense basis rows sum to one inside the box.
    np.testing.assert_allclose(dense.B.sum(axis=1), 1.0, rtol=1e-12)
