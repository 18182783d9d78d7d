"""Geometric multigrid for stencil systems: the normal equations ``(D^T D + 2 lam L) C = D^T b``.

One code path for grids of any dimension d (2D curves, 3D surfaces): a stencil is an array
``grid_shape + (7,) * d`` (:mod:`jurs._normal`), and every operation here (transfer, coarse
operators, smoothing, coarsest solve) works axis by axis. Design and measurements:
``docs/multigrid.md``.

* **Transfer.** The cubic B-spline space of ``n`` functions on a box (``n - 3`` cells) holds
  the space of ``n // 2 + 2`` functions with cells twice as wide (knot insertion), and the
  subdivision mask ``(1, 4, 6, 4, 1) / 8`` writes coarse function ``I`` in the fine ones:
  ``B^c_I = sum_a mask[a] B_{2I - 3 + a}``. That matrix P is the exact prolongation, its
  transpose the restriction. With an odd number of fine cells the coarse box reaches one
  fine cell past the fine one: its splines, restricted to the fine box, are still fine
  splines, and no coarse function vanishes there, so P keeps full column rank; every axis
  coarsens whatever its parity.
* **Coarse operators** are Galerkin products ``P^T A P``, one axis at a time (P is a tensor
  product): the minimiser over the coarse space of the same quadratic energy, so each
  level's correction is its best possible one in the energy norm.
* **Smoother**: Chebyshev polynomials in ``M^-1 A``, M an additive Schwarz operator of
  overlapping patches (cubes of ``patch_size`` points per axis, each solved exactly): point
  smoothers (Jacobi) leave the data term's local near-null modes (splines small on the
  samples but not smooth) to neither the smoother nor the coarse grid. Symmetric, so the
  V-cycle is a symmetric positive definite preconditioner.
* **Coarsest level**: dense Cholesky once it has at most ``coarsest_size`` unknowns.
* **Solver**: conjugate gradients preconditioned by one V-cycle a step, started from a full
  multigrid pass (each level starts from the prolonged solution of the level below and
  takes one V-cycle), stopped on the energy norm of the error estimated by ``r . M r``.
"""

from __future__ import annotations

import itertools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import lineax as lx
import numpy as np
from jax import Array

from ._normal import HALF, SIDE, stencil_diagonal, stencil_matvec, stencil_ndim, stencil_to_dense

#: Uniform cubic B-spline subdivision mask: coarse function ``I`` is ``sum_a MASK[a]`` times
#: fine function ``2 I - 3 + a``.
MASK = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 8.0
#: Axes with fewer basis functions than this are not coarsened (4 -> 4 would not shrink).
MIN_COARSEN_SIDE = 8
#: Default largest level solved by dense Cholesky.
DEFAULT_COARSEST_SIZE = 512
#: The Chebyshev smoother damps ``M^-1 A``'s spectrum on ``[upper / CHEBYSHEV_RATIO, upper]``;
#: the rest is the coarse levels' job.
CHEBYSHEV_RATIO = 30.0
#: Points per axis of the smoother's patches (they overlap by half). Patches of 6 and 8 cut
#: the CG steps at lam = 1e-8 on Example 1 (64 x 64, 2e4 points) from 300+ (point Jacobi,
#: patches of 4) to 80 and 50: the data's near-null modes are local but span several cells.
DEFAULT_PATCH_SIZE = 8
#: Ridge of each patch block, relative to its largest diagonal entry, in units of the
#: dtype's epsilon (2e-15 in float64). On Example 1 at 30 x 30, lam = 1e-14, a ridge of
#: 1e-12 (above 2 lam) took 203 CG steps to a 1e-8 energy reduction, 2e-15 took 28.
PATCH_RIDGE = 10.0
#: Power iterations estimating the top of ``M^-1 A``'s spectrum, and the factor put on the
#: estimate.
POWER_STEPS = 15
POWER_SAFETY = 1.2


