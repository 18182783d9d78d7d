"""Normal equations (stencil assembly) and the exact LeastSquares solve."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
from conftest import dense_collocation

import jurs
from jurs._linalg import cholesky as _cholesky
from jurs._linalg import stencil as _stencil
from jurs._linalg.normal import moments_to_stencil
from jurs.solvers._least_squares import (
    DEFAULT_RIDGE,
    preconditioner_scale,
    solve_normal_equations,
)

# Every test here takes several seconds (compiles and long iterations): make test-fast skips them.
pytestmark = pytest.mark.slow

jax.config.update("jax_enable_x64", True)

LAM = 1e-4  # objective lambda used where the unregularised problem is too ill-posed

# Jitted once per solver configuration: op-by-op (eager) runs of the driver are slow.
solve = eqx.filter_jit(jurs.solve)
normal_equations = eqx.filter_jit(jurs.internal.normal_equations)


def least_squares(lam, **kwargs):
    """LeastSquares with lam as an array, so that jitted solves share one compilation."""
    return jurs.LeastSquares(lam=jnp.asarray(lam), **kwargs)


@pytest.fixture(scope="module")
def example1_problem():
    points, normals = jurs.datasets.example1(120)
    return jurs.make_problem(points, normals, grid=(9, 10), offset=0.1, eps=0.01)


def test_bspline_stencil_matches_dense_normal_equations(example1_problem):
    problem = example1_problem
    d = dense_collocation(problem, np.ones(problem.shape))
    b = np.asarray(problem.targets)
    normal = normal_equations(problem)
    np.testing.assert_allclose(normal.to_dense(), d.T @ d, atol=1e-13)
    np.testing.assert_allclose(np.asarray(normal.rhs).ravel(), d.T @ b, atol=1e-15)
    # 49 non-zeros a row at most (cubic 2D), and exactly 49 for an interior coefficient.
    nnz = np.diff(_stencil.stencil_to_scipy(normal.stencil).indptr)
    assert nnz.max() == 49
    control = jax.random.normal(jax.random.PRNGKey(0), problem.shape)
    np.testing.assert_allclose(
        normal.matvec(control).ravel(), d.T @ d @ np.ravel(control), atol=1e-12
    )
    np.testing.assert_allclose(
        normal.data_energy(control),
        jurs.internal.data_energy(problem, control, jnp.ones(problem.shape)),
        rtol=1e-12,
    )


def test_rational_stencil_chunked_matches_dense(example1_problem):
    problem = example1_problem
    weights = jnp.exp(0.4 * jax.random.normal(jax.random.PRNGKey(1), problem.shape))
    d = dense_collocation(problem, weights)
    # chunk_size 100 forces several scan blocks and a zero-padded last block.
    normal = normal_equations(problem, weights, chunk_size=100)
    np.testing.assert_allclose(normal.to_dense(), d.T @ d, atol=1e-13)
    np.testing.assert_allclose(
        np.asarray(normal.rhs).ravel(), d.T @ np.asarray(problem.targets), atol=1e-15
    )


def test_masked_samples_do_not_contribute():
    points, normals = jurs.datasets.example1(60)
    padded_p = np.concatenate([points, points[:7] + 0.3])
    padded_n = np.concatenate([normals, normals[:7]])
    mask = np.arange(67) < 60
    domain = ((-5.0, -9.0), (5.0, 3.0))
    full = jurs.make_problem(padded_p, padded_n, grid=8, mask=mask, domain=domain)
    plain = jurs.make_problem(points, normals, grid=8, domain=domain)
    for weights in (None, jnp.ones((8, 8))):
        a = normal_equations(full, weights)
        b = normal_equations(plain, weights)
        np.testing.assert_allclose(a.stencil, b.stencil, atol=1e-14)
        np.testing.assert_allclose(a.rhs, b.rhs, atol=1e-15)


@pytest.mark.parametrize("shape", [(64, 64), (20, 20, 20)])
def test_stencil_fold_holds_two_grids_at_a_time(shape):
    """The moment-to-stencil fold writes one grid-sized array an axis (a convolution), so
    its compiled working memory stays under two stencils; four shifted products summed
    an axis kept 3.3-4.2 stencils alive, the largest buffers of a surface's fit."""
    d = len(shape)
    cells = int(np.prod([n - 3 for n in shape]))
    sums = jax.ShapeDtypeStruct((cells, 7**d + 4**d), jnp.float64)
    compiled = jax.jit(lambda s: moments_to_stencil(s, shape)).lower(sums).compile()
    analysis = compiled.memory_analysis()
    if analysis is None:
        pytest.skip("this backend reports no memory analysis")
    stencil_bytes = np.prod(shape) * 7**d * 8
    assert analysis.temp_size_in_bytes <= 2.0 * stencil_bytes


