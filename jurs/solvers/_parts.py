"""[`jurs.LeastSquares`][] run on a cloud taken in parts of a fixed size, so that what it
compiles depends on the grid only, never on the number of points.

[`jurs.solve`][] compiles one program over the whole problem, whose sample arrays are
part of every compiled shape: a cloud in a new octave of points compiled the whole fit
again, seconds for a fit that runs in a tenth of one (docs/performance.md, "A new
cloud's first fit"). The exact solve needs the samples only through sums: the normal
equations are a sum over the samples, and so are the metrics and the offset-sign check.
``solve_in_parts`` therefore runs four compiled programs:

1. ``_assembled_part``: the normal equations of ``part_points`` points (their three
   samples each), added to the running total; compiled per grid;
2. ``_solved``: the solve of the summed equations; per grid and solver. The linear
   solve that the solver runs first runs alone (``LeastSquares.first_try``): the
   fallback where a factorisation breaks down compiles only where one did;
3. ``_measured_part``: the sums of [`jurs.internal.metrics`][] and of the offset-sign
   check over a part, for the solved spline; per grid;
4. ``_concluded``: the verdict and the [`jurs.Solution`][] from the sums; per grid.

A cloud that is one part of ``SMALL_PART_POINTS`` points runs the four in one program
(``_solved_small``): there each program's dispatch costs about what its work does.

The parts are the problem's own points, three samples each, in one sample a slot; the
solution equals ``solve(LeastSquares(...), problem)``'s to rounding (the sums run in
another order). [`jurs.fit`][] takes this path at top level where it applies
(``solves_in_parts``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._jit import FlatJit
from .._kept import KeptByIdentity
from .._linalg.normal import NormalEquations, bernstein_moments, moments_to_stencil
from .._model.basis import num_cells
from .._model.spline import ImplicitSpline, bspline_values
from .._problem.energy import metrics_from_sums, regulariser, residual_sums
from .._problem.problem import Problem, build_problem
from .._solution.solution import Solution
from .._solution.verdicts import sign_check_stride, sign_counts
from ._base import run_first_try
from ._driver import Carry, concluded
from ._least_squares import LeastSquares, LeastSquaresState, singular_solve

#: Points in a part: every compiled part has this many, the last one padded with masked
#: copies. Large enough that a large cloud's parts are few calls, small enough that a
#: cloud of a few thousand points pads little.
PART_POINTS = 1 << 11
#: The one part of a cloud of at most this many (padded) points: a cloud of a hundred
#: points padded to ``PART_POINTS`` would cost its fit several times its own work. A
#: second size compiles the two per-part programs once more a grid, not the solve; kept
#: to the smallest clouds, whose grids are small, so that clouds from a few hundred
#: points up share one size.
SMALL_PART_POINTS = 1 << 7


def part_points(num_points: int) -> int:
    """The points of each part of a cloud of ``num_points`` (padded) points."""
    return SMALL_PART_POINTS if num_points <= SMALL_PART_POINTS else PART_POINTS


#: The largest (padded) cloud solved in parts. Above it the whole compiled problem's
#: layout (buckets of samples sharing a cell and their coefficients) evaluates the
#: spline faster than parts of one sample a slot can, and its compilation is a smaller
#: share of the fit (measured: docs/performance.md, "A new cloud's first fit").
PARTS_MAX_POINTS = 1 << 16


def solves_in_parts(num_points: int, shape: tuple[int, ...], solver, init) -> bool:
    """Whether ``solve_in_parts`` serves the solve of ``num_points`` points (padded, or
    not: ``PARTS_MAX_POINTS`` is a padded size) on the grid ``shape``:
    [`jurs.LeastSquares`][] with the B-spline (``keep_weights`` False) from the default
    start, on a cloud of at most ``PARTS_MAX_POINTS`` points, on a curve or a surface whose
    solve reads no samples beyond the normal equations
    (``LeastSquares.needs_samples_to_solve``)."""
    return (
        num_points <= PARTS_MAX_POINTS
        and type(solver) is LeastSquares
        and not solver.keep_weights
        and init is None
        # Through the class: a method read off a Module instance is wrapped in a new
        # Module each time (equinox's bound methods), a cost a warm small fit notices.
        and not LeastSquares.needs_samples_to_solve(solver, shape)
    )


#: The parts of the problems solved lately (``_parts``): a fit repeated on a kept problem
#: (``jurs.fit``'s kept clouds) reuses them on the device.
_KEPT_PARTS = KeptByIdentity()


def _parts(problem: Problem) -> list[tuple[Array, ...]] | None:
    """``(points, normals, mask)`` of each part, ``part_points`` rows each, on the device;
    None where a point's three samples do not share one mask (then the problem is solved
    whole)."""
    return _KEPT_PARTS.get(problem, _split)


def _split(problem: Problem) -> list[tuple[Array, ...]] | None:
    """``_parts``, made."""
    m = problem.num_points
    mask, index = np.asarray(problem.mask), np.asarray(problem.sample_index)
    real = mask > 0
    by_kind = np.zeros((3, m), mask.dtype)
    by_kind[index[real] // m, index[real] % m] = mask[real]
    if not (np.array_equal(by_kind[0], by_kind[1]) and np.array_equal(by_kind[0], by_kind[2])):
        return None
    points, normals = np.asarray(problem.points), np.asarray(problem.normals)
    size = part_points(m)
    pad = -m % size
    points = np.pad(points, ((0, pad), (0, 0)), mode="edge")
    normals = np.pad(normals, ((0, pad), (0, 0)), mode="edge")
    point_mask = np.pad(by_kind[0], (0, pad))
    parts = [
        (points[i : i + size], normals[i : i + size], point_mask[i : i + size])
        for i in range(0, m + pad, size)
    ]
    return jax.device_put(parts)


def _part_problem(points, normals, mask, offset, eps, lower, upper, shape) -> Problem:
    """The problem of one part: its points' samples, one a slot, in the whole cloud's box."""
    return build_problem(
        points, normals, shape, offset, eps, (lower, upper), mask=mask, bucket_size=1
    )


def _assembled_part(
    total: tuple[Array, Array], points, normals, mask, offset, eps, lower, upper, shape, chunk_size
) -> tuple[Array, Array]:
    """``total`` plus one part's per-cell Bernstein moments and sum of squared targets:
    sums that the normal equations are folded from once (``moments_to_stencil``)."""
    part = _part_problem(points, normals, mask, offset, eps, lower, upper, shape)
    target = part.mask * part.targets
    moments = bernstein_moments(part, chunk_size)
    return total[0] + moments, total[1] + jnp.sum(target * target)


_assembled_part_jit = jax.jit(_assembled_part, static_argnums=(8, 9))


def _solved(solver: LeastSquares, moments: Array, target_norm2: Array, shape: tuple[int, ...]):
    """``(C, lineax result, D's column sums)``: ``LeastSquares.minimise`` from the summed
    moments."""
    stencil, rhs = moments_to_stencil(moments, shape)
    normal = NormalEquations(stencil=stencil, rhs=rhs, target_norm2=target_norm2)
    start = jnp.zeros(shape, rhs.dtype)
    control, result = solver.solve_without_samples(normal, solver.lam, start)
    # D's column sums (eq. 25's norm, w = 1): D 1 = 1, the partition of unity, so
    # D^T 1 = D^T D 1, read off the stencil instead of a pass over the samples.
    column_sums = normal.matvec(jnp.ones_like(control))
    return control, singular_solve(normal, solver.lam, control, result), column_sums


_solved_jit = FlatJit(_solved)


def _measured_part(
    total: dict, control, points, normals, mask, offset, eps, lower, upper, stride, first, shape
) -> dict:
    """``total`` plus the metrics' sums and the offset-sign counts of one part."""
    part = _part_problem(points, normals, mask, offset, eps, lower, upper, shape)
    # The B-spline's residuals in one evaluation: W = 1 (the partition of unity).
    r = part.mask * (bspline_values(part.local, control) - part.targets)
    sums = residual_sums(part, r)
    wrong, counted = sign_counts(part, r, stride, first, in_order=True)
    sums = dict(sums, wrong=wrong.astype(control.dtype), counted=counted.astype(control.dtype))
    return {
        key: jnp.maximum(total[key], value) if key == "E_max" else total[key] + value
        for key, value in sums.items()
    }


_measured_part_jit = jax.jit(_measured_part, static_argnums=11)


def _concluded(solver: LeastSquares, control, linear_result, start_energy, sums, lower, upper):
    """The [`jurs.Solution`][] of the one step of [`jurs.LeastSquares`][], as
    [`jurs.solve`][] concludes it, from the parts' sums."""
    weights = jnp.ones_like(control)
    state = LeastSquaresState(control, weights, jnp.array(True), linear_result)
    lam = solver.fitted_lam(state)
    metrics = metrics_from_sums(sums, regulariser(control), lam)
    energy = metrics["E"]
    carry = Carry(
        step=jnp.array(1),
        state=state,
        energy=energy,
        nonfinite=~jnp.isfinite(energy),
        history=jnp.stack([start_energy, energy]),
        stopped=jnp.array(True),
    )
    disagreement = sums["wrong"] / jnp.maximum(sums["counted"], 1)
    fitted = ImplicitSpline(control, weights, lower, upper)
    return concluded(carry, solver.verdict(state), fitted, lam, metrics, disagreement, False)


_concluded_jit = FlatJit(_concluded)

#: The sums that ``_measured_part`` adds up over the parts.
_SUMS = ("E_d", "on_data2", "count", "E_max", "wrong", "counted")


def _solved_small(
    solver: LeastSquares, points, normals, mask, offset, eps, lower, upper, stride, shape
) -> Solution:
    """The four programs in one, for a cloud that is one part of ``SMALL_PART_POINTS``
    points: a small fit's compiled work is as short as the dispatch of each program, so
    one call instead of four is what its host work comes to."""
    dtype = points.dtype
    channels = 7 ** len(shape) + 4 ** len(shape)
    total = jnp.zeros((num_cells(shape), channels), dtype), jnp.zeros((), dtype)
    part = points, normals, mask, offset, eps, lower, upper
    moments, target_norm2 = _assembled_part(total, *part, shape, solver.chunk_size)
    control, linear_result, column_sums = _solved(solver, moments, target_norm2, shape)
    sums = {key: jnp.zeros((), dtype) for key in _SUMS}
    sums = _measured_part(sums, control, *part, stride, jnp.int32(0), shape)
    sums["column_sums"] = column_sums
    return _concluded(solver, control, linear_result, target_norm2, sums, lower, upper)


_solved_small_jit = FlatJit(_solved_small)


def _jitted(fn, jitted, *args):
    """``jitted(*args)``: the default way ``solve_in_parts`` calls each program."""
    del fn
    return jitted(*args)


def solve_in_parts(problem: Problem, solver: LeastSquares, call=_jitted) -> Solution | None:
    """``solve(solver, problem, throw=False)`` for a concrete ``problem`` where
    ``solves_in_parts`` says so, run in parts (see the module's docstring); None where
    it cannot be (a point's samples with masks of their own, or a solve that ends
    non-finite, which [`jurs.solve`][] keeps at its start: the caller then solves whole).

    ``call(fn, jitted, *args)`` runs each program: ``jitted(*args)`` by default, or a
    stored export of ``fn`` (``jurs._fit.compile.call_stored``)."""
    parts = _parts(problem)
    if parts is None:
        return None
    shape = problem.shape
    box = (problem.offset, problem.eps, problem.lower, problem.upper)
    stride = np.int32(sign_check_stride(problem.num_points))
    if len(parts) == 1 and len(parts[0][0]) == SMALL_PART_POINTS:
        args = (*parts[0], *box, stride, shape)
        solution = run_first_try(
            lambda s: call(_solved_small, _solved_small_jit, s, *args),
            solver,
            shape,
            lambda solved: not _finite(solved.spline.control),
        )
    else:
        solution = _solved_over_parts(problem, solver, parts, box, stride, call)
    return solution if _finite(solution.metrics["E"]) else None


def _finite(values) -> bool:
    return bool(np.all(np.isfinite(np.asarray(values))))


def _solved_over_parts(problem: Problem, solver: LeastSquares, parts, box, stride, call):
    """``solve_in_parts``' solution from its four programs, each part summed in turn."""
    shape = problem.shape
    zeros = functools.partial(np.zeros, dtype=problem.samples.dtype)
    channels = 7 ** len(shape) + 4 ** len(shape)
    total = zeros((num_cells(shape), channels)), zeros(())
    for part in parts:
        args = (total, *part, *box, shape, solver.chunk_size)
        total = call(_assembled_part, _assembled_part_jit, *args)
    moments, target_norm2 = total
    # The linear solve that the solver runs first, alone (``LeastSquares.first_try``):
    # its fallback is compiled and run only where that solve's C is not finite.
    control, linear_result, column_sums = run_first_try(
        lambda s: call(_solved, _solved_jit, s, moments, target_norm2, shape),
        solver,
        shape,
        lambda solved: not _finite(solved[0]),
    )
    sums = {key: zeros(()) for key in _SUMS}
    for k, part in enumerate(parts):
        args = (sums, control, *part, *box, stride, np.int32(k * len(part[0])), shape)
        sums = call(_measured_part, _measured_part_jit, *args)
    sums["column_sums"] = column_sums
    # E at C = 0, the start's: the targets' sum of squares.
    args = (solver, control, linear_result, target_norm2, sums, problem.lower, problem.upper)
    return call(_concluded, _concluded_jit, *args)
