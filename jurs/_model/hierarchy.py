"""Truncated hierarchical cubic B-splines (THB) on a box: fine cells only where asked.

Level 0 is the uniform cubic basis of ``jurs._model.basis`` on ``base`` cells along each
axis; level ``l`` halves the cells of level ``l - 1``. The domain ``Omega_0`` is the whole
box; ``Omega_{l+1}`` is the union of the level-``l`` cells chosen for refinement (each
split into ``2^d`` level-``l+1`` cells), nested by construction. A point's *leaf* is the
finest cell that holds it; the leaves partition the box.

**Active functions** (Kraft's selection). A level-``l`` B-spline is active when its support
(within the box) lies in ``Omega_l`` and not in ``Omega_{l+1}``. **Truncation**
(Giannelli, Juettler and Speleers 2012): an active function is refined to each finer level
(cubic subdivision, ``B^l_i = sum_k (1, 4, 6, 4, 1)_k / 8 B^{l+1}_{2i-3+k}`` per axis) and,
there, its terms on functions whose support lies in ``Omega_{l+1}`` are dropped. The
truncated basis is non-negative, linearly independent, a partition of unity, and spans the
same space as the plain hierarchical basis; a spline of a coarse level is represented
exactly (docs/design.md section 8).

**Evaluation without a dense finest grid.** By linearity a THB spline ``sum c_tau tau`` is,
on the leaves of level ``l``, the level-``l`` B-spline with *cascaded* coefficients

    a^0 = c^0,   a^{l+1} = keep_{l+1} * (R_l a^l) + c^{l+1},

``R_l`` the subdivision, ``keep`` zero on the functions whose support lies in
``Omega_{l+1}``. Each level keeps ``a^l`` only on its *relevant* functions (those whose
support meets ``Omega_l``), looked up by a sorted search of integer keys; nothing is ever
sized by the finest level's full grid.

The structure (which cells, which functions) is built on the host from concrete data, like
the sample layout of a uniform fit; the values (coefficients, basis values at points) are
JAX arrays, so a fit through it can be jitted and differentiated.
"""

from __future__ import annotations

import functools
import itertools
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .._threads import by_rows
from .precision import on_device

#: Cubic B-spline subdivision mask: ``B^l_i = sum_k SUBDIVISION[k] B^{l+1}_{2i-3+k}``.
SUBDIVISION = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 8.0


#: Largest flat key held in int32 (JAX without x64 has no int64).
MAX_KEY = 2**31 - 1


@functools.cache
def cube_offsets(ndim: int, count: int) -> np.ndarray:
    """All ``count ** ndim`` integer offsets in ``[0, count)^d``, row-major; ``(k, d)``
    (cached, read-only)."""
    out = np.array(list(itertools.product(range(count), repeat=ndim)), dtype=np.int64)
    out = out.reshape(-1, ndim)
    out.flags.writeable = False
    return out


def ravel_keys(index: np.ndarray, extent: tuple[int, ...]) -> np.ndarray:
    """Row-major flat keys of multi-indices ``(..., d)`` inside ``extent``."""
    key = index[..., 0].astype(np.int64)
    for axis in range(1, len(extent)):
        key = key * extent[axis] + index[..., axis]
    return key


def unravel_keys(key: np.ndarray, extent: tuple[int, ...]) -> np.ndarray:
    return np.stack(np.unravel_index(key, extent), axis=-1).astype(np.int64)


#: Key ranges up to this many entries are looked up in a table (``_KeySet``), larger ones
#: by a sorted search. The table is allocated zeroed (untouched pages cost nothing) and
#: read at random: on a 2D hierarchy it replaces a slower binary search per key
#: (docs/performance.md).
TABLE_KEYS = 1 << 24


