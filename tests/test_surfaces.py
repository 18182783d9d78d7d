"""The model in 3D: trivariate evaluation, its transpose, the 343-point normal equations,
autodiff against the hand-derived gradients, the automatic settings and fits of surfaces.

The 2D code paths are the same functions (the dimension comes from the arrays' shapes);
these tests check what the 3D grids add."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import BSpline

import jurs
from jurs._linalg import stencil as _normal
from jurs._model.spline import bspline_transpose, bspline_values, local_basis

SHAPE = (6, 7, 5)
LOWER = np.array([-1.0, -2.0, 0.0])
UPPER = np.array([1.0, 1.0, 2.0])


def axis_basis_scipy(x, lower, upper, n):
    """All ``n`` cubic B-splines of one axis at ``x``, built by SciPy (knots extended three
    cells past the box), independently of jurs."""
    h = (upper - lower) / (n - 3)
    knots = lower + h * np.arange(-3, n + 1)
    columns = [BSpline.basis_element(knots[i : i + 5], extrapolate=False)(x) for i in range(n)]
    return np.nan_to_num(np.stack(columns, axis=1))


def dense_rows(x):
    """``(n, N M K)`` tensor-product basis values at ``x (n, 3)``."""
    bx, by, bz = (axis_basis_scipy(x[:, a], LOWER[a], UPPER[a], SHAPE[a]) for a in range(3))
    return np.einsum("pi,pj,pk->pijk", bx, by, bz).reshape(len(x), -1)


@pytest.fixture(scope="module")
def sphere():
    return jurs.datasets.sphere3d(400, seed=1)


@pytest.mark.slow
def test_trivariate_rational_spline_matches_dense_definition(rng):
    control, weights = rng.normal(size=SHAPE), rng.uniform(0.5, 2.0, size=SHAPE)
    spline = jurs.ImplicitSpline(
        jnp.asarray(control), jnp.asarray(weights), jnp.asarray(LOWER), jnp.asarray(UPPER)
    )
    x = rng.uniform(LOWER, UPPER, size=(80, 3))
    rows = dense_rows(x)
    expected = rows @ (control * weights).ravel() / (rows @ weights.ravel())  # eq. 14
    np.testing.assert_allclose(np.asarray(spline(x)), expected, rtol=1e-12, atol=1e-13)
    assert spline.ndim == 3 and np.asarray(spline.grad(x)).shape == (80, 3)
    assert float(spline(x[0])) == pytest.approx(float(expected[0]), rel=1e-12)


@pytest.mark.slow
def test_transpose_is_the_adjoint_in_3d(rng):
    local = local_basis(
        jnp.asarray(rng.uniform(LOWER, UPPER, size=(70, 3))),
        jnp.asarray(LOWER),
        jnp.asarray(UPPER),
        SHAPE,
    )
    grid, values = jnp.asarray(rng.normal(size=SHAPE)), jnp.asarray(rng.normal(size=70))
    lhs = jnp.vdot(bspline_values(local, grid), values)
    rhs = jnp.vdot(grid, bspline_transpose(local, values, SHAPE))
    assert float(lhs) == pytest.approx(float(rhs), rel=1e-12)


@pytest.mark.slow
def test_normal_equations_in_3d_match_the_samples(sphere, rng):
    problem = jurs.make_problem(*sphere, grid=(7, 8, 6), offset=0.1, eps=0.1)
    assert problem.ndim == 3 and problem.local.s.shape == (3, 1200)
    normal = jurs.internal.normal_equations(problem)
    assert normal.stencil.shape == (7, 8, 6, 7, 7, 7)
    grid = jnp.asarray(rng.normal(size=problem.shape))
    direct = bspline_transpose(
        problem.local, problem.mask * bspline_values(problem.local, grid), problem.shape
    )
    scale = float(jnp.max(jnp.abs(direct)))
    assert float(jnp.max(jnp.abs(normal.matvec(grid) - direct))) <= 1e-12 * scale
    rhs = bspline_transpose(problem.local, problem.mask * problem.targets, problem.shape)
    np.testing.assert_allclose(np.asarray(normal.rhs), np.asarray(rhs), atol=1e-13)
    # The stencil's energy equals the samples' (eq. 16, w = 1).
    energy = jurs.internal.data_energy(problem, grid, jnp.ones_like(grid))
    assert float(normal.data_energy(grid)) == pytest.approx(float(energy), rel=1e-11)


@pytest.mark.parametrize("lam", [0.0, 0.3])
@pytest.mark.slow
def test_autodiff_matches_hand_derived_in_3d(sphere, rng, lam):
    problem = jurs.make_problem(*sphere, grid=(5, 6, 5), offset=0.1, eps=0.1)
    control = jnp.asarray(0.02 * rng.standard_normal(problem.shape))
    weights = jnp.asarray(0.5 + rng.random(problem.shape))
    auto_c, auto_w = jax.grad(jurs.objective, argnums=(1, 2))(problem, control, weights, lam)
    hand_c = jurs.internal.data_energy_grad_control(
        problem, control, weights
    ) + lam * jurs.internal.regulariser_grad(control)
    hand_w = jurs.internal.data_energy_grad_weights(problem, control, weights)
    for auto, hand in ((auto_c, hand_c), (auto_w, hand_w)):
        assert np.linalg.norm(auto - hand) <= 1e-10 * np.linalg.norm(hand)


def test_regulariser_is_the_six_neighbour_sum(rng):
    c = rng.normal(size=(4, 5, 6))
    edges = sum(np.sum(np.diff(c, axis=a) ** 2) for a in range(3))
    assert float(jurs.internal.regulariser(jnp.asarray(c))) == pytest.approx(2.0 * edges, rel=1e-12)
    # L is the 6-neighbour graph Laplacian, and R's gradient is 4 L C (eq. 34).
    lap = np.asarray(_normal.stencil_to_dense(_normal.laplacian_stencil(c.shape)))
    np.testing.assert_allclose(
        np.asarray(jurs.internal.grid_laplacian(jnp.asarray(c))).ravel(),
        lap @ c.ravel(),
        atol=1e-12,
    )


@pytest.fixture(scope="module")
def sphere_fit(sphere):
    """The sphere fitted with the default solver on a grid small enough for the dense
    Cholesky (6^3): one compiled fit, which test_surface_fit_is_differentiable runs
    again (the same settings)."""
    return jurs.fit(*sphere, grid=6, offset=0.05, eps=0.05)


@pytest.mark.slow
def test_surface_fit_recovers_a_sphere(sphere_fit):
    sol = sphere_fit
    assert sol.result == jurs.RESULTS.successful
    x = jurs.datasets.sphere3d(300, seed=5)[0]
    g, grad = np.asarray(sol.spline(x)), np.asarray(sol.spline.grad(x))
    assert np.max(np.abs(g) / np.linalg.norm(grad, axis=1)) < 0.02  # zero set near r = 1
    inside, outside = sol.spline(jnp.zeros(3)), sol.spline(jnp.array([1.3, 0.0, 0.0]))
    assert float(inside) < 0 < float(outside)


def test_automatic_settings_in_3d(sphere):
    settings = jurs.auto_settings(*sphere)
    assert len(settings.grid) == 3 and len(settings.domain[0]) == 3
    assert max(settings.grid) <= jurs._fit.settings.DEFAULT_MAX_GRID_3D
    assert settings.smoothing == jurs._fit.settings.CLEAN_SURFACE_SMOOTHING  # exact samples
    # Exact samples of a smooth surface: only the quadratic's misfit to the sphere (its
    # fourth-order term over a few spacings).
    assert settings.noise < 1e-2 * settings.spacing
    noisy = jurs.datasets.sphere3d(400, seed=1)[0] * (
        1 + 0.02 * np.random.default_rng(0).standard_normal((400, 1))
    )
    assert jurs.auto_settings(noisy, sphere[1]).noise > 0.005


@pytest.mark.slow
def test_paper_iterations_run_in_3d(sphere):
    sol = jurs.fit(*sphere, grid=6, offset=0.05, eps=0.05, solver=jurs.IPIA(max_steps=30))
    energy = np.asarray(sol.stats["energy_history"])
    # I-PIA's steps (eq. 11) descend monotonically (mu = 2 / ||D^T D||, eq. 13).
    assert np.all(np.diff(energy) <= 1e-12 * energy[0]) and energy[-1] < 0.9 * energy[0]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(grid=(6, 6)), "triple"),
        (dict(grid=6, bucket_size=4), "bucket_size"),
        (dict(grid=6, domain=((0, 0), (1, 1))), "domain"),
    ],
)
def test_surface_inputs_are_checked(sphere, kwargs, match):
    with pytest.raises(ValueError, match=match):
        jurs.make_problem(*sphere, offset=0.05, **kwargs)


def test_spline_refuses_mismatched_box():
    with pytest.raises(ValueError, match="lower and upper"):
        jurs.ImplicitSpline.bspline(jnp.zeros((5, 5, 5)), [0.0, 0.0], [1.0, 1.0])


@pytest.mark.slow
def test_cascade_reaches_the_far_field():
    """Above the dense size the final CG starts from the cascade of coarser grids: CG from 0
    left the sphere's centre at g = 0 and grew a second surface there."""
    from jurs.solvers._cascade import coarse_grid

    points, normals = jurs.datasets.sphere3d(1500, seed=2)
    sol = jurs.fit(points, normals, grid=20)
    assert coarse_grid((20, 20, 20)) == (12, 12, 12)
    assert sol.result == jurs.RESULTS.successful
    assert float(sol.spline(jnp.zeros(3))) < -0.5 * float(sol.settings.eps)
    vertices, faces = jurs.levelset.mesh(sol.spline)
    report = jurs.levelset.analyze_mesh(vertices, faces, points)
    assert report.num_components == 1 and report.components[0].genus == 0


