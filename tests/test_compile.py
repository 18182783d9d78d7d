"""``jurs.COMPILER_OPTIONS`` (opt-in): they keep IEEE NaN/Inf semantics and move jurs's own
solvers only at rounding level."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from conftest import PAPER

import jurs


def test_options_are_accepted_and_keep_non_finite_semantics():
    """XLA rejects unknown option names, so this also guards against a renamed option; the
    driver's divergence check relies on isfinite / isnan seeing NaN and Inf."""
    def probe(x):
        total = jnp.sum(x * x)
        return jnp.isfinite(total), jnp.isnan(total), jnp.sum(x) / x[0]

    compiled = jax.jit(probe, compiler_options=jurs.COMPILER_OPTIONS)
    finite, nan, ratio = compiled(jnp.array([0.0, 1.0, jnp.inf]))
    assert not bool(finite) and not bool(nan) and np.isinf(float(ratio))
    finite, nan, _ = compiled(jnp.array([jnp.nan, 1.0, 2.0]))
    assert not bool(finite) and bool(nan)


def test_options_move_iurs_only_at_rounding_level():
    """The same IURS run compiled with and without the options: the same steps,
    coefficients and weights equal to rounding."""
    points, normals = jurs.datasets.example1(300)
    problem = jurs.make_problem(points, normals, **PAPER)
    solver = jurs.IURS(tau=1e-2, lam=1e-3, max_steps=300, tol=1e-9)

    def run(problem, solver):
        return jurs.solve(solver, problem)

    tuned = eqx.filter_jit(run, compiler_options=jurs.COMPILER_OPTIONS)(problem, solver)
    plain = eqx.filter_jit(run)(problem, solver)
    assert int(tuned.stats["num_steps"]) == int(plain.stats["num_steps"])
    for a, b in ((tuned.spline.control, plain.spline.control),
                 (tuned.spline.weights, plain.spline.weights)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-11, atol=1e-14)
