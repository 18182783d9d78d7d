"""I-PIA: the implicit progressive-iterative approximation for B-splines (paper, Section II)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .._energy import rational_residuals, step_size
from .._spline import bspline_transpose
from .._problem import Problem, check_nonnegative
from .._spline import ImplicitSpline
from ._base import AbstractSolver


class IPIAState(eqx.Module):
    control: Array  # C
    residual: Array  # r = D C - b at the current C (3m,)
    mu: Array  # eq. 13, fixed: D does not change


class IPIA(AbstractSolver[IPIAState]):
    """I-PIA, eq. 11-13: ``C <- C + mu D^T (b - D C)`` with ``mu = 2 / ||D^T D||_inf``.

    A polynomial B-spline (all weights 1). It is gradient descent on E_d with step mu/2 and
    tends to the least-squares minimiser, slowly. Stops when ``|E_new - E_old| < tol``
    (eq. 38) or after ``max_steps``. ``lam`` is always 0 (no regulariser in Section II).
    """

    max_steps: int = eqx.field(static=True, default=200)
    tol: float = 1e-7

    lam: ClassVar[float] = 0.0  # Section II has no regulariser

    def __check_init__(self):
        check_nonnegative("tol", self.tol)
        if int(self.max_steps) < 0:
            raise ValueError(f"max_steps must be >= 0, got {self.max_steps}")

    def init(self, problem: Problem, spline: ImplicitSpline):
        control = spline.control
        ones = jnp.ones_like(control)
        r = rational_residuals(problem, control, ones)[0]
        return IPIAState(control, r, step_size(problem, ones)), jnp.sum(r * r)

    def step(self, problem: Problem, state: IPIAState):
        ones = jnp.ones_like(state.control)
        # eq. 11 with r = DC - b: C + mu D^T (b - DC) = C - mu D^T r, and D^T = T for w = 1.
        dtr = bspline_transpose(problem.local, state.residual, problem.shape)
        control = state.control - state.mu * dtr
        r = rational_residuals(problem, control, ones)[0]
        return IPIAState(control, r, state.mu), jnp.sum(r * r)

    def to_spline(self, problem: Problem, state: IPIAState) -> ImplicitSpline:
        return ImplicitSpline(state.control, jnp.ones_like(state.control), problem.lower,
                              problem.upper)
