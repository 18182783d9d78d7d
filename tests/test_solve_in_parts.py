"""The exact solve run on a cloud taken in parts (jurs/solvers/_parts.py) against the same
solve compiled whole: the same solution to rounding, the same verdicts."""

import equinox as eqx
import jax
import lineax as lx
import numpy as np
import pytest

import jurs
from jurs._solution.verdicts import offset_sign_counts
from jurs.solvers._parts import PART_POINTS, solve_in_parts, solves_in_parts


def _compare(problem, solver):
    whole = eqx.filter_jit(jurs.solve)(solver, problem, throw=False)
    parts = solve_in_parts(problem, solver)
    assert parts is not None
    assert jax.tree_util.tree_structure(parts) == jax.tree_util.tree_structure(whole)
    assert parts.message == whole.message
    control = np.asarray(whole.spline.control)
    np.testing.assert_allclose(
        np.asarray(parts.spline.control), control, rtol=0, atol=1e-8 * np.abs(control).max()
    )
    for key, value in whole.metrics.items():
        np.testing.assert_allclose(np.asarray(parts.metrics[key]), np.asarray(value), rtol=1e-8)
    np.testing.assert_allclose(
        np.asarray(parts.stats["energy_history"]), np.asarray(whole.stats["energy_history"]),
        rtol=1e-8,
    )  # fmt: skip
    assert int(parts.stats["num_steps"]) == int(whole.stats["num_steps"]) == 1
    return whole, parts


@pytest.mark.parametrize(
    "points, grid, lam, mask_every",
    [
        (120, 9, 0.0, None),  # the dense solve, one small part: the four steps in one program
        (400, 24, 1e-5, None),  # one part of 2048 points
        (PART_POINTS + 1500, 24, 1e-5, None),  # the block Cholesky, two parts
        (PART_POINTS + 1500, 24, 1e-5, 3),  # a mask: every third point left out
    ],
)
def test_parts_give_the_whole_solve(points, grid, lam, mask_every):
    p, n = jurs.datasets.example1(points)
    mask = None
    if mask_every:
        mask = np.ones(points)
        mask[::mask_every] = 0.0
    problem = jurs.make_problem(p, n, grid=grid, offset=0.05, eps=0.01, mask=mask)
    solver = jurs.LeastSquares(lam=lam)
    assert solves_in_parts(problem.num_points, problem.shape, solver, None)
    _compare(problem, solver)


def test_parts_read_inconsistent_normals_as_the_whole_solve_does():
    p, n = jurs.datasets.example1(600)
    n = n * np.where(np.random.default_rng(0).random(len(n)) < 0.5, -1.0, 1.0)[:, None]
    problem = jurs.make_problem(p, n, grid=24, offset=0.05, eps=0.01)
    whole, _ = _compare(problem, jurs.LeastSquares(lam=1e-5))
    assert whole.status == "inconsistent_normals"


def test_the_offset_sign_counts_of_parts_add_up():
    """Read with a stride (a cloud above ``SIGN_CHECK_POINTS`` points), the counts of a
    cloud's parts, each told the index of its first point, are the whole cloud's."""
    p, n = jurs.datasets.example1(900)
    whole = jurs.make_problem(p, n, grid=24, offset=0.05, eps=0.01)
    spline = eqx.filter_jit(jurs.solve)(jurs.LeastSquares(lam=1e-5), whole, throw=False).spline
    counts = eqx.filter_jit(offset_sign_counts)
    expected = [int(x) for x in counts(whole, spline, 3)]
    box = ((np.asarray(whole.lower), np.asarray(whole.upper)),)
    total = np.zeros(2, int)
    for first in (0, 350, 700):
        part = jurs.make_problem(
            p[first : first + 350], n[first : first + 350], grid=24, offset=0.05, eps=0.01,
            domain=box[0],
        )  # fmt: skip
        total += [int(x) for x in counts(part, spline, np.int32(3), np.int32(first))]
    assert list(total) == expected
    assert expected[1] == 300  # every third of 900 points


def test_solves_that_read_samples_are_solved_whole():
    p, n = jurs.datasets.example1(200)
    problem = jurs.make_problem(p, n, grid=12, offset=0.05, eps=0.01)
    size = problem.num_points, problem.shape
    assert not solves_in_parts(*size, jurs.LeastSquares(keep_weights=True), None)
    assert not solves_in_parts(*size, jurs.IPIA(), None)
    start = jurs.ImplicitSpline(
        np.zeros(problem.shape), np.ones(problem.shape), problem.lower, problem.upper
    )
    assert not solves_in_parts(*size, jurs.LeastSquares(), start)
    assert solves_in_parts(*size, jurs.LeastSquares(), None)


@pytest.mark.parametrize("grid, linear_solver", [(6, None), (8, "cg")])
def test_parts_give_the_whole_solve_of_a_surface(grid, linear_solver):
    """A surface's dense solve (6^3 coefficients), and one whose CG is given (so no
    cascade reads the samples), in parts as whole."""
    p, n = jurs.datasets.sphere3d(600)
    problem = jurs.make_problem(p, n, grid=grid, offset=0.05, eps=0.01)
    given = None if linear_solver is None else lx.CG(rtol=1e-12, atol=1e-14, max_steps=2000)
    solver = jurs.LeastSquares(lam=1e-5, linear_solver=given)
    assert solves_in_parts(problem.num_points, problem.shape, solver, None)
    _compare(problem, solver)


