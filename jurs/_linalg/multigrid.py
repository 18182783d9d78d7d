"""Geometric multigrid for stencil systems: the normal equations ``(D^T D + 2 lam L) C = D^T b``.

One code path for grids of any dimension d (2D curves, 3D surfaces): a stencil is an array
``grid_shape + (7,) * d`` (:mod:`jurs._linalg.normal`), and every operation here (transfer, coarse
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
  overlapping box patches, each solved exactly: point smoothers (Jacobi) leave the data
  term's local near-null modes (splines small on the samples but not smooth) to neither
  the smoother nor the coarse grid. Patches are cut from the grid by pads, reshapes and
  slices (no gathers), their inverses computed by matrix products (no LAPACK) and
  stored; the top of ``M^-1 A``'s spectrum is bounded a priori by a colouring of the
  patches (no power iterations).
* **Coarsest level**: a dense inverse once it has at most ``coarsest_size`` unknowns.
* **Solver**: conjugate gradients preconditioned by one V-cycle a step, from a full
  multigrid pass, stopped on an estimate of the objective's gap to its minimum.

The hierarchy (coarse operators, patch inverses, coarsest inverse) is the lineax state of
:class:`Multigrid`: ``Multigrid.init`` builds it once (most of a solve's cost), and
``lineax.linear_solve(..., state=...)`` reuses it for further right-hand sides.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax import Array

from .normal import HALF, SIDE, stencil_matvec, stencil_ndim, stencil_to_dense

#: Uniform cubic B-spline subdivision mask: coarse function ``I`` is ``sum_a MASK[a]`` times
#: fine function ``2 I - 3 + a``.
MASK = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 8.0
#: Axes with fewer basis functions than this are not coarsened (4 -> 4 would not shrink).
MIN_COARSEN_SIDE = 8
#: Default largest level solved by a dense inverse (19 x 19 below 128 x 128, 7^3 in 3D).
DEFAULT_COARSEST_SIZE = 512
#: The Chebyshev smoother damps ``M^-1 A``'s spectrum on ``[upper / CHEBYSHEV_RATIO, upper]``;
#: the rest is the coarse levels' job.
CHEBYSHEV_RATIO = 30.0
#: Default patch side and stride (points per axis) of the Schwarz smoother, by dimension.
#: Patches must overlap by 3 (the stencil's reach) for the data term's near-null modes: on
#: Example 1 at 128 x 128, lam = 1e-4, patches 8/4 and 6/3 took 13 and 20 CG steps to an
#: energy error of 1e-20, overlaps of 2 or less (8/6, 6/4, 5/4, 4/2) stalled near 1e-11.
#: 8/4 holds 256 inverse entries a grid point and needs 28k multiply-adds a point to set
#: up, 6/3 144 and 9k, but 6/3 converged much more slowly at small lam (gap 1e-4 of the
#: objective after 60 steps at lam = 1e-8, where 8/4 reached 1e-8 in 52). In 3D an overlap
#: of 3 (6^3 patches at stride 3) converged as well (torus, 32^3, lam = 1e-4: gap 1e-8 in
#: 15 steps) but holds 1728 entries a point and 630k multiply-adds a point to set up;
#: 4^3 at stride 2 (512 entries, 55k) reached 1e-4 of the objective in 37 steps, 3^3 at
#: stride 2 and 4^3 at stride 3 stalled near 2e-3.
DEFAULT_PATCH = {2: (8, 4), 3: (4, 2)}
#: Ridge of each patch block, relative to its diagonal, in units of the dtype's epsilon
#: times the block's size: it must exceed the rounding of the factorisation, or the
#: computed inverse can exceed ``A_p^-1`` and the a priori spectrum bound fails.
PATCH_RIDGE = 1.0


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
    where the fine index is off the grid. (One padded copy of ``x``: slicing the existing
    rows and padding each window instead made XLA keep all five, 1.8 times the memory.)"""
    pad = [(0, 0)] * x.ndim
    pad[axis] = (3, 4)
    padded = jnp.pad(x, pad)
    return [
        jax.lax.slice_in_dim(padded, a, a + 2 * n_coarse - 1, stride=2, axis=axis)
        for a in range(MASK.size)
    ]