def coarse_size(n: int) -> int:
    """Basis functions along an axis after one coarsening: ``n // 2 + 2`` (cells
    ``ceil((n - 3) / 2)``), or ``n`` for axes below :data:`MIN_COARSEN_SIDE`."""
    return n // 2 + 2 if n >= MIN_COARSEN_SIDE else n


def level_shapes(shape: tuple[int, ...], coarsest_size: int = DEFAULT_COARSEST_SIZE) -> list:
    """The grid shapes of the hierarchy, finest first: coarsen until a level has at most
    ``coarsest_size`` unknowns or no axis shrinks."""
    shapes = [tuple(int(n) for n in shape)]
    while np.prod(shapes[-1]) > coarsest_size:
        coarse = tuple(coarse_size(n) for n in shapes[-1])
        if coarse == shapes[-1]:
            break
        shapes.append(coarse)
    return shapes


def _fine_windows(x: Array, axis: int, n_coarse: int) -> list:
    """The five arrays ``x[2 I - 3 + a]`` along ``axis`` (``a = 0..4``, ``I < n_coarse``), zero
    where the fine index is off the grid."""
    pad = [(0, 0)] * x.ndim
    pad[axis] = (3, 4)
    padded = jnp.pad(x, pad)
    return [jax.lax.slice_in_dim(padded, a, a + 2 * n_coarse - 1, stride=2, axis=axis)
            for a in range(MASK.size)]


def restrict(grid: Array, coarse_shape: tuple[int, ...]) -> Array:
    """``P^T grid``: the fine residual's moments against the coarse basis functions."""
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse != grid.shape[axis]:
            windows = _fine_windows(grid, axis, n_coarse)
            grid = sum(float(w) * x for w, x in zip(MASK, windows))
    return grid


def prolong(coarse: Array, fine_shape: tuple[int, ...]) -> Array:
    """``P coarse``: the coarse spline's coefficients in the fine basis (knot insertion);
    the transpose of :func:`restrict`."""
    fine = jax.ShapeDtypeStruct(tuple(fine_shape), coarse.dtype)
    (out,) = jax.linear_transpose(lambda g: restrict(g, coarse.shape), fine)(coarse)
    return out


def _galerkin_weights() -> np.ndarray:
    """``W[a, e, D] = MASK[a] MASK[a + (e - 3) - 2 (D - 3)]`` (0 off the mask): coarse
    ``A_c[I, I + D - 3]`` sums ``W[a, e, D] A[2 I - 3 + a, e]`` over the fine row's window
    ``a`` and stencil offset ``e``."""
    out = np.zeros((MASK.size, SIDE, SIDE))
    for a, e, d in itertools.product(range(MASK.size), range(SIDE), range(SIDE)):
        k = a + (e - HALF) - 2 * (d - HALF)
        if 0 <= k < MASK.size:
            out[a, e, d] = MASK[a] * MASK[k]
    return out


def galerkin(stencil: Array, coarse_shape: tuple[int, ...]) -> Array:
    """The stencil of ``P^T A P`` on ``coarse_shape`` (one axis at a time; P is a tensor
    product). Coarse functions couple within 3 of each other, as fine ones do."""
    d = stencil_ndim(stencil)
    weights = _galerkin_weights()
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse == stencil.shape[axis]:
            continue
        windows = _fine_windows(stencil, axis, n_coarse)
        w = jnp.asarray(weights, stencil.dtype)
        out = sum(jnp.tensordot(x, w[a], axes=[[d + axis], [0]]) for a, x in enumerate(windows))
        out = jnp.moveaxis(out, -1, d + axis)
        # Entries towards coarse functions off the grid: zero (they are, up to rounding).
        index = np.arange(n_coarse)[:, None] + np.arange(SIDE)[None, :] - HALF
        valid = (index >= 0) & (index < n_coarse)
        shape = [1] * out.ndim
        shape[axis], shape[d + axis] = n_coarse, SIDE
        stencil = jnp.where(jnp.asarray(valid.reshape(shape)), out, 0.0)
    return stencil


