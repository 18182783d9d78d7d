"""I-PIA: the implicit progressive-iterative approximation for B-splines (paper, Section II)."""

from __future__ import annotations

from typing import ClassVar, Protocol, TypeVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .._linalg.normal import NormalEquations, normal_equations
from .._model.spline import ImplicitSpline, bspline_transpose
from .._problem.energy import bspline_residuals, step_size
from .._problem.problem import Problem
from .._problem.validate import check_count, check_nonnegative
from ._base import AbstractSolver


class _HasControl(Protocol):
    @property
    def control(self) -> Array: ...


_PIAState = TypeVar("_PIAState", bound=_HasControl)


class _AbstractPIA(AbstractSolver[_PIAState]):
    """Shared by the two forms of I-PIA: settings, checks, and a B-spline (w = 1) result.
    The state carries the coefficients as ``state.control``."""

    max_steps: int = eqx.field(static=True, default=200)
    tol: float = 1e-7
    lam: ClassVar[float] = 0.0  # Section II has no regulariser
    reassociation_safe: ClassVar[bool] = True

    def __check_init__(self):
        check_nonnegative("tol", self.tol)
        check_count("max_steps", self.max_steps)

    def to_spline(self, problem: Problem, state) -> ImplicitSpline:
        return ImplicitSpline(
            state.control, jnp.ones_like(state.control), problem.lower, problem.upper
        )


class IPIAState(eqx.Module):
    control: Array  # C
    residual: Array  # r = D C - b at the current C, one entry a sample slot
    mu: Array  # eq. 13, fixed: D does not change


class IPIA(_AbstractPIA[IPIAState]):
    """I-PIA, eq. 11-13: ``C <- C + mu D^T (b - D C)`` with ``mu = 2 / ||D^T D||_inf``.

    A polynomial B-spline (all weights 1). It is gradient descent on E_d with step mu/2 and
    tends to the least-squares minimiser, slowly. Stops when ``|E_new - E_old| < tol``
    (eq. 38) or after ``max_steps``. ``lam`` is always 0 (no regulariser in Section II).
    """

    per_sample_iterations: ClassVar[bool] = True

    def init(self, problem: Problem, spline: ImplicitSpline):
        r = bspline_residuals(problem, spline.control)
        mu = step_size(problem, jnp.ones_like(spline.control))
        return IPIAState(spline.control, r, mu), jnp.sum(r * r)

    def step(self, problem: Problem, state: IPIAState):
        # eq. 11 with r = DC - b: C + mu D^T (b - DC) = C - mu D^T r, and D^T = T for w = 1.
        dtr = bspline_transpose(problem.local, state.residual, problem.shape)
        control = state.control - state.mu * dtr
        r = bspline_residuals(problem, control)
        return IPIAState(control, r, state.mu), jnp.sum(r * r)


class NormalIPIAState(eqx.Module):
    control: Array  # C
    product: Array  # D^T D C at the current C: the energy's and the next step's matvec
    normal: NormalEquations  # D^T D (stencil), D^T b, b.b: assembled once
    mu: Array  # eq. 13


class NormalIPIA(_AbstractPIA[NormalIPIAState]):
    """I-PIA (eq. 11-13) in normal-equation form: ``C <- C - mu (D^T D C - D^T b)``.

    The same iterates as [`IPIA`][jurs.IPIA] (to rounding), but ``D^T D`` (a 49-point stencil)
    and ``D^T b`` are assembled once in ``init``, so each step costs O(49 N M)
    whatever the number of points, and E_d comes from ``C.(D^T D) C - 2 C.(D^T b) + b.b``.
    That last form cancels: in float32 the energy (and so the ``tol`` test) is only good to
    about ``1e-7 b.b``. Use it for large clouds; [`IPIA`][jurs.IPIA] for the paper's per-sample
    form.

    One stencil product a step: ``D^T D C`` at the new C serves both that energy and the
    next step's update, so the state carries it. The state also carries the assembled
    ``D^T D`` (6.4 MB at 128 x 128): a jitted ``step`` called on its own returns it in a
    new buffer each call, which costs more than the step itself; [`jurs.solve`][] runs
    the steps in one compiled loop, which updates the state in place.
    """

    def init(self, problem: Problem, spline: ImplicitSpline):
        normal = normal_equations(problem)
        # D >= 0, so D^T D >= 0 entrywise and ||D^T D||_inf is its largest row sum (eq. 13).
        mu = 2.0 / jnp.max(jnp.sum(normal.stencil, axis=(2, 3)))
        product = normal.matvec(spline.control)
        return (
            NormalIPIAState(spline.control, product, normal, mu),
            normal.data_energy(spline.control, product),
        )

    def step(self, problem: Problem, state: NormalIPIAState):
        normal = state.normal
        control = state.control - state.mu * (state.product - normal.rhs)  # eq. 11
        product = normal.matvec(control)
        return (
            NormalIPIAState(control, product, normal, state.mu),
            normal.data_energy(control, product),
        )
