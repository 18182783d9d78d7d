"""The multilevel solve of a THB hierarchy's normal equations: its nested spaces'
prolongations are exact, its solve agrees with the direct one, and its step count stays
flat as levels are added."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs._fit.adaptive import (
    adaptive_layout,
    size_class,
    solve_direct,
    solve_host_cg,
    solve_host_multigrid,
    solve_multigrid,
)
from jurs._linalg.sparse import normal_system
from jurs._linalg.thb_multigrid import ThbMultigrid, multigrid_cg, nested_prolongations
from jurs._model.hierarchy import refined_cells
from jurs._problem.adaptive import assemble_adaptive_problem
from jurs.internal import (
    build_hierarchy,
    hierarchy_values,
    make_adaptive_problem,
    multilevel_preconditioner,
    solve_adaptive,
)

RTOL = 1e-10


def _problem(ndim, finest, count=None):
    """A fit's problem on a circle (2D) or a sphere (3D) for ``finest`` cells."""
    if ndim == 2:
        t = np.linspace(0, 2 * np.pi, count or 400, endpoint=False)
        points = np.stack([np.cos(t), np.sin(t)], 1)
        normals = points
    else:
        points, normals = jurs.datasets.sphere3d(count or 1500)
    lower, upper = np.full(ndim, -1.3), np.full(ndim, 1.3)
    lower, upper, base, levels = adaptive_layout(lower, upper, 2.6 / finest)
    problem, matrices = assemble_adaptive_problem(
        points, normals, offset=0.05, eps=0.01, lower=lower, upper=upper, base=base,
        levels=levels, band=1,
    )  # fmt: skip
    return problem, matrices, 1e-4


def _cut(hierarchy, level):
    """The hierarchy cut after ``level``: the THB basis of ``V_level``."""
    refine = refined_cells(hierarchy)[:level]
    return build_hierarchy(hierarchy.lower, hierarchy.upper, hierarchy.base, refine)


@pytest.mark.parametrize("ndim, finest", [(2, 64), (3, 32)])
def test_prolongation_reproduces_coarse_splines_exactly(ndim, finest):
    """A spline of V_l, prolonged into V_{l+1}, is the same function at random points; the
    cut hierarchies' own bases are the spaces' bases in the order the prolongations use."""
    problem, _, _ = _problem(ndim, finest)
    hierarchy = problem.hierarchy
    prolongations = nested_prolongations(hierarchy)
    assert len(prolongations) == hierarchy.num_levels - 1 >= 2
    rng = np.random.default_rng(0)
    lower, upper = np.asarray(hierarchy.lower), np.asarray(hierarchy.upper)
    x = jnp.asarray(rng.uniform(lower, upper, (2000, ndim)))
    for level, prolongation in enumerate(prolongations):
        coarse, fine = _cut(hierarchy, level), _cut(hierarchy, level + 1)
        assert prolongation.shape == (fine.num_active, coarse.num_active)
        c = rng.normal(size=coarse.num_active)
        expected = np.asarray(hierarchy_values(coarse, jnp.asarray(c), x))
        got = np.asarray(hierarchy_values(fine, jnp.asarray(prolongation @ c), x))
        np.testing.assert_allclose(got, expected, atol=1e-12)
    assert _cut(hierarchy, hierarchy.num_levels - 1).num_active == hierarchy.num_active


@pytest.mark.parametrize(
    "ndim, finest, smoother", [(2, 128, "schwarz"), (2, 128, "chebyshev"), (3, 16, "schwarz")]
)
def test_multigrid_solve_agrees_with_the_direct_solve(ndim, finest, smoother):
    problem, matrices, lam = _problem(ndim, finest, 600 if ndim == 3 else None)
    direct, _ = solve_direct(problem, lam, matrices)
    control, steps, residual = solve_host_multigrid(
        problem, matrices, lam, RTOL, 500, smoother=smoother
    )
    assert residual <= RTOL and 0 < steps < 500
    scale = np.linalg.norm(direct)
    assert np.linalg.norm(control - direct) <= 1e-6 * scale


def test_steps_stay_flat_as_levels_are_added():
    """Finest 32, 64, 128 cells in 2D (3, 4, 5 levels): the V-cycle's CG steps at the
    finest are at most 1.5 times those at the coarsest, and a quarter of Jacobi's."""
    steps, jacobi = [], []
    for finest in (32, 64, 128):
        problem, matrices, lam = _problem(2, finest)
        _, count, residual = solve_host_multigrid(problem, matrices, lam, RTOL, 500)
        assert residual <= RTOL
        steps.append(count)
        jacobi.append(solve_host_cg(problem, matrices, lam, RTOL, 5000)[1])
    assert steps[-1] <= 1.5 * steps[0], steps
    assert all(4 * s <= j for s, j in zip(steps, jacobi)), (steps, jacobi)


def test_functions_nothing_reaches_stay_zero():
    """A function with a zero row (no sample, no neighbour pair: here lam = 0 leaves the
    far ones so) keeps 0 under the cycle, as under Jacobi."""
    problem, matrices, _ = _problem(2, 64)
    matrix, rhs = normal_system(matrices, problem.targets, 0.0)
    dead = matrix.diagonal() == 0
    assert dead.any()
    multigrid = ThbMultigrid(problem.hierarchy, matrix)
    out = multigrid.cycle(np.random.default_rng(0).normal(size=rhs.shape))
    assert np.all(out[dead] == 0)
    x, _, _ = multigrid_cg(problem.hierarchy, matrix, rhs, 1e-8, 500)
    assert np.all(x[dead] == 0)