def restrict(grid: Array, coarse_shape: tuple[int, ...]) -> Array:
    """``P^T grid``: the fine residual's moments against the coarse basis functions."""
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse != grid.shape[axis]:
            windows = _fine_windows(grid, axis, n_coarse)
            grid = sum(float(w) * x for w, x in zip(MASK, windows))  # pyright: ignore[reportAssignmentType]
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
    product). Coarse functions couple within 3 of each other, as fine ones do. Each coarse
    offset is one weighted sum of fine slices, which XLA fuses into a single pass: as
    ``tensordot`` contractions the 3D Galerkin product needed 4.6 times the stencil's size
    in temporaries (32^3)."""
    d = stencil_ndim(stencil)
    weights = _galerkin_weights()
    for axis, n_coarse in enumerate(coarse_shape):
        if n_coarse == stencil.shape[axis]:
            continue
        windows = _fine_windows(stencil, axis, n_coarse)
        offsets = []
        for coarse_offset in range(SIDE):
            offsets.append(
                sum(
                    float(weights[a, e, coarse_offset])
                    * jax.lax.index_in_dim(windows[a], e, axis=d + axis, keepdims=False)
                    for a in range(MASK.size)
                    for e in range(SIDE)
                    if weights[a, e, coarse_offset] != 0.0
                )
            )
        out = jnp.stack(offsets, axis=d + axis)
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
    probes = np.stack(
        [np.all([index[k] % SIDE == c[k] for k in range(d)], axis=0) for c in classes]
    ).astype(dtype)
    products = jax.lax.map(matvec, jnp.asarray(probes))  # (7^d,) + shape
    entries = []
    for offset in itertools.product(range(SIDE), repeat=d):
        target = [(index[k] + offset[k] - HALF) % SIDE for k in range(d)]
        which = np.ravel_multi_index(target, (SIDE,) * d)
        entries.append(jnp.take_along_axis(products, jnp.asarray(which)[None], axis=0)[0])
    return jnp.stack(entries, axis=-1).reshape(tuple(shape) + (SIDE,) * d)


class PatchLayout(eqx.Module):
    """Overlapping box patches of a grid: along each axis, patches of ``sides[k]`` points
    start every ``strides[k]`` points (``counts[k]`` of them, the last one reaching past
    the grid where the side does not fit: those points are padding)."""

    shape: tuple = eqx.field(static=True)
    sides: tuple = eqx.field(static=True)
    strides: tuple = eqx.field(static=True)
    counts: tuple = eqx.field(static=True)

    @property
    def size(self) -> int:
        """Points of a patch."""
        return math.prod(self.sides)

    def colours(self) -> int:
        """Colours such that patches of one colour are decoupled: patches ``c`` apart along
        an axis are once ``c * stride >= side + HALF`` (a gap of more than HALF points)."""
        return math.prod(
            min(n, -(-(k + HALF) // s)) for n, k, s in zip(self.counts, self.sides, self.strides)
        )


def patch_layout(shape: tuple[int, ...], side: int, stride: int) -> PatchLayout:
    """The :class:`PatchLayout` of ``side``-point patches every ``stride`` points (``1 <=
    stride <= side``), both capped by the grid's extent along each axis."""
    if not 1 <= stride <= side:
        raise ValueError(f"patch stride must be in [1, side], got side {side}, stride {stride}")
    sides, strides, counts = [], [], []
    for n in shape:
        k, s = (side, stride) if n > side else (n, n)
        sides.append(k)
        strides.append(s)
        counts.append(1 + -(-(n - k) // s))
    return PatchLayout(tuple(shape), tuple(sides), tuple(strides), tuple(counts))


def _axis_windows(x: Array, axis: int, count: int, side: int, stride: int) -> Array:
    """Replace ``axis`` of ``x`` by ``(count, side)``: window ``p`` holds points
    ``p * stride ... p * stride + side - 1`` (zero past the end). Pads, reshapes and slices
    only, so its transpose (the scatter-add back) is as cheap."""
    shifts = -(-side // stride)
    pad = [(0, 0)] * x.ndim
    pad[axis] = (0, (count + shifts - 1) * stride - x.shape[axis])
    x = jnp.pad(x, pad)
    split = x.shape[:axis] + (count, stride) + x.shape[axis + 1 :]
    parts = [
        jax.lax.slice_in_dim(x, j * stride, (j + count) * stride, axis=axis).reshape(split)
        for j in range(shifts)
    ]
    return jax.lax.slice_in_dim(jnp.concatenate(parts, axis=axis + 1), 0, side, axis=axis + 1)


def extract_patches(layout: PatchLayout, grid: Array) -> Array:
    """The patches of a ``layout.shape + channels`` array, ``(patches, patch points) +
    channels``; points past the grid are 0."""
    d = len(layout.shape)
    x = grid
    for axis in range(d):
        x = _axis_windows(
            x, 2 * axis, layout.counts[axis], layout.sides[axis], layout.strides[axis]
        )
    order = [2 * k for k in range(d)] + [2 * k + 1 for k in range(d)]
    x = jnp.transpose(x, order + list(range(2 * d, x.ndim)))
    return x.reshape((-1, layout.size) + grid.shape[d:])


def add_patches(layout: PatchLayout, values: Array) -> Array:
    """The transpose of :func:`extract_patches` for a grid without channels: every patch's
    ``(patch points,)`` values added back onto the grid."""
    grid = jax.ShapeDtypeStruct(layout.shape, values.dtype)
    (out,) = jax.linear_transpose(lambda g: extract_patches(layout, g), grid)(values)
    return out


def _shear(x: Array, side: int) -> Array:
    """``(..., side, 7)`` band rows (row ``a``, stencil offset ``e``) to the ``(..., side,
    side)`` matrix ``T[a, b] = x[a, b - a + 3]`` (0 off the band): rows of length
    ``side + 7`` read back with length ``side + 6`` shift row ``a`` right by ``a``."""
    lead = x.shape[:-2]
    x = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, side)])
    x = x.reshape(lead + (side * (side + SIDE),))[..., : side * (side + SIDE - 1)]
    return x.reshape(lead + (side, side + SIDE - 1))[..., HALF : HALF + side]


