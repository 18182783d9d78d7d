"""Geometric multigrid for stencil systems (jurs._linalg.multigrid): transfer, Galerkin operators,
patch smoother, the stencil operator type, and solves against direct ones.

Systems are built in NumPy/SciPy (dense B-spline collocation of Example 1's curve and its
offsets), so the only compilations are the solver's own; configurations that compare
alike share one jitted solve. About 45 s on a 2-core CPU."""

import dataclasses

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
import scipy.linalg as sla
from scipy.interpolate import BSpline

import jurs
from jurs._linalg import coarsen
from jurs._linalg import multigrid as mg
from jurs._linalg import patches as _patches
from jurs._linalg import stencil as _stencil
from jurs._linalg.cholesky import BlockCholesky
from jurs.solvers import _cascade
from jurs.solvers._least_squares import solve_normal_equations

#: Every test here compiles solvers for seconds: the whole module is slow.
pytestmark = pytest.mark.slow

jax.config.update("jax_enable_x64", True)

#: XLA's backend optimisation off for the tests' compilations: their systems are tiny, so
#: compiling is nearly all their cost, and this cuts it by about 30 % (a 3D solve: 10.2 ->
#: 7.3 s on a 2-core CPU). The numerics are the same.
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def jit(fn, **kwargs):
    return jax.jit(fn, compiler_options=FAST_COMPILE, **kwargs)


def basis_1d(x, n, lower, upper):
    """The n cubic B-splines of jurs' basis on [lower, upper] at x (scipy, knots extended
    3 cells past the box), ``(len(x), n)``."""
    h = (upper - lower) / (n - 3)
    knots = lower + (np.arange(n + 4) - 3.0) * h
    return BSpline.design_matrix(x, knots, 3).toarray()


def design(points, shape, lower, upper):
    """Dense tensor-product collocation rows of ``points`` (any dimension)."""
    rows = np.ones((len(points), 1))
    for axis, n in enumerate(shape):
        b = basis_1d(points[:, axis], n, lower[axis], upper[axis])
        rows = (rows[:, :, None] * b[:, None, :]).reshape(len(points), -1)
    return rows


def dense_to_stencil(a, shape):
    """The ``shape + (7,) * d`` stencil of a banded dense matrix (NumPy)."""
    d = len(shape)
    index = np.indices(shape).reshape(d, -1).T
    out = np.zeros(shape + (7,) * d)
    for offset in np.ndindex(*(7,) * d):
        target = index + np.array(offset) - 3
        ok = np.all((target >= 0) & (target < np.array(shape)), axis=1)
        rows = np.ravel_multi_index(index[ok].T, shape)
        cols = np.ravel_multi_index(target[ok].T, shape)
        values = np.zeros(len(index))
        values[ok] = a[rows, cols]
        out[(Ellipsis,) + offset] = values.reshape(shape)
    return out


def laplacian(shape):
    """jurs' grid Laplacian (free boundary) as a dense matrix: a sum over axes of path
    Laplacians (NumPy; jurs._linalg.stencil.laplacian_stencil's matrix)."""
    out = 0
    for axis, n in enumerate(shape):
        path = np.diag(np.r_[1.0, np.full(n - 2, 2.0), 1.0]) - np.eye(n, k=1) - np.eye(n, k=-1)
        eyes = [np.eye(m) for m in shape]
        eyes[axis] = path
        term = np.ones((1, 1))
        for m in eyes:
            term = np.kron(term, m)
        out = out + term
    return out


def curve_systems(n, lams, points=1500):
    """``{lam: (A, rhs, b.b)}`` of Example 1 (its curve at target 0, offsets at +-0.1 with
    targets +-0.01, as jurs.make_problem) on ``n x n``: ``A = D^T D + 2 lam L`` dense."""
    p, normals = jurs.datasets.example1(points)
    samples = np.concatenate([p, p + 0.1 * normals, p - 0.1 * normals])
    targets = np.concatenate([np.zeros(points), np.full(points, 0.01), np.full(points, -0.01)])
    lower, upper = samples.min(0) - 0.3, samples.max(0) + 0.3
    d = design(samples, (n, n), lower, upper)
    gram, lap = d.T @ d, laplacian((n, n))
    rhs = (d.T @ targets).reshape(n, n)
    return {lam: (gram + 2 * lam * lap, rhs, float(targets @ targets)) for lam in lams}


