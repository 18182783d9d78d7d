"""``jurs.COMPILER_OPTIONS``: they keep IEEE NaN/Inf semantics, move jurs's own solvers only
at rounding level, and ``jurs.fit`` uses them only where XLA accepts them."""

import os
import subprocess
import sys

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


def _bucketed(points, normals):
    """Example 1 in the bucketed power form (what large clouds get automatically)."""
    return jurs.make_problem(points, normals, grid=12, offset=0.1, eps=0.01, bucket_size=8)


def test_fit_reassociates_only_own_solvers_on_large_layouts_at_top_level():
    from jurs._fit import reassociates

    points, normals = jurs.datasets.example1(300)
    bucketed = _bucketed(points, normals)
    table = jurs.make_problem(points, normals, grid=12, offset=0.1, eps=0.01)
    assert bucketed.local.terms is None and bucketed.local.bucket_size == 8
    for solver in (jurs.IURS(), jurs.IPIA(), jurs.NormalIPIA(), jurs.LeastSquares(lam=1e-4)):
        assert reassociates(bucketed, solver), type(solver).__name__
        assert not reassociates(table, solver), type(solver).__name__
    assert not reassociates(bucketed, jurs.JointLevenbergMarquardt())
    assert not reassociates(bucketed, jurs.JaxoptLBFGS())
    # Under a transformation: a traced leaf, or a concrete problem inside a caller's trace.
    seen = []
    jax.jit(lambda p: seen.append(reassociates(p, jurs.IURS())) or 0.0)(bucketed)
    jax.jit(lambda x: seen.append(reassociates(bucketed, jurs.IURS())) or x)(0.0)
    jax.grad(lambda lam: seen.append(reassociates(bucketed, jurs.IURS(lam=lam))) or lam)(1e-3)
    assert seen == [False, False, False]


def test_fit_of_a_large_layout_with_and_without_transformations(monkeypatch):
    """At top level jurs.fit compiles a bucketed IURS fit with the options, under grad it
    cannot (XLA refuses options on a nested jit) and must not try; both agree at rounding
    level with the plain compilation."""
    import jurs._fit as fit_module

    calls = []
    tuned = fit_module._solve_reassociating
    monkeypatch.setattr(fit_module, "_solve_reassociating",
                        lambda *args: calls.append(1) or tuned(*args))
    points, normals = jurs.datasets.example1(300)
    settings = dict(grid=12, offset=0.1, eps=0.01, bucket_size=8)
    sol = jurs.fit(points, normals, solver=jurs.IURS(lam=1e-3), **settings)
    assert calls == [1]
    plain = jurs.solve(jurs.IURS(lam=1e-3), _bucketed(points, normals))
    assert int(sol.stats["num_steps"]) == int(plain.stats["num_steps"])
    np.testing.assert_allclose(np.asarray(sol.spline.control), np.asarray(plain.spline.control),
                               rtol=1e-11, atol=1e-14)

    def energy(lam):
        return jurs.fit(points, normals, solver=jurs.IURS(lam=lam), **settings).metrics["E_ave"]

    value, slope = jax.value_and_grad(energy)(1e-3)
    assert calls == [1] and np.isfinite(float(slope))
    np.testing.assert_allclose(float(value), float(sol.metrics["E_ave"]), rtol=1e-10)


FIT_IN_A_FRESH_PROCESS = """
import jax
jax.config.update("jax_enable_x64", True)
import jurs
points, normals = jurs.datasets.example1(60)
sol = jurs.fit(points, normals, grid=9, offset=0.1, eps=0.01, solver=jurs.IURS(max_steps=5))
problem = jurs.make_problem(points, normals, grid=9, offset=0.1, eps=0.01)
def users_solve(problem):
    return jurs.solve(jurs.IURS(max_steps=4), problem, throw=False)
print(int(sol.stats["num_steps"]), int(jax.jit(users_solve)(problem).stats["num_steps"]))
"""


def test_a_fit_is_kept_by_the_persistent_compilation_cache(tmp_path):
    """jurs.fit at top level (throw=True by default) compiles no host callback into the fit,
    so JAX's persistent compilation cache writes it, for new processes to load; it writes
    a caller's jit of jurs.solve with throw=False too, as solve's docstring says."""
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(tmp_path),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", FIT_IN_A_FRESH_PROCESS], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["5", "4"]
    for name in ("jit__run-", "jit_users_solve-"):
        assert [p for p in os.listdir(tmp_path) if p.startswith(name)], os.listdir(tmp_path)
