"""``jurs.COMPILER_OPTIONS``: they keep IEEE NaN/Inf semantics, move jurs's own solvers only
at rounding level, and ``jurs.fit`` uses them only where XLA accepts them."""

import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
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


@pytest.mark.slow
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
    for a, b in (
        (tuned.spline.control, plain.spline.control),
        (tuned.spline.weights, plain.spline.weights),
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-11, atol=1e-14)


def _bucketed(points, normals):
    """Example 1 in the bucketed power form (what large clouds get automatically)."""
    return jurs.make_problem(points, normals, grid=12, offset=0.1, eps=0.01, bucket_size=8)


def test_fit_reassociates_only_own_solvers_on_large_layouts_at_top_level():
    from jurs._fit.call import reassociates

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


@pytest.mark.slow
def test_fit_of_a_large_layout_with_and_without_transformations(monkeypatch):
    """At top level jurs.fit compiles a bucketed IURS fit with the options, under grad it
    cannot (XLA refuses options on a nested jit) and must not try; both agree at rounding
    level with the plain compilation."""
    import jurs._fit.call as fit_module

    calls = []
    tuned = fit_module._solve_reassociating
    monkeypatch.setattr(
        fit_module, "_solve_reassociating", lambda *args: calls.append(1) or tuned(*args)
    )
    points, normals = jurs.datasets.example1(300)
    settings = dict(grid=12, offset=0.1, eps=0.01, bucket_size=8)
    sol = jurs.fit(points, normals, solver=jurs.IURS(lam=1e-3), **settings)
    assert calls == [1]
    plain = jurs.solve(jurs.IURS(lam=1e-3), _bucketed(points, normals))
    assert int(sol.stats["num_steps"]) == int(plain.stats["num_steps"])
    np.testing.assert_allclose(
        np.asarray(sol.spline.control), np.asarray(plain.spline.control), rtol=1e-11, atol=1e-14
    )

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


