"""Preconditioned conjugate gradients for a matrix given as a function, behind
``lax.custom_linear_solve`` so that ``jax.grad`` through a solve is one more solve (the
matrix is symmetric), not a differentiation of the loop.

A ``lax.while_loop``, with no host work inside, so the same program runs on a GPU; the
step count comes back for the solution's statistics. ``host_conjugate_gradients`` is the
same recurrence and stop rule in NumPy, for the hierarchy's host solves.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jax import Array, lax


def jacobi_inverse(diagonal, xp=jnp):
    """``1 / diagonal``, and 0 where the diagonal is 0: the Jacobi preconditioner of a
    normal matrix whose function no sample and no counted neighbour pair reaches (a zero
    row) keeps that coefficient at 0 instead of dividing by 0. ``xp=numpy`` on the host."""
    positive = diagonal > 0
    return xp.where(positive, 1.0 / xp.where(positive, diagonal, 1.0), 0.0)


def _pcg(matvec, rhs, precondition, start, rtol, max_steps):
    """``(x, steps, relative residual)`` of CG on ``matvec x = rhs`` from ``start``,
    stopping at ``|r| <= rtol |rhs|`` or after ``max_steps``."""
    bound = rtol * jnp.linalg.norm(rhs)
    r = rhs - matvec(start)
    z = precondition(r)
    rz = jnp.vdot(r, z)

    def cond(state):
        _, r, _, _, steps = state
        return (jnp.linalg.norm(r) > bound) & (steps < max_steps)

    def body(state):
        x, r, p, rz, steps = state
        q = matvec(p)
        alpha = rz / jnp.vdot(p, q)
        x = x + alpha * p
        r = r - alpha * q
        z = precondition(r)
        rz_new = jnp.vdot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, p, rz_new, steps + 1

    x, r, _, _, steps = lax.while_loop(cond, body, (start, r, z, rz, jnp.asarray(0)))
    scale = jnp.maximum(jnp.linalg.norm(rhs), jnp.finfo(rhs.dtype).tiny)
    return x, steps, jnp.linalg.norm(r) / scale


def conjugate_gradients(
    matvec: Callable[[Array], Array],
    rhs: Array,
    *,
    precondition: Callable[[Array], Array] = lambda r: r,
    start: Array | None = None,
    rtol: float = 1e-10,
    max_steps: int = 10_000,
) -> tuple[Array, Array, Array]:
    """Solve the symmetric positive definite system ``matvec(x) = rhs``.

    Returns ``(x, steps, relative residual)``; the last two are statistics (no gradient).
    Differentiating ``x`` (with respect to ``rhs`` or to anything ``matvec`` closes over)
    solves the same system again with the cotangent: ``lax.custom_linear_solve`` with
    ``symmetric=True``.
    """
    start = jnp.zeros_like(rhs) if start is None else start

    def solve(mv, b):
        x, steps, residual = _pcg(mv, b, precondition, start, rtol, max_steps)
        return x, (steps, residual)

    def transpose_solve(mv, b):
        x, steps, residual = _pcg(mv, b, precondition, jnp.zeros_like(b), rtol, max_steps)
        return x, (steps, residual)

    x, (steps, residual) = lax.custom_linear_solve(
        matvec, rhs, solve, transpose_solve, symmetric=True, has_aux=True
    )
    return x, steps, residual


def _host_dot(a: np.ndarray, b: np.ndarray) -> float:
    """``a . b`` without BLAS: OpenBLAS threads a long dot product and its threads then
    spin between calls, taking the cores from the threads of the host's sparse products
    (``jurs._linalg.sparse.normal_product``)."""
    return float(np.add.reduce(a * b))


def host_conjugate_gradients(
    matvec: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    *,
    precondition: Callable[[np.ndarray], np.ndarray] = lambda r: r,
    start: np.ndarray | None = None,
    rtol: float = 1e-10,
    max_steps: int = 10_000,
) -> tuple[np.ndarray, int, float]:
    """``conjugate_gradients`` on the host, in NumPy float64: the same recurrence, stop
    rule (``|r| <= rtol |rhs|``, or ``max_steps``) and ``(x, steps, relative residual)``
    (the recurrence's residual). No derivative."""
    rhs = np.asarray(rhs, float)
    x = np.zeros_like(rhs) if start is None else np.array(start, float)
    bound = rtol * np.sqrt(_host_dot(rhs, rhs))
    r = rhs - matvec(x)
    z = precondition(r)
    rz = _host_dot(r, z)
    p = z
    steps = 0
    while np.sqrt(_host_dot(r, r)) > bound and steps < max_steps:
        q = matvec(p)
        alpha = rz / _host_dot(p, q)
        x += alpha * p
        r -= alpha * q
        z = precondition(r)
        rz_new = _host_dot(r, z)
        p = z + (rz_new / rz) * p
        rz = rz_new
        steps += 1
    scale = max(np.sqrt(_host_dot(rhs, rhs)), np.finfo(float).tiny)
    return x, steps, float(np.sqrt(_host_dot(r, r)) / scale)
