"""Uniform cubic B-spline basis on a box.

With ``N`` basis functions along an axis the box ``[lo, hi]`` is cut into ``N - 3`` equal
cells of width ``h = (hi - lo) / (N - 3)``; the knots run on past both ends so that every
``x`` in the box lies under exactly four non-zero basis functions, which sum to one.
Basis function ``i`` (0-based) covers cells ``i - 3 .. i``, so a point in cell ``c`` sees
functions ``c .. c + 3``.

In 2D a sample sees the 4 x 4 tensor products of the two axes' functions: 16 local terms
(partition of unity); in 3D the 64 products of three axes. The helpers here take the
dimension from the grid's shape. Everything downstream works on these local terms, never on a dense
collocation matrix, through two adjoint maps between the ``(N, M)`` coefficient grid and
per-cell ``(cells, 16)`` patches.
"""

from __future__ import annotations

import itertools
from typing import cast

import jax.numpy as jnp
import numpy as np
from jax import Array, lax

#: Local terms per 2D sample: 4 x 4 tensor products.
NUM_LOCAL = 16

#: The four cubic pieces of [`cubic_weights`][jurs.internal.cubic_weights] in powers of the
#: centred local coordinate ``s = t - 1/2``: ``B_a(t) = sum_p CENTRED_POWER[a, p] s^p``. On a
#: cell ``|s| <= 1/2`` and ``sum_p |CENTRED_POWER[a, p]| |s|^p <= 1``, so sums in this basis
#: lose no more to rounding than sums in the B-spline basis, while a value costs a Horner
#: scheme instead of the four pieces (the speed of every solver step rests on this).
CENTRED_POWER = (
    np.array([[1, -6, 12, -8], [23, -30, -12, 24], [23, 30, -12, -24], [1, 6, 12, 8]], dtype=float)
    / 48.0
)


def cubic_weights(t: Array | np.ndarray, xp=jnp) -> Array:
    """Values of the four uniform cubic B-spline pieces at ``t`` in ``[0, 1]``; ``(..., 4)``.

    Outside ``[0, 1]`` the end pieces are continued as polynomials, so evaluation beyond the
    box extrapolates smoothly instead of dropping to zero. ``xp=numpy`` evaluates on the
    host (layouts built from concrete data), with the same arithmetic.
    """
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        xp.stack(
            [s * s * s, 3.0 * t3 - 6.0 * t2 + 4.0, -3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0, t3],
            axis=-1,
        )
        / 6.0
    )


def cubic_derivatives(t: Array) -> Array:
    """d/dt of [`cubic_weights`][jurs.internal.cubic_weights]; ``(..., 4)``. Divide by
    the cell width for d/dx."""
    s = 1.0 - t
    t2 = t * t
    return jnp.stack([-0.5 * s * s, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2], axis=-1)


def cell_width(lower: Array, upper: Array, shape: tuple[int, ...], xp=jnp) -> Array:
    """Knot spacing along each axis (``(hx, hy)`` or ``(hx, hy, hz)``) of a basis of
    ``shape`` functions on the box ``[lower, upper]``."""
    return (upper - lower) / (xp.asarray(shape, dtype=xp.result_type(lower)) - 3.0)


def locate(xy: Array, lower: Array, upper: Array, shape: tuple[int, ...], xp=jnp):
    """Cell of each point and its local coordinate in that cell, for a grid of any
    dimension d (``xy (n, d)``, ``shape`` d basis counts).

    Returns ``(cell, t)``: ``cell`` is ``(n, d)`` int32 with entry ``a`` in ``[0, shape[a]
    - 4]`` (points outside the box are clamped to the border cell), ``t`` is ``(n, d)``, in
    ``[0, 1]`` inside the box. ``xp=numpy`` computes on the host, with the same arithmetic.
    """
    h = cell_width(lower, upper, shape, xp)
    u = (xy - lower) / h
    top = xp.asarray([n - 4 for n in shape])
    cell = xp.clip(xp.floor(u), 0, top).astype(xp.int32)
    return cell, u - cell.astype(u.dtype)


def cell_shape(shape: tuple[int, ...]) -> tuple[int, ...]:
    """The cells along each axis of a basis of ``shape`` functions: ``n - 3`` each."""
    return tuple(int(n) - 3 for n in shape)


def flat_cell(cell: Array, shape: tuple[int, ...]) -> Array:
    """Row-major index of a cell (``(..., d)``) in the cell grid ``cell_shape``."""
    cells = cell_shape(shape)
    index = cell[..., 0]
    for axis in range(1, len(cells)):
        index = index * cells[axis] + cell[..., axis]
    return index


def num_cells(shape: tuple[int, ...]) -> int:
    return int(np.prod(cell_shape(shape)))


def patch_offsets(shape: tuple[int, ...]) -> np.ndarray:
    """``(4 ** d,)`` offsets, in the row-major flattened coefficient grid of ``shape``, of
    the ``4 x ... x 4`` patch a cell sees from its first coefficient, in the order of
    ``tensor_basis``."""
    strides = np.cumprod((1,) + tuple(shape[:0:-1]))[::-1]
    steps = np.stack(np.meshgrid(*[np.arange(4)] * len(shape), indexing="ij"), -1)
    return (steps.reshape(-1, len(shape)) @ strides).astype(np.int32)


