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
the same way once. No sample-sized array leaves its device (``shard_map``: the program
says so, not a partitioner's choice; docs/sharding.md, "Adaptive fits").

The direct path (a curve's default) factorises ``D^T D + lam 2 G^T W G`` on the host: in
one process every shard is addressable there, so it reads the whole cloud and solves
exactly as unsharded.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._linalg.pcg import conjugate_gradients
from .._model.precision import on_device
from .adaptive import _padded, size_class
from .sharding import _axis_size


def device_rows(count: int, points: int, shards: int) -> np.ndarray:
    """The device (``0 .. shards - 1``) of each of the ``count = 3 points`` sample rows:
    that of its point's block (``ceil(points / shards)`` points a device, in order), as
    the points are split."""
    block = -(-points // shards)
    return (np.arange(count) % points) // block


def _host_coo(matrix, nnz: int, dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, values)`` of a SciPy sparse matrix on the host, padded to ``nnz``
    entries with zeros at (0, 0), which add exactly nothing."""
    coo = matrix.tocoo()
    return (
        _padded(coo.row.astype(np.int32), nnz),
        _padded(coo.col.astype(np.int32), nnz),
        _padded(coo.data.astype(dtype), nnz),
    )


def split_rows(collocation, targets: np.ndarray, points: int, shards: int, dtype):
    """``((rows, cols, values), targets, is_data)``: host arrays of the rows of
    ``collocation`` (SciPy, ``(3 points, n)``) and of ``targets`` split over ``shards``
    devices by ``device_rows``, each device's part padded to one length (a size class)
    and laid end to end: its entries with row indices local to its part (padding: zeros
    at (0, 0), which add nothing), its targets padded with zeros (rows without entries:
    a residual of 0), ``is_data`` True on its rows of data points (eq. 4's ``P``)."""
    count = collocation.shape[0]
    owner = device_rows(count, points, shards)
    csr = collocation.tocsr()
    parts = [np.flatnonzero(owner == k) for k in range(shards)]
    length = size_class(max(len(rows) for rows in parts))
    blocks = [csr[rows] for rows in parts]
    nnz = size_class(max(block.nnz for block in blocks))
    entries, values, data = [], [], []
    for rows, block in zip(parts, blocks):
        entries.append(_host_coo(block, nnz, dtype))
        values.append(_padded(np.asarray(targets, float)[rows], length))
        data.append(_padded(rows < points, length, False))
    coo = tuple(np.concatenate([e[i] for e in entries]) for i in range(3))
    return coo, np.concatenate(values).astype(dtype), np.concatenate(data)


@functools.partial(jax.jit, static_argnames=("mesh", "names"))
def _sharded_cg(
    collocation, targets, is_data, regulariser, regulariser_diagonal, lam, rtol, max_steps,
    *, mesh: Mesh, names,
):  # fmt: skip
    """``(control, steps, relative residual, E_d, E_max)``: ``_assembled_cg``'s solve
    with ``D``'s rows (``collocation``, local row indices), ``targets`` and ``is_data``
    split over ``mesh``'s ``names`` axis, everything else replicated. The data term runs
    per device under ``shard_map``; its sums onto the active functions are all-reduced."""
    reg_rows, reg_cols, reg_values = regulariser
    n = regulariser_diagonal.shape[0]
    split, whole = PartitionSpec(names), PartitionSpec()
    on_parts = functools.partial(jax.shard_map, mesh=mesh, check_vma=False)

    def apply(entries, c, count):  # this device's D_k c
        rows, cols, values = entries
        return jax.ops.segment_sum(values * c[cols], rows, count)

    def transpose(entries, v):  # this device's D_k^T v: active-function-sized
        rows, cols, values = entries
        return jax.ops.segment_sum(values * v[rows], cols, n)

    local = targets.shape[0] // _axis_size(NamedSharding(mesh, split))  # rows a device

    @functools.partial(on_parts, in_specs=(split, whole), out_specs=whole)
    def data_normal(entries, c):  # D^T D c = sum_k D_k^T D_k c
        return lax.psum(transpose(entries, apply(entries, c, local)), names)

    @functools.partial(on_parts, in_specs=(split, split), out_specs=(whole, whole))
    def once(entries, b):  # D^T b and the diagonal of D^T D
        rows, cols, values = entries
        diagonal = jax.ops.segment_sum(values * values, cols, n)
        return lax.psum(transpose(entries, b), names), lax.psum(diagonal, names)

    @functools.partial(on_parts, in_specs=(split, split, split, whole), out_specs=(whole, whole))
    def data_metrics(entries, b, data, c):  # E_d and E_max
        r = apply(entries, c, b.shape[0]) - b
        largest = jnp.max(jnp.where(data, jnp.abs(r), 0.0))
        return lax.psum(jnp.sum(r * r), names), lax.pmax(largest, names)

    def matvec(c):
        regular = jax.ops.segment_sum(reg_values * c[reg_cols], reg_rows, n)
        return data_normal(collocation, c) + lam * regular

    rhs, data_diagonal = once(collocation, targets)
    diagonal = data_diagonal + lam * regulariser_diagonal
    inverse = jnp.where(diagonal > 0, 1.0 / jnp.where(diagonal > 0, diagonal, 1.0), 0.0)
    control, steps, residual = conjugate_gradients(
        matvec, rhs, precondition=lambda r: inverse * r, rtol=rtol, max_steps=max_steps
    )
    data, largest = data_metrics(collocation, targets, is_data, control)
    return control, steps, residual, data, largest


def solve_sharded(
    problem, matrices, lam: float, rtol: float, max_steps: int, dtype, sharding: NamedSharding
) -> tuple[np.ndarray, int, float, dict]:
    """``(control, steps, relative residual, metrics)``: ``solve_assembled``'s CG (the
    same matrix, preconditioner and stop rule) with the collocation matrix's rows and the
    targets split over ``sharding``'s point axis (module docstring). Agrees with the
    one-device solve to the CG tolerance (the sums run in another order)."""
    collocation, regulariser = matrices
    count, n = collocation.shape
    shards = _axis_size(sharding)
    mesh, names = sharding.mesh, sharding.spec[0]
    coo, targets, is_data = split_rows(
        collocation, np.asarray(problem.targets), count // 3, shards, dtype
    )
    split = NamedSharding(mesh, PartitionSpec(names))
    replicated = NamedSharding(mesh, PartitionSpec())
    n_class = size_class(n)
    reg_coo = _host_coo(regulariser, size_class(regulariser.nnz), dtype)
    regulariser_diagonal = _padded(np.asarray(problem.regulariser_diagonal, float), n_class)
    control, steps, residual, data, largest = _sharded_cg(
        tuple(jax.device_put(a, split) for a in coo),
        jax.device_put(targets, split),
        jax.device_put(is_data, split),
        tuple(jax.device_put(a, replicated) for a in reg_coo),
        jax.device_put(regulariser_diagonal.astype(dtype), replicated),
        jax.device_put(np.asarray(lam, dtype), replicated),
        jax.device_put(np.asarray(rtol, dtype), replicated),
        jax.device_put(np.asarray(max_steps, np.int32), replicated),
        mesh=mesh,
        names=names,
    )
    c = np.asarray(control)[:n]
    reg = float(c @ (regulariser @ c))
    data = float(data)
    metrics = {
        name: on_device(value, dtype)
        for name, value in (
            ("E", data + lam * reg),
            ("E_d", data),
            ("R", reg),
            ("E_ave", data / count),
            ("E_max", float(largest)),
            ("lam", lam),
        )
    }
    return c, int(steps), float(residual), metrics