def test_plus_laplacian_adds_the_laplacian_s_entries():
    """``plus_laplacian``: the stencil plus a multiple of ``laplacian_stencil``, entry for
    entry, in 2D and 3D."""
    for shape in [(6, 9), (4, 5, 3)]:
        stencil = jax.random.normal(jax.random.PRNGKey(3), shape + (7,) * len(shape))
        expected = stencil + 0.37 * _stencil.laplacian_stencil(shape)
        np.testing.assert_array_equal(_stencil.plus_laplacian(stencil, 0.37), expected)


def test_a_robust_surface_fit_holds_no_second_stencil():
    """A robust fit's compiled program (a loop of exact solves) holds at most about one
    stencil more than the exact fit's; the regularised stencil made as the stencil plus a
    whole Laplacian stencil let XLA hoist that Laplacian (mostly zeros) out of the loop
    and hold it throughout."""
    p, n = jurs.datasets.sphere3d(2000)
    problem = jurs.make_problem(p, n, grid=20, offset=0.05, eps=0.01)
    temps = []
    for solver in [jurs.LeastSquares(lam=1e-3), jurs.RobustLeastSquares(lam=1e-3)]:
        fit = jax.jit(lambda problem, solver=solver: solve(solver, problem, throw=False))
        analysis = fit.lower(problem).compile().memory_analysis()
        if analysis is None:
            pytest.skip("this backend reports no memory analysis")
        temps.append(analysis.temp_size_in_bytes)
    stencil_bytes = np.prod(problem.shape) * 7**3 * 8
    assert temps[1] - temps[0] <= 1.5 * stencil_bytes


def test_laplacian_stencil_is_grid_laplacian():
    control = jax.random.normal(jax.random.PRNGKey(2), (6, 9))
    lap = _stencil.laplacian_stencil((6, 9))
    np.testing.assert_allclose(
        _stencil.stencil_matvec(lap, control), jurs.internal.grid_laplacian(control), atol=1e-14
    )


@pytest.mark.parametrize("lam", [0.0, LAM])
def test_least_squares_is_the_minimiser(example1_problem, lam):
    """Against an independent dense solve of the same objective (SVD least squares on the
    stacked [D; sqrt(2 lam) differences] system)."""
    problem = example1_problem
    sol = solve(least_squares(lam, ridge=0.0), problem)  # the exact minimiser, no ridge
    assert sol.succeeded and int(sol.stats["num_steps"]) == 1
    d = dense_collocation(problem, np.ones(problem.shape))
    n, m = problem.shape
    eye_n, eye_m = np.eye(n), np.eye(m)
    diff_x = np.kron(np.diff(eye_n, axis=0), eye_m)
    diff_y = np.kron(eye_n, np.diff(eye_m, axis=0))
    stacked = np.concatenate([d, np.sqrt(2 * lam) * diff_x, np.sqrt(2 * lam) * diff_y])
    rhs = np.concatenate([np.asarray(problem.targets), np.zeros(stacked.shape[0] - d.shape[0])])
    best = np.linalg.lstsq(stacked, rhs, rcond=1e-14)[0]
    best_energy = float(np.sum((stacked @ best - rhs) ** 2))
    energy = float(sol.metrics["E"])
    assert abs(energy - best_energy) <= 1e-9 * best_energy
    np.testing.assert_allclose(sol.metrics["E_d"] + lam * sol.metrics["R"], energy, rtol=1e-12)
    # Gradient of the objective vanishes at the solution (hand-derived gradients).
    grad = jurs.internal.data_energy_grad_control(
        problem, sol.spline.control, sol.spline.weights
    ) + lam * jurs.internal.regulariser_grad(sol.spline.control)
    scale = jnp.abs(
        jurs.internal.data_energy_grad_control(
            problem, jnp.zeros(problem.shape), sol.spline.weights
        )
    ).max()
    assert float(jnp.abs(grad).max()) < 1e-8 * float(scale)


def test_cg_and_cholesky_agree(example1_problem):
    chol = solve(least_squares(LAM, linear_solver=lx.Cholesky()), example1_problem)
    cg = solve(
        least_squares(LAM, linear_solver=lx.CG(rtol=1e-12, atol=1e-14, max_steps=2000)),
        example1_problem,
    )
    assert cg.succeeded
    np.testing.assert_allclose(cg.spline.control, chol.spline.control, atol=1e-7)
    np.testing.assert_allclose(cg.metrics["E"], chol.metrics["E"], rtol=1e-10)