class _KeySet:
    """A sorted unique array of flat keys in ``[0, span)`` with membership and position
    queries: a table of positions where the span is at most ``TABLE_KEYS``, a sorted search
    beyond. Both answer alike."""

    def __init__(self, keys: np.ndarray, span: int):
        self.keys = keys
        self.table = None
        if span <= TABLE_KEYS and keys.size:
            self.table = np.zeros(span, dtype=np.int32)
            self.table[keys] = np.arange(1, keys.size + 1, dtype=np.int32)

    def member(self, keys: np.ndarray) -> np.ndarray:
        """Whether each key (in ``[0, span)``) is in the set."""
        if self.table is not None:
            return self.table[keys] > 0
        return is_member(keys, self.keys)

    def position(self, keys: np.ndarray) -> np.ndarray:
        """The index of each key in the set; every key must be present."""
        if self.table is None:
            return index_in(keys, self.keys)
        at = self.table[keys] - 1  # int32, as the hierarchy stores positions
        if np.any(at < 0):
            raise AssertionError("hierarchy: a function's key is missing from its level")
        return at


#: Offsets of a cell's ``4^d`` functions merged at a time by ``_functions_over``'s sort.
OFFSETS_AT_ONCE = 8


def _functions_over(cells: np.ndarray, extent: tuple[int, ...]) -> np.ndarray:
    """The sorted flat keys, in the function grid ``extent``, of the ``4^d`` functions over
    each of ``cells`` (``(k, d)`` multi-indices). A cell plus an offset stays inside the
    function grid, so its key is the sum of the two keys. Marked in a table one offset at
    a time where the span is small beside the keys (no sort), else merged by
    ``np.unique`` ``OFFSETS_AT_ONCE`` offsets at a time: never a ``(k, 4^d)`` array of
    keys, which was the largest array of a fine hierarchy's build."""
    span = int(np.prod(extent))
    base = ravel_keys(cells, extent)
    offsets = ravel_keys(cube_offsets(len(extent), 4), extent)
    if span <= TABLE_KEYS and span <= 8 * base.size * offsets.size:
        table = np.zeros(span, dtype=bool)
        for offset in offsets:
            table[base + offset] = True
        return np.flatnonzero(table)
    out = np.zeros(0, base.dtype)
    for start in range(0, offsets.size, OFFSETS_AT_ONCE):
        chunk = base[:, None] + offsets[None, start : start + OFFSETS_AT_ONCE]
        out = np.unique(np.concatenate([out, chunk.ravel()]))
    return out


