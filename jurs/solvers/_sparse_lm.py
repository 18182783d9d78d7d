"""A Levenberg-Marquardt solver for the joint (C, w) fit that uses the Jacobian's sparsity.

Each residual ``g(x_k) - b_k`` depends on the 16 coefficients and 16 weights of its cell,
through the hand-derived derivatives of docs/design.md section 2 (with ``w = exp(v)``):

    dg/dC_ij = w_ij B_ij / W = R_ij,      dg/dv_ij = w_ij B_ij (C_ij - g) / W.

So ``J^T J`` is the sum over cells of 32 x 32 blocks (one pass over the samples, chunked),
and a Gauss-Newton system costs one small dense Cholesky: no dense Jacobian, no automatic
differentiation, and a step costs about as much as two evaluations of the energy.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array

from .._linalg.normal import DEFAULT_CHUNK, chunked_segment_sum
from .._model.basis import NUM_LOCAL, grid_to_patches, num_cells
from .._model.spline import ImplicitSpline
from .._problem.energy import objective, residuals, transpose_apply
from .._problem.problem import Problem
from .._problem.validate import check_nonnegative
from . import _parameterisation as param
from ._base import AbstractSolver


class JointLMState(eqx.Module):
    control: Array  # C
    log_weights: Array  # v = log w, mean 0
    damping: Array  # Levenberg-Marquardt parameter (relative to diag(J^T J))
    energy: Array  # E_d + lam R at (C, v)


def _jacobian_rows(problem: Problem, control: Array, weights: Array):
    """Residuals and the 32 non-zero Jacobian entries of every residual row:
    ``(r (3m,), rows (3m, 32))``, C terms then v terms, masked."""
    r, wb, denom, g = residuals(problem, control, weights)
    c_rows = grid_to_patches(control)[problem.local.cell]
    scale = (problem.mask / denom)[:, None]
    d_control = wb * scale  # collocation row R_ij (eq. 23)
    d_log_weight = wb * (c_rows - g[:, None]) * scale  # w_ij dg/dw_ij (eq. 19's factor)
    return r, jnp.concatenate([d_control, d_log_weight], axis=1)


def _global_index(shape: tuple[int, ...]) -> np.ndarray:
    """``(cells, 32)`` position of each cell's local C and v terms in the unknown vector
    ``[C.ravel(), v.ravel()]``."""
    n, m = shape[0] - 3, shape[1] - 3
    cx, cy = np.divmod(np.arange(n * m), m)
    a, b = np.divmod(np.arange(NUM_LOCAL), 4)
    flat = (cx[:, None] + a[None]) * shape[1] + cy[:, None] + b[None]
    return np.concatenate([flat, flat + shape[0] * shape[1]], axis=1)


def _laplacian_matrix(shape: tuple[int, ...]) -> np.ndarray:
    """The grid Laplacian L (free boundary) as a dense ``NM x NM`` matrix."""

    def path(k):
        lap = np.diag(np.r_[1.0, 2.0 * np.ones(k - 2), 1.0]) if k > 1 else np.zeros((1, 1))
        return lap - np.eye(k, k=1) - np.eye(k, k=-1)

    return np.kron(path(shape[0]), np.eye(shape[1])) + np.kron(np.eye(shape[0]), path(shape[1]))


class JointLevenbergMarquardt(AbstractSolver[JointLMState]):
    """Levenberg-Marquardt over (C, log w) jointly with the sparse, hand-derived Jacobian.

    Minimises ``E_d(C, w) + lam R(C)`` (eq. 32 with the objective's lambda) over rational
    splines (eq. 14). Weights are ``w = exp(v)``, positive by construction; after every
    step v is shifted to mean 0, which leaves g unchanged (it is invariant under scaling
    all weights), and a residual ``mean(v)`` in the Gauss-Newton system removes that flat
    direction. Each driver step assembles ``J^T J`` from per-cell 32 x 32 blocks, solves
    ``(J^T J + 2 lam L + damping diag) delta = -gradient`` (lineax Cholesky), and retries
    with more damping until the energy decreases (at most ``max_tries``): every accepted
    step lowers E, and the driver's ``|E_new - E_old| < tol`` rule (eq. 38) stops it.

    By default (``warm_start``) the search starts from the exact best C for the start
    weights (the B-spline least-squares fit for the default w = 1), so the result is never
    worse than ``LeastSquares``. Dense in 2NM unknowns: meant for grids up to ~30 x 30.
    """

    lam: float = 0.0
    max_steps: int = eqx.field(static=True, default=100)
    tol: float = 1e-14
    damping: float = 1e-3
    max_tries: int = eqx.field(static=True, default=12)
    warm_start: bool = eqx.field(static=True, default=True)
    chunk_size: int = eqx.field(static=True, default=DEFAULT_CHUNK // 4)

    def __check_init__(self):
        for name in ("lam", "tol"):
            check_nonnegative(name, getattr(self, name))
        check_nonnegative("damping", self.damping, strict=True)
        if int(self.max_steps) < 0 or int(self.max_tries) < 1:
            raise ValueError("max_steps must be >= 0 and max_tries >= 1")

    def init(self, problem: Problem, spline: ImplicitSpline):
        control, log_weights = param.initial_parameters(
            problem, spline, self.lam, True, self.warm_start
        )
        energy = objective(problem, control, jnp.exp(log_weights), self.lam)
        damping = jnp.asarray(self.damping, energy.dtype)
        return JointLMState(control, log_weights, damping, energy), energy

    def _system(self, problem: Problem, control: Array, log_weights: Array):
        """Gauss-Newton matrix ``J^T J + 2 lam L (+ gauge)`` and gradient / 2."""
        shape = problem.shape
        size = shape[0] * shape[1]
        r, rows = _jacobian_rows(problem, control, jnp.exp(log_weights))

        def outer(rows):
            return (rows[:, :, None] * rows[:, None, :]).reshape(rows.shape[0], -1)

        gram = chunked_segment_sum(
            outer, [rows], problem.local.cell, num_cells(shape), self.chunk_size,
            problem.local.parts,
        )  # fmt: skip
        index = jnp.asarray(_global_index(shape))
        hessian = (
            jnp.zeros((2 * size, 2 * size), r.dtype)
            .at[index[:, :, None], index[:, None, :]]
            .add(gram.reshape(-1, 2 * NUM_LOCAL, 2 * NUM_LOCAL))
        )
        lap = jnp.asarray(_laplacian_matrix(shape), r.dtype)
        hessian = hessian.at[:size, :size].add(2.0 * self.lam * lap)
        # Gauge residual mean(v): its Jacobian row is 1/NM on every v.
        hessian = hessian.at[size:, size:].add(1.0 / size**2)
        grads = transpose_apply(
            problem, jnp.stack([rows[:, :NUM_LOCAL], rows[:, NUM_LOCAL:]], 1) * r[:, None, None]
        )
        grad_c = grads[0].ravel() + 2.0 * self.lam * (lap @ control.ravel())
        grad_v = grads[1].ravel() + jnp.mean(log_weights) / size
        return hessian, jnp.concatenate([grad_c, grad_v])

    def step(self, problem: Problem, state: JointLMState):
        shape = problem.shape
        size = shape[0] * shape[1]
        hessian, grad = self._system(problem, state.control, state.log_weights)
        diag = jnp.diag(hessian)
        # Marquardt's scaling, floored so that unseen coefficients (zero diagonal) move
        # only as far as the damping lets them.
        scale = jnp.maximum(diag, 1e-12 * jnp.max(diag))

        def trial(damping):
            operator = lx.MatrixLinearOperator(
                hessian + jnp.diag(damping * scale), lx.positive_semidefinite_tag
            )
            delta = lx.linear_solve(operator, -grad, lx.Cholesky(), throw=False).value
            control = state.control + delta[:size].reshape(shape)
            log_weights = state.log_weights + delta[size:].reshape(shape)
            log_weights = log_weights - jnp.mean(log_weights)  # the gauge; g is unchanged
            energy = objective(problem, control, jnp.exp(log_weights), self.lam)
            energy = jnp.where(jnp.isfinite(energy), energy, jnp.inf)
            return control, log_weights, energy

        def cond(carry):
            tries, _, _, _, energy = carry
            return (tries < self.max_tries) & ~(energy < state.energy)

        def body(carry):
            tries, damping, *_ = carry
            damping = jnp.where(tries == 0, damping, damping * 4.0)
            return (tries + 1, damping, *trial(damping))

        carry0 = (
            jnp.array(0),
            state.damping,
            state.control,
            state.log_weights,
            jnp.asarray(jnp.inf, state.energy.dtype),
        )
        _, damping, control, log_weights, energy = jax.lax.while_loop(cond, body, carry0)
        accepted = energy < state.energy
        new = JointLMState(
            jnp.where(accepted, control, state.control),
            jnp.where(accepted, log_weights, state.log_weights),
            jnp.where(accepted, damping / 3.0, damping),
            jnp.where(accepted, energy, state.energy),
        )
        return new, new.energy

    def to_spline(self, problem: Problem, state: JointLMState) -> ImplicitSpline:
        return ImplicitSpline(
            state.control, jnp.exp(state.log_weights), problem.lower, problem.upper
        )