def test_cascade_keeps_the_given_start_where_the_coarse_solve_breaks_down(sphere):
    """A coarse Cholesky that breaks down (NaN: a system singular at rounding level) leaves
    the start the final CG was given; a finite coarse solve replaces it."""
    from jurs.solvers._cascade import cascadic_start

    problem = jurs.make_problem(*sphere, grid=16, offset=0.05, eps=0.05)
    start = jnp.full(problem.shape, 0.25)
    broken = lambda system, rhs, begin, solver: jnp.full_like(begin, jnp.nan)  # noqa: E731
    kept = cascadic_start(problem, 1e-3, broken, start)
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(start))
    ones = lambda system, rhs, begin, solver: jnp.ones_like(begin)  # noqa: E731
    # The transfer of the constant 1 (Greville values of a spline that is 1 everywhere).
    np.testing.assert_allclose(np.asarray(cascadic_start(problem, 1e-3, ones, start)), 1.0)


def test_cascade_transfer_reproduces_quadratics():
    """The transfer between levels gives the coarse spline's values at the fine grid's
    Greville points: checked on a coarse spline that is exactly x^2 along one axis."""
    from jurs._linalg.coarsen import greville_transfer as transfer

    coarse_n, fine_n = 9, 15
    greville = lambda n: (np.arange(n) - 1.0) / (n - 3)  # noqa: E731 (box [0, 1])
    # Coefficients at the Greville points of a quadratic's spline minus its h^2 term.
    quad = lambda x, n: x**2 - (1.0 / (n - 3)) ** 2 / 3.0  # noqa: E731
    x = greville(coarse_n)
    coarse = jnp.asarray(quad(x, coarse_n))[:, None, None] * jnp.ones((1, 5, 5))
    fine = transfer(coarse, (fine_n, 5, 5))
    expected = greville(fine_n) ** 2
    np.testing.assert_allclose(np.asarray(fine[:, 2, 2]), expected, atol=1e-12)