def probe_stencil(matvec, shape: tuple[int, ...], dtype) -> Array:
    """The stencil of a linear map on a grid that couples points at most 3 apart along
    every axis, from ``7^d`` products with colour-class indicators: point ``q`` is in class
    ``q mod 7``, and ``(A v_c)[p]`` is the one entry ``A[p, q]`` with ``q`` in class c."""
    d = len(shape)
    index = np.indices(shape)
    classes = list(itertools.product(range(SIDE), repeat=d))
    probes = np.stack([np.all([index[k] % SIDE == c[k] for k in range(d)], axis=0)
                       for c in classes]).astype(dtype)
    products = jax.lax.map(matvec, jnp.asarray(probes))  # (7^d,) + shape
    entries = []
    for offset in itertools.product(range(SIDE), repeat=d):
        target = [(index[k] + offset[k] - HALF) % SIDE for k in range(d)]
        which = np.ravel_multi_index(target, (SIDE,) * d)
        entries.append(jnp.take_along_axis(products, jnp.asarray(which)[None], axis=0)[0])
    return jnp.stack(entries, axis=-1).reshape(tuple(shape) + (SIDE,) * d)


def _patch_starts(n: int, size: int) -> np.ndarray:
    """First indices of the patches along an axis: every ``size // 2``, the last one flush
    with the end (so every point lies in one or two patches)."""
    if n <= size:
        return np.array([0])
    starts = np.arange(0, n - size + 1, size // 2)
    return starts if starts[-1] == n - size else np.append(starts, n - size)


def patch_indices(shape: tuple[int, ...], size: int) -> np.ndarray:
    """Flat grid indices of the points of every patch, ``(patches, size^d)`` (NumPy): cubes
    of ``min(size, n)`` points per axis, overlapping by half."""
    d = len(shape)
    sides = [min(size, n) for n in shape]
    local = np.array(list(itertools.product(*[range(k) for k in sides])))
    corners = np.array(list(itertools.product(*[_patch_starts(n, size) for n in shape])))
    points = corners[:, None, :] + local[None]
    return np.ravel_multi_index(tuple(points[..., k] for k in range(d)), shape)


def patch_inverses(stencil: Array, patches: np.ndarray) -> Array:
    """``A_p^-1`` of every patch's principal submatrix, ``(patches, k, k)``. Each block gets a
    ridge of ``PATCH_RIDGE`` epsilons times its largest diagonal: with lam -> 0 a block on
    sparse data is singular to working precision, and an inverse at rounding level would
    make the smoother indefinite; a larger ridge would hide the regulariser itself."""
    d = stencil_ndim(stencil)
    shape = stencil.shape[:d]
    points = np.stack(np.unravel_index(patches[0], shape), axis=-1)
    step = points[None, :, :] - points[:, None, :]  # [a, b]: from point a to point b
    near = np.all(np.abs(step) <= HALF, axis=-1)
    offset = np.ravel_multi_index(tuple(np.clip(step[..., k], -HALF, HALF) + HALF
                                        for k in range(d)), (SIDE,) * d)
    rows = stencil.reshape(-1, SIDE**d)[jnp.asarray(patches)]  # (patches, k, 7^d)
    blocks = jnp.take_along_axis(rows, jnp.asarray(offset)[None], axis=2)
    blocks = jnp.where(jnp.asarray(near), blocks, 0.0)
    diag = jnp.diagonal(blocks, axis1=1, axis2=2)
    ridge = PATCH_RIDGE * jnp.finfo(blocks.dtype).eps * jnp.max(diag, axis=1)[:, None, None]
    eye = jnp.eye(blocks.shape[1], dtype=blocks.dtype)
    # Cholesky and one triangular solve: 0.12 s for 1024 blocks of 64 on a 2-core CPU, where
    # jnp.linalg.inv (LU) took 3.2 s.
    low = jnp.linalg.cholesky(blocks + ridge * eye)
    low_inv = jax.lax.linalg.triangular_solve(low, jnp.broadcast_to(eye, low.shape),
                                              left_side=True, lower=True)
    return jnp.einsum("pca,pcb->pab", low_inv, low_inv)  # L^-T L^-1


class Level(eqx.Module):
    """One level of the hierarchy: its stencil and the patch inverses of its smoother."""

    stencil: Array
    inverses: Array
    patches: Array
    upper: Array = 1.0

    def matvec(self, x: Array) -> Array:
        return stencil_matvec(self.stencil, x)

    def smooth(self, residual: Array) -> Array:
        """Additive Schwarz: ``sum_p R_p^T A_p^-1 R_p r`` over the overlapping patches."""
        local = residual.ravel()[self.patches]
        solved = jnp.einsum("pab,pb->pa", self.inverses, local.astype(self.inverses.dtype))
        out = jnp.zeros(residual.size, residual.dtype)
        return out.at[self.patches.ravel()].add(solved.ravel().astype(residual.dtype)
                                                ).reshape(residual.shape)


def spectrum_upper(level: Level, steps: int = POWER_STEPS) -> Array:
    """An estimate from above of the largest eigenvalue of ``M^-1 A`` (M the smoother):
    ``steps`` power iterations, Rayleigh quotient ``(Av . M^-1 Av) / (v . Av)``, times
    :data:`POWER_SAFETY` (power iteration approaches it from below)."""
    diag = stencil_diagonal(level.stencil)
    v = jax.random.uniform(jax.random.key(0), diag.shape, diag.dtype, -1.0, 1.0)

    def power(_, v):
        w = level.smooth(level.matvec(v))
        return w / jnp.max(jnp.abs(w))

    v = jax.lax.fori_loop(0, steps, power, v)
    product = level.matvec(v)
    return POWER_SAFETY * jnp.vdot(product, level.smooth(product)) / jnp.vdot(v, product)


class Hierarchy(eqx.Module):
    """The system's stencil, the multigrid levels above the coarsest (finest first) and the
    coarsest level's Cholesky factor."""

    stencil: Array
    levels: tuple
    coarsest: Array
    coarsest_shape: tuple = eqx.field(static=True)
    degree: int = eqx.field(static=True)


def build_hierarchy(stencil: Array, *, coarsest_size: int = DEFAULT_COARSEST_SIZE,
                    degree: int = 2, patch_size: int = DEFAULT_PATCH_SIZE,
                    patch_dtype=None) -> Hierarchy:
    """Galerkin levels of a symmetric positive definite stencil, their patch smoothers, and a
    dense Cholesky factor of the coarsest level. ``degree`` Chebyshev steps smooth before
    and after each coarse correction; ``patch_dtype`` stores the patch inverses (default:
    the stencil's dtype; float32 halves the largest array of the hierarchy)."""
    d = stencil_ndim(stencil)
    shapes = level_shapes(stencil.shape[:d], coarsest_size)
    fine, levels = stencil, []
    for shape, coarse in zip(shapes, shapes[1:]):
        patches = patch_indices(shape, patch_size)
        inverses = patch_inverses(stencil, patches)
        if patch_dtype is not None:
            inverses = inverses.astype(patch_dtype)
        level = Level(stencil, inverses, jnp.asarray(patches))
        levels.append(eqx.tree_at(lambda lv: lv.upper, level, spectrum_upper(level)))
        stencil = galerkin(stencil, coarse)
    dense = stencil_to_dense(stencil)
    # A ridge at rounding level keeps the factor finite where the coarse matrix is
    # singular to working precision (float32, lam -> 0); it only shapes the preconditioner.
    ridge = 10 * jnp.finfo(dense.dtype).eps * jnp.max(jnp.diag(dense))
    factor = jnp.linalg.cholesky(dense + ridge * jnp.eye(dense.shape[0], dtype=dense.dtype))
    return Hierarchy(fine, tuple(levels), factor, shapes[-1], degree)


def _coarsest_solve(hierarchy: Hierarchy, rhs: Array) -> Array:
    solved = jsl.cho_solve((hierarchy.coarsest, True), rhs.ravel())
    return solved.reshape(hierarchy.coarsest_shape)


def chebyshev(level: Level, rhs: Array, x: Array | None, degree: int) -> Array:
    """``degree`` Chebyshev steps for ``A x = rhs`` in ``M^-1 A`` (M the additive Schwarz
    smoother) on ``[upper / CHEBYSHEV_RATIO, upper]``, ``upper`` from
    :func:`spectrum_upper` (Saad, Iterative Methods, alg. 12.1). From ``x`` (``None``:
    zero, saving a product)."""
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
        return levels[index + 1].stencil.shape[: levels[index + 1].stencil.ndim // 2]
    return hierarchy.coarsest_shape


def v_cycle(hierarchy: Hierarchy, rhs: Array, index: int = 0) -> Array:
    """One V-cycle for ``A_index x = rhs`` from x = 0: a symmetric positive definite
    approximation of ``A^-1`` (the same smoother before and after the correction)."""
    if index == len(hierarchy.levels):
        return _coarsest_solve(hierarchy, rhs)
    level = hierarchy.levels[index]
    x = chebyshev(level, rhs, None, hierarchy.degree)
    coarse_rhs = restrict(rhs - level.matvec(x), _shape_below(hierarchy, index))
    x = x + prolong(v_cycle(hierarchy, coarse_rhs, index + 1), rhs.shape)
    return chebyshev(level, rhs, x, hierarchy.degree)


def full_multigrid(hierarchy: Hierarchy, rhs: Array) -> Array:
    """Cascadic start: solve the coarsest level exactly, then on each finer level start from
    the prolonged coarser solution and take one V-cycle (about 1.3 V-cycles of work)."""
    right = [rhs]
    for index in range(len(hierarchy.levels)):
        right.append(restrict(right[-1], _shape_below(hierarchy, index)))
    x = _coarsest_solve(hierarchy, right[-1])
    for index in reversed(range(len(hierarchy.levels))):
        level, b = hierarchy.levels[index], right[index]
        x = prolong(x, b.shape)
        x = x + v_cycle(hierarchy, b - level.matvec(x), index)
    return x


def preconditioned_cg(matvec, precondition, rhs: Array, start: Array, rtol, atol,
                      max_steps: int):
    """Conjugate gradients for ``A x = rhs`` preconditioned by ``precondition`` (~A^-1),
    from ``start``. Stops once ``r . M r <= rtol^2 (b . M b) + atol^2``: ``r . M r``
    estimates the energy norm of the error ``e . A e`` (exactly so for ``M = A^-1``),
    which is the gap of the quadratic objective to its minimum. Returns
    ``(x, steps, r . M r / b . M b)``."""
    scale = jnp.vdot(rhs, precondition(rhs))
    bound = rtol**2 * scale + atol**2
    residual = rhs - matvec(start)
    z = precondition(residual)
    gamma = jnp.vdot(residual, z)

    def keep_going(carry):
        _, _, _, gamma, steps = carry
        return (gamma > bound) & (steps < max_steps)

    def step(carry):
        x, residual, direction, gamma, steps = carry
        product = matvec(direction)
        alpha = gamma / jnp.vdot(direction, product)
        x = x + alpha * direction
        residual = residual - alpha * product
        z = precondition(residual)
        gamma_next = jnp.vdot(residual, z)
        direction = z + (gamma_next / gamma) * direction
        return x, residual, direction, gamma_next, steps + 1

    x, _, _, gamma, steps = jax.lax.while_loop(
        keep_going, step, (start, residual, z, gamma, jnp.array(0)))
    return x, steps, gamma / jnp.where(scale > 0, scale, 1.0)


def _grid_structure(operator: lx.AbstractLinearOperator) -> jax.ShapeDtypeStruct:
    structure = operator.in_structure()
    if not isinstance(structure, jax.ShapeDtypeStruct) or structure.ndim not in (2, 3):
        raise ValueError("Multigrid solves operators on a single 2D or 3D grid array, got "
                         f"in_structure {structure}")
    if operator.out_structure() != structure:
        raise ValueError("Multigrid needs a square operator (same in and out structure)")
    return structure


class Multigrid(lx.AbstractLinearSolver):
    """Geometric multigrid-preconditioned conjugate gradients for symmetric positive definite
    stencil systems on B-spline coefficient grids (2D or 3D), as a lineax solver.

    The operator must act on one ``grid_shape`` array, couple points at most 3 apart per axis
    (a cubic B-spline normal matrix) and be tagged positive (semi-)definite. Its stencil is
    taken from ``options["stencil"]`` (``grid_shape + (7,) * d``, no gradient; LeastSquares
    passes it) or else probed from the operator with ``7^d`` products. Coefficients are
    prolonged by B-spline knot insertion and coarse operators are Galerkin products (see
    the module docstring). Differentiable like any lineax solve (implicit differentiation:
    the adjoint system is solved by the same method).

    Args:
        rtol: stop once the estimated energy norm of the error is ``rtol`` times that of the
            solution (``r . M r <= rtol^2 b . M b``); the objective's gap to its minimum is
            then about ``rtol^2`` times ``C.A C``. Default 1e-9 (float32 reaches ~1e-4).
        atol: absolute floor of that estimate.
        max_steps: CG steps (one V-cycle each) before giving up with ``max_steps_reached``.
        degree: Chebyshev smoothing steps before and after each coarse correction.
        patch_size: points per axis of the overlapping patches of the Schwarz smoother.
        coarsest_size: largest level solved by dense Cholesky.
        full_multigrid: start from a full multigrid pass (True) or from ``options["y0"]``
            (else zero).
    """

    rtol: float = 1e-9
    atol: float = 0.0
    max_steps: int = 200
    degree: int = eqx.field(static=True, default=2)
    patch_size: int = eqx.field(static=True, default=DEFAULT_PATCH_SIZE)
    coarsest_size: int = eqx.field(static=True, default=DEFAULT_COARSEST_SIZE)
    full_multigrid: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and value < 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        if int(self.max_steps) < 1 or int(self.degree) < 1 or int(self.coarsest_size) < 1:
            raise ValueError("max_steps, degree and coarsest_size must be >= 1, got "
                             f"{self.max_steps}, {self.degree}, {self.coarsest_size}")

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]) -> Hierarchy:
        structure = _grid_structure(operator)
        if not lx.is_positive_semidefinite(operator):
            raise ValueError("Multigrid needs an operator tagged "
                             "lineax.positive_semidefinite_tag (symmetric positive definite)")
        stencil = options.get("stencil")
        if stencil is None:
            stencil = probe_stencil(operator.mv, structure.shape, structure.dtype)
        elif stencil.shape != structure.shape + (SIDE,) * structure.ndim:
            raise ValueError(f"options['stencil'] must be shaped {structure.shape} + "
                             f"(7,) * {structure.ndim}, got {stencil.shape}")
        return build_hierarchy(jax.lax.stop_gradient(stencil),
                               coarsest_size=self.coarsest_size, degree=self.degree,
                               patch_size=self.patch_size)

    def compute(self, state: Hierarchy, vector: Array, options: dict[str, Any]):
        matvec = lambda x: stencil_matvec(state.stencil, x)  # noqa: E731
        if self.full_multigrid:
            start = full_multigrid(state, vector)
        else:
            start = options.get("y0", jnp.zeros_like(vector))
        x, steps, error2 = preconditioned_cg(matvec, lambda r: v_cycle(state, r), vector, start,
                                             self.rtol, self.atol, self.max_steps)
        result = lx.RESULTS.where(steps >= self.max_steps, lx.RESULTS.max_steps_reached,
                                  lx.RESULTS.successful)
        return x, result, {"num_steps": steps, "relative_error2": error2}

    def transpose(self, state: Hierarchy, options: dict[str, Any]):
        return state, options  # symmetric

    def conj(self, state: Hierarchy, options: dict[str, Any]):
        return state, options  # real

    def assume_full_rank(self) -> bool:
        return True