@pytest.mark.slow
def test_a_fit_is_kept_by_the_persistent_compilation_cache(tmp_path):
    """jurs.fit at top level (throw=True by default) compiles no host callback into the fit,
    so JAX's persistent compilation cache writes it, for new processes to load; it writes
    a caller's jit of jurs.solve with throw=False too, as solve's docstring says."""
    env = dict(
        os.environ,
        JAX_COMPILATION_CACHE_DIR=str(tmp_path),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PLATFORMS="cpu",
    )
    proc = subprocess.run(
        [sys.executable, "-c", FIT_IN_A_FRESH_PROCESS],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["5", "4"]
    for name in ("jit__run-", "jit_users_solve-"):
        assert [p for p in os.listdir(tmp_path) if p.startswith(name)], os.listdir(tmp_path)


# --- Shape-stable fits: padding, rounded layouts and grids ------------------------------


def test_size_ladders_round_up_with_four_sizes_and_one_size_an_octave():
    from jurs._problem.sizes import OCTAVE_PADDING_MAX, padded_count, round_octave, round_size

    sizes = np.arange(1, 5000)
    rounded = np.array([round_size(n) for n in sizes])
    assert (rounded >= sizes).all() and (np.diff(rounded) >= 0).all()
    assert (rounded[sizes > 8] < 1.25 * sizes[sizes > 8]).all()
    assert (rounded[sizes <= 8] == sizes[sizes <= 8]).all()
    assert all(round_size(r) == r for r in rounded)  # a rung rounds to itself
    octave = [r for r in set(rounded) if 1024 < r <= 2048]
    assert sorted(octave) == [1280, 1536, 1792, 2048]
    # Point counts: one size an octave, a power of two, at most twice the count.
    padded = np.array([padded_count(int(n)) for n in sizes])
    assert (padded >= sizes).all() and (padded < np.maximum(2 * sizes, 33)).all()
    assert sorted({int(r) for r in padded if 1024 < r <= 2048}) == [2048]
    assert all(round_octave(int(r)) == r for r in padded)
    assert padded_count(3) == 32 and padded_count(1000) == 1024 and padded_count(1100) == 2048
    big = OCTAVE_PADDING_MAX + 1  # above it, four sizes an octave again
    assert padded_count(big) == round_size(big) < 1.25 * big


def _fit_problem(points, normals, **settings):
    """The problem jurs.fit builds: padded cloud, layout sized for the band."""
    from jurs._problem.padding import padded_cloud

    p, n, mask = padded_cloud(points, normals)
    return jurs.make_problem(p, n, mask=mask, stable_shapes=True, **settings)


def test_clouds_in_one_band_get_problems_of_one_shape():
    """Every array of the problem (table included) has the same shape for 200 and 215
    points (both padded to 256), in the table form and in the bucketed power form; the
    layout holds every real sample once and no padding sample."""
    shapes = []
    for m in (200, 215):
        points, normals = jurs.datasets.example1(m)
        for bucket_size in (None, 4):
            problem = _fit_problem(
                points, normals, grid=(11, 13), offset=0.1, eps=0.01, bucket_size=bucket_size
            )
            real = np.asarray(problem.mask) > 0
            assert np.array_equal(
                np.sort(np.asarray(problem.sample_index)[real]),
                np.arange(3 * m) // m * 256 + np.arange(3 * m) % m,
            )
            if bucket_size is None:  # table: the real slots, each at one filled position
                filled = np.asarray(problem.local.filled) > 0
                assert (
                    np.sort(np.asarray(problem.local.order)[filled]).tolist()
                    == np.flatnonzero(real).tolist()
                )
            shapes.append(jax.tree.map(jnp.shape, problem))
    assert shapes[0] == shapes[2] and shapes[1] == shapes[3]


def _assert_padded_fit_agrees_with_the_unpadded_fit(solver):
    """jurs.fit pads 150 points to 256 and lays out the samples for the band; the result is
    the unpadded solve's to rounding (float64)."""
    points, normals = jurs.datasets.example1(150)
    settings = dict(grid=(10, 12), offset=0.1, eps=0.01)
    padded = jurs.fit(points, normals, solver=solver, **settings)
    plain = jurs.solve(solver, jurs.make_problem(points, normals, **settings))
    assert int(padded.stats["num_steps"]) == int(plain.stats["num_steps"])
    for a, b in (
        (padded.spline.control, plain.spline.control),
        (padded.spline.weights, plain.spline.weights),
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-13)
    for key in ("E", "E_ave", "E_max", "mu"):
        np.testing.assert_allclose(float(padded.metrics[key]), float(plain.metrics[key]), rtol=1e-9)
    np.testing.assert_array_equal(np.asarray(padded.spline.lower), np.asarray(plain.spline.lower))


@pytest.mark.slow
def test_padded_exact_fit_agrees_with_the_unpadded_one():
    _assert_padded_fit_agrees_with_the_unpadded_fit(jurs.LeastSquares(lam=1e-4))


@pytest.mark.slow
def test_padded_iurs_fit_agrees_with_the_unpadded_one():
    _assert_padded_fit_agrees_with_the_unpadded_fit(jurs.IURS(lam=1e-3, max_steps=20))


class _CompileCounter:
    """Counts XLA compilations of jurs.fit's jitted solve (or, with ``name=""``, of
    anything), through JAX's public monitoring events."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self, name: str = "_run"):
        self.count = 0
        self.name = name

    def __call__(self, event, duration, **kwargs):
        if event == self.EVENT and self.name in str(kwargs.get("fun_name", "")):
            self.count += 1

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self)


@pytest.mark.slow
def test_new_clouds_on_one_grid_compile_nothing():
    """A new cloud of another size (in the same band or the next, another shape of the same
    extent) on a grid fitted before compiles nothing: the exact solve runs in parts of a
    fixed size (jurs/solvers/_parts.py). A grid of its own compiles anew (the counter
    works)."""
    settings = dict(offset=0.1, eps=0.01, solver=jurs.LeastSquares(lam=1e-4))
    counts = []
    for (points, normals), grid in (
        (jurs.datasets.example1(330), (10, 11)),
        (jurs.datasets.example1(370), (10, 11)),
        (jurs.datasets.add_noise(*jurs.datasets.example1(350), sigma=0.01), (10, 11)),
        (jurs.datasets.example1(520), (10, 11)),
        (jurs.datasets.example1(520), (10, 13)),
    ):
        with _CompileCounter(name="") as counter:
            jax.block_until_ready(jurs.fit(points, normals, grid=grid, **settings).spline)
        counts.append(counter.count)
    assert counts[1:4] == [0, 0, 0] and counts[4] >= 1, counts


LADDER = (1000, 1050, 1130, 1300, 1600, 2000)


def test_a_ladder_of_cloud_sizes_gets_one_problem_shape_an_octave():
    """The problems jurs.fit builds for clouds of 1000 to 2000 points on one grid: one
    shape for 1000 points (padded to 1024), one for the five of the next octave."""
    shapes = []
    for m in LADDER:
        points, normals = jurs.datasets.example1(m)
        problem = _fit_problem(points, normals, grid=12, offset=0.1, eps=0.01)
        shapes.append(jax.tree.map(jnp.shape, problem))
    assert shapes[0] != shapes[1] and all(s == shapes[1] for s in shapes[2:])


@pytest.mark.slow  # compilations of the exact solve; the shapes' test above is fast
def test_a_ladder_of_cloud_sizes_compiles_once_a_grid():
    """Clouds of 1000 to 2000 points fitted in one process (one grid, every setting given,
    the exact solve): what the first compiles serves the other five, across the octave
    that their problems' shapes cross (jurs/solvers/_parts.py)."""
    solver = jurs.LeastSquares(lam=1e-4)
    counts = []
    for m in LADDER:
        points, normals = jurs.datasets.example1(m)
        with _CompileCounter(name="") as counter:
            sol = jurs.fit(points, normals, grid=(12, 13), offset=0.1, eps=0.01, solver=solver)
            jax.block_until_ready(sol.spline)
        counts.append(counter.count)
    assert counts[0] >= 1 and counts[1:] == [0] * 5, counts


@pytest.mark.slow
def test_a_new_cloud_above_the_host_layout_compiles_nothing():
    """Clouds too large for the table form (above 21 845 points) are laid out on the host
    for the solve in parts, one sample a slot: a new one in another octave on the same grid
    compiles nothing, not even its layout's geometry."""
    settings = dict(grid=(20, 21), offset=0.05, eps=0.01, solver=jurs.LeastSquares(lam=1e-5))
    counts = []
    for m in (25_000, 40_000):
        points, normals = jurs.datasets.example1(m)
        with _CompileCounter(name="") as counter:
            jax.block_until_ready(jurs.fit(points, normals, **settings).spline)
        counts.append(counter.count)
    assert counts[0] >= 1 and counts[1] == 0, counts


@pytest.mark.slow
def test_a_new_cloud_reuses_the_compiled_checks_of_automatic_settings():
    """With automatic settings the fit is checked on the host (orientation, doubts), which
    evaluates the spline at the cloud's points: a new cloud of another size (in the same
    band, on the same grid) compiles nothing, not even those evaluations."""
    counts = []
    for m in (3200, 3300):
        points, normals = jurs.datasets.example1(m)
        with _CompileCounter(name="") as counter:
            sol = jurs.fit(points, normals, grid=64)
            jax.block_until_ready(sol.spline)
        assert "far_point_fraction" in sol.metrics  # the checks ran
        counts.append(counter.count)
    assert counts[0] >= 1 and counts[1] == 0, counts


def test_automatic_grids_are_rounded_up_to_the_ladder():
    from jurs._fit.settings import DEFAULT_MAX_GRID, choose_grid
    from jurs._problem.sizes import round_size

    lower = np.zeros(2)
    for extent, spacing in (
        ((10.0, 7.0), 0.3),
        ((10.0, 7.0), 0.27),
        ((4.0, 1.0), 0.01),
        ((3.0, 2.0), 1.0),
    ):
        upper = np.asarray(extent)
        grid = choose_grid(lower, upper, spacing, 0.0)
        exact = np.ceil(upper / max(1.5 * spacing, upper.max() / (DEFAULT_MAX_GRID - 3)) - 1e-9)
        for n, cells in zip(grid, exact):
            assert n - 3 >= min(cells, DEFAULT_MAX_GRID - 3)  # never coarser
            assert n - 3 in (round_size(n - 3), DEFAULT_MAX_GRID - 3) or n == 8
            assert n <= DEFAULT_MAX_GRID
    # Spacings 8 % apart (25-27 and 18-19 cells): one grid, 32 x 24 cells (the longer
    # side a power of two, tests/test_grid_classes.py).
    assert (
        choose_grid(lower, np.array([10.0, 7.0]), 0.27, 0.0)
        == choose_grid(lower, np.array([10.0, 7.0]), 0.25, 0.0)
        == (35, 27)
    )


def test_public_calls_outside_a_jit_compile_whole():
    """A spline's evaluation and gradient, ``jurs.solve`` and ``jax.grad`` of
    ``jurs.objective`` called outside a jit compile a few programs each, not one per
    operation (op by op they compiled 40-140), and a new lambda compiles nothing. Shapes no
    other test uses, so that nothing is compiled before."""
    points, normals = jurs.datasets.example1(37)
    problem = jurs.make_problem(points, normals, grid=(6, 7))
    query = jnp.asarray(points[:11])
    with _CompileCounter(name="") as first_solve:
        sol = jurs.solve(jurs.IURS(tau=0.0, lam=0.002, max_steps=30, tol=0.0), problem)
    with _CompileCounter(name="") as new_lam:
        jurs.solve(jurs.IURS(tau=0.0, lam=0.003, max_steps=30, tol=0.0), problem)
    spline = sol.spline
    with _CompileCounter(name="") as evaluations:
        values, gradients = spline(query), spline.grad(query)
    with _CompileCounter(name="") as objective_grad:
        jax.grad(jurs.objective, argnums=1)(problem, spline.control, spline.weights, 0.01)
    assert first_solve.count <= 6 and new_lam.count == 0, (first_solve.count, new_lam.count)
    assert evaluations.count <= 8 and objective_grad.count <= 8
    assert values.shape == (11,) and gradients.shape == (11, 2)
    np.testing.assert_allclose(spline(query[0]), values[0], rtol=1e-12)