def patch_corner(cell: Array, shape: tuple[int, ...]) -> Array:
    """The flat grid index of the first coefficient of the patch of each flat ``cell``
    index (``flat_cell``): the same multi-index, raveled in the coefficient grid."""
    cells = cell_shape(shape)
    corner = 0
    rest = cell
    stride = 1
    for axis in reversed(range(len(cells))):
        corner = corner + (rest % cells[axis]) * stride
        rest = rest // cells[axis]
        stride *= int(shape[axis])
    return cast(Array, corner)  # the loop runs at least once: never the int 0


def tensor_basis(*axes: Array) -> Array:
    """The ``4 ** d`` products of the per-axis values ``(n, 4)`` each (``B_a(x) B_b(y)`` in
    2D), row-major (first axis slowest, ``a * 4 + b`` in 2D); ``(n, 4 ** d)``."""
    out = axes[0]
    for values in axes[1:]:
        out = (out[:, :, None] * values[:, None, :]).reshape(out.shape[0], -1)
    return out


def grid_to_patches(grid: Array, ndim: int = 2) -> Array:
    """``(..., *grid)`` coefficients over ``ndim`` trailing axes -> ``(..., cells, 4 **
    ndim)``: the ``4 x ... x 4`` block each cell sees.

    Gathering one patch row per cell (or bucket of samples) is one contiguous read, much
    cheaper than 16 scattered element reads.
    """
    lead = grid.shape[: grid.ndim - ndim]
    cells = cell_shape(grid.shape[grid.ndim - ndim :])
    blocks = [
        grid[(Ellipsis, *(slice(a, a + c) for a, c in zip(start, cells)))]
        for start in itertools.product(range(4), repeat=ndim)
    ]
    return jnp.stack(blocks, axis=-1).reshape(lead + (int(np.prod(cells)), 4**ndim))


def patches_to_grid(patches: Array, shape: tuple[int, ...]) -> Array:
    """Adjoint of ``grid_to_patches``: add each cell's ``4 ** d`` values back onto the
    grid of ``shape``; ``(..., cells, 4 ** d)`` -> ``(..., *shape)``.
    """
    ndim = len(shape)
    lead = patches.shape[:-2]
    blocks = patches.reshape(lead + cell_shape(shape) + (4**ndim,))
    keep = [(0, 0)] * len(lead)
    # A sum of shifted (zero-padded) blocks: one fused loop, where 16 in-place slice
    # updates were 16 kernels (their per-kernel cost dominates small fits).
    grid = jnp.zeros(lead + tuple(shape), dtype=patches.dtype)
    for j, start in enumerate(itertools.product(range(4), repeat=ndim)):
        grid = grid + jnp.pad(blocks[..., j], keep + [(a, 3 - a) for a in start])
    return grid


def patch_to_power() -> np.ndarray:
    """``(16, 16)`` matrix taking a cell's 4 x 4 patch of coefficients (``a * 4 + b``) to
    the coefficients of the same bicubic in powers ``sx^p sy^q`` of the centred local
    coordinates (``p * 4 + q``): ``patch @ patch_to_power()``. Its transpose takes power
    moments ``sum_k v_k sx^p sy^q`` back to the 16 B-spline sums ``sum_k v_k B_a B_b``."""
    return np.kron(CENTRED_POWER, CENTRED_POWER)


def power_values(coeffs, sx: Array, sy: Array) -> Array:
    """The bicubic ``sum_pq coeffs[p * 4 + q] sx^p sy^q`` by Horner's scheme.

    ``coeffs`` is a sequence of 16 arrays that broadcast against ``sx`` and ``sy`` (for
    example one value per bucket against one per sample of the bucket).
    """
    value = None
    for p in (3, 2, 1, 0):
        row = coeffs[p * 4 + 3]
        for q in (2, 1, 0):
            row = row * sy + coeffs[p * 4 + q]
        value = row if value is None else value * sx + row
    return value


def power_moments(sx: Array, sy: Array, values: Array, extra=()):
    """``sum_k values[c, ..., k] sx_k^p sy_k^q`` over the last axis, for every leading
    channel ``c``; ``sx, sy (..., K)``, ``values (C, ..., K)`` -> ``(..., C, 16)`` in
    ``p * 4 + q`` order. ``extra`` arrays (``(..., K)`` each) are summed over the last axis
    alongside; their sums come back as a second result.

    All the sums are one variadic reduction, so the samples are read once (separate sums
    would each read them again).
    """
    terms = []
    for v in values:
        # Each term a short chain of products from v: no power of sx or sy is shared
        # between channels or calls, so the compiler has no reason to store one.
        column = v
        for q in range(4):
            if q:
                column = column * sy
            term = column
            terms.append(term)
            for _ in range(3):
                term = term * sx
                terms.append(term)
    order = [p + 4 * q for p in range(4) for q in range(4)]  # terms come q-major
    terms = [terms[16 * c + j] for c in range(len(values)) for j in order]
    terms += list(extra)
    zeros = tuple(jnp.zeros((), t.dtype) for t in terms)
    sums = lax.reduce(
        tuple(terms), zeros, lambda a, b: tuple(x + y for x, y in zip(a, b)), (sx.ndim - 1,)
    )
    count = 16 * len(values)
    out = jnp.stack(sums[:count], axis=-1)
    return out.reshape(out.shape[:-1] + (len(values), NUM_LOCAL)), tuple(sums[count:])
