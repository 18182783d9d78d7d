"""``jurs.fit``: points and normals in, a fitted implicit spline out."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._problem import DEFAULT_MARGIN, make_problem, normalise_grid
from ._solution import Solution
from ._spline import ImplicitSpline
from .solvers import AbstractSolver, IURS, solve


def _as_arrays(tree, dtype):
    """Python floats -> 0-d arrays, so new hyperparameter values do not recompile."""
    return jax.tree_util.tree_map(
        lambda x: jnp.asarray(x, dtype) if isinstance(x, float) else x, tree
    )


@eqx.filter_jit
def _solve(problem, solver, init, throw):
    return solve(solver, problem, init, throw=throw)


def fit(
    points,
    normals,
    *,
    grid=(9, 9),
    solver: AbstractSolver | None = None,
    offset=0.1,
    eps=0.01,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    init: ImplicitSpline | None = None,
    mask=None,
    bucket_size: int | None = None,
    throw: bool = True,
) -> Solution:
    """Fit an implicit spline whose zero set passes through ``points``.

    Args:
        points: ``(m, 2)`` data points.
        normals: ``(m, 2)`` outward normals (normalised here).
        grid: ``N`` or ``(N, M)`` basis functions along x and y (>= 4). Default: the
            paper's Example 1 grid, 9 x 9.
        solver: any jurs solver; default ``IURS()`` (Algorithm 1, tau = 1e-2, lam = 0).
        offset: d, distance of the offset samples (eq. 4); default 0.1 as in the paper.
        eps: target value at the offsets (eq. 5); default 0.01 as in the paper.
        domain: ``((x_min, y_min), (x_max, y_max))`` or None for the samples' bounding box
            plus ``margin`` x its longest side.
        init: starting spline on the same box and grid; default C = 0, w = 1.
        mask: optional ``(m,)`` booleans, False marking padding points that take no part
            (for ``jax.vmap`` over clouds padded to one size).
        bucket_size: sample layout, see :func:`jurs.make_problem` (None chooses).
        throw: raise if the energy becomes NaN/Inf (the last finite iterate is kept either
            way; ``sol.result`` says what happened).

    Returns:
        :class:`jurs.Solution`. Jit-compiled inside; traceable, so ``jax.grad`` and
        ``jax.vmap`` go through it (input checks run only on concrete inputs).
    """
    shape = normalise_grid(grid)
    solver = IURS() if solver is None else solver
    if not isinstance(solver, AbstractSolver):
        raise TypeError(f"solver must be a jurs solver, got {type(solver).__name__}")
    dtype = jnp.result_type(float)
    if init is not None and tuple(init.shape) != shape:
        raise ValueError(f"init spline has grid {init.shape}, expected {shape}")
    # The problem is built outside the solver's jit: its sample layout is chosen on the
    # host from concrete data (see make_problem); under a caller's jit/grad/vmap it is traced.
    problem = make_problem(points, normals, grid=shape, offset=offset, eps=eps, domain=domain,
                           margin=margin, mask=mask, bucket_size=bucket_size, dtype=dtype)
    return _solve(problem, _as_arrays(solver, dtype), init, throw)
