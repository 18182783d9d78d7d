"""LeastSquares: the exact minimiser of E_d + lam R for fixed weights, in one linear solve."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array

from .._kept import KeptByIdentity
from .._linalg.cholesky import DIRECT_MAX_ENTRIES, BlockCholesky
from .._linalg.multigrid import Multigrid
from .._linalg.normal import DEFAULT_CHUNK, normal_equations
from .._linalg.operator import AbstractGridOperator
from .._model.spline import ImplicitSpline
from .._problem.energy import objective
from .._problem.problem import Problem
from .._problem.validate import check_nonnegative
from .._solution.solution import RESULTS
from ._base import AbstractSolver
from ._cascade import cascadic_start

#: Largest grid (N * M coefficients) that the default linear solver solves densely
#: (Cholesky); above it, a block Cholesky of the stencil (lam > 0) or Jacobi-preconditioned
#: CG (lam = 0). The dense factorisation's cubic cost overtakes CG's between 16 x 16 and
#: 32 x 32 (benchmarks/solvers.py, Example 10; docs/multigrid.md, "Measurements behind the
#: constants").
DENSE_MAX_COEFFICIENTS = 256

#: The default 3D solve's tolerance on every entry of the residual, relative to the largest
#: entry of the right-hand side (``surface_linear_solver``), and its cap on CG steps.
#: Tighter tolerances cost more CG steps without moving the zero set (the mesh's distances
#: to the true surface stay the same to three digits), and a looser one saves little more
#: (docs/multigrid.md, "Measurements behind the constants").
SURFACE_RTOL = 1e-3
SURFACE_MAX_STEPS = 1000

#: Default Tikhonov ridge, relative to the largest diagonal of D^T D (see LeastSquares).
DEFAULT_RIDGE = 1e-14


class LeastSquaresState(eqx.Module):
    control: Array  # C
    weights: Array  # the fixed w
    done: Array  # bool: the solve has run
    result: lx.RESULTS  # the linear solver's verdict


def default_linear_solver(shape: tuple[int, ...]) -> lx.AbstractLinearSolver:
    """Cholesky on the assembled matrix for small grids, CG on the stencil above
    ``DENSE_MAX_COEFFICIENTS`` coefficients."""
    if math.prod(shape) <= DENSE_MAX_COEFFICIENTS:
        return lx.Cholesky()
    return stencil_cg(shape)


def surface_linear_solver(rhs: Array) -> lx.AbstractLinearSolver:
    """The final solve of 3D (343-point stencil) systems above the dense size: CG on the
    stencil preconditioned by its diagonal blocks (``jurs._linalg.stencil.BlockJacobi``,
    chosen by the operator) to ``SURFACE_RTOL``, started from the same fit on a coarse
    grid (``jurs.solvers._cascade``). No direct factorisation fits
    here (a block Cholesky of grid planes of a 64^3 grid would store 64 dense blocks of
    64^4 entries each), and ``jurs._linalg.multigrid.Multigrid`` takes several times
    the memory for at most a small gain in time (docs/multigrid.md, "Measurements behind
    the constants").

    The tolerance is absolute, ``SURFACE_RTOL * max |rhs|``, for every entry of the
    residual: lineax's CG tests each entry against ``atol + rtol |rhs_i|``, and the far
    field's right-hand side is 0, where a purely relative test never passes (it ran to its
    step cap, then drifted away from the solution).

    In float64 the residual is the recurrence's alone, never recomputed from the iterate
    (lineax's ``stabilise_every=None``): the drift between the two stays at rounding level,
    far below this tolerance, and each recomputation is one more copy of the
    343-point product in the compiled program (docs/performance.md, "What a surface
    fit's first call compiles"). Lower precisions keep lineax's recomputation."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(rhs)))  # a stop rule, not a variable
    stabilise_every = None if rhs.dtype == jnp.float64 else 10
    # lineax annotates atol as a float; an array tolerance works and can be traced.
    return lx.CG(
        rtol=0.0,
        atol=SURFACE_RTOL * scale,  # pyright: ignore[reportArgumentType]
        max_steps=SURFACE_MAX_STEPS,
        stabilise_every=stabilise_every,
    )


def solve_by_default(operator: AbstractGridOperator, rhs: Array, start: Array, ridge=0.0):
    """``solve_normal_equations`` with ``default_linear_solver``, and a second solver
    where the dense Cholesky breaks down (a system singular at rounding level). In float64
    LU: partial pivoting needs no positive definiteness, and it compiles to one more
    factorisation (cheaper to compile than a CG fallback). In lower precision CG, whose
    early stop regularises: LU's exact solve of the rounded system lands far above the
    float64 minimum energy, CG's close to it (docs/multigrid.md, "Measurements behind the
    constants")."""
    linear_solver = default_linear_solver(rhs.shape)
    if _is_matrix_free(linear_solver):
        fallback = None
    else:
        fallback = lx.LU() if rhs.dtype == jnp.float64 else stencil_cg(rhs.shape)
    return solve_normal_equations(operator, rhs, start, linear_solver, ridge, fallback)


def stencil_cg(shape: tuple[int, ...]) -> lx.CG:
    """The CG that solves on the stencil by default (with the operator's preconditioner:
    Jacobi in 2D, blocks in 3D), and where
    the block Cholesky of the stencil breaks down."""
    return lx.CG(rtol=1e-10, atol=1e-12, max_steps=10 * int(np.prod(shape)))


def _factors_by_lines(shape: tuple[int, ...]) -> bool:
    """Whether the default exact solve of a curve on ``shape`` is the block Cholesky of
    the stencil (lam > 0; CG where lam = 0): grids above the dense size whose factor
    stays under ``DIRECT_MAX_ENTRIES``."""
    n, m = sorted(shape, reverse=True)[:2]
    return len(shape) == 2 and n * m > DENSE_MAX_COEFFICIENTS and n * m * m <= DIRECT_MAX_ENTRIES


def _is_matrix_free(solver: lx.AbstractLinearSolver) -> bool:
    return isinstance(solver, (lx.CG, lx.BiCGStab, lx.GMRES, Multigrid))


def _unless_nonfinite(
    solved: tuple,
    operator: AbstractGridOperator,
    rhs: Array,
    start: Array,
    fallback: lx.AbstractLinearSolver,
) -> tuple:
    """``solved`` (``(C, lineax result)``), or where C is not finite the solve by
    ``fallback``. A Cholesky factorisation breaks down (NaN) where the matrix is not
    numerically positive definite: unregularised systems on sparse data are singular at
    rounding level, and whether they factor depends on the device's rounding."""
    control, result = solved
    return jax.lax.cond(
        jnp.all(jnp.isfinite(control)),
        lambda: (control, result),
        lambda: solve_normal_equations(operator, rhs, start, fallback),
    )


#: The smallest ratio ``p.Ap / r.z`` (CG's inverse step length) that the preconditioned
#: systems of the exact solve are taken to reach, relative to 1 (``preconditioner_scale``).
MIN_INVERSE_STEP = 1e-6


def preconditioner_scale(size: int, dtype) -> float:
    """A power of two by which the exact solve scales CG's preconditioner: 1 in float64
    below about 4e7 coefficients, more in float32 on large grids.

    lineax's CG declares a breakdown (NaN) at a step whose ``p.Ap`` is at most ``100 eps
    size`` times ``r.z``: a threshold that grows with the system, and in float32 on a 48^3
    surface (132k coefficients, 1.6) it fired on the second step of every fit. Scaling the
    preconditioner by ``c`` scales ``r.z`` by ``c`` and ``p.Ap`` by ``c^2`` and leaves every
    iterate as it was (exactly, ``c`` a power of two), so ``c`` lifts the ratio above that
    threshold wherever the ratio is at least ``MIN_INVERSE_STEP``."""
    threshold = 100 * float(jnp.finfo(dtype).eps) * size / MIN_INVERSE_STEP
    return float(2.0 ** max(0, math.ceil(math.log2(threshold))))


def solve_normal_equations(
    operator: AbstractGridOperator,
    rhs: Array,
    start: Array,
    linear_solver: lx.AbstractLinearSolver,
    ridge=0.0,
    fallback: lx.AbstractLinearSolver | None = None,
):
    """Solve ``operator C = rhs`` (a symmetric positive semi-definite system on the
    coefficient grid, [`jurs.internal.NormalEquations.regularised`][]) with the lineax
    ``linear_solver``.

    Coefficients whose diagonal is 0 are in no sample's support and (with lam = 0)
    unconstrained: they keep their value in ``start``, which makes the rest of the system
    positive definite whenever the data determine it. The solver takes the operator as it
    is: matrix-free solvers (CG, BiCGStab, GMRES) apply it, with the operator's own
    preconditioner (``AbstractGridOperator.preconditioner``: Jacobi, or blocks of 2 x 2 x 2
    coefficients on a 3D stencil);
    the stencil's own solvers (``jurs._linalg.multigrid.Multigrid``,
    ``jurs._linalg.cholesky.BlockCholesky``) recognise its type; dense ones
    (Cholesky, LU) assemble its ``NM x NM`` matrix. ``fallback`` solves instead where the
    solve's C is not finite (a factorisation that broke down). Returns ``(C, lineax
    result)``.
    """
    diag = operator.grid_diagonal()
    unseen = diag <= 0
    # A PSD matrix with a zero diagonal entry has that whole row and column zero: put 1 on
    # the diagonal and the start value on the right, and that coefficient stays put.
    # ``ridge`` (relative to the largest diagonal) bounds the condition number.
    diag = jnp.where(unseen, 1.0, diag + ridge * jnp.max(diag))
    operator = operator.with_grid_diagonal(diag)
    rhs = jnp.where(unseen, start, rhs)
    options: dict[str, Any] = {}
    if _is_matrix_free(linear_solver):
        # The preconditioner and initial guess change the path, not the solution: no
        # gradient through them (lineax refuses tangents in `options`).
        if not isinstance(linear_solver, Multigrid):  # which builds its own preconditioner
            tags = lx.positive_semidefinite_tag
            # The operator's own (jurs._linalg.operator.AbstractGridOperator.preconditioner):
            # Jacobi, or blocks of neighbouring coefficients on a 3D stencil.
            unscaled = jax.lax.stop_gradient(operator).preconditioner()
            scale = preconditioner_scale(rhs.size, rhs.dtype)

            def scaled(r: Array) -> Array:  # float32 on large grids: past lineax's test
                return scale * unscaled(r)

            precondition = unscaled if scale == 1.0 else scaled
            options["preconditioner"] = lx.FunctionLinearOperator(precondition, rhs, tags)
        options["y0"] = jax.lax.stop_gradient(start)
    sol = lx.linear_solve(operator, rhs, linear_solver, throw=False, options=options)
    solved = sol.value, sol.result
    return solved if fallback is None else _unless_nonfinite(solved, operator, rhs, start, fallback)


#: A solve whose coefficients, times the system's largest diagonal, exceed its largest
#: right-hand side by more than this is numerically singular (``singular_solve``).
#: Example 1 measured 1e2 to 1e3 with lam > 0; 1.2e6 at lam = 0 on 9 x 9 at 120 points
#: (ill-conditioned, but float32 and float64 agree on its coefficients of 1.2e3); 7e9 and
#: 9e12 at lam = 0 and ridge = 0 on 20 x 20 and 30 x 30 at 300 points (coefficients of
#: 1e8 and 1e11: rounding). In float32 a singular solve stops near ``1 / resolution``
#: (1e7) and may pass.
SINGULAR_AMPLIFICATION = 1e8


def amplification(normal, lam, control: Array) -> Array:
    """``max|diag A| max|C| / max|b|`` of the solve ``A C = b`` (``A = D^T D + 2 lam L``):
    about 1 to 1e3 where the data determine C, as large as the system's condition
    number (1e12 and more) where it is singular and the solve amplifies rounding."""
    diag = jnp.max(jnp.abs(normal.regularised(lam).grid_diagonal()))
    rhs = jnp.max(jnp.abs(normal.rhs))
    return diag * jnp.max(jnp.abs(control)) / jnp.maximum(rhs, jnp.finfo(rhs.dtype).tiny)


def singular_solve(normal, lam, control: Array, result):
    """``result``, or ``lineax.RESULTS.singular`` where the solve amplified the right-hand
    side past ``SINGULAR_AMPLIFICATION`` (``amplification``) or left C not finite: a
    numerically singular system (``lam = 0`` with ``ridge = 0`` on sparse data) whose
    "solution" is rounding, with signs as wrong as right. [`jurs.LeastSquares`][] then
    reports ``RESULTS.failed``."""
    bad = ~(amplification(normal, lam, control) <= SINGULAR_AMPLIFICATION)
    return lx.RESULTS.where(bad & (result == lx.RESULTS.successful), lx.RESULTS.singular, result)


#: ``LeastSquares.first_try``'s answers, by solver and grid.
_FIRST_TRIES = KeptByIdentity()


class LeastSquares(AbstractSolver[LeastSquaresState]):
    """Exact minimiser of ``E_d(C) + lam R(C)`` for fixed weights (docs/design.md section 3).

    Solves the normal equations ``(D^T D + 2 lam L) C = D^T b`` once: ``D^T D`` is
    assembled as a 49-point stencil in one pass over the samples
    ([`jurs.internal.normal_equations`][], never the dense collocation), then solved: Cholesky on
    the assembled matrix for grids up to ``DENSE_MAX_COEFFICIENTS`` coefficients (where
    it breaks down, as a numerically singular system can: LU in float64, CG in float32);
    above, a block Cholesky of the stencil in grid lines when ``lam > 0``
    (``jurs._linalg.cholesky.BlockCholesky``, up to
    ``jurs._linalg.cholesky.DIRECT_MAX_ENTRIES``, 256 x 256) and Jacobi-preconditioned CG
    when ``lam = 0`` or beyond (on a surface, CG preconditioned by blocks of 2 x 2 x 2
    coefficients from the cascade's start); or the lineax ``linear_solver`` given, which
    receives the system as a ``jurs._linalg.stencil.StencilOperator``. One driver step;
    the result is the point the paper's iterations (I-PIA, eq. 11; IURS's eq. 33 with
    fixed w) converge to.

    Args:
        lam: the objective's lambda (``E = E_d + lam R``, eq. 32), not the paper's eq. 33
            lambda; convert with [`jurs.objective_lam`][].
        keep_weights: False (default) fits a polynomial B-spline (w = 1; eq. 6); True keeps
            the start spline's weights fixed and solves for C with the rational rows of
            eq. 23.
        linear_solver: a lineax solver for the symmetric positive (semi-)definite system;
            default (None) per grid size and lam, as above. ``Multigrid()``
            (``jurs._linalg.multigrid``: knot-insertion multigrid-preconditioned CG, 2D or
            3D) is never chosen by default: it lost to the direct solves in 2D, and in 3D it
            takes several times the memory of CG from the cascade (docs/multigrid.md).
        chunk_size: samples accumulated at once when assembling rational rows.
        ridge: a Tikhonov term ``ridge * max(diag(D^T D)) * I`` added to the system
            (default 1e-14). It only matters when the system is numerically singular
            (``lam = 0`` on sparse data), where it keeps the solve finite and the
            coefficients bounded: on Example 1 at 9 x 9 it raises E_d by 0.015 % and lowers
            max |C| from 1.4e3 to 1.2e3; on Example 9 at 20 x 20 it lowers max |C| from
            4.9e10 to 7.7e3 (measured, float64). In float32 it is below rounding. 0
            disables it, for the exact minimiser.

    With ``lam = 0`` the minimiser is not unique where the data do not determine it:
    coefficients that no sample touches keep their start value (0 by default). The
    remaining unregularised system is numerically singular on sparse data (on Example 1 at
    9 x 9 the smallest eigenvalue of D^T D is at rounding level): its exact minimiser puts
    large coefficients in empty corners for a fraction of a percent of E_d, which the
    default ``ridge`` curbs. Use ``lam > 0`` for a sensible surface; in float32 the
    unregularised solve can lose all accuracy.
    A solve that the system's singularity leaves to rounding (``ridge = 0`` as well:
    coefficients of 1e8 and more, signs as wrong as right) ends with ``RESULTS.failed``
    (``singular_solve``).
    """

    lam: float = 0.0
    keep_weights: bool = eqx.field(static=True, default=False)
    linear_solver: lx.AbstractLinearSolver | None = None
    chunk_size: int = eqx.field(static=True, default=DEFAULT_CHUNK)
    ridge: float = DEFAULT_RIDGE

    max_steps: ClassVar[int] = 1  # one exact solve
    tol: ClassVar[float] = 0.0  # the driver's energy test is moot: terminate() stops it
    reassociation_safe: ClassVar[bool] = True

    def __check_init__(self):
        check_nonnegative("lam", self.lam)
        check_nonnegative("ridge", self.ridge)
        if int(self.chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1, got {self.chunk_size}")
        if self.linear_solver is not None and not isinstance(
            self.linear_solver, lx.AbstractLinearSolver
        ):
            raise TypeError(f"linear_solver must be a lineax solver, got {self.linear_solver!r}")

    def _level_solve(self, operator, rhs, start, linear_solver):
        """The cascade's coarse solve: ``solve_normal_equations`` with this solver's
        ridge."""
        return solve_normal_equations(operator, rhs, start, linear_solver, self.ridge)[0]

    def _weights(self, spline: ImplicitSpline) -> Array:
        return spline.weights if self.keep_weights else jnp.ones_like(spline.control)

    def init(self, problem: Problem, spline: ImplicitSpline):
        weights = self._weights(spline)
        energy = objective(problem, spline.control, weights, self.lam)
        return LeastSquaresState(
            spline.control, weights, jnp.array(False), lx.RESULTS.successful
        ), energy

    def step(self, problem: Problem, state: LeastSquaresState):
        control, result = self.minimise(problem, state.weights, state.control)
        energy = objective(problem, control, state.weights, self.lam)
        return LeastSquaresState(control, state.weights, jnp.array(True), result), energy

    def minimise(self, problem: Problem, weights: Array, start: Array, warm: bool | Array = False):
        """``(C, lineax result)``: the normal equations of ``problem`` assembled (with
        ``weights`` where ``keep_weights``) and solved from ``start``, the singular
        solves flagged (``singular_solve``). ``warm`` (a bool, may be traced): ``start``
        is already a fit of a problem like this one, whose far field a surface's solve
        keeps instead of the cascade's (``solve_assembled``)."""
        normal = normal_equations(
            problem, weights if self.keep_weights else None, chunk_size=self.chunk_size
        )
        control, result = self.solve_assembled(problem, normal, self.lam, start, warm)
        return control, singular_solve(normal, self.lam, control, result)

    def solve_assembled(
        self, problem: Problem, normal, lam, start: Array, warm: bool | Array = False
    ):
        """``(C, lineax result)``: the minimiser of ``E_d + lam R`` from the assembled
        ``normal`` equations ([`jurs.internal.NormalEquations`][] of ``problem``), by
        this solver's linear solver (see the class docstring), started from ``start``;
        on a surface from the cascade's start unless ``warm`` (see ``minimise``)."""
        if self.needs_samples_to_solve(problem.shape):
            # Surfaces: CG from the cascade's start (jurs/solvers/_cascade.py), which
            # carries the far field that CG from 0 leaves behind; a warm start (the
            # previous fit of a reweighted problem) has it already.
            cascade = lambda: cascadic_start(problem, lam, self._level_solve, start)  # noqa: E731
            if isinstance(warm, bool):
                start = start if warm else cascade()
            else:
                start = jax.lax.cond(warm, lambda: start, cascade)
            system = (normal.regularised(lam), normal.rhs, start)
            return solve_normal_equations(*system, surface_linear_solver(normal.rhs), self.ridge)
        return self.solve_without_samples(normal, lam, start)

    def solve_without_samples(self, normal, lam, start: Array):
        """``solve_assembled`` where it needs no samples: every solve but a surface's
        default one, whose cascade resamples the problem on a coarse grid. The grid's shape
        is ``start``'s."""
        system = (normal.regularised(lam), normal.rhs, start)
        shape = start.shape
        if self.linear_solver is None and _factors_by_lines(shape):
            # lam > 0: the regulariser makes the system positive definite, and a direct
            # solve beats the tens of thousands of CG steps that sparse data need
            # (docs/multigrid.md, "Measurements behind the constants"). lam = 0:
            # numerically singular systems, where CG's early stop acts as a further
            # regulariser (see ``ridge``). CG also where the factorisation breaks down.
            cg = stencil_cg(shape)
            return jax.lax.cond(
                jnp.asarray(lam) > 0,
                lambda: solve_normal_equations(*system, BlockCholesky(), self.ridge, cg),
                lambda: solve_normal_equations(*system, cg, self.ridge),
            )
        if self.linear_solver is None:
            return solve_by_default(*system, self.ridge)
        return solve_normal_equations(*system, self.linear_solver, self.ridge)

    def first_try(self, shape: tuple[int, ...]) -> LeastSquares:
        """This solver with the linear solver that its default ``solve_without_samples``
        runs first for its concrete ``lam`` on ``shape``, and no fallback: the block
        Cholesky (CG where ``lam = 0``), or the dense Cholesky. Where that solve's C is
        finite it is this solver's own; where it is not (the factorisation broke down),
        this solver's solve runs its fallback. A top-level fit runs the first try and this
        solver only where it must, so it compiles the fallback (a CG or an LU beside the
        factorisation) only where one is needed. ``self`` where a linear solver is given,
        the solve reads samples (a surface's cascade) or the default has no fallback."""
        # Kept while this solver lives: a warm fit calls with the same solver (its floats
        # converted once) and finds its compiled programs by the first try's identity.
        # (None where it is this solver: an entry holding the solver would keep it alive.)
        tries = _FIRST_TRIES.get(self, lambda _: {})
        if shape not in tries:
            first = self._first_linear_solver(shape)
            tries[shape] = (
                None
                if first is None
                else eqx.tree_at(
                    lambda s: s.linear_solver, self, first, is_leaf=lambda x: x is None
                )
            )
        return self if tries[shape] is None else tries[shape]

    def _first_linear_solver(self, shape: tuple[int, ...]) -> lx.AbstractLinearSolver | None:
        """``first_try``'s linear solver, or None where it is this solver itself."""
        if self.linear_solver is not None or self.needs_samples_to_solve(shape):
            return None
        if _factors_by_lines(shape):
            return BlockCholesky() if float(np.asarray(self.lam)) > 0 else stencil_cg(shape)
        # ``solve_by_default``'s: a factorisation has a fallback, a CG has none to spare.
        first = default_linear_solver(shape)
        return None if _is_matrix_free(first) else first

    def needs_samples_to_solve(self, shape: tuple[int, ...]) -> bool:
        """Whether ``solve_assembled`` reads the problem's samples beyond its normal
        equations (a surface's default solve: the cascade), or ``solve_without_samples``
        serves."""
        large = math.prod(shape) > DENSE_MAX_COEFFICIENTS
        return self.linear_solver is None and len(shape) == 3 and large

    def terminate(self, problem: Problem, state: LeastSquaresState):
        return state.done, self.verdict(state)

    def verdict(self, state: LeastSquaresState) -> RESULTS:
        """The solver's verdict on ``state`` (``terminate``'s), which reads no problem."""
        # A CG that hits its step cap still leaves a usable iterate; other failures do not.
        return RESULTS.where(
            state.result == lx.RESULTS.successful,
            RESULTS.successful,
            RESULTS.where(
                state.result == lx.RESULTS.max_steps_reached,
                RESULTS.max_steps_reached,
                RESULTS.failed,
            ),
        )

    def to_spline(self, problem: Problem, state: LeastSquaresState) -> ImplicitSpline:
        return ImplicitSpline(state.control, state.weights, problem.lower, problem.upper)