def test_rational_normal_equations_refuse_surfaces(sphere):
    """Fixed rational weights in 3D are not written yet: a clear error, not a wrong shape."""
    problem = jurs.make_problem(*sphere, grid=6, offset=0.05, eps=0.05)
    with pytest.raises(NotImplementedError, match="2D only"):
        jurs.internal.normal_equations(problem, jnp.ones(problem.shape))


@pytest.mark.slow
def test_surface_fit_is_differentiable(sphere, sphere_fit, rng):
    """jax.grad goes through a surface fit (implicit differentiation of the exact solve);
    checked against a central difference along one direction. A dense grid: the default
    CG's tolerance (1e-3 of max |rhs|) would be the difference's noise. The default
    solver, given explicitly (a traced cloud chooses nothing): the differences reuse
    ``sphere_fit``'s compiled fit."""
    points, normals = (jnp.asarray(a) for a in sphere)
    solver = jurs.LeastSquares(lam=sphere_fit.settings.lam)
    probe = jnp.array([[0.0, 0.0, 0.5]])

    def value(p):
        sol = jurs.fit(p, normals, grid=6, offset=0.05, eps=0.05, solver=solver)
        return sol.spline(probe)[0]

    direction = jnp.asarray(rng.standard_normal(points.shape))
    # The gradient compiled as one program (un-jitted, grad ran the traced layout op by op).
    slope = jnp.vdot(jax.jit(jax.grad(value))(points), direction)
    step = 1e-5
    central = (value(points + step * direction) - value(points - step * direction)) / (2 * step)
    assert float(slope) == pytest.approx(float(central), rel=1e-4)