def is_member(keys: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """Whether each key is in the sorted unique array ``sorted_set``."""
    if sorted_set.size == 0:
        return np.zeros(keys.shape, dtype=bool)
    at = np.minimum(np.searchsorted(sorted_set, keys), sorted_set.size - 1)
    return sorted_set[at] == keys


def index_in(keys: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """Index of each key in ``sorted_set``; every key must be present."""
    at = np.searchsorted(sorted_set, keys)
    if np.any(at >= sorted_set.size) or np.any(
        sorted_set[np.minimum(at, sorted_set.size - 1)] != keys
    ):
        raise AssertionError("hierarchy: a function's key is missing from its level")
    return at


class Hierarchy(eqx.Module):
    """The structure of a THB basis: levels, leaves, active functions and the cascade.

    Build it with [`build_hierarchy`][jurs.internal.build_hierarchy]. Per level ``l`` (all
    arrays ``int32`` or float, tuples indexed by level):

    * ``function_keys[l]``: sorted flat keys (row-major in the ``(n_l + 3)^d`` function
      grid) of the relevant functions, those whose support meets ``Omega_l``;
    * ``leaf_keys[l]``: sorted flat keys (in the ``n_l^d`` cell grid) of the leaves;
    * ``active[l]``: positions, in ``function_keys[l]``, of the active functions; the
      coefficient vector of a spline is the active functions of level 0, then 1, ...;
    * ``parents[l]`` (``l >= 1``): for each relevant function, the ``3^d`` level-``l - 1``
      positions it is refined from; their subdivision weights (0 pads where an axis has
      two parents) are ``parent_weights(l)``, computed from the keys;
    * ``keep[l]``: 1 where the refined coefficient survives truncation, 0 where the
      function's support lies in ``Omega_l``;
    * ``edges[l]``, ``edge_weights[l]``: the regulariser's neighbour pairs of level ``l``
      (positions in ``function_keys[l]``), those that sit on the level's leaves, and their
      weight ``(h_l / h_finest)^(d - 2)`` (see
      [`hierarchy_regulariser`][jurs.internal.hierarchy_regulariser]).

    ``lower``, ``upper`` are the box; ``base`` the level-0 cells per axis (static).
    """

    lower: Array
    upper: Array
    function_keys: tuple[Array, ...]
    leaf_keys: tuple[Array, ...]
    active: tuple[Array, ...]
    parents: tuple[Array, ...]
    keep: tuple[Array, ...]
    edges: tuple[Array, ...]
    edge_weights: tuple[Array, ...]
    base: tuple[int, ...] = eqx.field(static=True)

    @property
    def ndim(self) -> int:
        return len(self.base)

    @property
    def num_levels(self) -> int:
        return len(self.function_keys)

    def cells(self, level: int) -> tuple[int, ...]:
        """Cells along each axis of the box at ``level``."""
        return tuple(n << level for n in self.base)

    def functions(self, level: int) -> tuple[int, ...]:
        """The extent of the level's full function grid (``n_l + 3`` per axis)."""
        return tuple(n + 3 for n in self.cells(level))

    def cell_width(self, level: int, xp=jnp) -> Array:
        """The sides of a cell of ``level``; ``xp=numpy`` on the host (the same arithmetic
        on concrete JAX arrays would compile it)."""
        lower, upper = xp.asarray(self.lower), xp.asarray(self.upper)
        return (upper - lower) / xp.asarray(self.cells(level), lower.dtype)

    def parent_weights(self, level: int, xp=jnp) -> Array:
        """``(k, 3^d)``: the subdivision weights each relevant function of ``level`` (>= 1)
        takes from its ``parents[level]``, in the hierarchy's float dtype; ``xp=numpy`` on
        the host. They follow from the parity of the function's index along each axis
        (``subdivision_weights``), so they are computed here from its key rather than
        stored: a float per parent of every function was most of a fine hierarchy's
        memory."""
        keys = xp.asarray(self.function_keys[level])
        code = xp.zeros(keys.shape, keys.dtype)
        stride = 1
        for axis, extent in reversed(list(enumerate(self.functions(level)))):
            odd = ((keys // stride) % extent + 3) % 2
            code = code + odd * (1 << (self.ndim - 1 - axis))
            stride *= extent
        table = xp.asarray(parity_weights(self.ndim), xp.asarray(self.lower).dtype)
        return table[code]

    @property
    def num_active(self) -> int:
        """Active functions over all levels: the length of a coefficient vector."""
        return sum(int(a.shape[0]) for a in self.active)

    @property
    def level_sizes(self) -> tuple[int, ...]:
        """Relevant functions per level (the length of each cascaded ``a^l``)."""
        return tuple(int(k.shape[0]) for k in self.function_keys)

    @property
    def active_counts(self) -> tuple[int, ...]:
        return tuple(int(a.shape[0]) for a in self.active)


def _support_inside(functions: np.ndarray, cells: tuple[int, ...], region: _KeySet) -> np.ndarray:
    """Whether each function's support within the box lies in ``region`` (flat keys of
    cells at the same level); ``functions (k, d)`` multi-indices. Where the region has a
    table (its level's cells at most ``TABLE_KEYS``), by counting the cells outside it
    in each support (``_cells_outside``): ``2^d`` reads a function, not ``4^d``. Beyond,
    each function's ``4^d`` cells looked up, the functions shared out over the host's
    threads (``by_rows``)."""
    if region.table is not None:
        return _cells_outside(functions, cells, region) == 0
    return by_rows(lambda part: _support_inside_of(part, cells, region), functions)


def _cells_outside(functions: np.ndarray, cells: tuple[int, ...], region: _KeySet) -> np.ndarray:
    """For each function (``(k, d)`` multi-indices), how many cells of its support within
    the box lie outside ``region``: a box sum over the level's cell grid, from its prefix
    sums (``2^d`` corners a function). The grid is padded by 4 cells below (3 for the
    support cells before the box, 1 for the prefix sums' zero) and 3 above, so that a
    function ``f``'s cells ``f - 3 .. f`` are the padded ``f + 1 .. f + 4``."""
    ndim = len(cells)
    outside = np.ones(int(np.prod(cells)), bool)
    outside[region.keys] = False
    # int32: the counts are at most the cells of a table-sized level (TABLE_KEYS).
    sums = np.zeros(tuple(n + 7 for n in cells), np.int32)
    sums[tuple(slice(4, 4 + n) for n in cells)] = outside.reshape(cells)
    del outside
    for axis in range(ndim):
        np.cumsum(sums, axis=axis, out=sums)
    count = np.zeros(functions.shape[0], np.int64)
    for corner in itertools.product((0, 1), repeat=ndim):
        at = tuple(functions[:, axis] + 4 * corner[axis] for axis in range(ndim))
        count += (-1) ** (ndim - sum(corner)) * sums[at]
    return count


def _support_inside_of(
    functions: np.ndarray, cells: tuple[int, ...], region: _KeySet
) -> np.ndarray:
    """``_support_inside`` of one part of the functions."""
    ndim = functions.shape[1]
    strides = [int(np.prod(cells[axis + 1 :])) for axis in range(ndim)]
    # Per axis and offset o in 0..3: the support's cell f - 3 + o, whether it lies in the
    # box, and its (clipped) share of the flat key.
    parts, in_box = [], []
    for axis in range(ndim):
        cell = functions[:, axis, None] - 3 + np.arange(4)
        in_box.append((cell >= 0) & (cell < cells[axis]))
        parts.append(np.clip(cell, 0, cells[axis] - 1) * strides[axis])
    inside = np.ones(functions.shape[0], dtype=bool)
    for offset in cube_offsets(ndim, 4):
        key = parts[0][:, offset[0]]
        box = in_box[0][:, offset[0]]
        for axis in range(1, ndim):
            key = key + parts[axis][:, offset[axis]]
            box = box & in_box[axis][:, offset[axis]]
        inside &= ~box | region.member(key)
    return inside


def _subdivision_terms(odd: np.ndarray) -> np.ndarray:
    """``(k, 3)``: the subdivision terms ``k`` (``SUBDIVISION[k]``) of a function's three
    parents along one axis, child ``j = 2 i - 3 + k`` of parent ``i``: ``j + 3`` even
    takes ``k = 0, 2, 4``, odd ``k = 1, 3`` and the first parent again (weight 0)."""
    return np.where(np.asarray(odd)[:, None], np.array([1, 3, 1]), np.array([0, 2, 4]))


def subdivision_weights(odd: np.ndarray) -> np.ndarray:
    """``(k, 3^d)``: the weights a function takes from its ``3^d`` parents (``_parents``'
    order), given whether its index ``j + 3`` is odd along each axis (``odd (k, d)``):
    child ``j = 2 i - 3 + k`` of parent ``i`` takes ``SUBDIVISION[k]``, even ``j + 3``
    from ``k = 0, 2, 4``, odd from ``k = 1, 3`` (and a padding parent of weight 0). They
    depend on that parity alone, so a hierarchy computes them (``Hierarchy.parent_weights``)
    instead of storing a float per parent of every function."""
    odd = np.asarray(odd, bool)
    count, ndim = odd.shape
    weight = np.ones((count,) + (1,) * ndim)
    for axis in range(ndim):
        ks = _subdivision_terms(odd[:, axis])
        axis_weight = SUBDIVISION[ks] * np.where(odd[:, axis, None], np.array([1.0, 1.0, 0.0]), 1.0)
        shape = [count] + [1] * ndim
        shape[1 + axis] = 3
        weight = weight * axis_weight.reshape(shape)
    return weight.reshape(count, -1)


@functools.cache
def parity_weights(ndim: int) -> np.ndarray:
    """``subdivision_weights`` of every parity pattern, ``(2^d, 3^d)``, row ``sum_a odd_a
    2^(d-1-a)``."""
    return subdivision_weights(cube_offsets(ndim, 2).astype(bool))


def _parents(functions: np.ndarray, coarse_extent: tuple[int, ...]) -> np.ndarray:
    """The ``3^d`` coarser functions each function is refined from, as flat keys in the
    coarser level's function grid ``coarse_extent``, ``(k, 3^d)``, in row-major order of
    their per-axis offsets; an axis with two parents repeats its first one, with weight 0
    (``subdivision_weights``).

    Built by broadcasting the per-axis ``(k, 3)`` keys: a ``(k, 3^d, d)`` array of
    multi-indices, raveled after, took a third of a fine 3D hierarchy's build
    (docs/performance.md)."""
    ndim = functions.shape[1]
    # int32: every key of a hierarchy fits (MAX_KEY), and the array is (k, 3^d).
    key = np.zeros((functions.shape[0],) + (1,) * ndim, dtype=np.int32)
    stride = 1
    for axis in reversed(range(ndim)):
        j = functions[:, axis]
        ks = _subdivision_terms((j + 3) % 2 == 1)
        shape = [functions.shape[0]] + [1] * ndim
        shape[1 + axis] = 3
        key = key + (((j[:, None] + 3 - ks) // 2) * stride).astype(np.int32).reshape(shape)
        stride *= coarse_extent[axis]
    return key.reshape(functions.shape[0], -1)


def build_hierarchy(
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    base: tuple[int, ...],
    refine: list[np.ndarray],
    dtype=None,
) -> Hierarchy:
    """The THB structure on the box ``[lower, upper]`` with ``base`` level-0 cells per axis.

    ``refine[l]`` holds the level-``l`` cells to split (flat row-major keys in the level's
    cell grid, or ``(k, d)`` multi-indices); cells outside ``Omega_l`` are ignored, so the
    domains nest whatever is asked. ``len(refine)`` levels of refinement follow level 0
    (fewer where a level refines nothing). Host work, on concrete data.
    """
    ndim = len(base)
    base = tuple(int(n) for n in base)
    if any(n < 1 for n in base):
        raise ValueError(f"base cells must be at least 1 per axis, got {base}")
    lower_np = np.asarray(lower, dtype=float)
    upper_np = np.asarray(upper, dtype=float)
    dtype = dtype or jnp.result_type(float)

    def cells_at(level):
        return tuple(n << level for n in base)

    # Domains as sorted flat keys of their cells at their own level.
    omega = [np.arange(int(np.prod(base)), dtype=np.int64)]
    refined = []
    for level, asked in enumerate(refine):
        asked = np.asarray(asked, dtype=np.int64)
        if asked.ndim == 2:
            asked = ravel_keys(asked, cells_at(level))
        split = np.intersect1d(np.unique(asked), omega[level], assume_unique=True)
        if split.size == 0:
            break
        refined.append(split)
        children = (
            unravel_keys(split, cells_at(level))[:, None, :] * 2 + cube_offsets(ndim, 2)[None]
        ).reshape(-1, ndim)
        omega.append(np.unique(ravel_keys(children, cells_at(level + 1))))
    levels = len(omega)
    refined.append(np.zeros(0, dtype=np.int64))
    finest = levels - 1
    if (max(cells_at(finest)) + 3) ** ndim > MAX_KEY:
        raise ValueError(
            f"a hierarchy of {levels} levels on {base} base cells needs keys beyond int32; "
            "use fewer levels or fewer base cells"
        )

    function_keys, leaf_keys, active, parents, keep, edges, edge_weights = ([] for _ in range(7))
    previous = None
    for level in range(levels):
        cells = cells_at(level)
        extent = tuple(n + 3 for n in cells)
        region = unravel_keys(omega[level], cells)
        funcs = _functions_over(region, extent)
        function_set = _KeySet(funcs, int(np.prod(extent)))
        multi = unravel_keys(funcs, extent)
        in_level = (
            _support_inside(multi, cells, _KeySet(omega[level], int(np.prod(cells))))
            if level
            else np.ones(funcs.size, bool)
        )
        in_finer = _support_inside(multi, cells, _KeySet(refined[level], int(np.prod(cells))))
        function_keys.append(funcs)
        leaves = np.setdiff1d(omega[level], refined[level], assume_unique=True)
        leaf_set = _KeySet(leaves, int(np.prod(cells)))
        leaf_keys.append(leaves)
        active.append(np.flatnonzero(in_level & ~in_finer))
        keep.append((~in_level).astype(float))
        if level:
            # Padding parents (weight 0) name the first parent again, a function the
            # coarser level has.
            flat = _parents(multi, tuple(n + 3 for n in cells_at(level - 1)))
            assert previous is not None
            parents.append(previous.position(flat))
        else:
            parents.append(np.zeros((funcs.size, 0), dtype=np.int64))
        previous = function_set
        pairs, pair_weight = [], []
        scale = 2.0 ** ((finest - level) * (ndim - 2))  # (h_l / h_finest)^(d - 2)
        # The pair sits between the two functions' centres (node i - 1 in cell units):
        # at the cell i_axis - 1 along the axis, the cell i - 1 across it (clamped into
        # the box). It belongs to the level whose leaf holds that cell.
        on_leaf = leaf_set.member(ravel_keys(np.clip(multi - 1, 0, np.asarray(cells) - 1), cells))
        stride = 1
        for axis in reversed(range(ndim)):
            # The neighbour one step up along the axis has the key ``key + stride``.
            ok = on_leaf & (multi[:, axis] + 1 < extent[axis])
            nkey = np.where(ok, funcs + stride, funcs)
            ok &= function_set.member(nkey)
            first = np.flatnonzero(ok)
            pairs.append((axis, np.stack([first, function_set.position(nkey[first])], -1)))
            pair_weight.append((axis, np.full(first.size, scale)))
            stride *= extent[axis]
        edges.append(np.concatenate([p for _, p in sorted(pairs, key=lambda t: t[0])]))
        edge_weights.append(np.concatenate([w for _, w in sorted(pair_weight, key=lambda t: t[0])]))

    # on_device: nothing compiled per shape, as jnp.asarray would (30 programs a cloud).
    def ints(arrays):
        return tuple(on_device(a, np.int32) for a in arrays)

    def floats(arrays):
        return tuple(on_device(a, dtype) for a in arrays)

    return Hierarchy(
        lower=on_device(lower_np, dtype),
        upper=on_device(upper_np, dtype),
        function_keys=ints(function_keys),
        leaf_keys=ints(leaf_keys),
        active=ints(active),
        parents=ints(parents),
        keep=floats(keep),
        edges=ints(edges),
        edge_weights=floats(edge_weights),
        base=base,
    )


def refined_cells(hierarchy: Hierarchy) -> list[np.ndarray]:
    """The ``refine`` list that [`build_hierarchy`][jurs.internal.build_hierarchy] turns
    back into this hierarchy: at each level but the finest, the cells above a finer leaf
    (sorted flat keys, host)."""
    ndim = hierarchy.ndim
    out = []
    for level in range(hierarchy.num_levels - 1):
        cells = hierarchy.cells(level)
        above = [
            unravel_keys(np.asarray(hierarchy.leaf_keys[finer]), hierarchy.cells(finer))
            >> (finer - level)
            for finer in range(level + 1, hierarchy.num_levels)
        ]
        keys = ravel_keys(np.concatenate(above).reshape(-1, ndim), cells)
        out.append(np.unique(keys))
    return out


def refine_near(
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    base: tuple[int, ...],
    levels: int,
    samples: Float[ArrayLike, "n d"],
    band: int = 2,
) -> list[np.ndarray]:
    """The cells to split for a band around ``samples``: at each level ``l < levels``, the
    level-``l`` cells within ``band`` cells (Chebyshev distance, in that level's cells) of a
    cell holding a sample. The band narrows in absolute terms as the cells shrink, so the
    finest level covers about ``2 band + 1`` of its cells across the data and the active
    set grows with the data's boundary, not with the box."""
    samples = np.asarray(samples, dtype=float)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    ndim = samples.shape[1]
    around = cube_offsets(ndim, 2 * band + 1) - band
    out = []
    for level in range(levels):
        cells = np.asarray([n << level for n in base])
        hit = np.clip(np.floor((samples - lower) / (upper - lower) * cells), 0, cells - 1)
        hit = np.unique(ravel_keys(hit.astype(np.int64), tuple(cells)))
        near = (unravel_keys(hit, tuple(cells))[:, None, :] + around[None]).reshape(-1, ndim)
        near = near[np.all((near >= 0) & (near < cells), axis=1)]
        out.append(np.unique(ravel_keys(near, tuple(cells))))
    return out


def cascade(
    hierarchy: Hierarchy, coeffs: Float[Array, "*lead n"] | np.ndarray, xp=jnp
) -> Float[Array, "*lead s"]:
    """The cascaded coefficients ``a^0, ..., a^L`` of a THB spline, concatenated level by
    level over each level's relevant functions (module docstring). ``coeffs`` is the
    active functions' vector (leading axes carry several splines at once). Linear in
    ``coeffs``: its transpose (by JAX) spreads values back to the active functions.
    ``xp=numpy`` on the host: each level's truncated subdivision as a sparse product
    (``refinement_matrix``), nothing compiled and no cascade matrix built
    (``cascade_matrix`` costs about as much as assembling the fit)."""
    if xp is np:
        host: Any = _host_cascade(hierarchy, np.asarray(coeffs))  # NumPy, as xp says
        return host
    lead = coeffs.shape[:-1]
    out = []
    start = 0
    previous = None
    for level in range(hierarchy.num_levels):
        count = hierarchy.active_counts[level]
        mine = coeffs[..., start : start + count]
        start += count
        size = hierarchy.level_sizes[level]
        active = jnp.asarray(hierarchy.active[level])
        placed = jnp.zeros(lead + (size,), coeffs.dtype).at[..., active].add(mine)
        if previous is None:
            current = placed
        else:
            parents = jnp.asarray(hierarchy.parents[level])
            weights = hierarchy.parent_weights(level, jnp)
            refined = jnp.sum(previous[..., parents] * weights, axis=-1)
            current = jnp.asarray(hierarchy.keep[level]) * refined + placed
        out.append(current)
        previous = current
    return jnp.concatenate(out, axis=-1)


def refinement_matrix(hierarchy: Hierarchy, level: int, truncated: bool = True):
    """The cubic subdivision ``R_{level-1}`` (``level >= 1``) as a SciPy CSR matrix: rows
    the level's relevant functions, columns the coarser level's, ``3^d`` entries a row;
    ``truncated``: ``keep_level * R_{level-1}``, the truncated rows zero (the cascade's
    step), else untruncated (the nested spaces' prolongation). Built from ``parents`` as
    they are: no (row, column) pairs to sort; repeated padding parents have weight 0 and
    add nothing."""
    from scipy import sparse

    parents = np.asarray(hierarchy.parents[level])
    weights = hierarchy.parent_weights(level, np).astype(float)
    if truncated:
        weights *= np.asarray(hierarchy.keep[level], float)[:, None]
    size, width = parents.shape
    return sparse.csr_matrix(
        (weights.ravel(), parents.ravel(), np.arange(0, size * width + 1, width)),
        shape=(size, hierarchy.level_sizes[level - 1]),
    )


def _host_cascade(hierarchy: Hierarchy, coeffs: np.ndarray) -> np.ndarray:
    """``cascade`` in NumPy and SciPy: each level's refinement one sparse product (a
    gather of ``3^d`` parents and a sum over them allocates ``3^d`` times the level)."""
    lead = coeffs.shape[:-1]
    flat = coeffs.reshape(-1, coeffs.shape[-1]).T  # (n, splines)
    out, start, previous = [], 0, None
    for level in range(hierarchy.num_levels):
        count = hierarchy.active_counts[level]
        current = np.zeros((hierarchy.level_sizes[level], flat.shape[1]), flat.dtype)
        if previous is not None:
            current += refinement_matrix(hierarchy, level) @ previous
        # The active positions are distinct.
        current[np.asarray(hierarchy.active[level])] += flat[start : start + count]
        start += count
        out.append(current)
        previous = current
    return np.concatenate(out, axis=0).T.reshape(lead + (-1,))


def cascade_matrix(hierarchy: Hierarchy):
    """The cascade as a SciPy sparse matrix (host): rows the concatenated relevant
    functions of every level, columns the active functions; ``cascade(c) = M @ c``. Rows
    hold the truncated functions' coefficients, so its size follows the active band
    (a truncated function keeps terms only near the border of the finer domain)."""
    from scipy import sparse

    n = hierarchy.num_active
    blocks = []
    start = 0
    previous = None
    for level in range(hierarchy.num_levels):
        size, count = hierarchy.level_sizes[level], hierarchy.active_counts[level]
        rows = np.asarray(hierarchy.active[level])
        placed = sparse.csr_matrix(
            (np.ones(count), (rows, start + np.arange(count))), shape=(size, n)
        )
        start += count
        if previous is None:
            current = placed
        else:
            # No (row, column) pairs to sort: they were most of this function's memory on
            # fine hierarchies.
            current = sparse.csr_matrix(refinement_matrix(hierarchy, level) @ previous + placed)
            current.eliminate_zeros()
        blocks.append(current)
        previous = current
    return sparse.vstack(blocks).tocsr()


def hierarchy_regulariser(hierarchy: Hierarchy, coeffs: Float[Array, " n"]) -> Array:
    """The paper's R(C) (eq. 31) carried to the hierarchy: ``2 sum_l (h_l / h_L)^(d-2)
    sum (a^l_i - a^l_j)^2`` over each level's neighbour pairs that sit on its leaves.

    On a hierarchy refined everywhere to one level (or not refined at all) it is exactly
    eq. 31 on that level's grid; elsewhere each leaf region contributes the grid Laplacian
    of its own level, ``(h_l / h_L)^(d-2)`` keeping the sum about ``2 int |grad g|^2 /
    h_L^(d-2)`` as the uniform R is (see ``jurs._fit.settings.scale_free_lam``)."""
    a = cascade(hierarchy, coeffs)
    total = jnp.zeros((), a.dtype)
    start = 0
    for lev in range(hierarchy.num_levels):
        pairs = hierarchy.edges[lev] + start
        diff = a[pairs[:, 0]] - a[pairs[:, 1]]
        total = total + jnp.sum(hierarchy.edge_weights[lev] * diff * diff)
        start += hierarchy.level_sizes[lev]
    return 2.0 * total