@pytest.mark.parametrize("n", [9, 12])
def test_prolongation_is_knot_insertion(n):
    """A coarse spline (cells twice as wide, same lower end; with an odd cell count its box
    reaches one fine cell further) equals its prolongation in the fine basis on the box."""
    nc = coarsen.coarse_size(n)
    h = 1.0 / (n - 3)
    x = np.linspace(0.0, 1.0, 101)
    coarse = basis_1d(x, nc, 0.0, 2 * h * (nc - 3))
    p = np.stack([np.asarray(coarsen.prolong(jnp.eye(nc)[i], (n,))) for i in range(nc)], axis=1)
    np.testing.assert_allclose(basis_1d(x, n, 0.0, 1.0) @ p, coarse, atol=1e-14)
    assert np.linalg.matrix_rank(p) == nc  # no coarse function vanishes on the box


def random_gram(shape, seed):
    """``D^T D + 1e-3 L`` of random samples in a unit box, any dimension (dense)."""
    rng = np.random.default_rng(seed)
    rows = design(
        rng.random((3 * int(np.prod(shape)), len(shape))),
        shape,
        np.zeros(len(shape)),
        np.ones(len(shape)),
    )
    return rows.T @ rows + 1e-3 * laplacian(shape)


@pytest.mark.parametrize("shape", [(10, 11), (9, 8, 10)])
def test_galerkin_and_probe_match_dense(shape):
    """probe_stencil recovers a banded matrix exactly; galerkin is P^T A P (2D and 3D)."""
    a = random_gram(shape, 0)
    coarse = tuple(coarsen.coarse_size(n) for n in shape)

    @jit
    def probe_and_coarsen(a):
        stencil = _stencil.probe_stencil(lambda v: (a @ v.ravel()).reshape(shape), shape, a.dtype)
        return stencil, _stencil.stencil_to_dense(coarsen.galerkin(stencil, coarse))

    stencil, got = probe_and_coarsen(a)
    np.testing.assert_allclose(stencil, dense_to_stencil(a, shape), atol=1e-13)
    p = np.ones((1, 1))
    for n, nc in zip(shape, coarse):
        p = np.kron(p, np.stack([np.asarray(coarsen.prolong(e, (n,))) for e in jnp.eye(nc)], 1))
    expected = p.T @ a @ p
    np.testing.assert_allclose(got, expected, atol=1e-13 * np.abs(expected).max())


@pytest.mark.parametrize("shape", [(5, 4), (3, 4, 5)])
def test_stencil_product_derivatives_are_the_dense_products(shape):
    """stencil_matvec's own derivative rule (a contraction with the grid's windows): its
    forward and reverse derivatives in the stencil and the grid are the dense matrix's."""
    rng = np.random.default_rng(3)
    d = len(shape)
    stencil = jnp.asarray(rng.standard_normal(shape + (_stencil.SIDE,) * d))
    grid, d_grid, cotangent = (jnp.asarray(rng.standard_normal(shape)) for _ in range(3))
    d_stencil = jnp.asarray(rng.standard_normal(stencil.shape))

    def dense(s, x):
        return (_stencil.stencil_to_dense(s) @ x.ravel()).reshape(shape)

    def derivatives(fn):  # jvp, then vjp, in one compiled program
        def both(s, x, ds, dx, ct):
            return (jax.jvp(fn, (s, x), (ds, dx))[1], *jax.vjp(fn, s, x)[1](ct))

        return jit(both)(stencil, grid, d_stencil, d_grid, cotangent)

    got, expected = derivatives(_stencil.stencil_matvec), derivatives(dense)
    for a, b in zip(got, expected):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def test_generic_kernels_in_3d():
    """stencil_matvec, laplacian_stencil and stencil_to_scipy on a 3D grid."""
    shape = (5, 6, 7)
    lap = _stencil.laplacian_stencil(shape)
    x = np.random.default_rng(1).standard_normal(shape)
    padded = np.pad(x, 1, mode="edge")  # free boundary: a missing neighbour adds nothing
    expected = sum(
        x - np.roll(padded, s, axis)[1:-1, 1:-1, 1:-1] for axis in range(3) for s in (1, -1)
    )
    np.testing.assert_allclose(_stencil.stencil_matvec(lap, jnp.asarray(x)), expected, atol=1e-12)
    np.testing.assert_allclose(
        _stencil.stencil_to_scipy(lap) @ x.ravel(), expected.ravel(), atol=1e-12
    )
    assert _stencil.stencil_diagonal(lap).shape == shape