def test_a_surface_s_default_solve_is_solved_whole():
    p, n = jurs.datasets.sphere3d(300)
    problem = jurs.make_problem(p, n, grid=12, offset=0.05, eps=0.01)
    assert not solves_in_parts(
        problem.num_points, problem.shape, jurs.LeastSquares(lam=1e-5), None
    )  # the cascade


def test_the_first_try_is_the_default_s_first_solve():
    """``LeastSquares.first_try``: the linear solve the default runs first, without its
    fallback, for the concrete lam; the solver itself where there is nothing to spare."""
    from jurs._linalg.cholesky import BlockCholesky

    chosen = lambda solver, shape: type(solver.first_try(shape).linear_solver)  # noqa: E731
    assert chosen(jurs.LeastSquares(lam=1e-5), (96, 96)) is BlockCholesky
    assert chosen(jurs.LeastSquares(lam=0.0), (96, 96)) is lx.CG
    assert chosen(jurs.LeastSquares(lam=1e-5), (9, 9)) is lx.Cholesky
    for solver, shape in [
        (jurs.LeastSquares(lam=1e-5, linear_solver=lx.CG(rtol=1e-8, atol=0.0)), (96, 96)),
        (jurs.LeastSquares(lam=1e-5), (24, 24, 24)),  # the surface's cascade
        (jurs.LeastSquares(lam=1e-5), (512, 512)),  # CG: no factor that large
    ]:
        assert solver.first_try(shape) is solver


class _BreaksDown(lx.AbstractLinearSolver):
    """A factorisation that always breaks down: its solution is NaN."""

    def init(self, operator, options):
        return None

    def compute(self, state, vector, options):
        return jax.numpy.full_like(vector, jax.numpy.nan), lx.RESULTS.breakdown, {}

    def transpose(self, state, options):
        return state, options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


class _FlaggedSingular(_BreaksDown):
    """A solve that ends finite but is flagged as singular (as ``singular_solve`` flags an
    amplified one): the fit's verdict is ``failed``, its coefficients finite."""

    def compute(self, state, vector, options):
        return jax.numpy.zeros_like(vector), lx.RESULTS.singular, {}


def _first_tries_that_break_down(monkeypatch, linear_solver=None) -> list:
    """``LeastSquares.first_try`` patched to a solve that breaks down (or
    ``linear_solver``); the grids it is asked for are listed in the list returned."""
    tried = []
    linear_solver = _BreaksDown() if linear_solver is None else linear_solver

    def breaking(self, shape):
        tried.append(shape)
        return eqx.tree_at(
            lambda s: s.linear_solver, self, linear_solver, is_leaf=lambda x: x is None
        )

    monkeypatch.setattr(jurs.LeastSquares, "first_try", breaking)
    return tried


@pytest.mark.parametrize("points", [100, PART_POINTS + 1500])  # one small part; two parts
def test_a_first_try_that_breaks_down_falls_back_as_the_whole_solve(points, monkeypatch):
    """Where the first try's C is not finite, the parts run the solver's own solve, whose
    fallback takes over (as in the whole solve's compiled ``lax.cond``)."""
    p, n = jurs.datasets.example1(points)
    problem = jurs.make_problem(p, n, grid=24, offset=0.05, eps=0.01)
    solver = jurs.LeastSquares(lam=1e-5)
    tried = _first_tries_that_break_down(monkeypatch)
    _compare(problem, solver)
    assert tried == [problem.shape]


def test_a_whole_fit_falls_back_where_its_first_try_breaks_down(monkeypatch):
    """A top-level fit compiled whole (here: parts refused) runs ``first_try`` first, and
    the solver itself where that fit's coefficients are not finite."""
    import jurs._fit.call as call

    p, n = jurs.datasets.example1(400)
    settings = dict(grid=24, offset=0.05, eps=0.01, solver=jurs.LeastSquares(lam=1e-5))
    expected = jurs.fit(p, n, **settings)
    monkeypatch.setattr(call, "solves_in_parts", lambda *args: False)
    tried = _first_tries_that_break_down(monkeypatch)
    sol = jurs.fit(p, n, **settings)
    assert tried == [(24, 24)]
    assert sol.status == expected.status == "successful"
    control = np.asarray(expected.spline.control)
    np.testing.assert_allclose(
        np.asarray(sol.spline.control), control, rtol=0, atol=1e-8 * np.abs(control).max()
    )


def test_a_whole_fit_keeps_a_first_try_that_failed_with_finite_coefficients(monkeypatch):
    """A first try whose C is finite but flagged singular (verdict ``failed``) is the fit:
    the solver's own solve would run the same first solve and, its C being finite, not
    its fallback. (Here the patched first try differs from the solver's own, so a rerun
    would show as a successful fit.)"""
    import jurs._fit.call as call

    p, n = jurs.datasets.example1(400)
    settings = dict(grid=24, offset=0.05, eps=0.01, solver=jurs.LeastSquares(lam=1e-5))
    monkeypatch.setattr(call, "solves_in_parts", lambda *args: False)
    tried = _first_tries_that_break_down(monkeypatch, _FlaggedSingular())
    sol = jurs.fit(p, n, throw=False, **settings)
    assert tried == [(24, 24)]
    assert sol.status == "failed"
    assert np.all(np.asarray(sol.spline.control) == 0.0)
