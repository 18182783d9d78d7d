"""Geometric multigrid for stencil systems (jurs._multigrid): transfer, Galerkin operators,
dimension-generic kernels, and solves against direct ones."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
import scipy.sparse.linalg as spl
from scipy.interpolate import BSpline

import jurs
from jurs import _multigrid as mg
from jurs import _normal

jax.config.update("jax_enable_x64", True)


def basis_1d(x, n, lower, upper):
    """The n cubic B-splines of jurs' basis on [lower, upper] at x (scipy, knots extended
    3 cells past the box), ``(len(x), n)``."""
    h = (upper - lower) / (n - 3)
    knots = lower + (np.arange(n + 4) - 3.0) * h
    return BSpline.design_matrix(x, knots, 3).toarray()


def prolongation_matrix(coarse_shape, fine_shape):
    return np.asarray(jax.jacfwd(lambda c: mg.prolong(c, fine_shape))(
        jnp.zeros(coarse_shape))).reshape(int(np.prod(fine_shape)), -1)


@pytest.mark.parametrize("n", [8, 9, 12, 13])
def test_prolongation_is_knot_insertion(n):
    """A coarse spline (cells twice as wide, same lower end; with an odd cell count its box
    reaches one fine cell further) equals its prolongation in the fine basis on the box."""
    nc = mg.coarse_size(n)
    h = 1.0 / (n - 3)
    x = np.linspace(0.0, 1.0, 101)
    coarse = basis_1d(x, nc, 0.0, 2 * h * (nc - 3))
    fine = basis_1d(x, n, 0.0, 1.0)
    p = prolongation_matrix((nc,), (n,))
    np.testing.assert_allclose(fine @ p, coarse, atol=1e-14)
    assert np.linalg.matrix_rank(p) == nc  # no coarse function vanishes on the box


def random_gram(shape, rng, count=None):
    """``D^T D + 1e-3 L`` of random samples in a unit box, for a grid of any dimension
    (dense, from scipy's B-splines)."""
    count = count or 3 * int(np.prod(shape))
    points = rng.random((count, len(shape)))
    rows = np.ones((count, 1))
    for axis, n in enumerate(shape):
        b = basis_1d(points[:, axis], n, 0.0, 1.0)
        rows = (rows[:, :, None] * b[:, None, :]).reshape(count, -1)
    lap = np.asarray(_normal.stencil_to_dense(_normal.laplacian_stencil(shape)))
    return rows.T @ rows + 1e-3 * lap


@pytest.mark.slow
@pytest.mark.parametrize("shape", [(10, 11), (9, 8, 10)])
def test_galerkin_and_probe_match_dense(shape):
    """probe_stencil recovers a banded matrix exactly; galerkin is P^T A P (2D and 3D)."""
    rng = np.random.default_rng(0)
    a = random_gram(shape, rng)
    stencil = mg.probe_stencil(lambda v: (a @ v.ravel()).reshape(shape), shape, np.float64)
    np.testing.assert_allclose(_normal.stencil_to_dense(stencil), a, atol=1e-13)
    coarse = tuple(mg.coarse_size(n) for n in shape)
    p = prolongation_matrix(coarse, shape)
    expected = p.T @ a @ p
    got = np.asarray(_normal.stencil_to_dense(mg.galerkin(stencil, coarse)))
    np.testing.assert_allclose(got, expected, atol=1e-13 * np.abs(expected).max())


def test_generic_kernels_in_3d():
    """stencil_matvec, laplacian_stencil and stencil_to_scipy on a 3D grid."""
    shape = (5, 6, 7)
    lap = _normal.laplacian_stencil(shape)
    x = np.random.default_rng(1).standard_normal(shape)
    padded = np.pad(x, 1, mode="edge")  # free boundary: a missing neighbour adds nothing
    expected = sum(x - np.roll(padded, s, axis)[1:-1, 1:-1, 1:-1]
                   for axis in range(3) for s in (1, -1))
    np.testing.assert_allclose(_normal.stencil_matvec(lap, jnp.asarray(x)), expected, atol=1e-12)
    np.testing.assert_allclose(_normal.stencil_to_scipy(lap) @ x.ravel(), expected.ravel(),
                               atol=1e-12)
    assert _normal.stencil_diagonal(lap).shape == shape


def stencil_solve(stencil, rhs, solver):
    operator = lx.FunctionLinearOperator(lambda c: _normal.stencil_matvec(stencil, c),
                                         jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                         lx.positive_semidefinite_tag)
    sol = lx.linear_solve(operator, rhs, solver, options={"stencil": stencil}, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result


@pytest.mark.slow
def test_3d_solve_matches_dense():
    """A 10^3 B-spline Gram + Laplacian (two levels) solved to 1e-10 of numpy's solve; the
    stencil is probed from the operator when options give none."""
    shape = (10, 10, 10)
    a = random_gram(shape, np.random.default_rng(2))
    b = np.random.default_rng(3).standard_normal(shape)
    operator = lx.MatrixLinearOperator(jnp.asarray(a), lx.positive_semidefinite_tag)
    flat = lx.linear_solve(operator, jnp.asarray(b.ravel()), lx.Cholesky()).value
    grid_op = lx.FunctionLinearOperator(lambda c: (jnp.asarray(a) @ c.ravel()).reshape(shape),
                                        jax.ShapeDtypeStruct(shape, jnp.float64),
                                        lx.positive_semidefinite_tag)
    solver = mg.Multigrid(rtol=1e-12, coarsest_size=400, patch_size=4)
    assert len(mg.level_shapes(shape, 400)) == 2
    sol = lx.linear_solve(grid_op, jnp.asarray(b), solver)
    expected = np.asarray(flat).reshape(shape)
    assert np.linalg.norm(sol.value - expected) <= 1e-10 * np.linalg.norm(expected)


@pytest.fixture(scope="module")
def curve_systems():
    """The regularised normal equations of Example 1 (2000 points) on 30 x 30, unseen
    coefficients pinned as LeastSquares does, for several lam."""
    points, normals = jurs.datasets.example1(2000)
    problem = jurs.make_problem(points, normals, grid=30, offset=0.1, eps=0.01)
    normal = jurs.normal_equations(problem)
    systems = {}
    for lam in (1e-4, 1e-8, 1e-14):
        stencil = normal.regularised(lam)
        diag = _normal.stencil_diagonal(stencil)
        stencil = stencil.at[..., 3, 3].set(jnp.where(diag <= 0, 1.0, diag))
        systems[lam] = (stencil, jnp.where(diag <= 0, 0.0, normal.rhs), normal.target_norm2)
    return systems


@pytest.mark.slow
@pytest.mark.parametrize("lam", [1e-4, 1e-8, 1e-14])
def test_multigrid_matches_sparse_direct(curve_systems, lam):
    """Three levels on sparse curve data: the objective within 1e-10 (relative) of the exact
    minimiser by SciPy's sparse LU, and the solution within 1e-10 where lam keeps the system
    well posed."""
    stencil, rhs, b2 = curve_systems[lam]
    # r.Mr at 1e-26 of b.Mb for the solution error, 1e-22 for the objective alone.
    solver = mg.Multigrid(rtol=1e-13 if lam >= 1e-4 else 1e-11, max_steps=300,
                          coarsest_size=100)
    assert len(mg.level_shapes(rhs.shape, 100)) == 3
    x, steps, result = eqx.filter_jit(stencil_solve)(stencil, rhs, solver)
    assert result == lx.RESULTS.successful
    a = _normal.stencil_to_scipy(stencil).tocsc()
    exact = spl.spsolve(a, np.asarray(rhs).ravel())
    x, b = np.asarray(x).ravel(), np.asarray(rhs).ravel()

    def objective(c):
        return c @ (a @ c) - 2 * c @ b + float(b2)

    gap = (objective(x) - objective(exact)) / objective(exact)
    print(f"lam={lam:g}: {int(steps)} steps, objective gap {gap:.1e}, C error "
          f"{np.linalg.norm(x - exact) / np.linalg.norm(exact):.1e}")
    assert abs(gap) <= 1e-10
    if lam >= 1e-4:
        assert np.linalg.norm(x - exact) <= 1e-10 * np.linalg.norm(exact)


@pytest.mark.slow
def test_least_squares_with_multigrid_and_gradients():
    """LeastSquares(linear_solver=Multigrid()) is the minimiser (as the default solve), and
    jax.grad through it (implicit differentiation) matches central differences."""
    points, normals = (jnp.asarray(a) for a in jurs.datasets.example1(200))
    held_out = jnp.asarray(jurs.datasets.example1(23)[0]) * 1.03
    solver = mg.Multigrid(rtol=1e-12, coarsest_size=100)

    def fit(lam, linear_solver):
        return jurs.fit(points, normals, grid=(22, 21), offset=0.1, eps=0.01,
                        solver=jurs.LeastSquares(lam=lam, linear_solver=linear_solver))

    lam = jnp.asarray(1e-3)
    reference = fit(lam, None)
    ours = fit(lam, solver)
    assert ours.succeeded
    np.testing.assert_allclose(ours.spline.control, reference.spline.control, rtol=1e-8,
                               atol=1e-10 * float(jnp.abs(reference.spline.control).max()))

    def loss(lam):
        return jnp.mean(fit(lam, solver).spline(held_out) ** 2)

    grad = float(jax.grad(loss)(lam))
    h = 1e-7
    fd = (float(loss(lam + h)) - float(loss(lam - h))) / (2 * h)
    assert abs(fd) > 1e-12
    assert abs(grad - fd) <= 1e-5 * abs(fd)


@pytest.mark.slow
def test_float32_solve(curve_systems):
    """In float32 the solve converges to float32 accuracy of the float64 minimiser."""
    stencil, rhs, _ = curve_systems[1e-4]
    exact, _, _ = stencil_solve(stencil, rhs, mg.Multigrid(rtol=1e-11, coarsest_size=100))
    x, steps, result = stencil_solve(stencil.astype(jnp.float32), rhs.astype(jnp.float32),
                                     mg.Multigrid(rtol=1e-4, coarsest_size=100))
    assert x.dtype == jnp.float32 and result == lx.RESULTS.successful
    # 1.0e-3 measured: the float32 system itself is ill-conditioned at lam = 1e-4.
    assert np.linalg.norm(x - exact) <= 5e-3 * np.linalg.norm(exact)


def test_bad_input():
    with pytest.raises(ValueError, match="rtol"):
        mg.Multigrid(rtol=-1.0)
    operator = lx.MatrixLinearOperator(jnp.eye(4), lx.positive_semidefinite_tag)
    with pytest.raises(ValueError, match="2D or 3D grid"):
        lx.linear_solve(operator, jnp.ones(4), mg.Multigrid())
