"""The multigrid's smoother: overlapping box patches of a grid and their exact inverses.

A patch is a box of ``side`` points per axis, one starting every ``stride`` points
(``PatchLayout``). The additive Schwarz smoother of ``jurs._linalg.multigrid``
solves every patch's principal submatrix exactly: point smoothers (Jacobi) leave the data
term's local near-null modes (splines small on the samples but not smooth) to neither the
smoother nor the coarse grid. Patches are cut from the grid by pads, reshapes and slices
(no gathers), each patch's submatrix built from the stencil rows by a shear, and the
inverses computed by ``jurs._linalg.spd.spd_inverse`` (matrix products, no LAPACK)
and stored. The top of the smoother's spectrum is bounded a priori by a colouring of the
patches (``PatchLayout.colours``; docs/multigrid.md, "Spectrum bound by colouring").
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .spd import spd_inverse
from .stencil import HALF, SIDE

#: Default patch side and stride (points per axis) of the Schwarz smoother, by dimension.
#: In 2D patches must overlap by the stencil's reach, 3, or the data term's near-null
#: modes stall the solve, and 8 / 4 converges at small lam where 6 / 3 does not. In 3D the
#: overlap of 3 (6^3 patches at stride 3) costs several times the memory and setup of
#: 4 / 2, the smallest patches that did not stall (docs/multigrid.md: "Smoother" and
#: "Measurements behind the constants").
DEFAULT_PATCH = {2: (8, 4), 3: (4, 2)}
#: Ridge of each patch block, relative to its diagonal, in units of the dtype's epsilon
#: times the block's size: it must exceed the rounding of the factorisation, or the
#: computed inverse can exceed ``A_p^-1`` and the a priori spectrum bound fails.
PATCH_RIDGE = 1.0


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
    """The ``PatchLayout`` of ``side``-point patches every ``stride`` points (``1 <=
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
    """The transpose of ``extract_patches`` for a grid without channels: every patch's
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


#: Bytes of stencil rows cut into patches (or of patch blocks inverted) at once in the setup
#: (``_slab_map`` works through the grid in slabs of patches): every patch point
#: carries its whole stencil row there (343 entries in 3D), so the setup in one piece
#: would hold many times the stencil (docs/multigrid.md, "Measurements behind the
#: constants").
SETUP_CHUNK_BYTES = 1 << 26


#: Largest total of patch blocks (bytes) inverted as one batch across all levels. One batch
#: compiles one factorisation instead of one a level (a shorter compilation, which is what
#: small problems pay), but holds every block, their concatenation and the split inverses
#: at once, too much memory for large grids (docs/multigrid.md, "Measurements behind the
#: constants"). Above it, each level runs its own chunked loop, blocks cut and inverted
#: chunk by chunk.
SHARED_INVERSION_BYTES = 1 << 28


def _slab_map(layout: PatchLayout, stencil: Array, fn) -> Array:
    """``fn(patch_blocks)`` over the patches of ``layout``, a slab of patches (one patch along
    the first axis) at a time, several slabs a batch, about ``SETUP_CHUNK_BYTES`` of
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
    ``PATCH_RIDGE`` ``k`` epsilons: at least the factorisation's rounding, so that the
    computed ``B_p^-1`` stays below ``A_p^-1`` and ``PatchLayout.colours`` bounds
    ``M^-1 A``'s spectrum. Levels whose patches have the same size are inverted as one
    batch while that is small (``SHARED_INVERSION_BYTES``), else level by level."""

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
