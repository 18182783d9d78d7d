"""Geometric multigrid for stencil systems: the normal equations ``(D^T D + 2 lam L) C = D^T b``.

One code path for grids of any dimension d (2D curves, 3D surfaces): a system is a
``jurs._linalg.stencil.StencilOperator``, a stencil ``grid_shape + (7,) * d``, and
every operation works axis by axis. Design and measurements: ``docs/multigrid.md``.

* **Levels** are the nested coarser grids of ``jurs._linalg.coarsen``: cells twice as
  wide, the exact prolongation by knot insertion, its transpose the restriction.
* **Coarse operators** are Galerkin products ``P^T A P``
  (``jurs._linalg.coarsen.galerkin``): the minimiser over the coarse space of the same
  quadratic energy, so each level's correction is its best possible one in the energy
  norm.
* **Smoother**: Chebyshev polynomials in ``M^-1 A``, M the additive Schwarz operator of
  overlapping box patches, each solved exactly (``jurs._linalg.patches``); the top of
  ``M^-1 A``'s spectrum is bounded a priori by a colouring of the patches (no power
  iterations).
* **Coarsest level**: a dense inverse once it has at most ``coarsest_size`` unknowns.
* **Solver**: conjugate gradients preconditioned by one V-cycle a step, from a full
  multigrid pass, stopped on an estimate of the objective's gap to its minimum.

The hierarchy (coarse operators, patch inverses, coarsest inverse) is the lineax state of
``Multigrid``: ``Multigrid.init`` builds it once (most of a solve's cost), and
``lineax.linear_solve(..., state=...)`` reuses it for further right-hand sides.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jax import Array

from .coarsen import coarsening, galerkin, prolong, restrict
from .patches import (
    DEFAULT_PATCH,
    PATCH_RIDGE,
    PatchLayout,
    add_patches,
    extract_patches,
    patch_inverses,
    patch_layout,
)
from .spd import spd_inverse
from .stencil import StencilOperator, probe_stencil, stencil_matvec, stencil_ndim, stencil_to_dense

#: Default largest level solved by a dense inverse (19 x 19 below 128 x 128, 7^3 in 3D).
DEFAULT_COARSEST_SIZE = 512
#: The Chebyshev smoother damps ``M^-1 A``'s spectrum on ``[upper / CHEBYSHEV_RATIO, upper]``;
#: the rest is the coarse levels' job.
CHEBYSHEV_RATIO = 30.0


def level_shapes(shape: tuple[int, ...], coarsest_size: int = DEFAULT_COARSEST_SIZE) -> list:
    """The grid shapes of the hierarchy, finest first: ``jurs._linalg.coarsen.coarsening``
    until a level has at most ``coarsest_size`` unknowns or no axis shrinks."""
    return coarsening(shape, coarsest_size)


class Level(eqx.Module):
    """One level of the hierarchy: its stencil, its patches and their inverses, and the
    bound ``upper`` on the spectrum of ``M^-1 A`` (M the Schwarz smoother)."""

    stencil: Array
    inverses: Array
    layout: PatchLayout
    upper: float = eqx.field(static=True)

    def matvec(self, x: Array) -> Array:
        return stencil_matvec(self.stencil, x)

    def smooth(self, residual: Array) -> Array:
        """Additive Schwarz: ``sum_p R_p^T B_p^-1 R_p r`` over the overlapping patches (in
        the inverses' dtype)."""
        local = extract_patches(self.layout, residual.astype(self.inverses.dtype))
        solved = jnp.einsum("pab,pb->pa", self.inverses, local)
        return add_patches(self.layout, solved).astype(residual.dtype)


class Hierarchy(eqx.Module):
    """The system's stencil (for the outer CG, in its own dtype), the multigrid levels above
    the coarsest (finest first) and the inverse of the coarsest level's matrix."""

    stencil: Array
    levels: tuple
    coarsest: Array
    coarsest_shape: tuple = eqx.field(static=True)
    degree: int = eqx.field(static=True)

    @property
    def cycle_dtype(self):
        return self.coarsest.dtype


def build_hierarchy(
    stencil: Array,
    *,
    coarsest_size: int = DEFAULT_COARSEST_SIZE,
    degree: int = 2,
    patch: tuple[int, int] | None = None,
    patch_dtype=None,
    cycle_dtype=None,
) -> Hierarchy:
    """The multigrid hierarchy of a symmetric positive definite stencil: Galerkin levels,
    their Schwarz patches' inverses, and the coarsest level's inverse (dense, at most
    ``coarsest_size`` unknowns). All factorisations are computed in the stencil's dtype.

    Args:
        degree: Chebyshev steps before and after each coarse correction.
        patch: ``(side, stride)`` of the Schwarz patches; default ``DEFAULT_PATCH`` for
            the grid's dimension.
        patch_dtype: storage of the patch inverses, the largest arrays of the hierarchy;
            default the stencil's dtype. Float32 halves them and the smoother's memory
            traffic, but is only safe for well-conditioned patches (see
            ``Multigrid``).
        cycle_dtype: dtype of the V-cycle (level stencils, coarsest inverse); default the
            stencil's. The same caveat.
    """
    d = stencil_ndim(stencil)
    side, stride = patch or DEFAULT_PATCH[d]
    cycle_dtype = cycle_dtype or stencil.dtype
    patch_dtype = patch_dtype or stencil.dtype
    shapes = level_shapes(stencil.shape[:d], coarsest_size)
    stencils, layouts = [stencil], [patch_layout(shape, side, stride) for shape in shapes[:-1]]
    for coarse in shapes[1:]:
        stencils.append(galerkin(stencils[-1], coarse))
    inverses = patch_inverses(layouts, stencils[:-1], patch_dtype)
    levels = tuple(
        Level(st.astype(cycle_dtype), inv, lay, float(lay.colours()))
        for st, inv, lay in zip(stencils, inverses, layouts)
    )
    stencil = stencils[-1]
    dense = stencil_to_dense(stencil)
    ridge = PATCH_RIDGE * dense.shape[0] * float(jnp.finfo(dense.dtype).eps)
    coarsest = spd_inverse(dense, ridge).astype(cycle_dtype)
    return Hierarchy(stencils[0], levels, coarsest, shapes[-1], degree)


def _coarsest_solve(hierarchy: Hierarchy, rhs: Array) -> Array:
    return (hierarchy.coarsest @ rhs.ravel()).reshape(hierarchy.coarsest_shape)


def chebyshev(level: Level, rhs: Array, x: Array | None, degree: int) -> Array:
    """``degree`` Chebyshev steps for ``A x = rhs`` in ``M^-1 A`` (M the additive Schwarz
    smoother) on ``[upper / CHEBYSHEV_RATIO, upper]`` (Saad, Iterative Methods, alg.
    12.1). From ``x`` (``None``: zero, saving a product)."""
    upper = level.upper
    lower = upper / CHEBYSHEV_RATIO
    theta, delta = (upper + lower) / 2, (upper - lower) / 2
    sigma = theta / delta
    rho = 1.0 / sigma
    residual = rhs if x is None else rhs - level.matvec(x)
    step = level.smooth(residual) / theta
    x = step if x is None else x + step
    for _ in range(degree - 1):
        residual = residual - level.matvec(step)
        rho_next = 1.0 / (2.0 * sigma - rho)
        step = rho_next * rho * step + (2.0 * rho_next / delta) * level.smooth(residual)
        x = x + step
        rho = rho_next
    return x


def _shape_below(hierarchy: Hierarchy, index: int) -> tuple:
    levels = hierarchy.levels
    if index + 1 < len(levels):
        return levels[index + 1].layout.shape
    return hierarchy.coarsest_shape


def _v_cycle(hierarchy: Hierarchy, rhs: Array, index: int) -> Array:
    if index == len(hierarchy.levels):
        return _coarsest_solve(hierarchy, rhs)
    level = hierarchy.levels[index]
    x = chebyshev(level, rhs, None, hierarchy.degree)
    coarse_rhs = restrict(rhs - level.matvec(x), _shape_below(hierarchy, index))
    x = x + prolong(_v_cycle(hierarchy, coarse_rhs, index + 1), rhs.shape)
    return chebyshev(level, rhs, x, hierarchy.degree)


def v_cycle(hierarchy: Hierarchy, rhs: Array) -> Array:
    """One V-cycle for ``A x = rhs`` from x = 0 (in the hierarchy's cycle dtype): a
    symmetric positive definite approximation of ``A^-1`` (the same smoother before and
    after the correction)."""
    return _v_cycle(hierarchy, rhs.astype(hierarchy.cycle_dtype), 0).astype(rhs.dtype)


def full_multigrid(hierarchy: Hierarchy, rhs: Array) -> Array:
    """Cascadic start: solve the coarsest level exactly, then on each finer level start from
    the prolonged coarser solution and take one V-cycle (about 1.3 V-cycles of work)."""
    right = [rhs.astype(hierarchy.cycle_dtype)]
    for index in range(len(hierarchy.levels)):
        right.append(restrict(right[-1], _shape_below(hierarchy, index)))
    x = _coarsest_solve(hierarchy, right[-1])
    for index in reversed(range(len(hierarchy.levels))):
        level, b = hierarchy.levels[index], right[index]
        x = prolong(x, b.shape)
        x = x + _v_cycle(hierarchy, b - level.matvec(x), index)
    return x.astype(rhs.dtype)


#: CG steps whose objective drops estimate the gap (Strakos & Tichy, BIT 2002): the objective
#: drops by ``alpha_j gamma_j`` at step j, so the last drops bound from below the gap of
#: the iterate that many steps back. ``r . M r`` alone underestimates the gap where ``M A``
#: has small eigenvalues (small lam); two drops came within a small factor of it there and
#: overestimate it only where CG converges fast, which costs a step or two
#: (docs/multigrid.md, "Measurements behind the constants").
ESTIMATE_WINDOW = 2


def preconditioned_cg(
    matvec, precondition, rhs: Array, start: Array, rtol, atol, max_steps: int, target_norm2=None
):
    """Conjugate gradients for ``A x = rhs`` preconditioned by ``precondition`` (~A^-1),
    from ``start``, stopped on the gap of the quadratic objective to its minimum (the
    energy norm of the error ``e . A e``).

    The gap is estimated by the larger of ``r . M r`` (the gap itself for ``M = A^-1``) and
    the sum of the objective's last ``ESTIMATE_WINDOW`` drops. CG stops once the
    estimate is at most ``rtol^2`` times the reference plus ``atol^2``: the reference is
    ``x . A x`` or, given ``target_norm2 = b . b`` of the least-squares problem whose
    normal equations these are, the objective ``b . b - 2 x . rhs + x . A x`` itself. It
    also stops, flagging a breakdown, where ``r . M r`` or ``p . A p`` is not positive and
    finite (an indefinite preconditioner or operator). Returns ``(x, steps, estimate /
    reference, breakdown, converged)``; ``converged`` says the stop test passed (also on
    the last allowed step).
    """
    residual = rhs - matvec(start)
    z = precondition(residual)
    gamma = jnp.vdot(residual, z)
    window = jnp.zeros(ESTIMATE_WINDOW, gamma.dtype)

    def estimate_and_reference(x, residual, gamma, window):
        energy = jnp.vdot(x, rhs) - jnp.vdot(x, residual)  # x . A x, as A x = rhs - r
        reference = energy if target_norm2 is None else target_norm2 - 2 * jnp.vdot(x, rhs) + energy
        return jnp.maximum(gamma, jnp.sum(window)), jnp.maximum(reference, 0.0)

    def keep_going(carry):
        x, residual, _, gamma, window, steps, broken = carry
        estimate, reference = estimate_and_reference(x, residual, gamma, window)
        return (estimate > rtol**2 * reference + atol**2) & (steps < max_steps) & ~broken

    def step(carry):
        x, residual, direction, gamma, window, steps, _ = carry
        product = matvec(direction)
        curvature = jnp.vdot(direction, product)
        alpha = gamma / curvature
        x = x + alpha * direction
        residual = residual - alpha * product
        z = precondition(residual)
        gamma_next = jnp.vdot(residual, z)
        direction = z + (gamma_next / gamma) * direction
        window = jnp.roll(window, 1).at[0].set(alpha * gamma)
        broken = ~(jnp.isfinite(alpha) & (curvature > 0) & (gamma_next >= 0))
        return x, residual, direction, gamma_next, window, steps + 1, broken

    broken = ~(jnp.isfinite(gamma) & (gamma >= 0))
    x, residual, _, gamma, window, steps, broken = jax.lax.while_loop(
        keep_going, step, (start, residual, z, gamma, window, jnp.array(0), broken)
    )
    estimate, reference = estimate_and_reference(x, residual, gamma, window)
    converged = estimate <= rtol**2 * reference + atol**2
    return x, steps, estimate / jnp.where(reference > 0, reference, 1.0), broken, converged


def _grid_structure(operator: lx.AbstractLinearOperator) -> jax.ShapeDtypeStruct:
    structure = operator.in_structure()
    if not isinstance(structure, jax.ShapeDtypeStruct) or structure.ndim not in (2, 3):
        raise ValueError(
            "Multigrid solves operators on a single 2D or 3D grid array, got "
            f"in_structure {structure}"
        )
    if operator.out_structure() != structure:
        raise ValueError("Multigrid needs a square operator (same in and out structure)")
    return structure


class Multigrid(lx.AbstractLinearSolver):
    """Geometric multigrid-preconditioned conjugate gradients for symmetric positive definite
    stencil systems on B-spline coefficient grids (2D or 3D), as a lineax solver.

    The operator must act on one ``grid_shape`` array, couple points at most 3 apart per axis
    (a cubic B-spline normal matrix) and be tagged positive (semi-)definite. A
    ``jurs._linalg.stencil.StencilOperator`` (as LeastSquares passes) gives its stencil
    directly; of any other operator the stencil is probed with ``7^d`` products
    (``jurs._linalg.stencil.probe_stencil``). Coefficients are prolonged by B-spline
    knot insertion and coarse operators are Galerkin products (see the module docstring).
    Differentiable like any lineax solve (implicit differentiation: the adjoint system is
    solved by the same method; the hierarchy carries no gradient).

    ``init`` builds the hierarchy (the expensive part: the patch inverses); pass its result
    as ``lineax.linear_solve(..., state=...)`` to solve further right-hand sides with it.
    ``options["target_norm2"]`` (``b . b`` of the least-squares data) makes ``rtol``
    relative to the objective instead of ``C . A C``; ``options["y0"]`` is the start when
    ``full_multigrid`` is off.

    Args:
        rtol: stop once the estimated gap of the objective ``C.A C - 2 C.rhs (+ b.b)`` to
            its minimum is ``rtol^2`` times ``C.A C`` (or, with ``target_norm2``, times
            the objective). Default 1e-9 (float32 reaches ~1e-4).
        atol: absolute floor of the gap's square root.
        max_steps: CG steps (one V-cycle each) before giving up with ``max_steps_reached``.
        degree: Chebyshev smoothing steps before and after each coarse correction.
        patch: ``(side, stride)`` of the overlapping Schwarz patches; default by dimension
            (``DEFAULT_PATCH``).
        coarsest_size: largest level solved by a dense inverse.
        full_multigrid: start from a full multigrid pass (True) or from ``options["y0"]``
            (else zero).
        patch_dtype: storage of the patch inverses (computed in the system's dtype);
            default the system's. ``jnp.float32`` halves the hierarchy and the smoother's
            memory traffic, but rounds the inverse of an ill-conditioned patch (small lam)
            beyond use: the smoother's spectrum can leave its bound and CG break down
            (docs/multigrid.md, "Float32").
        cycle_dtype: dtype of the V-cycles; default the system's. Float32 (cycle and
            patches) has the same caveat.
    """

    rtol: float = 1e-9
    atol: float = 0.0
    max_steps: int = 200
    degree: int = eqx.field(static=True, default=2)
    patch: tuple | None = eqx.field(static=True, default=None)
    coarsest_size: int = eqx.field(static=True, default=DEFAULT_COARSEST_SIZE)
    full_multigrid: bool = eqx.field(static=True, default=True)
    patch_dtype: Any = eqx.field(static=True, default=None)
    cycle_dtype: Any = eqx.field(static=True, default=None)

    def __check_init__(self):
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and value < 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        if int(self.max_steps) < 1 or int(self.degree) < 1 or int(self.coarsest_size) < 1:
            raise ValueError(
                "max_steps, degree and coarsest_size must be >= 1, got "
                f"{self.max_steps}, {self.degree}, {self.coarsest_size}"
            )
        if self.patch is not None:
            patch_layout((), *self.patch)  # checks side and stride

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]) -> Hierarchy:
        structure = _grid_structure(operator)
        if not lx.is_positive_semidefinite(operator):
            raise ValueError(
                "Multigrid needs an operator tagged "
                "lineax.positive_semidefinite_tag (symmetric positive definite)"
            )
        if isinstance(operator, StencilOperator):
            stencil = operator.stencil
        else:
            stencil = probe_stencil(operator.mv, structure.shape, structure.dtype)
        return build_hierarchy(
            jax.lax.stop_gradient(stencil),
            coarsest_size=self.coarsest_size,
            degree=self.degree,
            patch=self.patch,
            patch_dtype=self.patch_dtype,
            cycle_dtype=self.cycle_dtype,
        )

    def compute(self, state: Hierarchy, vector: Array, options: dict[str, Any]):
        matvec = lambda x: stencil_matvec(state.stencil, x)  # noqa: E731
        if self.full_multigrid:
            start = full_multigrid(state, vector)
        else:
            start = options.get("y0", jnp.zeros_like(vector))
        x, steps, error2, broken, converged = preconditioned_cg(
            matvec,
            lambda r: v_cycle(state, r),
            vector,
            start,
            self.rtol,
            self.atol,
            self.max_steps,
            options.get("target_norm2"),
        )
        result = lx.RESULTS.where(converged, lx.RESULTS.successful, lx.RESULTS.max_steps_reached)
        result = lx.RESULTS.where(broken, lx.RESULTS.breakdown, result)
        return x, result, {"num_steps": steps, "relative_error2": error2}

    def transpose(self, state: Hierarchy, options: dict[str, Any]):
        return state, options  # symmetric

    def conj(self, state: Hierarchy, options: dict[str, Any]):
        return state, options  # real

    def assume_full_rank(self) -> bool:
        return True