def test_keep_weights_solves_for_fixed_rational_weights(example1_problem):
    problem = example1_problem
    weights = jnp.exp(0.3 * jax.random.normal(jax.random.PRNGKey(3), problem.shape))
    start = jurs.ImplicitSpline(jnp.zeros(problem.shape), weights, problem.lower, problem.upper)
    sol = solve(least_squares(LAM, keep_weights=True), problem, start)
    np.testing.assert_array_equal(sol.spline.weights, weights)
    grad = jurs.internal.data_energy_grad_control(
        problem, sol.spline.control, weights
    ) + LAM * jurs.internal.regulariser_grad(sol.spline.control)
    assert float(jnp.abs(grad).max()) < 1e-12
    # The default ignores the start weights and fits the B-spline.
    bspline = solve(least_squares(LAM), problem, start)
    np.testing.assert_array_equal(bspline.spline.weights, jnp.ones(problem.shape))


def test_least_squares_is_the_fixed_point_of_the_paper_iteration(example1_problem):
    """IURS with tau = 0 is eq. 33 with fixed w; its fixed point minimises E_d + (2 lam/mu) R
    (jurs.objective_lam): from the exact solution, one step must not move C."""
    problem = example1_problem
    mu = jurs.internal.step_size(problem, jnp.ones(problem.shape))
    paper_lam = 1e-3
    exact = solve(least_squares(jurs.objective_lam(paper_lam, mu)), problem)
    iurs = solve(jurs.IURS(tau=0.0, lam=paper_lam, max_steps=1), problem, exact.spline)
    np.testing.assert_allclose(iurs.spline.control, exact.spline.control, atol=1e-12)


@pytest.fixture(scope="module")
def example1_9x9():
    points, normals = jurs.datasets.example1(120)
    problem = jurs.make_problem(points, normals, grid=9, offset=0.1, eps=0.01)
    return problem, solve(least_squares(0.0), problem)


def test_example1_energy(example1_9x9):
    """Example 1 on the paper's 9 x 9 grid (d = 0.1, eps = 0.01): the exact B-spline fit
    beats 200 I-PIA steps, which chase the same minimiser from C = 0."""
    problem, sol = example1_9x9
    ipia = solve(jurs.IPIA(max_steps=200), problem)
    assert float(sol.metrics["E_d"]) < float(ipia.metrics["E_d"])
    assert float(sol.metrics["E_d"]) < 2.6e-4


def test_ridge_keeps_singular_solves_bounded():
    """Unregularised on noisy data at 20 x 20 the normal equations are numerically
    singular: without the ridge the solve puts coefficients of ~1e10 where no data are;
    the default ridge keeps them bounded at a negligible cost in energy."""
    points, normals = jurs.datasets.example9()
    problem = jurs.make_problem(points, normals, grid=20)
    plain = solve(least_squares(0.0, ridge=0.0), problem, throw=False)
    ridged = solve(least_squares(0.0), problem)
    assert float(jnp.abs(ridged.spline.control).max()) < 1e5
    assert float(jnp.abs(plain.spline.control).max()) > 100 * float(
        jnp.abs(ridged.spline.control).max()
    )
    e_plain, e_ridged = float(plain.metrics["E_d"]), float(ridged.metrics["E_d"])
    assert e_plain <= e_ridged <= 1.02 * e_plain
    with pytest.raises(ValueError, match="ridge"):
        jurs.LeastSquares(ridge=-1.0)


def test_float32_runs(example1_9x9):
    problem64, exact = example1_9x9
    points, normals = jurs.datasets.example1(120)
    problem = jurs.make_problem(points, normals, grid=9, dtype=jnp.float32)
    sol = solve(least_squares(np.float32(0.0)), problem)
    assert sol.spline.control.dtype == jnp.float32
    # The float32 system is singular at rounding level: whether its Cholesky factor exists
    # depends on the device's rounding. Where it does not, CG solves (see solve_by_default
    # and test_float32_dense_solve_falls_back_to_cg), and in float32 stops at its step cap.
    # On a GPU this also needs full-precision products (jurs._model.precision): with TF32 the
    # energy here ended 3.9 times the minimum.
    assert sol.result in (jurs.RESULTS.successful, jurs.RESULTS.max_steps_reached)
    assert np.isfinite(float(sol.metrics["E"]))
    # Even the ill-conditioned unregularised solve lands close in energy.
    np.testing.assert_allclose(float(sol.metrics["E"]), float(exact.metrics["E"]), rtol=1e-3)


