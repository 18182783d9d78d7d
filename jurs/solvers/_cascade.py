"""A cascadic start for the exact solve of surfaces: the same fit on coarser grids first.

Jacobi-preconditioned CG on a 3D normal-equation stencil converges near the data, where
``D^T D`` dominates, but leaves the far field (coefficients that only the regulariser
reaches: inside and around the surface) close to where it started, since the membrane term
``2 lam L`` spreads a correction by a few cells a step and its residual is too small for
CG's stop test to notice. Started from 0, a sphere's centre kept g = 0 exactly and grew a
second surface there. The cure is a start that already has the far field: the same
least-squares problem (same samples, box and lambda) solved on a grid coarse enough for a
dense Cholesky, then on finer grids in turn, each started from the previous one's spline
and corrected by a few CG steps, and the finest level's CG started from there; from that
start CG reaches the exact minimiser's far field (docs/design.md, "Surfaces: the same code
in 3D").

The grids are ``jurs._linalg.coarsen.coarsening``'s, the rule the multigrid's levels
follow too, each spanning the problem's box. A solution reaches the next grid by its
values at that grid's Greville points (``jurs._linalg.coarsen.greville_transfer``): a
quasi-interpolant, accurate to O(h^2), which is all a start needs (the finest level's CG
decides the answer).
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

#: Largest number of coefficients of the coarsest level, solved by dense Cholesky, whose
#: cost grows with the cube of this: 12^3 is a fraction of a second, 16^3 already seconds
#: (docs/multigrid.md, "Measurements behind the constants").
COARSEST_COEFFICIENTS = 1728
#: Axes with fewer basis functions than this keep their size in the cascade (4: every axis
#: that still shrinks under ``jurs._linalg.coarsen.coarse_size``).
MIN_SIDE = 4
#: CG on the intermediate levels: a loose tolerance and a step cap (a start, not a
#: solution).
LEVEL_RTOL = 1e-3
LEVEL_MAX_STEPS = 100
#: Samples a coefficient that a level of the cascade keeps at least: a level with more
#: assembles every ``k``-th sample only (lambda scaled by the fraction kept). The coarse
#: levels' assembly costs per sample, not per coefficient, and is a start only: with every
#: sample, the coarsest levels of a dense cloud take as long to assemble as the finer ones;
#: 8 rather than 32 halved the cascade of 1e6 points and moved the fit by less than the
#: final CG's tolerance (docs/multigrid.md, "Measurements behind the constants").
LEVEL_SAMPLES_PER_COEFFICIENT = 8


def cascade_shapes(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    """The grids of the cascade, coarsest first, ending one level below ``shape``: the
    coarser grids of ``jurs._linalg.coarsen.coarsening`` (cells about twice as wide a
    level; axes below ``MIN_SIDE`` kept), until one has at most
    ``COARSEST_COEFFICIENTS`` coefficients."""
    return coarsening(shape, COARSEST_COEFFICIENTS, MIN_SIDE)[1:][::-1]


def on_grid(problem: Problem, shape: tuple[int, ...], stride: int = 1) -> Problem:
    """``problem`` with the same box on another grid, with every ``stride``-th sample."""
    if stride > 1:
        keep = slice(None, None, stride)
        fields = ("samples", "targets", "mask", "is_data", "sample_index")
        problem = dataclasses.replace(problem, **{k: getattr(problem, k)[keep] for k in fields})
    local = local_basis(problem.samples, problem.lower, problem.upper, shape)
    return dataclasses.replace(problem, local=local, shape=tuple(shape))


def level_stride(problem: Problem, shape: tuple[int, ...]) -> int:
    """The sample stride of the cascade's level ``shape``: at least
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


def cascadic_start(problem: Problem, lam, solve, start: Array) -> Array:
    """A start for the exact solve of ``problem`` on its grid: the solves of
    ``cascade_shapes``' grids in turn, each transferred to the next; ``start`` itself
    where the grid is already coarse enough to have no cascade. ``solve(system, rhs,
    start, linear_solver)`` solves one level's regularised normal equations, a lineax
    operator (as ``jurs.solvers._least_squares.solve_normal_equations``). No gradient
    flows through the start (it changes the path of the final solve, not its solution)."""
    shapes = cascade_shapes(problem.shape)
    if not shapes:
        return start
    problem, lam = jax.lax.stop_gradient((problem, lam))
    start = None  # pyright: ignore[reportAssignmentType]  # the iterate: none before the coarsest
    samples = jnp.maximum(jnp.sum(problem.mask), 1.0)
    for shape in shapes:
        level = on_grid(problem, shape, level_stride(problem, shape))
        normal = normal_equations(level)
        # E_d sums the kept samples only: lambda scaled alike keeps the balance.
        kept = jnp.sum(level.mask) / samples
        system = normal.regularised(level_lam(lam, problem.shape, shape) * kept)
        if start is None:
            start, solver = jnp.zeros(shape, normal.rhs.dtype), lx.Cholesky()
        else:
            start = greville_transfer(start, shape)
            # Absolute per-entry tolerance: see surface_linear_solver (an array atol).
            solver = lx.CG(
                rtol=0.0,
                atol=LEVEL_RTOL * jnp.max(jnp.abs(normal.rhs)),  # pyright: ignore[reportArgumentType]
                max_steps=LEVEL_MAX_STEPS,
            )
        start = solve(system, normal.rhs, start, solver)
    return greville_transfer(start, problem.shape)