@pytest.mark.slow
def test_cascade_levels_assemble_a_stride_of_dense_clouds(monkeypatch):
    """A coarse level with many samples a coefficient assembles every k-th one (lambda
    scaled by the fraction kept): the start changes, the solution it leads to does not."""
    from jurs.solvers import _cascade

    points, normals = jurs.datasets.sphere3d(800, seed=2)
    problem = jurs.make_problem(points, normals, grid=16, offset=0.03, eps=0.03)
    solver = jurs.LeastSquares(lam=1e-3)

    def solve():  # traced afresh each call: the stride is read when it is traced
        start = jnp.zeros(problem.shape)
        normal = jurs.internal.normal_equations
        return jax.jit(lambda p: solver.solve_assembled(p, normal(p), solver.lam, start)[0])(
            problem
        )

    monkeypatch.setattr(_cascade, "LEVEL_SAMPLES_PER_COEFFICIENT", 10**9)
    whole = solve()
    monkeypatch.setattr(_cascade, "LEVEL_SAMPLES_PER_COEFFICIENT", 1)
    assert _cascade.coarse_grid(problem.shape) == (10, 10, 10)
    assert _cascade.level_stride(problem, (10, 10, 10)) == 2  # 2400 samples, 1000 coefficients
    strided = solve()
    assert np.max(np.abs(np.asarray(strided) - np.asarray(whole))) > 0  # another start
    # ... and the same fit near the data, to the CG's tolerance (1e-3 of max |rhs|).
    x = jurs.datasets.sphere3d(500, seed=7)[0] * np.linspace(0.9, 1.1, 500)[:, None]
    g = [jurs.ImplicitSpline.bspline(c, problem.lower, problem.upper)(x) for c in (whole, strided)]
    assert np.max(np.abs(np.asarray(g[1] - g[0]))) < 1e-2 * 0.03


@pytest.mark.slow
@pytest.mark.parametrize("parts", [1, 2])
def test_surface_values_are_gathered_a_block_at_a_time(monkeypatch, rng, parts):
    """Blocks of samples (padded at the end of each part) give the values of the whole
    gather; two grids evaluated in one pass."""
    import dataclasses

    from jurs._model import spline as _spline

    x = rng.uniform(LOWER, UPPER, size=(1000, 3))
    local = dataclasses.replace(local_basis(jnp.asarray(x), LOWER, UPPER, SHAPE), parts=parts)
    grids = jnp.asarray(rng.standard_normal((2,) + SHAPE))
    whole = _spline._gathered_values(local, grids)
    monkeypatch.setattr(_spline, "GATHER_BLOCK", 96)  # 1000 / parts is not a multiple
    blocked = _spline._gathered_values(local, grids)
    expected = np.einsum("pn,qn->qp", dense_rows(x), np.asarray(grids).reshape(2, -1))
    np.testing.assert_allclose(np.asarray(whole), expected, atol=1e-12)
    np.testing.assert_allclose(np.asarray(blocked), expected, atol=1e-12)
    # Reverse mode goes through the blocks: the gradient is D^T (D G) per grid.
    grad = jax.grad(lambda g: 0.5 * jnp.sum(_spline._gathered_values(local, g) ** 2))(grids)
    adjoint = np.einsum("pn,qp->qn", dense_rows(x), expected).reshape(grids.shape)
    np.testing.assert_allclose(np.asarray(grad), adjoint, atol=1e-10)
