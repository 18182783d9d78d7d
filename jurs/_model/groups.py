"""A surface's slots gathered by cell into groups of one size, and the kernels that read
them: F at the samples here, the normal equations' moments in ``jurs._linalg.normal``.

The slots of a [`LocalBasis`][jurs.internal.LocalBasis] keep their order (one sample a
slot); the groups are an index over them, built on the host (``with_groups``), so every
kernel that does not read them is unchanged. A problem split over devices drops them
(their gather would cross devices: ``jurs._fit.sharding``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .basis import cubic_weights, patch_corner, patch_offsets

if TYPE_CHECKING:
    from .local import LocalBasis

#: Groups a kernel takes at once: bounds the per-entry products (``K x 4 ** d`` a group
#: for F, ``K x 7 ** (d - 1)`` for the assembly: about 100 MB at K = 64 in 3D).
GROUP_CHUNK = 4096


def with_groups(local: LocalBasis, slot: np.ndarray, valid: np.ndarray) -> LocalBasis:
    """``local`` (one sample a slot, concrete) with its slots gathered by cell into
    groups, built on the host. ``slot`` and ``valid``, both ``(G, K)``: the slot at entry
    ``i`` of group ``g`` (all of a group's slots in one cell, the groups in cell order;
    padding entries repeat a slot of their group) and whether it is real.

    Why: the assembly of the normal equations sums ``7 ** d`` moments a sample into its
    cell. One sample a slot, that is a scatter of every sample's moments (a surface's
    343), slow on a CPU; by groups, a batched product of each group's per-axis Bernstein
    values and one scatter a group ([`jurs.internal.normal_equations`][]). F likewise
    gathers a group's ``4 ** d`` coefficients once, not every sample's
    (``grouped_values``; docs/design.md section 5, "Surfaces: the same code in 3D")."""
    position = np.zeros(local.cell.shape[0], np.int32)
    position[slot[valid]] = np.flatnonzero(valid.reshape(-1))
    return eqx.tree_at(
        lambda x: (x.group_slot, x.group_filled, x.group_position),
        local,
        jax.device_put((slot.astype(np.int32), valid.astype(local.s.dtype), position)),
        is_leaf=lambda x: x is None,
    )


def map_groups(fn, local: LocalBasis) -> Array:
    """``fn(slot, filled)`` over the groups of ``local`` (``(c, K)`` slots and fills),
    ``GROUP_CHUNK`` groups at a time, its ``(c, ...)`` results joined to ``(G, ...)``.
    Padding groups take slot 0 with fill 0."""
    slot, filled = local.group_slot, local.group_filled
    assert slot is not None and filled is not None  # the group fields are set together
    groups = slot.shape[0]
    chunk = min(groups, GROUP_CHUNK)
    pad = (-groups) % chunk

    def blocks(x):
        x = jnp.pad(x, ((0, pad), (0, 0)))
        return x.reshape((-1, chunk) + x.shape[1:])

    out = jax.lax.map(lambda b: fn(*b), (blocks(slot), blocks(filled)))
    return out.reshape((-1,) + out.shape[2:])[:groups]


def grouped_values(local: LocalBasis, flat: Array, shape: tuple[int, ...]) -> Array:
    """F of the flat grids ``(..., size)`` by the slots' groups: each group's ``4 ** d``
    coefficients gathered once and contracted with each entry's per-axis basis values one
    axis at a time (never the ``4 ** d`` products, which ran slower; docs/performance.md), then
    read back in slot order; ``(..., S)``."""
    assert local.group_position is not None  # the group fields are set together
    offsets = jnp.asarray(patch_offsets(shape))
    axes = "xyz"[: len(shape)]
    spec = f"...c{axes}," + ",".join(f"ck{a}" for a in axes) + "->...ck"

    def values(slot, filled):  # (c, K) -> (c, ..., K); padding entries are never read
        corner = patch_corner(local.cell[slot[:, 0]], shape)
        coeffs = jnp.take(flat, corner[:, None] + offsets, axis=-1)  # (..., c, 4 ** d)
        coeffs = coeffs.reshape(coeffs.shape[:-1] + (4,) * len(shape))
        basis = [cubic_weights(t) for t in local.t[:, slot]]  # d x (c, K, 4)
        out = jnp.einsum(spec, coeffs, *basis, precision=jax.lax.Precision.HIGHEST)
        return jnp.moveaxis(out, -2, 0)

    grouped = map_groups(values, local)  # (G, ..., K)
    grouped = jnp.moveaxis(grouped, 0, -2).reshape(flat.shape[:-1] + (-1,))
    return jnp.take(grouped, local.group_position, axis=-1)
