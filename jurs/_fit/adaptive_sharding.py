"""Adaptive fits ([`jurs.fit_adaptive`][]) of points sharded over several devices.

The hierarchy's structure (which cells are refined, ``refine_near``) is built on the host
from the whole cloud, once, so it is the same on every device. The conjugate-gradient path
then keeps the samples where the points are: the rows of the collocation matrix ``D``
(one a sample: its ``4^d`` cascaded basis values, assembled on the host) and the targets
are split over the points' mesh axis, each device holding the rows of the samples of its
own block of points (``[P, P + d n, P - d n]`` of them); the coefficients, the regulariser
(``2 G^T W G``, active-function-sized) and every CG vector are replicated. One CG step's
``D^T D c`` is a per-device product (``D_k c``, then its transpose, a scatter-add onto the
active functions) and one all-reduce of an active-function-sized vector; the right-hand
side ``D^T b``, the Jacobi diagonal of ``D^T D`` and the data term of the metrics reduce
the same way once. The placement is a grid fit's (``jurs._fit.sharding``): arrays put on
the point axis's ``NamedSharding`` and JAX's partitioner, with each device's rows one
element of a ``vmap`` so that no sample-sized array leaves its device (``_sharded_cg``;
docs/sharding.md, "Adaptive fits").

The direct path (a curve's default) factorises ``D^T D + lam 2 G^T W G`` on the host: in
one process every shard is addressable there, so it reads the whole cloud and solves
exactly as unsharded. Over several processes (``fit_adaptive_across_processes``) the
hierarchy refines the union of every process's cells to refine, each process assembles
its own samples' rows, and the direct path sums the processes' normal equations
(``solve_summed``: level-sized, one all-reduce) and factorises them in each.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import NamedSharding, PartitionSpec

from .._cloud.parts import agree, allgather, gather_ragged
from .._linalg.pcg import conjugate_gradients, jacobi_inverse
from .._linalg.sparse import padded_entries
from .._model.precision import on_device
from .._problem.adaptive import assemble_adaptive_problem
from .._problem.energy import metrics_from_sums
from .._problem.sizes import padded_to
from .._problem.validate import unit_normals, validate_inputs
from .._solution.solution import Solution, raise_unless_reconstruction
from .adaptive import (
    hierarchy_lam,
    hierarchy_layout,
    hierarchy_rtol,
    hierarchy_solution,
    size_class,
    solve_normal,
)
from .process_settings import (
    bounds_across_processes,
    check_global_arrays,
    local_cloud,
    settings_across_processes,
)
from .settings import Settings
from .sharding import input_sharding, point_axis_size, process_positions


def device_rows(count: int, points: int, shards: int) -> np.ndarray:
    """The device (``0 .. shards - 1``) of each of the ``count = 3 points`` sample rows:
    that of its point's block (``ceil(points / shards)`` points a device, in order), as
    the points are split."""
    block = -(-points // shards)
    return (np.arange(count) % points) // block


def split_rows(collocation, targets: np.ndarray, points: int, devices: int, dtype, agree=None):
    """``((rows, cols, values), targets, is_data)``: host arrays of the rows of
    ``collocation`` (SciPy, ``(3 points, n)``) and of ``targets`` split over ``devices``
    devices by ``device_rows``, each device's part padded to one length (a size class)
    and laid end to end: its entries with row indices local to its part (padding: zeros
    at (0, 0), which add nothing), its targets padded with zeros (rows without entries:
    a residual of 0), ``is_data`` True on its rows of data points (eq. 4's ``P``).
    ``agree``: maps this process's ``[rows, entries]`` a device (the most of its devices)
    to those of every process (their maximum), so that all pad to one length."""
    count = collocation.shape[0]
    owner = device_rows(count, points, devices)
    csr = collocation.tocsr()
    parts = [np.flatnonzero(owner == k) for k in range(devices)]
    blocks = [csr[rows] for rows in parts]
    sizes = [max(len(rows) for rows in parts), max(block.nnz for block in blocks)]
    if agree is not None:
        sizes = agree(sizes)
    length, nnz = (size_class(int(x)) for x in sizes)
    entries, values, data = [], [], []
    for rows, block in zip(parts, blocks):
        entries.append(padded_entries(block, nnz, dtype))
        values.append(padded_to(np.asarray(targets, float)[rows], length))
        data.append(padded_to(rows < points, length, False))
    coo = tuple(np.concatenate([e[i] for e in entries]) for i in range(3))
    return coo, np.concatenate(values).astype(dtype), np.concatenate(data)


@functools.partial(jax.jit, static_argnames=("sharding",))
def _sharded_cg(
    collocation, targets, is_data, regulariser, regulariser_diagonal, lam, rtol, max_steps,
    *, sharding: NamedSharding,
):  # fmt: skip
    """``(control, steps, relative residual, E_d, sum of g(P)^2, E_max)``: ``_assembled_cg``'s solve
    with ``D``'s rows (``collocation``, row indices local to each device's part),
    ``targets`` and ``is_data`` placed on ``sharding`` (split over its point axis,
    each device's part laid end to end), everything else replicated.

    Placed data and JAX's partitioner, as a grid fit's (``jurs._fit.sharding``): the
    parts are viewed as ``(devices, rows a device)``, each device's part one element of a
    ``vmap``, so the partitioner keeps every product on the device that holds its rows and
    sums over the leading axis alone (an all-reduce of an active-function-sized vector, or
    of a scalar). A flat row axis would not tell it that a device's row indices are its
    own: the sample-sized ``D c`` would then be all-reduced every step."""
    reg_rows, reg_cols, reg_values = regulariser
    n = regulariser_diagonal.shape[0]
    names = sharding.spec[0]
    by_device = NamedSharding(sharding.mesh, PartitionSpec(names, None))
    shards = point_axis_size(sharding)

    def parts(x):  # (devices, rows a device), the leading axis the placed one
        return lax.with_sharding_constraint(x.reshape(shards, -1), by_device)

    rows, cols, values = (parts(a) for a in collocation)
    b, data = parts(targets), parts(is_data)
    local = b.shape[1]
    # Each device's D_k c (sample rows) and D_k^T v (active-function-sized).
    apply = jax.vmap(lambda r, k, v, c: jax.ops.segment_sum(v * c[k], r, local), (0, 0, 0, None))
    transpose = jax.vmap(lambda r, k, v, y: jax.ops.segment_sum(v * y[r], k, n))

    def matvec(c):  # D^T D c = sum_k D_k^T D_k c, plus lam times the regulariser's product
        regular = jax.ops.segment_sum(reg_values * c[reg_cols], reg_rows, n)
        return transpose(rows, cols, values, apply(rows, cols, values, c)).sum(0) + lam * regular

    rhs = transpose(rows, cols, values, b).sum(0)  # D^T b
    squares = jax.vmap(lambda k, v: jax.ops.segment_sum(v * v, k, n))  # diagonal of D_k^T D_k
    inverse = jacobi_inverse(squares(cols, values).sum(0) + lam * regulariser_diagonal)
    control, steps, residual = conjugate_gradients(
        matvec, rhs, precondition=lambda r: inverse * r, rtol=rtol, max_steps=max_steps
    )
    r = apply(rows, cols, values, control) - b  # E_d, sum of g(P)^2 (for E_ave) and E_max
    on_data = jnp.where(data, r, 0.0)
    return (
        control,
        steps,
        residual,
        jnp.sum(r * r),
        jnp.sum(on_data * on_data),
        jnp.max(jnp.abs(on_data)),
    )


def solve_sharded(
    problem,
    matrices,
    lam: float,
    rtol: float,
    max_steps: int,
    dtype,
    sharding: NamedSharding,
    samples: int | None = None,
) -> tuple[np.ndarray, int, float, dict]:
    """``(control, steps, relative residual, metrics)``: ``solve_assembled``'s CG (the
    same matrix, preconditioner and stop rule) with the collocation matrix's rows and the
    targets split over ``sharding``'s point axis (module docstring). Agrees with the
    one-device solve to the CG tolerance (the sums run in another order).

    Over several processes each calls it with its own samples' rows (``matrices`` and
    ``problem.targets`` its own, the regulariser the same in all) and ``samples``, the
    sample count of all processes; the rows go to this process's devices (one small
    all-gather agrees on the padded lengths) and the control points come back in every
    process."""
    collocation, regulariser = matrices
    count, n = collocation.shape
    shards = point_axis_size(sharding)
    mesh, names = sharding.mesh, sharding.spec[0]
    split = NamedSharding(mesh, PartitionSpec(names))
    replicated = NamedSharding(mesh, PartitionSpec())
    if jax.process_count() == 1:
        coo, targets, is_data = split_rows(
            collocation, np.asarray(problem.targets), count // 3, shards, dtype
        )
        put_split = functools.partial(jax.device_put, device=split)
    else:
        mine = len(process_positions(sharding, shards))
        coo, targets, is_data = split_rows(
            collocation, np.asarray(problem.targets), count // 3, mine, dtype, _agreed_max
        )

        def put_split(x):  # this process's devices' parts of the global rows
            size = (x.shape[0] // mine * shards,)
            return jax.make_array_from_process_local_data(split, x, size)

    def put_whole(x):  # the same host value on every device of every process
        x = np.asarray(x)
        return jax.make_array_from_process_local_data(replicated, x, x.shape)

    reg_coo = padded_entries(regulariser, size_class(regulariser.nnz), dtype)
    regulariser_diagonal = padded_to(np.asarray(problem.regulariser_diagonal, float), size_class(n))
    control, steps, residual, data, on_data, largest = _sharded_cg(
        tuple(put_split(a) for a in coo),
        put_split(targets),
        put_split(is_data),
        tuple(put_whole(a) for a in reg_coo),
        put_whole(regulariser_diagonal.astype(dtype)),
        put_whole(np.asarray(lam, dtype)),
        put_whole(np.asarray(rtol, dtype)),
        put_whole(np.asarray(max_steps, np.int32)),
        sharding=split,
    )
    c = np.asarray(control.addressable_data(0))[:n]  # replicated: every device holds it
    reg = float(c @ (regulariser @ c))
    samples = count if samples is None else samples
    # E_ave is the mean of g^2 over the data points alone (a third of the samples), as on
    # the uniform grid (jurs._problem.energy.metrics), not E_d over every sample.
    sums = dict(
        E_d=float(data.addressable_data(0)),
        on_data2=float(on_data.addressable_data(0)),
        count=samples // 3,
        E_max=float(largest.addressable_data(0)),
    )
    metrics = dict(metrics_from_sums(sums, reg, lam), lam=lam)
    metrics = {name: on_device(value, dtype) for name, value in metrics.items()}
    return c, int(steps.addressable_data(0)), float(residual.addressable_data(0)), metrics


def _summed(local: np.ndarray, sharding: NamedSharding) -> np.ndarray:
    """Every process's ``local`` (one vector, the same length in all) summed: an
    all-reduce over the processes' devices (this process's vector on its first device,
    zeros on the others), the sum back on the host of every process."""
    shards = point_axis_size(sharding)
    mine = len(process_positions(sharding, shards))
    rows = np.zeros((mine, local.shape[0]), local.dtype)
    rows[0] = local
    mesh, names = sharding.mesh, sharding.spec[0]
    spread = jax.make_array_from_process_local_data(
        NamedSharding(mesh, PartitionSpec(names, None)), rows, (shards, local.shape[0])
    )
    total = _sum_rows(spread, NamedSharding(mesh, PartitionSpec()))
    return np.asarray(total.addressable_data(0))


@functools.partial(jax.jit, static_argnums=1)
def _sum_rows(x, replicated):
    return jax.lax.with_sharding_constraint(x.sum(axis=0), replicated)


def solve_summed(
    problem, matrices, lam: float, sharding: NamedSharding, samples: int
) -> tuple[np.ndarray, float, dict]:
    """``(control, relative residual, metrics)``: ``solve_direct``'s factorisation of
    ``sum_k D_k^T D_k + lam 2 G^T W G`` over several processes, each calling it with its
    own samples' rows (``matrices``: its ``D_k`` and the regulariser, the same in all).
    The pattern of the sum is the union of the processes' patterns (an all-gather of
    their entries' keys), the values and ``sum_k D_k^T b_k`` one all-reduce of a vector
    of that many entries plus the active functions; every process then factorises the
    same matrix (the same numbers in all). ``samples``: all processes' sample count. The
    sums travel in JAX's float: float64 with ``jax_enable_x64``, else float32 (then
    factorised in float64)."""
    from scipy import sparse

    collocation, regulariser = matrices
    n = collocation.shape[1]
    targets = np.asarray(problem.targets, float)
    local = sparse.coo_matrix(collocation.T @ collocation)
    local.sum_duplicates()
    keys = local.row.astype(np.int64) * n + local.col
    # Sent as (row, col) pairs: each below n fits int32, which JAX keeps without x64;
    # a key row * n + col would not.
    pairs = gather_ragged(np.stack([local.row, local.col], axis=1).astype(np.int32))
    union = np.unique(pairs[:, 0].astype(np.int64) * n + pairs[:, 1])
    values = np.zeros(len(union) + n)
    values[np.searchsorted(union, keys)] = local.data
    values[len(union) :] = collocation.T @ targets
    values = _summed(values, sharding)
    rows, cols = np.divmod(union, n)
    normal = sparse.csc_matrix((values[: len(union)], (rows, cols)), shape=(n, n))
    control, residual = solve_normal((normal + lam * regulariser).tocsc(), values[len(union) :])
    r = collocation @ control - targets
    m = len(targets) // 3
    on_data = r[:m]  # this process's data points' samples come first (targets 0)
    largest = np.max(np.abs(on_data), initial=0.0)
    table = allgather(np.array([r @ r, on_data @ on_data, largest]))
    data, squares = float(table[:, 0].sum()), float(table[:, 1].sum())
    largest = float(table[:, 2].max())
    reg = float(control @ (regulariser @ control))
    # E_ave: mean g^2 over all processes' data points, as on the uniform grid.
    metrics = dict(E=data + lam * reg, E_d=data, R=reg, E_ave=squares / (samples // 3))
    return control, residual, dict(metrics, E_max=largest, lam=lam)


def _agreed_max(sizes: list[int]) -> list[int]:
    """``sizes`` of every process, their maximum (one small all-gather)."""
    return allgather(np.asarray(sizes, np.int64)).max(axis=0).tolist()


def _union(refined: list[np.ndarray]) -> list[np.ndarray]:
    """Every process's cells to refine (one sorted array of keys a level), joined: the
    OR of the level's refinement flags, sent as the keys of the set flags (a few
    all-gathers a level). A level's keys fit int32 (``MAX_FINEST``), which JAX keeps
    without x64."""
    return [
        np.unique(gather_ragged(np.asarray(keys, np.int32))).astype(np.int64) for keys in refined
    ]


def fit_adaptive_across_processes(
    points,
    normals,
    *,
    finest=None,
    band=None,
    offset=None,
    eps=None,
    domain=None,
    smoothing=None,
    lam=None,
    rtol=None,
    max_steps: int = 10_000,
    settings: Settings | None = None,
    method=None,
    dtype=None,
    throw: bool = True,
) -> Solution:
    """[`jurs.fit_adaptive`][] of points and normals held by several processes (global
    ``jax.Array`` s split along the point axis); every process calls it with the same
    arguments and gets the same fit. Settings not given are chosen over every process's
    points (``jurs._fit.process_settings.settings_across_processes``); the hierarchy is
    built from the union of every process's cells to refine (``_union``), so it is the
    same in all; each process assembles the collocation rows of its own samples. The
    solve is ``solve_sharded``'s CG over all devices, or (``method="direct"``, a curve's
    default) ``solve_summed``'s factorisation of the processes' summed normal equations
    in every process. What reads the whole cloud on a host (the orientation and doubt
    checks) is not run (docs/sharding.md, "Adaptive fits")."""
    if method in ("host_cg", "multigrid", "host_multigrid"):
        raise ValueError(
            f"method={method!r} reads every sample on one host; points split over processes "
            "fit with 'cg' (over every device) or 'direct'"
        )
    if normals is None:  # estimated over all processes' points, split like them
        # SciPy's graphs and KD-trees: loaded when first needed, not on import jurs.
        from .._cloud.normals import normals_across_processes

        normals = normals_across_processes(points)
    check_global_arrays(points, normals)
    sharding = input_sharding(points, normals)
    assert sharding is not None
    if settings is None:
        settings = settings_across_processes(
            points, normals, None, offset, eps, domain, smoothing=smoothing
        )
    _, p, n, total = local_cloud(points, normals)
    failure = None
    try:  # this process's rows, checked as one process checks its cloud
        validate_inputs(p, n, offset=offset, eps=eps, domain=settings.domain)
    except (TypeError, ValueError) as error:
        failure = type(error)(f"process {jax.process_index()}, its own part: {error}")
    agree(failure, "checking its points")
    n = unit_normals(n)
    ndim = p.shape[1]
    layout = hierarchy_layout(settings, ndim, finest, band, offset, eps, dtype)
    dtype = layout["dtype"]
    problem, matrices = assemble_adaptive_problem(p, n, **layout, combine_refined=_union)
    if lam is None:
        lo, hi = bounds_across_processes(p)
        diagonal = float(np.linalg.norm(hi - lo))
        lam = hierarchy_lam(settings, smoothing, 3 * total, diagonal, layout, problem.hierarchy)
    rtol = hierarchy_rtol(rtol, dtype)
    method = method or ("direct" if ndim == 2 else "cg")
    if method == "direct":
        control, residual, metrics = solve_summed(
            problem, matrices, float(lam), sharding, 3 * total
        )
        metrics = {name: on_device(value, dtype) for name, value in metrics.items()}
        steps = 0
    else:
        control, steps, residual, metrics = solve_sharded(
            problem, matrices, float(lam), float(rtol), int(max_steps), dtype, sharding, 3 * total
        )
    sol = hierarchy_solution(
        problem.hierarchy, control, metrics, settings, method=method, steps=steps,
        residual=residual, rtol=rtol, dtype=dtype, devices=len(sharding.device_set),
        processes=jax.process_count(),
    )  # fmt: skip
    raise_unless_reconstruction(sol, throw)
    return sol
