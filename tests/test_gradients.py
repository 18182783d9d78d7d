"""Autodiff of E + lambda R against the hand-derived gradients (docs/design.md section 2), and the
energies, regulariser and step size against dense definitions."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import dense_basis, dense_collocation, without_table

import jurs

GRIDS = [(5, 5), (9, 7), (12, 12)]


def relative_error(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def random_state(rng, shape):
    return jnp.asarray(0.02 * rng.standard_normal(shape)), jnp.asarray(0.5 + rng.random(shape))


@pytest.fixture(scope="module")
def data():
    return jurs.datasets.example1(60)


# Both sides compiled whole, once a grid (lambda is an array argument: both lambdas of a
# grid share the compilation). Run op by op, each side took seconds a grid in dispatch.
auto_gradients = eqx.filter_jit(jax.grad(jurs.objective, argnums=(1, 2)))


@eqx.filter_jit
def hand_gradients(problem, control, weights, lam):
    hand_c = jurs.internal.data_energy_grad_control(
        problem, control, weights
    ) + lam * jurs.internal.regulariser_grad(control)
    hand_w = jurs.internal.data_energy_grad_weights(
        problem, control, weights
    )  # R does not depend on w
    return hand_c, hand_w


@pytest.mark.parametrize("shape", GRIDS)
@pytest.mark.parametrize("lam", [0.0, 0.3])
@pytest.mark.slow
def test_autodiff_matches_hand_derived(data, rng, shape, lam):
    problem = jurs.make_problem(*data, grid=shape)
    control, weights = random_state(rng, shape)
    lam = jnp.asarray(lam)
    auto_c, auto_w = auto_gradients(problem, control, weights, lam)
    hand_c, hand_w = hand_gradients(problem, control, weights, lam)
    assert relative_error(auto_c, hand_c) <= 1e-10
    assert relative_error(auto_w, hand_w) <= 1e-10


@eqx.filter_jit
def kernels(problem, control, weights):
    """E_d, its two hand-derived gradients and the explicit-row path's D^T r, compiled
    as one program."""
    rr, wb, denom, _ = jurs.internal.residuals(problem, control, weights)
    return (
        jurs.internal.data_energy(problem, control, weights),
        jurs.internal.data_energy_grad_control(problem, control, weights),
        jurs.internal.data_energy_grad_weights(problem, control, weights),
        jurs.internal.transpose_apply(problem, wb * (rr / denom)[:, None]),
    )


@pytest.mark.parametrize("shape", GRIDS[:2])
@pytest.mark.slow
def test_hand_derived_matches_dense_formulas(data, rng, shape):
    problem = jurs.make_problem(*data, grid=shape)
    control, weights = random_state(rng, shape)
    energy, grad_control, grad_weights, via_rows = kernels(problem, control, weights)
    d = dense_collocation(problem, weights)
    b = np.asarray(problem.targets)
    c = np.asarray(control).ravel()
    r = d @ c - b
    np.testing.assert_allclose(float(energy), r @ r, rtol=1e-12)
    grad_c = np.asarray(grad_control).ravel()
    np.testing.assert_allclose(grad_c, 2 * d.T @ r, rtol=1e-10, atol=1e-14)
    # nabla_w by the quotient rule on dense basis rows: dg_k/dw_ij = B_ij (C_ij - g_k) / W_k.
    basis = dense_basis(
        np.asarray(problem.samples), np.asarray(problem.lower), np.asarray(problem.upper), shape
    )
    w = np.asarray(weights).ravel()
    denom = basis @ w
    g = basis @ (w * c) / denom
    grad_w = 2 * ((r / denom)[:, None] * basis * (c[None, :] - g[:, None])).sum(axis=0)
    np.testing.assert_allclose(
        np.asarray(grad_weights).ravel(),
        grad_w,
        rtol=1e-10,
        atol=1e-14,
    )
    # Explicit-row path agrees with the fast path.
    np.testing.assert_allclose(
        2 * np.asarray(via_rows).ravel(), 2 * d.T @ r, rtol=1e-10, atol=1e-14
    )


def regulariser_by_definition(c):
    """eq. 31 literally: four neighbour differences per coefficient, missing ones 0."""
    n, m = c.shape
    total = 0.0
    for i in range(n):
        for j in range(m):
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                if 0 <= i + di < n and 0 <= j + dj < m:
                    total += (c[i + di, j + dj] - c[i, j]) ** 2
    return total


@pytest.mark.parametrize("shape", [(4, 4), (6, 9)])
def test_regulariser_and_its_gradient(rng, shape):
    c = rng.standard_normal(shape)
    np.testing.assert_allclose(
        float(jurs.internal.regulariser(jnp.asarray(c))), regulariser_by_definition(c), rtol=1e-13
    )
    auto = jax.grad(jurs.internal.regulariser)(jnp.asarray(c))
    np.testing.assert_allclose(
        np.asarray(jurs.internal.regulariser_grad(jnp.asarray(c))), np.asarray(auto), atol=1e-12
    )
    # Constants are free: the regulariser only sees differences.
    assert float(jurs.internal.regulariser(jnp.full(shape, 3.0))) == 0.0


step_size = eqx.filter_jit(jurs.internal.step_size)  # compiled whole, once a layout


@pytest.mark.parametrize("uniform", [True, False])
@pytest.mark.slow
def test_step_size_equals_dense_norm(data, rng, uniform):
    shape = (7, 8)
    problem = jurs.make_problem(*data, grid=shape)
    weights = jnp.ones(shape) if uniform else random_state(rng, shape)[1]
    d = dense_collocation(problem, weights)
    dense_mu = 2.0 / np.abs(d.T @ d).sum(axis=1).max()  # 2 / ||D^T D||_inf, eq. 13 / 25
    np.testing.assert_allclose(float(step_size(problem, weights)), dense_mu, rtol=1e-12)


@pytest.mark.slow
def test_bucketed_layout_gives_same_energy_and_gradients(rng):
    points, normals = jurs.datasets.example1(500)
    shape = (9, 9)
    flat = jurs.make_problem(points, normals, grid=shape, bucket_size=1)
    bucketed = jurs.make_problem(points, normals, grid=shape, bucket_size=16)
    assert bucketed.local.bucket_size == 16
    control, weights = random_state(rng, shape)
    for fn in (
        jurs.internal.data_energy,
        jurs.internal.data_energy_grad_control,
        jurs.internal.data_energy_grad_weights,
    ):
        fn = eqx.filter_jit(fn)  # compiled whole: op by op, dispatch took seconds
        np.testing.assert_allclose(
            np.asarray(fn(bucketed, control, weights)),
            np.asarray(fn(flat, control, weights)),
            rtol=1e-11,
            atol=1e-15,
        )
    np.testing.assert_allclose(
        float(step_size(bucketed, weights)),
        float(step_size(flat, weights)),
        rtol=1e-13,
    )


@pytest.mark.slow
def test_iurs_steps_agree_across_layouts(rng):
    """The table form (small problems), the power form one sample a bucket (traced builds)
    and the bucketed power form give the same IURS iterates (Algorithm 1)."""
    points, normals = jurs.datasets.example1(400)
    shape = (9, 8)
    table = jurs.make_problem(points, normals, grid=shape)
    assert table.local.terms is not None
    power = without_table(table)
    bucketed = jurs.make_problem(points, normals, grid=shape, bucket_size=8)
    control, weights = random_state(rng, shape)
    spline = jurs.ImplicitSpline(control, weights, table.lower, table.upper)
    solver = jurs.IURS(tau=0.05, lam=0.01)
    results = []
    init, step = eqx.filter_jit(solver.init), eqx.filter_jit(solver.step)  # compiled whole
    for problem in (table, power, bucketed):
        state, _ = init(problem, spline)
        for _ in range(3):
            state, energy = step(problem, state)
        results.append((state, energy))
    (ref, e_ref), others = results[0], results[1:]
    for state, energy in others:
        for name in ("control", "weights", "weight_grad", "mu"):
            np.testing.assert_allclose(
                np.asarray(getattr(state, name)),
                np.asarray(getattr(ref, name)),
                rtol=1e-11,
                atol=1e-15,
            )
        np.testing.assert_allclose(float(energy), float(e_ref), rtol=1e-12)


@pytest.mark.parametrize("layout", ["table", "power", "bucketed"])
@pytest.mark.slow
def test_metrics_match_their_definitions(rng, layout):
    """``jurs.internal.metrics`` (eq. 35-37 and mu of eq. 25, computed in the kernels' layout in one
    pass) against the spline evaluated at the points and the dense collocation."""
    points, normals = jurs.datasets.example1(150)
    shape, lam = (8, 9), 0.02
    problem = jurs.make_problem(
        points, normals, grid=shape, bucket_size=8 if layout == "bucketed" else None
    )
    if layout == "power":
        problem = without_table(problem)
    assert (problem.local.terms is not None) == (layout == "table")
    control, weights = random_state(rng, shape)
    spline = jurs.ImplicitSpline(control, weights, problem.lower, problem.upper)
    got = eqx.filter_jit(jurs.internal.metrics)(problem, spline, lam)  # compiled whole
    on_points = np.asarray(spline(jnp.asarray(points)))
    d = dense_collocation(problem, weights)[np.asarray(problem.mask) > 0]  # padding: no row
    e_d = float(jurs.internal.data_energy(problem, control, weights))
    reg = float(jurs.internal.regulariser(control))
    expected = {
        "E_d": e_d,
        "R": reg,
        "E": e_d + lam * reg,
        "E_ave": np.mean(on_points**2),
        "E_max": np.max(np.abs(on_points)),
        "mu": 2.0 / np.abs(d.T @ d).sum(axis=1).max(),
    }
    for name, value in expected.items():
        np.testing.assert_allclose(float(got[name]), value, rtol=1e-11, err_msg=name)


def test_objective_takes_lambda_in_the_problems_dtype(data):
    """A lambda given as a Python or NumPy number enters the objective in the problem's
    dtype, as a solver's floats do (``as_arrays``): a float32 problem's objective is
    float32 for a float64 NumPy lambda and an integer one too."""
    problem = jurs.make_problem(*data, grid=(5, 5), dtype=jnp.float32)
    control = jnp.zeros((5, 5), jnp.float32)
    weights = jnp.ones((5, 5), jnp.float32)
    for lam in (0.3, np.float64(0.3), 1):
        assert jurs.objective(problem, control, weights, lam).dtype == jnp.float32, lam
