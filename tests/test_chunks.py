"""Chunked runs (jurs._fit.progress.solve_in_chunks, jurs.fit_in_chunks): the state carried
from chunk to chunk, so a chunked run is the run of jurs.solve."""

import dataclasses

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import PAPER  # noqa: E402

import jurs  # noqa: E402
from jurs._fit.progress import solve_in_chunks  # noqa: E402


@pytest.fixture(scope="module")
def problem():
    p, n = jurs.datasets.example1(120)
    return jurs.make_problem(p, n, **PAPER)


def _solve(solver, problem, throw=False):
    return eqx.filter_jit(jurs.solve)(solver, problem, throw=throw)


def _assert_same_run(chunked, one):
    for key in ("control", "weights"):
        np.testing.assert_allclose(
            np.asarray(getattr(chunked.spline, key)),
            np.asarray(getattr(one.spline, key)),
            rtol=0,
            atol=1e-13,
        )
    assert int(chunked.stats["num_steps"]) == int(one.stats["num_steps"])
    assert chunked.result == one.result
    history = np.asarray(chunked.stats["energy_history"])
    assert history.shape == np.asarray(one.stats["energy_history"]).shape
    np.testing.assert_allclose(history, np.asarray(one.stats["energy_history"]), rtol=1e-12)
    for name in ("E", "E_d", "E_max", "offset_sign_disagreement"):
        np.testing.assert_allclose(
            float(chunked.metrics[name]), float(one.metrics[name]), rtol=1e-10, atol=1e-14
        )