@pytest.mark.parametrize("shape, side, stride", [((13, 5), 8, 4), ((9, 7, 6), 4, 2)])
def test_patches_are_principal_submatrices(shape, side, stride):
    """Patches cover the grid (every point in 1..(side/stride)^d of them); each block is
    the matrix's principal submatrix on its points (identity on padding) and
    patch_inverses inverts it up to its ridge; add_patches is extract_patches' transpose."""
    d = len(shape)
    a = random_gram(shape, 1)
    layout = _patches.patch_layout(shape, side, stride)

    @jit
    def patches(stencil):
        ids = _patches.extract_patches(layout, jnp.arange(1.0, a.shape[0] + 1).reshape(shape))
        cover = _patches.add_patches(layout, jnp.ones(ids.shape))
        (inverses,) = _patches.patch_inverses([layout], [stencil])
        return ids, cover, _patches.patch_blocks(layout, stencil), inverses

    ids, cover, blocks, inverses = (np.asarray(x) for x in patches(dense_to_stencil(a, shape)))
    ids = ids.astype(int) - 1  # -1: padding
    for p in range(len(ids)):
        real = ids[p] >= 0
        np.testing.assert_array_equal(
            blocks[p][np.ix_(real, real)], a[np.ix_(ids[p][real], ids[p][real])]
        )
        np.testing.assert_array_equal(blocks[p][np.ix_(~real, ~real)], np.eye((~real).sum()))
    assert cover.min() == 1 and cover.max() <= np.ceil(side / stride) ** d
    np.testing.assert_allclose(
        np.einsum("pab,pbc->pac", inverses, blocks),
        np.broadcast_to(np.eye(layout.size), blocks.shape),
        atol=1e-11,
    )


