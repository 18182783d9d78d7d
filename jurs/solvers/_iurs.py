"""IURS: the paper's Algorithm 1, alternating weight-gradient and regularised PIA steps."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .._model.spline import ImplicitSpline, transpose_and_sum
from .._problem.energy import (
    layout_residuals,
    regulariser,
    regulariser_grad,
    step_size_from_column_sums,
)
from .._problem.problem import Problem
from .._problem.validate import check_count, check_nonnegative
from .._solution.solution import RESULTS
from ._base import AbstractSolver

#: More than this fraction of the weights at ``min_weight`` ends a run with
#: ``RESULTS.weights_at_floor``: sound steps (tau <= 1) leave none at the floor, far too
#: large ones pin a good share (docs/robustness.md, "Verdicts, after the fit";
#: docs/performance.md, "Measurements behind the defaults").
MAX_FLOOR_FRACTION = 0.1

#: A weight above this many times the start's largest ends a run with
#: ``RESULTS.weights_at_ceiling``: sound steps keep the weights within a factor of about
#: ten of their start, and an absurd tau (1e12, 1e300) drove them to 1e8 and 1e296
#: (overflow next) while the energy still read as converged.
WEIGHT_CEILING = 1e6


class IURSState(eqx.Module):
    control: Array  # C
    weights: Array  # w
    weight_grad: Array  # nabla_w E_d at (C, w): computed with the energy, used by the next step
    mu: Array  # eq. 25 for the current weights
    ceiling: Array  # WEIGHT_CEILING times the start's largest weight


class IURS(AbstractSolver[IURSState]):
    """Implicit uniform rational spline reconstruction (Algorithm 1, Sections III-IV).

    Each step:
      1. weights: ``w <- max(w - tau nabla_w E_d, min_weight)`` (eq. 20, projected);
      2. rebuild the collocation D of eq. 23 with the new w and its ``mu`` (eq. 25);
      3. coefficients: ``C <- C + mu D^T (b - D C) - lam nabla_C R(C)`` (eq. 33);
      4. energy ``E = E_d + lam R(C)`` (eq. 35); stop when ``|E_new - E_old| < tol`` (eq. 38).

    **Positive weights.** The paper asks for non-negative weights, but W(x) = 0 is a pole
    of g; step 1 is therefore a projected gradient step onto ``w >= min_weight`` (default
    1e-6; g is invariant under scaling all weights, so only ratios matter).

    **Which lambda.** ``lam`` is the paper's lambda of eq. 33, and the reported
    ``E = E_d + lam R`` is eq. 35 with it. For fixed weights the fixed point of eq. 33
    minimises ``E_d + (2 lam / mu) R``: the objective's lambda is ``2 lam / mu`` (see
    [`jurs.objective_lam`][]). The step is stable only while ``mu ||D^T D|| +
    4 lam ||L|| < 2`` with ``||L|| <= 8``, so ``lam`` must stay well below 1/16; larger values
    diverge and end with ``RESULTS.nonfinite``.

    ``tau = 0, lam = 0`` is exactly I-PIA (``IPIA``) on the B-spline.
    """

    per_sample_iterations: ClassVar[bool] = True

    tau: float = 1e-2
    lam: float = 0.0
    max_steps: int = eqx.field(static=True, default=200)
    tol: float = 1e-7
    min_weight: float = 1e-6

    reassociation_safe: ClassVar[bool] = True

    def __check_init__(self):
        for name in ("tau", "lam", "tol"):
            check_nonnegative(name, getattr(self, name))
        check_nonnegative("min_weight", self.min_weight, strict=True)
        check_count("max_steps", self.max_steps)

    @staticmethod
    def _data(problem):
        """Mask and targets in the kernels' layout (LocalBasis.to_layout): for small problems
        the table's own order, so no step permutes samples back and forth."""
        return problem.local.to_layout(problem.mask), problem.local.to_layout(problem.targets)

    def _energy_and_weight_grad(
        self, problem, data: tuple[Array, Array], control, weights, inv_denom=None
    ):
        local = problem.local
        # Where W is known for these weights (a step's), g costs one B-spline evaluation.
        r, inv_denom, g = layout_residuals(local, *data, control, weights, inv_denom)
        # nabla_w E_d (eq. 19, as weight_gradient) and E_d in one pass over the samples.
        t, (e_d,) = transpose_and_sum(
            local,
            jnp.stack([r * inv_denom, r * g * inv_denom]),
            problem.shape,
            [r * r],
            layout=True,
        )
        energy = e_d + self.lam * regulariser(control)
        return energy, 2.0 * (control * t[0] - t[1])

    def init(self, problem: Problem, spline: ImplicitSpline):
        energy, grad_w = self._energy_and_weight_grad(
            problem, self._data(problem), spline.control, spline.weights
        )
        mu = jnp.zeros((), energy.dtype)  # set by the first step, from the new weights
        ceiling = WEIGHT_CEILING * jnp.max(jnp.abs(spline.weights))
        return IURSState(spline.control, spline.weights, grad_w, mu, ceiling), energy

    def step(self, problem: Problem, state: IURSState):
        local = problem.local
        data = self._data(problem)
        # 1. eq. 20, projected onto w >= min_weight.
        weights = jnp.maximum(state.weights - self.tau * state.weight_grad, self.min_weight)
        # 2. D of eq. 23 with the new weights, applied to the residual of the current C;
        #    D^T r and the column sums of D (for mu, eq. 25) share one pass:
        #    D^T v = w * T(v / W). W and F(w C) are computed together and kept, so that the
        #    pass over the samples only sums (1/W serves step 4 too).
        r, inv_denom, _ = layout_residuals(local, *data, state.control, weights)
        grids, _ = transpose_and_sum(
            local, jnp.stack([r * inv_denom, inv_denom]), problem.shape, layout=True
        )
        dtr, col_sums = weights * grids
        mu = step_size_from_column_sums(col_sums)
        # 3. eq. 33: C + mu D^T (b - DC) - lam grad R(C).
        control = state.control - mu * dtr - self.lam * regulariser_grad(state.control)
        # 4. eq. 35 at the new (C, w), with nabla_w E_d there for the next step.
        energy, grad_w = self._energy_and_weight_grad(problem, data, control, weights, inv_denom)
        return IURSState(control, weights, grad_w, mu, state.ceiling), energy

    def terminate(self, problem: Problem, state: IURSState):
        # Never stops the loop; its verdict (weights pinned or blown up by a far too
        # large tau) is reported whether the run converged or reached max_steps.
        at_floor = jnp.mean(state.weights <= self.min_weight * (1.0 + 1e-6))
        # Not finite counts as past the ceiling too (an overflowed weight).
        past = ~(jnp.max(state.weights) <= state.ceiling)
        ceiling = RESULTS.where(past, RESULTS.weights_at_ceiling, RESULTS.successful)
        return jnp.array(False), RESULTS.where(
            at_floor > MAX_FLOOR_FRACTION, RESULTS.weights_at_floor, ceiling
        )

    def to_spline(self, problem: Problem, state: IURSState) -> ImplicitSpline:
        return ImplicitSpline(state.control, state.weights, problem.lower, problem.upper)


def objective_lam(lam, mu):
    """The objective lambda that the paper's eq. 33 with ``lam`` and step ``mu`` minimises:
    the fixed point of eq. 33 solves ``nabla E_d + (2 lam / mu) nabla R = 0``."""
    return 2.0 * lam / mu