class _CompileCounter:
    """XLA compilations by function name, through JAX's public monitoring events."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self):
        self.names = []

    def __call__(self, event, duration, **kwargs):
        if event == self.EVENT:
            self.names.append(str(kwargs.get("fun_name", "")))

    def count(self, name):
        return sum(name in n for n in self.names)

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self)


@pytest.mark.parametrize(
    "solver",
    [
        jurs.IURS(tau=1e-2, lam=0.005, max_steps=60, tol=0.0),
        jurs.IPIA(max_steps=60, tol=0.0),
        jurs.IURS(max_steps=300, tol=1e-6),  # converges early, mid-chunk
    ],
    ids=["iurs", "ipia", "iurs-converges"],
)
@pytest.mark.parametrize("chunk", [10, 7], ids=["divides", "does-not-divide"])
def test_chunked_run_equals_one_solve(problem, solver, chunk):
    one = _solve(solver, problem)
    calls = []
    chunked, snaps = solve_in_chunks(
        solver,
        problem,
        chunk=chunk,
        checkpoints=(0, 10, 25),
        callback=lambda done, total: calls.append((done, total)),
        throw=False,
    )
    _assert_same_run(chunked, one)
    steps = int(one.stats["num_steps"])
    total = solver.max_steps
    done = [d for d, _ in calls]
    assert all(t == total for _, t in calls)
    assert done == sorted(done) and done[-1] == steps
    # Every chunk ran at most ``chunk`` steps and ended at each checkpoint it reached.
    assert all(0 < b - a <= chunk for a, b in zip([0] + done, done))
    assert {10, 25} <= set(done) or steps < 25
    assert sorted(snaps) == [c for c in (0, 10, 25) if c <= steps]
    assert float(np.abs(np.asarray(snaps[0].control)).max()) == 0.0
    assert float(np.abs(np.asarray(snaps[0].weights) - 1.0).max()) == 0.0
    ten = _solve(dataclasses.replace(solver, max_steps=10), problem)
    for key in ("control", "weights"):
        np.testing.assert_allclose(
            np.asarray(getattr(snaps[10], key)),
            np.asarray(getattr(ten.spline, key)),
            rtol=0,
            atol=1e-13,
        )


def test_a_chunked_run_compiles_each_piece_once(problem):
    """A chunk size that divides neither max_steps nor the checkpoints: chunks of 13, 5
    (to a checkpoint) and the rest all run the one compiled chunk."""
    solver = jurs.IPIA(max_steps=47, tol=0.0)
    calls = []
    with _CompileCounter() as counter:
        solve_in_chunks(
            solver,
            problem,
            chunk=13,
            checkpoints=(5, 20),
            callback=lambda done, total: calls.append(done),
            throw=False,
        )
    assert calls == [5, 18, 20, 33, 46, 47]
    assert counter.count("_start") == 1
    assert counter.count("_advance") == 1
    assert counter.count("_finish") == 1


def test_a_one_call_solver_runs_in_one_solve(problem):
    solver = jurs.LeastSquares(lam=1e-4)
    calls = []
    sol, snaps = solve_in_chunks(
        solver, problem, checkpoints=(1,), callback=lambda d, t: calls.append((d, t))
    )
    one = _solve(solver, problem)
    np.testing.assert_allclose(
        np.asarray(sol.spline.control), np.asarray(one.spline.control), rtol=0, atol=1e-12
    )
    assert calls == [(1, 1)] and sorted(snaps) == [1]
    with pytest.raises(ValueError, match="runs in one call"):
        solve_in_chunks(solver, problem, checkpoints=(0,))


def test_checkpoints_checked(problem):
    with pytest.raises(ValueError, match="checkpoints must lie"):
        solve_in_chunks(jurs.IPIA(max_steps=5), problem, checkpoints=(6,))


def test_no_steps(problem):
    solver = jurs.IPIA(max_steps=0)
    calls = []
    sol, snaps = solve_in_chunks(
        solver, problem, checkpoints=(0,), callback=lambda d, t: calls.append(d), throw=False
    )
    one = _solve(solver, problem)
    _assert_same_run(sol, one)
    assert calls == [] and sorted(snaps) == [0]


def test_the_final_verdict_is_raised_once(problem):
    """Chunks run on whatever the verdict on the iterate so far; the run's own verdict is
    raised at the end with throw=True, and returned with throw=False."""
    solver = jurs.IURS(tau=1e6, max_steps=20)
    sol, _ = solve_in_chunks(solver, problem, chunk=5, throw=False)
    assert sol.status == "weights_at_floor"
    assert int(sol.stats["num_steps"]) == 20
    with pytest.raises(eqx.EquinoxRuntimeError, match="weights_at_floor"):
        solve_in_chunks(solver, problem, chunk=5)


def test_fit_in_chunks_builds_one_problem(example1_cloud, monkeypatch):
    """fit_in_chunks lays the problem out once, whatever the number of chunks, and gives
    the fit of jurs.fit."""
    from jurs._fit import fit as fit_module

    built = []
    padded_problem = fit_module.padded_problem

    def counted(*args, **kwargs):
        built.append(1)
        return padded_problem(*args, **kwargs)

    monkeypatch.setattr(fit_module, "padded_problem", counted)
    p, n = example1_cloud
    solver = jurs.IURS(tau=1e-2, lam=0.005, max_steps=30, tol=0.0)
    calls = []
    sol, snaps = jurs.fit_in_chunks(
        p,
        n,
        solver=solver,
        chunk=4,
        checkpoints=(8,),
        callback=lambda d, t: calls.append(d),
        **PAPER,
    )
    assert len(built) == 1 and len(calls) == 8 and sorted(snaps) == [8]
    one = jurs.fit(p, n, solver=solver, **PAPER)
    _assert_same_run(sol, one)
    assert sol.settings is None


def test_fit_in_chunks_takes_what_fit_takes(example1_cloud):
    p, n = example1_cloud
    with pytest.raises(TypeError):
        jurs.fit_in_chunks(p, n, solver=jurs.IPIA(max_steps=2), colour="red", **PAPER)
    with pytest.raises(ValueError, match="smoothing"):
        jurs.fit_in_chunks(p, n, solver=jurs.IPIA(max_steps=2), smoothing=1.0, **PAPER)
    with pytest.raises(ValueError, match="init spline has grid"):
        init = jurs.ImplicitSpline.bspline(np.zeros((5, 5)), (-1.0, -1.0), (1.0, 1.0))
        jurs.fit_in_chunks(p, n, solver=jurs.IPIA(max_steps=2), init=init, **PAPER)