@pytest.mark.parametrize("shape", [(7, 6, 5), (4, 4, 4), (5, 6)])
def test_block_jacobi_inverts_the_diagonal_blocks(shape):
    """BlockJacobi applies the inverses of the matrix's diagonal blocks of 2^d neighbouring
    points (odd sides padded), up to its ridge; a zero row (a coefficient no sample reaches)
    is inverted as an identity row; a 3D StencilOperator chooses it, a 2D one Jacobi."""
    d = len(shape)
    a = random_gram(shape, 2)
    a[0, :] = a[:, 0] = 0.0  # the first point unseen
    stencil = jnp.asarray(dense_to_stencil(a, shape))
    r = np.random.default_rng(3).standard_normal(shape)
    got = np.asarray(jit(lambda s, r: _stencil.BlockJacobi(s)(r))(stencil, jnp.asarray(r)))
    block = np.ravel_multi_index(
        tuple(i.ravel() // 2 for i in np.indices(shape)), tuple(-(-n // 2) for n in shape)
    )
    expected = np.zeros(a.shape[0])
    for b in np.unique(block):
        members = np.flatnonzero(block == b)
        sub = a[np.ix_(members, members)] + np.diag(a.diagonal()[members] == 0)
        expected[members] = np.linalg.solve(sub, r.ravel()[members])
    np.testing.assert_allclose(got.ravel(), expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())
    chosen = _stencil.StencilOperator(stencil).preconditioner()
    assert isinstance(chosen, _stencil.BlockJacobi) == (d == 3)


@pytest.fixture(scope="module")
def systems():
    """Example 1 on 24 x 24 and 48 x 48 for the lam the tests use: ``{(n, lam): (A, rhs,
    b.b)}``."""
    lams = {24: (1e-4, 1e-14), 48: (1e-4, 1e-8, 1e-14)}
    return {(n, lam): system for n in lams for lam, system in curve_systems(n, lams[n]).items()}


def test_smoother_spectrum_within_its_bound(systems):
    """The Schwarz smoother's ``M^-1 A`` has its spectrum in (0, colours]: the a priori
    bound the Chebyshev smoother relies on (no power iteration), even at lam = 1e-14
    where the patch blocks are singular to rounding but for their ridge."""
    a, _, _ = systems[(24, 1e-14)]

    @jit
    def smoother(stencil):
        level = mg.build_hierarchy(stencil, coarsest_size=COARSEST).levels[0]
        return jax.vmap(lambda e: level.smooth(e.reshape(24, 24)).ravel())(jnp.eye(24 * 24))

    eigenvalues = sla.eigvals(np.asarray(smoother(dense_to_stencil(a, (24, 24)))) @ a).real
    upper = _patches.patch_layout((24, 24), *_patches.DEFAULT_PATCH[2]).colours()
    assert 0 < eigenvalues.min() and eigenvalues.max() <= upper == 9


def stencil_solve(stencil, rhs, solver, target_norm2):
    """A lineax solve as LeastSquares calls it: the system as a StencilOperator."""
    operator = _stencil.StencilOperator(stencil)
    options = {"target_norm2": target_norm2}
    sol = lx.linear_solve(operator, rhs, solver, options=options, throw=False)
    return sol.value, sol.stats["num_steps"], sol.result


jitted_solve = jit(stencil_solve, static_argnums=2)
#: Two smoothing levels on 48 x 48 (48, 26; coarsest 15 x 15), one on 24 x 24: each level
#: adds seconds of compilation.
COARSEST = 256
#: rtol relative to the objective (target_norm2 given): gap <= 1e-14 E* by the estimate.
#: The full multigrid start (the default) is compiled in test_float32_solve only.
SOLVER = mg.Multigrid(rtol=1e-7, max_steps=300, coarsest_size=COARSEST, full_multigrid=False)


def objective_gap(a, rhs, b2, x):
    """The objective's relative gap to the exact minimiser, ``(x - x*) A (x - x*) / E*``
    (no cancellation against b.b), and ``x``'s relative error."""
    exact = np.linalg.solve(a, rhs.ravel())  # (scipy warns of the condition at lam = 1e-14)
    d = np.asarray(x).ravel() - exact
    optimum = b2 - exact @ rhs.ravel()
    return d @ a @ d / optimum, np.linalg.norm(d) / np.linalg.norm(exact)


@pytest.mark.parametrize("lam", [1e-4, 1e-8, 1e-14])
def test_multigrid_matches_direct(systems, lam):
    """Three levels on sparse curve data: the objective within 1e-10 (relative) of the exact
    minimiser's at every lam, the solution within 1e-8 where lam keeps it well posed; the
    steps stay near those measured (15, 36, 61 on a 2-core CPU: a regression guard)."""
    a, rhs, b2 = systems[(48, lam)]
    stencil = jnp.asarray(dense_to_stencil(a, (48, 48)))
    assert len(mg.level_shapes((48, 48), COARSEST)) == 3
    x, steps, result = jitted_solve(stencil, jnp.asarray(rhs), SOLVER, b2)
    assert result == lx.RESULTS.successful
    gap, error = objective_gap(a, rhs, b2, x)
    print(f"lam={lam:g}: {int(steps)} steps, objective gap {gap:.1e}, C error {error:.1e}")
    assert abs(gap) <= 1e-10
    assert int(steps) <= {1e-4: 20, 1e-8: 48, 1e-14: 80}[lam]
    if lam >= 1e-4:
        assert error <= 1e-8


def test_steps_do_not_grow_with_the_grid(systems):
    """At lam = 1e-4, refining 24 x 24 to 48 x 48 (same data) costs no more CG steps."""
    steps = {}
    for n in (24, 48):
        a, rhs, b2 = systems[(n, 1e-4)]
        stencil = jnp.asarray(dense_to_stencil(a, (n, n)))
        _, steps[n], _ = jitted_solve(stencil, jnp.asarray(rhs), SOLVER, b2)
    assert int(steps[48]) <= int(steps[24]) + 1, steps


def test_success_on_the_last_allowed_step(systems):
    """A solve whose stop test passes on its last allowed step is successful; one step
    fewer is max_steps_reached."""
    a, rhs, b2 = systems[(24, 1e-4)]
    stencil, rhs = jnp.asarray(dense_to_stencil(a, (24, 24))), jnp.asarray(rhs)
    _, steps, _ = jitted_solve(stencil, rhs, SOLVER, b2)
    for cap, expected in (
        (int(steps), lx.RESULTS.successful),
        (int(steps) - 1, lx.RESULTS.max_steps_reached),
    ):
        solver = dataclasses.replace(SOLVER, max_steps=cap)
        _, capped_steps, result = jitted_solve(stencil, rhs, solver, b2)
        assert int(capped_steps) == cap and result == expected


def test_float32_solve(systems):
    """In float32 the solve converges to float32 accuracy of the float64 minimiser."""
    a, rhs, b2 = systems[(24, 1e-4)]
    stencil = jnp.asarray(dense_to_stencil(a, (24, 24)), jnp.float32)
    solver = mg.Multigrid(rtol=1e-3, coarsest_size=COARSEST)  # with the full multigrid start
    x, _, result = jitted_solve(stencil, jnp.asarray(rhs, jnp.float32), solver, np.float32(b2))
    assert x.dtype == jnp.float32 and result == lx.RESULTS.successful
    exact = sla.solve(a, rhs.ravel(), assume_a="pos")
    # 1e-4 measured: the float32 system itself is ill-conditioned at lam = 1e-4.
    assert np.linalg.norm(np.asarray(x).ravel() - exact) <= 1e-3 * np.linalg.norm(exact)


def test_cg_flags_an_indefinite_preconditioner():
    """A preconditioner that is not positive definite (as float32 patch inverses of
    ill-conditioned patches are) stops CG with a breakdown instead of a wrong answer."""
    a = jnp.diag(jnp.arange(1.0, 7.0))
    sign = jnp.array([1.0, 1.0, -1.0, 1.0, 1.0, 1.0])
    _, steps, _, broken, _ = jit(
        lambda b: mg.preconditioned_cg(
            lambda x: a @ x, lambda r: sign * r / jnp.diag(a), b, jnp.zeros(6), 1e-12, 0.0, 50
        )
    )(jnp.ones(6))
    assert bool(broken) and int(steps) < 50


def test_3d_solve_matches_dense():
    """A 9 x 8 x 10 B-spline Gram + Laplacian (two levels, default 3D patches, one smoothing
    step each way) solved to 1e-10 of the dense solve (hierarchy and CG called directly:
    a 3D solve is the costliest to compile)."""
    shape = (9, 8, 10)
    a = random_gram(shape, 2)
    b = np.random.default_rng(3).standard_normal(shape)
    assert len(mg.level_shapes(shape, COARSEST)) == 2

    @jit
    def solve(stencil, b):
        hierarchy = mg.build_hierarchy(stencil, coarsest_size=COARSEST, degree=1)
        return mg.preconditioned_cg(
            lambda x: _stencil.stencil_matvec(stencil, x),
            lambda r: mg.v_cycle(hierarchy, r),
            b,
            jnp.zeros_like(b),
            1e-12,
            0.0,
            100,
        )

    x, _, _, broken, converged = solve(dense_to_stencil(a, shape), b)
    expected = sla.solve(a, b.ravel(), assume_a="pos").reshape(shape)
    assert not broken and converged
    assert np.linalg.norm(x - expected) <= 1e-10 * np.linalg.norm(expected)


def test_gradients_through_lineax(systems):
    """jax.grad through the solve (lineax's implicit differentiation, the adjoint solved by
    Multigrid too) matches central differences, in lam (through the operator) and in the
    right-hand side."""
    gram, rhs, _ = systems[(24, 1e-4)]
    gram = gram - 2e-4 * laplacian((24, 24))
    g, lap = (jnp.asarray(dense_to_stencil(m, (24, 24))) for m in (gram, laplacian((24, 24))))
    solver = mg.Multigrid(rtol=1e-10, coarsest_size=COARSEST, full_multigrid=False, degree=1)
    weights = jnp.asarray(np.random.default_rng(4).standard_normal((24, 24)))

    def loss(lam, scale):
        x, _, _ = stencil_solve(g + 2 * lam * lap, scale * jnp.asarray(rhs), solver, None)
        return jnp.vdot(weights, x)

    lam, scale, h = 1e-4, 1.0, 1e-7
    grads = jit(jax.grad(loss, argnums=(0, 1)))(lam, scale)
    value = jit(loss)
    fd = (
        (value(lam + h * lam, scale) - value(lam - h * lam, scale)) / (2 * h * lam),
        (value(lam, scale + h) - value(lam, scale - h)) / (2 * h),
    )
    for got, want in zip(grads, fd):
        assert abs(float(got) - float(want)) <= 1e-5 * abs(float(want))


def test_stencil_operator_is_recognised_by_type(systems):
    """StencilOperator is a lineax operator whose mv and as_matrix are its stencil's matrix,
    tagged symmetric positive semi-definite; the solvers that use the stencil itself take
    it by type, in a lineax solve and through LeastSquares' solve_normal_equations:
    Multigrid and BlockCholesky agree with the dense solve."""
    a, rhs, b2 = systems[(24, 1e-4)]
    stencil, rhs = jnp.asarray(dense_to_stencil(a, (24, 24))), jnp.asarray(rhs)
    operator = _stencil.StencilOperator(stencil)
    assert lx.is_symmetric(operator) and lx.is_positive_semidefinite(operator)
    assert not (lx.is_diagonal(operator) or lx.is_negative_semidefinite(operator))
    assert operator.transpose() is operator and lx.materialise(operator) is operator
    assert (
        operator.in_structure()
        == operator.out_structure()
        == jax.ShapeDtypeStruct((24, 24), stencil.dtype)
    )
    x = np.random.default_rng(5).standard_normal((24, 24))
    np.testing.assert_allclose(operator.as_matrix(), a, rtol=0, atol=0)
    np.testing.assert_allclose(operator.mv(jnp.asarray(x)).ravel(), a @ x.ravel(), atol=1e-12)
    np.testing.assert_array_equal(lx.diagonal(operator), np.diag(a))

    exact = sla.solve(a, np.asarray(rhs).ravel(), assume_a="pos")
    multigrid, _, result = jitted_solve(stencil, rhs, SOLVER, b2)
    assert result == lx.RESULTS.successful
    direct = jit(lambda s, b: lx.linear_solve(_stencil.StencilOperator(s), b, BlockCholesky()))(
        stencil, rhs
    )
    assert direct.result == lx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(direct.value).ravel(), exact, rtol=1e-10)
    gap, error = objective_gap(a, np.asarray(rhs), b2, multigrid)
    assert abs(gap) <= 1e-10 and error <= 1e-8

    policy = jit(solve_normal_equations, static_argnums=3)
    start = jnp.zeros_like(rhs)
    for solver in (BlockCholesky(), SOLVER):
        control, result = policy(operator, rhs, start, solver)
        assert result == lx.RESULTS.successful
        # Multigrid here stops at rtol 1e-7 of C.A C (no target_norm2): the error's scale.
        np.testing.assert_allclose(
            np.asarray(control).ravel(), exact, rtol=0, atol=1e-6 * np.abs(exact).max()
        )
    with pytest.raises(ValueError, match="StencilOperator"):
        BlockCholesky().init(lx.MatrixLinearOperator(jnp.asarray(a)), {})