def patch_blocks(layout: PatchLayout, stencil: Array) -> Array:
    """Every patch's principal submatrix of the stencil's matrix, ``(patches, k, k)``;
    identity rows and columns at padding points (and at zero rows). Built by a shear per
    axis (no gather)."""
    d = len(layout.shape)
    x = extract_patches(layout, stencil)  # (P, k, 7, .., 7)
    x = x.reshape((-1,) + layout.sides + (SIDE,) * d)
    for axis in range(d):  # local point a (axis 1 + axis), offset e (axis 1 + d + axis)
        x = jnp.moveaxis(x, (1 + axis, 1 + d + axis), (-2, -1))
        x = jnp.moveaxis(_shear(x, layout.sides[axis]), (-2, -1), (1 + axis, 1 + d + axis))
    blocks = x.reshape(-1, layout.size, layout.size)
    diag = jnp.diagonal(blocks, axis1=1, axis2=2)
    eye = jnp.eye(layout.size, dtype=blocks.dtype)
    return blocks + jnp.where(diag > 0, 0.0, 1.0)[:, None, :] * eye


#: Largest block factorised column by column (a loop); larger ones are split in halves
#: joined by matrix products. No LAPACK: XLA runs independent kernels concurrently, and two
#: batched LAPACK calls (two levels' patches) inside scipy's threaded OpenBLAS deadlocked
#: this 2-core machine (every thread asleep, reproducibly on the second call of the
#: hierarchy at 256 x 256). Splitting down to 1 x 1 instead took 40 s to compile.
LEAF_BLOCK = 12


def _leaf_cholesky_inverse(a: Array, floor: float) -> Array:
    """``L^-1`` of a batch of small symmetric positive definite ``a = L L^T``: Cholesky by
    columns, then forward substitution, each a loop over the columns with batched vector
    operations. Pivots are clamped at ``floor`` (a block that is not numerically positive
    definite gets a large finite inverse, not NaN)."""
    m = a.shape[-1]
    index = jnp.arange(m)

    def factor(j, carry):
        rest, low = carry
        column = jax.lax.dynamic_index_in_dim(rest, j, axis=-1, keepdims=False)
        pivot = jax.lax.dynamic_index_in_dim(column, j, axis=-1)
        column = jnp.where(index >= j, column * jax.lax.rsqrt(jnp.maximum(pivot, floor)), 0.0)
        rest = rest - column[..., :, None] * column[..., None, :]
        return rest, jax.lax.dynamic_update_index_in_dim(low, column[..., None], j, axis=-1)

    _, low = jax.lax.fori_loop(0, m, factor, (a, jnp.zeros_like(a)))

    def substitute(j, inverse):  # row j of L^-1: (e_j - L[j, :j] L^-1[:j]) / L[j, j]
        row = jax.lax.dynamic_index_in_dim(low, j, axis=-2, keepdims=False)
        pivot = jax.lax.dynamic_index_in_dim(row, j, axis=-1)
        unit = (index == j).astype(a.dtype)
        new = (unit - jnp.einsum("...i,...ij->...j", row, inverse)) / pivot
        return jax.lax.dynamic_update_index_in_dim(inverse, new[..., None, :], j, axis=-2)

    return jax.lax.fori_loop(0, m, substitute, jnp.zeros_like(a))