def test_float32_cg_on_a_large_grid_does_not_break_down():
    """lineax's CG declares a breakdown where ``p.Ap <= 100 eps size r.z``, a threshold
    that grows with the grid (0.78 in float32 at 256 x 256): solve_normal_equations scales
    the preconditioner so that a float32 solve there runs to its tolerance, with the
    iterates of the unscaled one (in float64 the scale is 1)."""
    shape = (256, 256)
    stencil = _stencil.laplacian_stencil(shape, jnp.float32)
    stencil = stencil.at[..., 3, 3].add(0.01)  # positive definite
    rhs = jnp.asarray(np.random.default_rng(0).standard_normal(shape), jnp.float32)
    cg = lx.CG(rtol=0.0, atol=1e-3, max_steps=2000)

    @jax.jit
    def solve(stencil, rhs):
        operator = _stencil.StencilOperator(stencil)
        control, result = solve_normal_equations(operator, rhs, jnp.zeros_like(rhs), cg)
        return control, result, operator.mv(control) - rhs

    control, result, residual = solve(stencil, rhs)
    assert result == lx.RESULTS.successful and bool(jnp.all(jnp.isfinite(control)))
    assert float(jnp.max(jnp.abs(residual))) <= 2e-3
    assert preconditioner_scale(rhs.size, np.float64) == 1.0


def test_default_dense_solve_falls_back_to_lu():
    """Where the default dense Cholesky breaks down, LU solves instead of the fit failing:
    Example 1 at 15 x 15 with lam = 0 and no ridge is singular at rounding level, and
    lineax's Cholesky of it is NaN on this CPU in float64."""
    points, normals = jurs.datasets.example1(120)
    problem = jurs.make_problem(points, normals, grid=15, offset=0.1, eps=0.01)
    normal = normal_equations(problem)
    start = jnp.zeros(problem.shape)
    plain, _ = jax.jit(solve_normal_equations, static_argnums=3)(
        normal.regularised(0.0), normal.rhs, start, lx.Cholesky()
    )
    if np.all(np.isfinite(plain)):
        pytest.skip("this device's Cholesky factors the system: no breakdown to fall back from")
    sol = solve(least_squares(0.0, ridge=0.0), problem)
    assert bool(sol.succeeded) and np.all(np.isfinite(np.asarray(sol.spline.control)))
    # Near the minimum: the ridged solve (which factors) fits no better.
    ridged = solve(least_squares(0.0), problem)
    assert bool(ridged.succeeded)
    assert float(sol.metrics["E_d"]) <= 1.001 * float(ridged.metrics["E_d"])


def test_bad_arguments():
    with pytest.raises(ValueError, match="lam"):
        jurs.LeastSquares(lam=-1.0)
    with pytest.raises(ValueError, match="chunk_size"):
        jurs.LeastSquares(chunk_size=0)
    with pytest.raises(TypeError, match="lineax"):
        jurs.LeastSquares(linear_solver="cholesky")


@pytest.mark.parametrize("shape", [(4, 4), (5, 9), (12, 7)])
def test_block_cholesky_matches_dense_solve(shape):
    points, normals = jurs.datasets.example1(150)
    problem = jurs.make_problem(points, normals, grid=shape, offset=0.1, eps=0.01)
    normal = normal_equations(problem)
    system = normal.regularised(1e-3).stencil
    expected = np.linalg.solve(
        np.asarray(_stencil.stencil_to_dense(system)), np.asarray(normal.rhs).ravel()
    )
    got = np.asarray(jax.jit(_cholesky.stencil_cholesky_solve)(system, normal.rhs)).ravel()
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-13 * np.abs(expected).max())