@pytest.mark.parametrize("method", ["multigrid", "host_multigrid"])
def test_fit_adaptive_with_the_multigrid_method_matches_the_direct_fit(method):
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    points = np.stack([np.cos(t), 0.6 * np.sin(t)], 1)
    normals = np.stack([0.6 * np.cos(t), np.sin(t)], 1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    direct = jurs.fit_adaptive(points, normals, finest=64, method="direct")
    multigrid = jurs.fit_adaptive(points, normals, finest=64, method=method)
    assert multigrid.status == "successful"
    assert multigrid.stats["method"] == method and multigrid.stats["num_steps"] > 0
    np.testing.assert_allclose(
        np.asarray(multigrid.spline.control), np.asarray(direct.spline.control), atol=1e-7
    )


def test_unknown_smoother_is_refused():
    problem, matrices, lam = _problem(2, 32)
    matrix, _ = normal_system(matrices, problem.targets, lam)
    with pytest.raises(ValueError, match="smoother"):
        ThbMultigrid(problem.hierarchy, matrix, smoother="gauss-seidel")


@pytest.mark.parametrize("method", ["multigrid", "host_multigrid"])
def test_a_hierarchy_of_one_level_is_solved_directly(method):
    """No refinement: the only space is the coarsest, and one cycle is its exact solve."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    multigrid = jurs.fit_adaptive(points, points, finest=8, method=method)
    direct = jurs.fit_adaptive(points, points, finest=8, method="direct")
    assert multigrid.stats["levels"] == 1 and multigrid.stats["num_steps"] == 1
    np.testing.assert_allclose(
        np.asarray(multigrid.spline.control), np.asarray(direct.spline.control), atol=1e-10
    )


@pytest.mark.parametrize(
    "ndim, finest, smoother", [(2, 64, "schwarz"), (2, 64, "chebyshev"), (3, 16, "schwarz")]
)
def test_the_device_cycle_is_the_host_cycle(ndim, finest, smoother):
    """``ThbMultigrid.on_device``: the same V-cycle in JAX, its padding inert."""
    problem, matrices, lam = _problem(ndim, finest, 600 if ndim == 3 else None)
    matrix, rhs = normal_system(matrices, problem.targets, lam)
    multigrid = ThbMultigrid(problem.hierarchy, matrix, smoother=smoother)
    cycle = multigrid.on_device(jnp.float64, pad=size_class)
    r = np.random.default_rng(2).normal(size=rhs.shape)
    padded = np.concatenate([r, np.zeros(cycle.mask.shape[0] - r.size)])
    got = np.asarray(jax.jit(lambda cycle, r: cycle(r))(cycle, jnp.asarray(padded)))
    np.testing.assert_allclose(got[: r.size], multigrid.cycle(r), rtol=1e-9, atol=1e-12)
    assert np.all(got[r.size :] == 0)


@pytest.mark.parametrize("ndim, finest", [(2, 128), (3, 16)])
def test_the_device_multigrid_solve_agrees_with_the_direct_solve(ndim, finest):
    problem, matrices, lam = _problem(ndim, finest, 600 if ndim == 3 else None)
    direct, _ = solve_direct(problem, lam, matrices)
    control, steps, residual = solve_multigrid(problem, matrices, lam, RTOL, 500, jnp.float64)
    host_steps = solve_host_multigrid(problem, matrices, lam, RTOL, 500)[1]
    assert residual <= RTOL and abs(steps - host_steps) <= 2, (steps, host_steps)
    np.testing.assert_allclose(control, direct, atol=1e-6 * np.linalg.norm(direct))


def test_gradient_through_a_multilevel_solve_matches_finite_differences():
    """``solve_adaptive`` preconditioned by the V-cycle: ``jax.grad`` through the solve (in
    the points and in lam) agrees with central differences, and the cycle cuts CG's
    steps."""
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    points = np.stack([1.3 * np.cos(t), np.sin(t)], 1)
    normals = np.stack([np.cos(t) / 1.3, np.sin(t)], 1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lower, upper, base, levels = adaptive_layout(np.full(2, -2.0), np.full(2, 2.0), 0.0625)
    problem = make_adaptive_problem(
        points, normals, offset=0.05, eps=0.05, lower=lower, upper=upper, base=base, levels=levels
    )
    assert problem.hierarchy.num_levels >= 3
    cycle = multilevel_preconditioner(problem, 1e-4)
    query = jnp.array([[0.3, 0.2], [1.2, 0.4], [-0.5, 0.95]])

    def loss(targets, lam):
        moved = eqx.tree_at(lambda problem: problem.targets, problem, targets)
        control, steps, _, _ = solve_adaptive(moved, lam, rtol=1e-13, precondition=cycle)
        return jnp.sum(hierarchy_values(problem.hierarchy, control, query) ** 2), steps

    targets = jnp.asarray(problem.targets)
    (value, steps), grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(
        targets, 1e-4
    )
    loss = jax.jit(loss)  # the differences below: one compiled solve, many right-hand sides
    jacobi_steps = solve_adaptive(problem, 1e-4, rtol=1e-13)[1]
    assert int(steps) < int(jacobi_steps) / 2, (steps, jacobi_steps)
    step = 1e-6
    for i in (0, 61, 150):
        e = jnp.zeros_like(targets).at[i].set(step)
        fd = (loss(targets + e, 1e-4)[0] - loss(targets - e, 1e-4)[0]) / (2 * step)
        np.testing.assert_allclose(grads[0][i], fd, rtol=1e-5, atol=1e-10)
    fd = (loss(targets, 1e-4 + 1e-9)[0] - loss(targets, 1e-4 - 1e-9)[0]) / 2e-9
    np.testing.assert_allclose(grads[1], fd, rtol=1e-4)
