"""Where the samples sit on a grid ([`LocalBasis`][jurs.internal.LocalBasis]): the data
every kernel of ``spline.py`` and ``groups.py`` reads, built once per problem."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .basis import cubic_weights, patch_corner, patch_offsets, tensor_basis


class LocalBasis(eqx.Module):
    """Where ``S`` samples sit on the grid: the cell of each and its local coordinates there.

    These depend on the samples, the box and the grid only, never on C or w, so solvers
    build them once and reuse them every step (only the weights move the rational rows).
    Samples come in buckets of ``bucket_size`` consecutive entries sharing one cell. The
    basis values are recomputed from the local coordinates where needed: reading 2 numbers
    a sample is cheaper than reading 8 stored ones. The optional fields hold the table form
    (see ``jurs._model.spline``'s notes), or the groups: a surface's slots gathered by cell
    ([`with_groups`][jurs.internal.with_groups], ``jurs._model.groups``), which the normal
    equations' assembly and F read.
    """

    cell: Array  # (S,) int32 flat cell index
    s: Array  # (d, S) centred local coordinates t - 1/2 in the cell, one row an axis
    terms: Array | None = None  # table: (16, B, K) basis products at the table positions
    terms_t: Array | None = None  # table: the same as (B, K, 16)
    index: Array | None = None  # table: (B, 16) flat grid index of each bucket's terms
    corner: Array | None = None  # table: (B, 2) grid row and column of each bucket's patch
    order: Array | None = None  # table: (P,) sample slot at each table position
    position: Array | None = None  # table: (S,) table position of each sample slot
    filled: Array | None = None  # table: (P,) 1.0 where a table position holds a sample
    group_slot: Array | None = None  # groups: (G, K) slots sharing a cell, K a group
    group_filled: Array | None = None  # groups: (G, K) 1.0 where a group's entry is a slot
    group_position: Array | None = None  # groups: (S,) flat group entry of each slot
    bucket_size: int = eqx.field(static=True, default=1)
    # The slot axis in this many equal parts, one a device of a sharded fit: sums over the
    # slots taken a chunk at a time run per part, so that no device reads another's slots.
    parts: int = eqx.field(static=True, default=1)

    @property
    def num_buckets(self) -> int:
        return self.cell.shape[0] // self.bucket_size

    @property
    def bucket_cell(self) -> Array:
        """The cell of each bucket; ``(num_buckets,)``."""
        return self.cell[:: self.bucket_size]

    @property
    def ndim(self) -> int:
        """The dimension d of the grid: 2 for curves, 3 for surfaces."""
        return self.s.shape[0]

    @property
    def t(self) -> Array:
        """Local coordinates in the cell, ``(d, S)``; ``[0, 1]`` inside the box."""
        return self.s + 0.5

    @property
    def bx(self) -> Array:
        """x-direction basis values ``B_a(x)``; ``(S, 4)``."""
        return cubic_weights(self.t[0])

    @property
    def by(self) -> Array:
        """y-direction basis values ``B_b(y)``; ``(S, 4)``."""
        return cubic_weights(self.t[1])

    @property
    def products(self) -> Array:
        """The ``4 ** d`` local terms ``B_a(x) B_b(y) [B_c(z)]``; ``(S, 4 ** d)``."""
        return tensor_basis(*(cubic_weights(t) for t in self.t))

    def patch_index(self, shape: tuple[int, ...]) -> Array:
        """``(S, 4 ** d)``: the flat index, in the coefficient grid of ``shape``, of every
        coefficient each sample sees, in the order of
        [`products`][jurs.internal.LocalBasis.products]."""
        return patch_corner(self.cell, shape)[:, None] + jnp.asarray(patch_offsets(shape))

    def to_layout(self, values: Array) -> Array:
        """Per-slot ``(..., S)`` values in the layout the kernels work in (``layout=True``
        of [`bspline_values`][jurs.internal.bspline_values] and ``transpose_and_sum``):
        the slots themselves, or in the table form the table positions, 0 at its padding.
        Values given to the kernels in this layout must be 0 at the padding."""
        if self.terms is None:
            return values
        assert self.filled is not None  # the table fields are set together
        return values[..., self.order] * self.filled

    def centred(self):
        """``(sx, sy)``, the centred local coordinates, as ``(num_buckets, bucket_size)``."""
        s = self.s.reshape(2, self.num_buckets, self.bucket_size)
        return s[0], s[1]