def _cholesky_inverse(a: Array, floor: float) -> Array:
    """``L^-1`` (lower triangular) of a batch of symmetric positive definite ``a = L L^T``,
    recursively by halves: ``L^-1 = [[L1^-1, 0], [-L2^-1 B L1^-1, L2^-1]]`` with
    ``B = A21 L1^-T`` and ``L2 L2^T = A22 - B B^T``; pivots clamped at ``floor``."""
    n = a.shape[-1]
    if n <= LEAF_BLOCK:
        return _leaf_cholesky_inverse(a, floor)
    h = n // 2
    i1 = _cholesky_inverse(a[..., :h, :h], floor)
    b = a[..., h:, :h] @ jnp.swapaxes(i1, -1, -2)
    i2 = _cholesky_inverse(a[..., h:, h:] - b @ jnp.swapaxes(b, -1, -2), floor)
    top = jnp.concatenate([i1, jnp.zeros(i1.shape[:-1] + (n - h,), a.dtype)], axis=-1)
    return jnp.concatenate([top, jnp.concatenate([-(i2 @ b) @ i1, i2], axis=-1)], axis=-2)


def spd_inverse(blocks: Array, ridge: float) -> Array:
    """``(D^1/2 (S + ridge I) D^1/2)^-1`` for a batch of symmetric positive semi-definite
    ``blocks = D^1/2 S D^1/2`` (D the diagonal, S unit-diagonal): the ridge is relative to
    each diagonal entry, and Cholesky's rounding is relative to them too. Pivots below the
    ridge are raised to it; a zero row is inverted as an identity row."""
    diag = jnp.diagonal(blocks, axis1=-2, axis2=-1)
    scale = jax.lax.rsqrt(jnp.where(diag > 0, diag, 1.0))
    unit = blocks * scale[..., :, None] * scale[..., None, :]
    eye = jnp.eye(blocks.shape[-1], dtype=blocks.dtype)
    unit = unit + jnp.where(diag > 0, 0.0, 1.0)[..., None, :] * eye
    low_inv = _cholesky_inverse(unit + ridge * eye, ridge)
    inverse = jnp.swapaxes(low_inv, -1, -2) @ low_inv
    return inverse * scale[..., :, None] * scale[..., None, :]


#: Bytes of stencil rows cut into patches (or of patch blocks inverted) at once in the setup
#: (:func:`_slab_map` works through the grid in slabs of patches): every patch
#: point carries its whole stencil row there, 22 KB a grid point for 4^3 patches at
#: stride 2, which took the setup of a 32^3 system to 1.3 GB in one piece.
SETUP_CHUNK_BYTES = 1 << 26


#: Largest total of patch blocks (bytes) inverted as one batch across all levels. One batch
#: compiles one factorisation instead of one a level (hierarchy compile 7.1 -> 4.6 s at
#: 48 x 48, which is what small problems pay), but holds every block, their concatenation
#: and the split inverses at once: XLA planned 8.6 GB for a 1024 x 1024 solve that way.
#: Above it, each level runs its own chunked loop, blocks cut and inverted chunk by chunk.
SHARED_INVERSION_BYTES = 1 << 28


