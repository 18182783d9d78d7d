"""A cascadic start for the exact solve of surfaces: the same fit on a coarse grid first.

Jacobi-preconditioned CG on a 3D normal-equation stencil converges near the data, where
``D^T D`` dominates, but leaves the far field (coefficients that only the regulariser
reaches: inside and around the surface) close to where it started, since the membrane term
``2 lam L`` spreads a correction by a few cells a step and its residual is too small for
CG's stop test to notice. Started from 0, a sphere's centre kept g = 0 exactly and grew a
second surface there. The cure is a start that already has the far field: the same
least-squares problem (same samples, box and lambda) solved exactly on a grid coarse
enough for a dense Cholesky, and the final CG started from that spline (docs/design.md,
"Surfaces: the same code in 3D"). The far field is smooth, so the coarse grid carries it;
the data's detail is what the final CG resolves, where it converges well. Passing through
the grids between, each corrected by a few CG steps, gave the same fits to the final
CG's tolerance for twice the compilation (docs/multigrid.md, "Cascade").

The coarse grid is the last of ``jurs._linalg.coarsen.coarsening``, the rule the
multigrid's levels follow too, and spans the problem's box. Its solution reaches the
problem's grid by its values at that grid's Greville points
(``jurs._linalg.coarsen.greville_transfer``): a quasi-interpolant, accurate to O(h^2),
which is all a start needs (the final CG decides the answer).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array

from .._linalg.coarsen import coarsening, greville_transfer
from .._linalg.normal import normal_equations
from .._model.spline import local_basis
from .._problem.problem import Problem

#: Largest number of coefficients of the coarse grid, solved by dense Cholesky, whose
#: cost grows with the cube of this: 12^3 is a fraction of a second, 16^3 already seconds
#: (docs/multigrid.md, "Measurements behind the constants").
COARSEST_COEFFICIENTS = 1728
#: Axes with fewer basis functions than this keep their size on the coarse grid (4: every
#: axis that still shrinks under ``jurs._linalg.coarsen.coarse_size``).
MIN_SIDE = 4
#: Samples a coefficient that the coarse grid keeps at least: a cloud with more
#: assembles every ``k``-th sample only (lambda scaled by the fraction kept). The coarse
#: assembly costs per sample, not per coefficient, and is a start only: with every
#: sample, a dense cloud's coarse grid takes as long to assemble as a fine one;
#: 8 rather than 32 moved the fit by less than the final CG's tolerance
#: (docs/multigrid.md, "Measurements behind the constants").
LEVEL_SAMPLES_PER_COEFFICIENT = 8


def coarse_grid(shape: tuple[int, ...]) -> tuple[int, ...] | None:
    """The grid of the cascadic start of a solve on ``shape``: the coarsest of
    ``jurs._linalg.coarsen.coarsening`` (cells about twice as wide a level; axes below
    ``MIN_SIDE`` kept), the first with at most ``COARSEST_COEFFICIENTS`` coefficients;
    None where ``shape`` is itself that coarse."""
    shapes = coarsening(shape, COARSEST_COEFFICIENTS, MIN_SIDE)
    return shapes[-1] if len(shapes) > 1 else None


def on_grid(problem: Problem, shape: tuple[int, ...], stride: int = 1) -> Problem:
    """``problem`` with the same box on another grid, with every ``stride``-th sample."""
    if stride > 1:
        keep = slice(None, None, stride)
        fields = ("samples", "targets", "mask", "is_data", "sample_index")
        problem = dataclasses.replace(problem, **{k: getattr(problem, k)[keep] for k in fields})
    local = local_basis(problem.samples, problem.lower, problem.upper, shape)
    return dataclasses.replace(problem, local=local, shape=tuple(shape))


def level_stride(problem: Problem, shape: tuple[int, ...]) -> int:
    """The sample stride of the coarse grid ``shape``: at least
    ``LEVEL_SAMPLES_PER_COEFFICIENT`` samples a coefficient kept. 1 on a problem split
    over devices (a strided slice of its samples would move them between devices)."""
    if problem.local.parts > 1:
        return 1
    per_level = LEVEL_SAMPLES_PER_COEFFICIENT * int(np.prod(shape))
    return max(1, problem.samples.shape[0] // per_level)


def level_lam(lam, fine: tuple[int, ...], coarse: tuple[int, ...]):
    """The lambda that weighs the regulariser on the ``coarse`` grid as ``lam`` does on the
    ``fine`` one: R of a fixed g grows as ``h^(2 - d)``
    (``jurs._fit.settings.scale_free_lam``)."""
    ratio = (fine[0] - 3) / (coarse[0] - 3)  # h_coarse / h_fine
    return lam * ratio ** (len(fine) - 2)


def coarse_system(problem: Problem, lam):
    """``(level, normal, system)`` of the cascade's coarse grid (``coarse_grid``), or None
    where the problem's grid is already that coarse: ``level`` the problem on that grid
    with every ``level_stride``-th sample, ``normal`` its
    [`jurs.internal.NormalEquations`][] and ``system`` the regularised operator, whose
    lambda weighs the regulariser as ``lam`` does on the problem's grid
    (``level_lam``), scaled by the fraction of samples kept (E_d sums those only)."""
    shape = coarse_grid(problem.shape)
    if shape is None:
        return None
    level = on_grid(problem, shape, level_stride(problem, shape))
    normal = normal_equations(level)
    kept = jnp.sum(level.mask) / jnp.maximum(jnp.sum(problem.mask), 1.0)
    return level, normal, normal.regularised(level_lam(lam, problem.shape, shape) * kept)


def cascadic_start(problem: Problem, lam, solve, start: Array) -> Array:
    """A start for the exact solve of ``problem`` on its grid: the same fit solved by dense
    Cholesky on ``coarse_grid``'s grid and transferred to the problem's; ``start``
    itself where the grid is already that coarse, or where the coarse Cholesky breaks down
    (a system singular at rounding level: ``lam = 0`` on sparse data, where no start
    carries a far field the data leave undetermined). ``solve(system, rhs, start,
    linear_solver)`` solves the coarse regularised normal equations, a lineax operator (as
    ``jurs.solvers._least_squares.solve_normal_equations``). No gradient flows through
    the start (it changes the path of the final solve, not its solution)."""
    problem, lam = jax.lax.stop_gradient((problem, lam))
    coarse = coarse_system(problem, lam)
    if coarse is None:
        return start
    level, normal, system = coarse
    solved = solve(system, normal.rhs, jnp.zeros(level.shape, normal.rhs.dtype), lx.Cholesky())
    return transferred_start(solved, problem.shape, start)


def transferred_start(solved: Array, shape: tuple[int, ...], start: Array) -> Array:
    """The coarse grid's ``solved`` coefficients transferred to the grid ``shape``
    (``greville_transfer``), or ``start`` where they are not all finite (the coarse
    Cholesky broke down). The start decides the final CG's path, not its answer: a
    breakdown keeps ``start`` rather than compiling a second factorisation (an LU) for a
    case no default fit meets."""
    return jnp.where(jnp.all(jnp.isfinite(solved)), greville_transfer(solved, shape), start)