def test_bucketed_normal_equations_match_flat():
    points, normals = jurs.datasets.example1(3000)
    flat = normal_equations(jurs.make_problem(points, normals, grid=(10, 12), bucket_size=1))
    bucketed = normal_equations(jurs.make_problem(points, normals, grid=(10, 12), bucket_size=16))
    np.testing.assert_allclose(bucketed.stencil, flat.stencil, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(bucketed.rhs, flat.rhs, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(bucketed.target_norm2, flat.target_norm2, rtol=1e-13)


def test_large_grid_default_is_direct_and_agrees_with_cg(monkeypatch):
    """Above DENSE_MAX_COEFFICIENTS the default solves lam > 0 by the block Cholesky of the
    stencil (a direct solve: no CG iterations) and lam = 0 by CG; both are the minimiser."""
    points, normals = jurs.datasets.example1(400)
    problem = jurs.make_problem(points, normals, grid=(18, 17), offset=0.1, eps=0.01)
    assert 18 * 17 > jurs.solvers._least_squares.DENSE_MAX_COEFFICIENTS
    # Record, at run time, whether the factorisation ran (lam is traced: both branches of
    # the choice are compiled, only one runs).
    factorised = []
    direct_solve = _cholesky.stencil_cholesky_solve

    def recording(stencil, rhs):
        jax.debug.callback(lambda: factorised.append(True))
        return direct_solve(stencil, rhs)

    monkeypatch.setattr(_cholesky, "stencil_cholesky_solve", recording)
    fresh_solve = eqx.filter_jit(
        lambda solver, problem, throw: jurs.solve(solver, problem, throw=throw)
    )
    direct = fresh_solve(least_squares(LAM), problem, True)
    jax.block_until_ready(direct.spline.control)
    assert factorised, "lam > 0 took the block Cholesky"
    factorised.clear()
    unregularised = fresh_solve(least_squares(0.0), problem, False)
    jax.block_until_ready(unregularised.spline.control)
    assert not factorised, "lam = 0 took CG"
    cg = solve(
        least_squares(LAM, linear_solver=lx.CG(rtol=1e-13, atol=1e-16, max_steps=20000)), problem
    )
    assert direct.succeeded and cg.succeeded
    np.testing.assert_allclose(direct.spline.control, cg.spline.control, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(direct.metrics["E"], cg.metrics["E"], rtol=1e-11)
    assert unregularised.succeeded or unregularised.result == jurs.RESULTS.max_steps_reached
    # lam = 0 minimises E_d alone: no regularised solution fits the data better.
    assert float(unregularised.metrics["E_d"]) <= float(direct.metrics["E_d"])


def test_gradient_through_the_direct_solve():
    """jax.grad through a fit that takes the block Cholesky path (implicit differentiation
    with the same factorisation), against central differences in lambda."""
    points, normals = (jnp.asarray(a) for a in jurs.datasets.example1(80))
    held_out = jnp.asarray(jurs.datasets.example1(23)[0]) * 1.03

    def loss(lam):
        sol = jurs.fit(
            points, normals, grid=(17, 16), solver=jurs.LeastSquares(lam=lam), offset=0.1, eps=0.01
        )
        return jnp.mean(sol.spline(held_out) ** 2)

    # Jitted: one compile for the two evaluations, one for the gradient (unjitted, the
    # fit under grad runs op by op).
    loss = jax.jit(loss)
    lam = jnp.asarray(1e-3)
    grad = float(jax.grad(loss)(lam))
    h = 1e-7
    fd = (float(loss(lam + h)) - float(loss(lam - h))) / (2 * h)
    assert abs(fd) > 1e-12
    assert abs(grad - fd) <= 1e-5 * abs(fd)


def test_float32_dense_solve_falls_back_to_cg():
    """In float32 the dense Cholesky's fallback is CG, whose early stop regularises: on
    Example 1 with 60 points at 14 x 14 the float32 system does not factor on this CPU; CG
    lands at the float64 minimum energy (an LU solve lands 25 % above it)."""
    points, normals = jurs.datasets.example1(60)
    problem = jurs.make_problem(points, normals, grid=14, offset=0.1, eps=0.01, dtype=jnp.float32)
    normal = normal_equations(problem)
    chol, _ = jax.jit(solve_normal_equations, static_argnums=3)(
        normal.regularised(np.float32(0.0)),
        normal.rhs,
        jnp.zeros(problem.shape, jnp.float32),
        lx.Cholesky(),
        DEFAULT_RIDGE,
    )  # as the default solve calls it
    if np.all(np.isfinite(chol)):
        pytest.skip("this device's Cholesky factors the system: no breakdown to fall back from")
    sol = solve(least_squares(np.float32(0.0)), problem)
    assert sol.result in (jurs.RESULTS.successful, jurs.RESULTS.max_steps_reached)
    exact = solve(
        least_squares(0.0), jurs.make_problem(points, normals, grid=14, offset=0.1, eps=0.01)
    )
    np.testing.assert_allclose(float(sol.metrics["E"]), float(exact.metrics["E"]), rtol=1e-3)