def test_cascade_and_multigrid_coarsen_by_one_rule(monkeypatch):
    """The multigrid's levels and the cascade's grids both come from
    jurs._linalg.coarsen.coarsening (each caller choosing where to stop): changing the
    rule changes both."""
    assert mg.level_shapes((20, 20, 20), 1728) == [(20, 20, 20), (12, 12, 12)]
    assert _cascade.coarse_grid((20, 20, 20)) == (12, 12, 12)
    rule = coarsen.coarse_size

    def narrower(n, min_side=coarsen.MIN_COARSEN_SIDE):
        return rule(n, min_side) - 1 if n >= min_side else n

    monkeypatch.setattr(coarsen, "coarse_size", narrower)
    assert mg.level_shapes((20, 20, 20), 1728) == [(20, 20, 20), (11, 11, 11)]
    assert _cascade.coarse_grid((20, 20, 20)) == (11, 11, 11)


def test_bad_input():
    with pytest.raises(ValueError, match="rtol"):
        mg.Multigrid(rtol=-1.0)
    with pytest.raises(ValueError, match="stride"):
        mg.Multigrid(patch=(4, 5))
    operator = lx.MatrixLinearOperator(jnp.eye(4), lx.positive_semidefinite_tag)
    with pytest.raises(ValueError, match="2D or 3D grid"):
        lx.linear_solve(operator, jnp.ones(4), mg.Multigrid())
