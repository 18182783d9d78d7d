"""Fits of clouds sharded over several devices (jurs._fit.sharding, docs/sharding.md).

JAX fixes its device count when it starts, so the multi-device checks run in a child
process with four CPU devices (``--xla_force_host_platform_device_count``), each fit
there compared with the one-device fit of the same cloud in the same process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jurs
from jurs._fit.adaptive import UNIFORM_RESIDUAL_SPACINGS
from jurs._fit.sharding import input_sharding, place_fit, spans_processes

#: The module fixture runs fits on forced devices in a process of its own (about 30 s).
pytestmark = pytest.mark.slow

# Run in a child process with 4 CPU devices and float64. Prints one JSON line.
CHILD = textwrap.dedent(
    """
    import json, re
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    import jurs
    from jurs._fit import call as _fit
    from jurs._jit import as_arrays
    from jurs._problem import padding as _problem
    from jurs._fit.sharding import place_fit

    assert len(jax.devices()) == 4 and jnp.result_type(float) == jnp.float64
    mesh = Mesh(np.array(jax.devices()), ("points",))
    split = NamedSharding(mesh, P("points"))
    out = {}

    # The solves of the sharded fits, recorded as they are called: the collectives check
    # below reads the program the bucketed fit ran (compiled already, not compiled again).
    from jurs._fit.sharding import is_sharded

    ran = []

    def recording(jitted):
        def call(problem, solver, init, throw):
            if is_sharded(problem):
                ran.append((jitted, problem, solver, init, throw))
            return jitted(problem, solver, init, throw)

        return call

    for name in ("_solve", "_solve_reassociating"):
        setattr(_fit, name, recording(getattr(_fit, name)))

    def compare(name, points, normals, **kw):
        ref = jurs.fit(points, normals, **kw)
        sol = jurs.fit(jax.device_put(points, split), jax.device_put(normals, split), **kw)
        c0, c1 = np.asarray(ref.spline.control), np.asarray(sol.spline.control)
        out[name] = dict(
            rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()),
            status=[ref.status, sol.status],
            devices=len(sol.spline.control.sharding.device_set),
        )

    # Automatic settings, table form: the uniform grid asked for (this cloud's capped
    # grid reads a residual just above UNIFORM_RESIDUAL_SPACINGS; basis="auto" would go
    # on to the hierarchy).
    compare("table", *jurs.datasets.example1(2000), basis="uniform")
    p, n = jurs.datasets.example1(3000)
    grid, offset, eps = (24, 24), 0.02, 0.02
    compare("buckets", p, n, grid=grid, offset=offset, eps=eps, bucket_size=8)
    solve, problem, solver, init, throw = ran[-1]  # the sharded bucketed fit's solve

    # basis="auto" on sharded points chooses as unsharded (the capped grid fitted sharded,
    # its residual measured on the whole cloud on the host): a star of 12 spikes, whose
    # corners the capped grid rounds off, goes on to the hierarchy, fitted with the sharded
    # points; a circle keeps the grid. Both take the table case's 96 x 96 grid (compiled).
    angles = np.arange(24) * np.pi / 12
    corners = np.c_[np.cos(angles), np.sin(angles)] * np.where(np.arange(24) % 2, 0.8, 1)[:, None]
    edges = np.roll(corners, -1, axis=0) - corners  # 24 edges of 62 points each
    star = (corners[:, None] + (np.arange(62) / 62)[:, None] * edges[:, None]).reshape(-1, 2)
    star_normals = np.repeat(np.c_[edges[:, 1], -edges[:, 0]], 62, axis=0)
    t = np.linspace(0.0, 2.0 * np.pi, len(star), endpoint=False)
    circle = np.c_[np.cos(t), np.sin(t)]
    clouds = ("auto_star", star, star_normals), ("auto_circle", circle, circle)
    for name, points, normals in clouds:
        ref = jurs.fit(points, normals)
        sol = jurs.fit(jax.device_put(points, split), jax.device_put(normals, split))
        c0, c1 = np.asarray(ref.spline.control), np.asarray(sol.spline.control)
        out[name] = dict(
            rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()),
            status=[ref.status, sol.status],
            bases=[type(ref.spline).__name__, type(sol.spline).__name__],
            residuals=[ref.stats["uniform_residual"], sol.stats["uniform_residual"]],
            devices=[ref.stats.get("devices"), sol.stats.get("devices")],
            spread=len(sol.spline.control.sharding.device_set),
        )
    compare("sphere", *jurs.datasets.sphere3d(1000), grid=(6, 6, 6), offset=0.05, eps=0.05)

    # The compiled bucketed (power-form) solve: which collectives GSPMD put in.
    out["power_form"] = problem.local.terms is None and problem.local.bucket_size == 8
    out["slots_per_device"] = sorted({s.data.shape[0] for s in problem.samples.addressable_shards})
    out["slots"] = problem.samples.shape[0]
    hlo = solve.lower(problem, solver, init, throw).compile().compiled.as_text()
    out["collectives"] = sorted(
        set(re.findall(r"(all-reduce|all-gather|all-to-all|reduce-scatter)(?:-start)?\\(", hlo))
    )

    # A surface's normal equations summed a chunk at a time (3 x 24000 samples, more than
    # a chunk a device): per device, then all-reduced; no chunk gathered.
    from jurs._linalg.normal import normal_equations

    s3, n3 = jurs.datasets.sphere3d(24000)
    grid3 = (6, 6, 6)
    solver = as_arrays(jurs.LeastSquares(lam=1e-4), jnp.float64)
    problem3 = _problem.padded_problem(
        s3, n3, None, grid3, 0.05, 0.05, None, 0.1, None, jnp.float64
    )
    moments = jax.jit(normal_equations)
    ref = moments(problem3)
    placed, _, _ = place_fit(
        jax.device_put(s3, split), jax.device_put(n3, split), problem3, solver, None
    )
    got = moments(placed)
    rel = max(
        float(jnp.abs(a - b).max() / jnp.abs(a).max())
        for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got))
    )
    hlo3 = moments.lower(placed).compile().as_text()
    out["surface_sums"] = dict(
        parts=placed.local.parts,
        rel=rel,
        collectives=sorted(set(re.findall(
            r"(all-reduce|all-gather|all-to-all|reduce-scatter|collective-permute)(?:-start)?\\(",
            hlo3,
        ))),
    )
    print(json.dumps(out))
    """
)


# Adaptive fits (jurs._fit.adaptive_sharding) in a child process with 4 CPU devices: each
# sharded fit against the one-device fit of the same cloud. Prints one JSON line.
ADAPTIVE_CHILD = textwrap.dedent(
    """
    import json, re
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    import jurs
    from jurs._fit import adaptive_sharding

    assert len(jax.devices()) == 4 and jnp.result_type(float) == jnp.float64
    mesh = Mesh(np.array(jax.devices()), ("points",))
    split = NamedSharding(mesh, P("points"))
    out = {}

    ran = []  # the sharded CG solves, as called: the collectives check reads the last one
    solve = adaptive_sharding._sharded_cg

    def recording(*args, **kw):
        ran.append((args, kw))
        return solve(*args, **kw)

    adaptive_sharding._sharded_cg = recording

    def compare(name, fit, points, normals, **kw):
        ref = fit(points, normals, **kw)
        sol = fit(jax.device_put(points, split), jax.device_put(normals, split), **kw)
        c0, c1 = np.asarray(ref.spline.control), np.asarray(sol.spline.control)
        out[name] = dict(
            rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()),
            status=[ref.status, sol.status],
            devices=sol.stats.get("devices"),
            method=sol.stats["method"],
            metrics=max(
                abs(float(sol.metrics[k]) - float(ref.metrics[k])) / abs(float(ref.metrics[k]))
                for k in ("E_d", "E_ave", "E_max", "R")
            ),
        )

    p, n = jurs.datasets.example1(600)
    compare("curve_direct", jurs.fit, p, n, basis="adaptive")
    # CG to a tight tolerance: the two orders of summation then agree closely.
    compare("curve_cg", jurs.fit_adaptive, p, n, finest=64, method="cg", rtol=1e-10)
    compare("sphere", jurs.fit_adaptive, *jurs.datasets.sphere3d(800), finest=16, rtol=1e-10)

    # A robust fit reweighs on one host: refused on sharded points by either entry.
    robust = jurs.RobustLeastSquares(lam=1e-4)
    refusals = []
    for fit, kw in ((jurs.fit, dict(basis="adaptive")), (jurs.fit_adaptive, {})):
        try:
            fit(jax.device_put(p, split), jax.device_put(n, split), solver=robust, **kw)
            refusals.append(None)
        except ValueError as error:
            refusals.append(str(error))
    out["robust_refusals"] = refusals

    # The compiled sharded CG of the sphere: which collectives, of what sizes.
    args, kw = ran[-1]
    hlo = solve.lower(*args, **kw).compile().as_text()
    reduced = re.findall(r"= \\(?([^=]*?)\\)? all-reduce(?:-start)?\\(", hlo)
    sizes = sorted({
        int(np.prod([int(d) for d in dims.split(",") if d] or [1]))
        for shapes in reduced for dims in re.findall(r"\\[([0-9,]*)\\]", shapes)
    })
    out["collectives"] = dict(
        kinds=sorted(set(re.findall(
            r"(all-reduce|all-gather|all-to-all|reduce-scatter|collective-permute)(?:-start)?\\(",
            hlo,
        ))),
        sizes=sizes,
        functions=int(args[4].shape[0]),  # the active functions, padded to a size class
        rows=int(args[1].shape[0]),  # the sample rows over all devices
        rows_per_device=sorted({s.data.shape[0] for s in args[1].addressable_shards}),
    )
    print(json.dumps(out))
    """
)

FORCED_DEVICES = dict(
    XLA_FLAGS="--xla_force_host_platform_device_count=4",
    JAX_ENABLE_X64="1",
    JAX_PLATFORMS="cpu",
)


def _run_child(script: str) -> dict:
    env = dict(os.environ, **FORCED_DEVICES)
    run = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=240
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def child():
    return _run_child(CHILD)


@pytest.fixture(scope="module")
def adaptive_child():
    return _run_child(ADAPTIVE_CHILD)


@pytest.mark.parametrize("case", ["table", "buckets", "sphere"])
def test_sharded_fit_equals_one_device_fit(child, case):
    """Control points of the fit over 4 devices within 1e-9 (relative) of the one-device
    fit: the small-cloud table form, the bucketed form, and a surface (on 6^3 = 216
    coefficients, a direct solve: a surface's default CG stops at a tolerance of 1e-3,
    and two fits whose sums differ in order then agree only to about that)."""
    result = child[case]
    assert result["rel"] < 1e-9
    assert result["status"] == ["successful", "successful"]
    assert result["devices"] == 4  # the result lives on the mesh


@pytest.mark.parametrize("case", ["auto_star", "auto_circle"])
def test_sharded_auto_basis_chooses_as_unsharded(child, case):
    """``basis="auto"`` on points sharded over 4 devices makes the unsharded fit's choice:
    the capped grid's residual (measured on the whole cloud on the host) the same to
    rounding; a star goes on to the hierarchy, whose fit sees the sharded points
    (``stats["devices"]``: a curve's direct solve runs on the host, 1) and equals the
    unsharded one; a circle keeps the grid, fitted over the devices."""
    result = child[case]
    assert result["status"] == ["successful", "successful"]
    ref, sharded = result["residuals"]
    assert abs(sharded - ref) < 1e-9 * ref
    if case == "auto_star":
        assert ref > UNIFORM_RESIDUAL_SPACINGS
        assert result["bases"] == ["AdaptiveSpline", "AdaptiveSpline"]
        assert result["devices"] == [None, 1]  # the hierarchy fit read the sharding
    else:
        assert ref <= UNIFORM_RESIDUAL_SPACINGS
        assert result["bases"] == ["ImplicitSpline", "ImplicitSpline"]
        assert result["spread"] == 4  # the grid's fit lives on the mesh
    assert result["rel"] < 1e-9


def test_sharded_samples_stay_on_their_devices(child):
    """The bucketed solve splits the slots evenly (whole buckets a device) and its compiled
    form (the program the sharded fit ran) reduces across devices without gathering the
    samples."""
    assert child["power_form"]
    assert len(child["slots_per_device"]) == 1
    assert child["slots_per_device"][0] * 4 == child["slots"]
    assert child["slots_per_device"][0] % 8 == 0  # bucket_size=8
    assert child["collectives"] == ["all-reduce"]


def test_surface_sums_stay_on_their_devices(child):
    """A surface's normal equations, summed a chunk of samples at a time, run per device
    (``LocalBasis.parts``) and reduce the grid-sized sums: no chunk is gathered, and the
    sums equal the one-device ones to rounding."""
    result = child["surface_sums"]
    assert result["parts"] == 4
    assert result["rel"] < 1e-12
    assert result["collectives"] == ["all-reduce"]


def test_unsharded_fit_unaffected():
    """One-device inputs (NumPy or a jax.Array) take the one-device path unchanged."""
    p, n = jurs.datasets.example1(200)
    assert input_sharding(p, n) is None
    assert input_sharding(jax.device_put(p), jax.device_put(n)) is None
    assert not spans_processes(p, n)  # the several-process path (tests/test_distributed.py)
    assert not spans_processes(jax.device_put(p), jax.device_put(n))
    problem = jurs.make_problem(p, n, grid=9, offset=0.1, eps=0.01)
    solver = jurs.LeastSquares(lam=1e-3)
    assert place_fit(p, n, problem, solver, None) == (problem, solver, None)
    kw: dict = dict(grid=9, offset=0.1, eps=0.01, solver=solver)
    a = jurs.fit(p, n, **kw)
    b = jurs.fit(jax.device_put(p), jax.device_put(n), **kw)
    np.testing.assert_array_equal(np.asarray(a.spline.control), np.asarray(b.spline.control))


@pytest.mark.parametrize("case", ["curve_direct", "curve_cg", "sphere"])
def test_sharded_adaptive_fit_equals_one_device_fit(adaptive_child, case):
    """Adaptive fits of points sharded over 4 devices against the one-device fit: a curve's
    direct solve (``jurs.fit(basis="adaptive")``, host-assembled from the whole cloud) to
    rounding; CG (a curve with ``method="cg"``, a surface) over the 4 devices, whose sums
    run in another order, to its tolerance (relative residual 1e-10)."""
    result = adaptive_child[case]
    assert result["status"] == ["successful", "successful"]
    if case == "curve_direct":
        assert result["method"] == "direct" and result["devices"] == 1
        assert result["rel"] < 1e-9 and result["metrics"] < 1e-9
    else:
        assert result["method"] == "cg" and result["devices"] == 4
        assert result["rel"] < 1e-7 and result["metrics"] < 1e-7


def test_sharded_adaptive_cg_reduces_only_function_sums(adaptive_child):
    """The compiled sharded CG splits the sample rows evenly over the devices and its only
    collectives are all-reduces of active-function-sized vectors (``D_k^T D_k c``, ``D^T
    b``, the diagonal) and of scalars (the data term's metrics: E_d, the sum of g^2 at the
    data points, the largest |g|): no sample array travels."""
    result = adaptive_child["collectives"]
    assert len(result["rows_per_device"]) == 1
    assert result["rows_per_device"][0] * 4 == result["rows"]
    assert result["kinds"] == ["all-reduce"]
    assert result["functions"] in result["sizes"]
    assert all(size <= 2 for size in result["sizes"] if size != result["functions"])
    assert result["functions"] != result["rows"]  # the sizes tell the two apart


def test_split_rows_gives_each_device_its_points_samples():
    """``split_rows`` hands each device the collocation rows and targets of the samples
    of its block of points (``[P, P + d n, P - d n]``), with row indices local to its
    part and padding that adds nothing: the parts rebuild ``D`` and ``b`` exactly."""
    from scipy import sparse

    from jurs._fit.adaptive_sharding import device_rows, split_rows

    points, functions, devices = 10, 7, 3
    rng = np.random.default_rng(0)
    matrix = sparse.random(3 * points, functions, density=0.4, rng=rng, format="csr")
    targets = rng.normal(size=3 * points)
    (rows, cols, values), b, is_data = split_rows(matrix, targets, points, devices, np.float64)
    owner = device_rows(3 * points, points, devices)
    assert owner.tolist()[:points] == [0] * 4 + [1] * 4 + [2] * 2  # blocks of 4 points
    length, nnz = len(b) // devices, len(values) // devices
    dense = matrix.toarray()
    for k in range(devices):
        mine = np.flatnonzero(owner == k)
        part = np.zeros((length, functions))
        entries = slice(k * nnz, (k + 1) * nnz)
        np.add.at(part, (rows[entries], cols[entries]), values[entries])
        np.testing.assert_array_equal(part[: len(mine)], dense[mine])
        np.testing.assert_array_equal(part[len(mine) :], 0.0)
        np.testing.assert_array_equal(b[k * length : k * length + len(mine)], targets[mine])
        np.testing.assert_array_equal(b[k * length + len(mine) : (k + 1) * length], 0.0)
        assert is_data[k * length : (k + 1) * length].tolist() == (
            (mine < points).tolist() + [False] * (length - len(mine))
        )


def test_a_robust_hierarchy_fit_of_sharded_points_is_refused(adaptive_child):
    """``RobustLeastSquares`` on the hierarchy reweighs on one host: ``jurs.fit(...,
    basis="adaptive")`` of sharded points took the sharded CG and fitted plain least
    squares without a word; both entries now refuse it, saying why."""
    refusals = adaptive_child["robust_refusals"]
    assert all(r is not None and "robust fit on the hierarchy" in r for r in refusals), refusals