def _slab_map(layout: PatchLayout, stencil: Array, fn) -> Array:
    """``fn(patch_blocks)`` over the patches of ``layout``, a slab of patches (one patch along
    the first axis) at a time, several slabs a batch, about :data:`SETUP_CHUNK_BYTES` of
    patch rows each; ``(patches, ...)``."""
    side, stride, count = layout.sides[0], layout.strides[0], layout.counts[0]
    slab = PatchLayout(
        (side,) + layout.shape[1:], layout.sides, layout.strides, (1,) + layout.counts[1:]
    )
    padded = jnp.pad(
        stencil,
        [(0, (count - 1) * stride + side - stencil.shape[0])] + [(0, 0)] * (stencil.ndim - 1),
    )

    def one(index):
        rows = jax.lax.dynamic_slice_in_dim(padded, index * stride, side, axis=0)
        return fn(patch_blocks(slab, rows))

    slab_bytes = (
        math.prod(slab.counts) * layout.size * SIDE ** len(layout.shape) * stencil.dtype.itemsize
    )
    batch = max(1, min(count, SETUP_CHUNK_BYTES // max(slab_bytes, 1)))
    out = jax.lax.map(one, jnp.arange(count), batch_size=batch)
    return out.reshape((-1,) + out.shape[2:])


def patch_inverses(layouts: list, stencils: list, dtype=None) -> list:
    """``B_p^-1`` for every patch of every level, ``(patches, k, k)`` each in ``dtype``
    (default the stencils'), ``B_p = A_p + ridge diag(A_p)`` with the ridge
    :data:`PATCH_RIDGE` ``k`` epsilons: at least the factorisation's rounding, so that the
    computed ``B_p^-1`` stays below ``A_p^-1`` and :meth:`PatchLayout.colours` bounds
    ``M^-1 A``'s spectrum. Levels whose patches have the same size are inverted as one
    batch while that is small (:data:`SHARED_INVERSION_BYTES`), else level by level."""

    def ridge(size, dtype_):
        return PATCH_RIDGE * size * float(jnp.finfo(dtype_).eps)

    def invert(blocks):
        return spd_inverse(blocks, ridge(blocks.shape[-1], blocks.dtype)).astype(
            dtype or blocks.dtype
        )

    total = sum(
        math.prod(lay.counts) * lay.size**2 * st.dtype.itemsize
        for lay, st in zip(layouts, stencils)
    )
    if total > SHARED_INVERSION_BYTES:
        return [_slab_map(lay, st, invert) for lay, st in zip(layouts, stencils)]
    blocks = [_slab_map(lay, st, lambda b: b) for lay, st in zip(layouts, stencils)]
    out: list = [None] * len(blocks)
    for size in sorted({b.shape[-1] for b in blocks}):
        which = [i for i, b in enumerate(blocks) if b.shape[-1] == size]
        batch = jnp.concatenate([blocks[i] for i in which])
        chunk = max(1, SETUP_CHUNK_BYTES // (size * size * batch.dtype.itemsize))
        inverses = jax.lax.map(invert, batch, batch_size=min(chunk, batch.shape[0]))
        ends = np.cumsum([blocks[i].shape[0] for i in which])
        for i, part in zip(which, jnp.split(inverses, ends[:-1])):
            out[i] = part
    return out


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
        patch: ``(side, stride)`` of the Schwarz patches; default :data:`DEFAULT_PATCH` for
            the grid's dimension.
        patch_dtype: storage of the patch inverses, the largest arrays of the hierarchy;
            default the stencil's dtype. Float32 halves them and the smoother's memory
            traffic, but is only safe for well-conditioned patches (see
            :class:`Multigrid`).
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
#: the iterate that many steps back. On Example 1 at 128 x 128, lam = 1e-8, ``r . M r`` was
#: 5-20 times below the true gap (small eigenvalues of ``M A``), the last 2 drops 0.45-2.4
#: times it (and 100-500 times above it at lam = 1e-4, where CG gains a decade a step: 2
#: extra steps).
ESTIMATE_WINDOW = 2


def preconditioned_cg(
    matvec, precondition, rhs: Array, start: Array, rtol, atol, max_steps: int, target_norm2=None
):
    """Conjugate gradients for ``A x = rhs`` preconditioned by ``precondition`` (~A^-1),
    from ``start``, stopped on the gap of the quadratic objective to its minimum (the
    energy norm of the error ``e . A e``).

    The gap is estimated by the larger of ``r . M r`` (the gap itself for ``M = A^-1``) and
    the sum of the objective's last :data:`ESTIMATE_WINDOW` drops. CG stops once the
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
    (a cubic B-spline normal matrix) and be tagged positive (semi-)definite. Its stencil is
    taken from ``options["stencil"]`` (``grid_shape + (7,) * d``, no gradient; LeastSquares
    passes it) or else probed from the operator with ``7^d`` products. Coefficients are
    prolonged by B-spline knot insertion and coarse operators are Galerkin products (see
    the module docstring). Differentiable like any lineax solve (implicit differentiation:
    the adjoint system is solved by the same method).

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
            (:data:`DEFAULT_PATCH`).
        coarsest_size: largest level solved by a dense inverse.
        full_multigrid: start from a full multigrid pass (True) or from ``options["y0"]``
            (else zero).
        patch_dtype: storage of the patch inverses (computed in the system's dtype);
            default the system's. ``jnp.float32`` halves the hierarchy and the smoother's
            memory traffic (solves 2x faster at 128 x 128, same steps, at lam = 1e-4), but
            rounds the inverse of an ill-conditioned patch beyond use: at 256 x 256, lam =
            1e-8 the smoother's spectrum doubled past its bound and CG broke down.
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
        stencil = options.get("stencil")
        if stencil is None:
            stencil = probe_stencil(operator.mv, structure.shape, structure.dtype)
        elif stencil.shape != structure.shape + (SIDE,) * structure.ndim:
            raise ValueError(
                f"options['stencil'] must be shaped {structure.shape} + "
                f"(7,) * {structure.ndim}, got {stencil.shape}"
            )
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
