"""An adaptive spline packed for evaluation: one compiled program per size class.

[`jurs.AdaptiveSpline`][] evaluates through its ``Hierarchy``, whose per-level arrays fix
the shapes of any program that reads them: every new fit (every new hierarchy) would
compile its evaluation again, seconds for a user's first ``sol.spline(x)`` after a fit
that took less. Evaluation needs less than the hierarchy: the leaves and the relevant
functions of every level as flat sorted keys, and the cascaded coefficients of numerator
and denominator (eq. 14). ``pack`` builds those on the host, each level's keys shifted
past the previous levels' grids so that all levels form one sorted array, and pads them
(and the number of levels) to size classes:

* keys and coefficients to the next power of two (at least ``MIN_KEYS``), padded with
  ``PAD_KEY``, which no query equals;
* levels to a multiple of ``LEVEL_CLASS``, the extra levels holding no leaf (their
  queries are ``-1``, below every key);
* the points evaluated, to the next power of two (at least ``MIN_POINTS``), with copies
  of the first.

So a program compiled for one fit serves every fit of the same dimension, dtype and size
class. Packing reads concrete arrays on the host, so only a spline and points outside
any JAX transformation take this path (``packed_values_at``); traced ones (``jax.grad``
through a fit, ``jax.jit`` of a loss) evaluate through the hierarchy, the same function.
Values and gradients agree with the hierarchy's evaluation to rounding
(``tests/test_hierarchy.py``).
"""

from __future__ import annotations

from collections import OrderedDict

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.core import Tracer
from jaxtyping import Float

from .hierarchy import MAX_KEY, Hierarchy, cascade_matrix, cube_offsets
from .leaves import hierarchy_basis, local_values_and_gradients, rational_values_and_gradients
from .precision import on_device

#: Smallest padded length of the key and coefficient arrays.
MIN_KEYS = 256
#: Levels are padded to a multiple of this.
LEVEL_CLASS = 4
#: Smallest padded number of points evaluated.
MIN_POINTS = 256
#: Packed splines kept for their next evaluation (a fit's spline is evaluated again and
#: again: a level set, a plot, a loss), the most recently used first to stay.
CACHE_SIZE = 4
#: The padding key, above every real key (the shifted keys stay below it; ``pack``
#: refuses hierarchies whose keys would not).
PAD_KEY = MAX_KEY


class PackedSpline(eqx.Module):
    """The arrays an adaptive spline's evaluation reads (module docstring); ``L`` levels
    after padding. ``cells (L, d)`` per level and axis; ``leaf_keys (KL,)`` and
    ``function_keys (KF,)`` sorted, shifted by ``leaf_shift`` / ``function_shift (L,)``
    (``-1`` for padding levels); ``numerator``, ``denominator (KF,)`` the cascaded
    coefficients of ``w c`` and ``w``."""

    lower: Array
    upper: Array
    cells: Array
    leaf_keys: Array
    leaf_shift: Array
    function_keys: Array
    function_shift: Array
    numerator: Array
    denominator: Array


def _size_class(count: int) -> int:
    return max(MIN_KEYS, 1 << max(0, int(count - 1).bit_length()))


def _shifts(sizes: list[int]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)


def pack(hierarchy: Hierarchy, control, weights) -> PackedSpline | None:
    """The ``PackedSpline`` of the spline with ``control`` and ``weights`` on
    ``hierarchy``, built on the host (NumPy and SciPy: nothing is compiled); None where its
    shifted keys would leave int32 (a 3D hierarchy near 1024 finest cells a side), whose
    evaluation then goes through the hierarchy."""
    h = hierarchy
    levels, ndim = h.num_levels, h.ndim
    cells = [h.cells(lev) for lev in range(levels)]
    grids = [int(np.prod(h.functions(lev))) for lev in range(levels)]
    function_shift = _shifts(grids)
    leaf_shift = _shifts([int(np.prod(c)) for c in cells])
    if int(function_shift[-1]) + grids[-1] >= PAD_KEY:
        return None
    function_keys = np.concatenate(
        [np.asarray(h.function_keys[lev], np.int64) + function_shift[lev] for lev in range(levels)]
    )
    leaf_keys = np.concatenate(
        [np.asarray(h.leaf_keys[lev], np.int64) + leaf_shift[lev] for lev in range(levels)]
    )
    dtype = np.asarray(control).dtype
    weights = np.asarray(weights, np.float64)
    weighted = weights * np.asarray(control, np.float64)
    cascaded = cascade_matrix(h)
    numerator, denominator = cascaded @ weighted, cascaded @ weights

    padded_levels = -(-levels // LEVEL_CLASS) * LEVEL_CLASS
    extra = padded_levels - levels

    def padded(values, fill, dtype):
        out = np.full(_size_class(len(values)), fill, dtype)
        out[: len(values)] = values
        return on_device(out)

    return PackedSpline(
        lower=h.lower,
        upper=h.upper,
        cells=on_device(np.concatenate([cells, np.ones((extra, ndim), int)]), np.int32),
        leaf_keys=padded(leaf_keys, PAD_KEY, np.int32),
        leaf_shift=on_device(np.concatenate([leaf_shift, -np.ones(extra, int)]), np.int32),
        function_keys=padded(function_keys, PAD_KEY, np.int32),
        function_shift=on_device(np.concatenate([function_shift, -np.ones(extra, int)]), np.int32),
        numerator=padded(numerator, 0.0, dtype),
        denominator=padded(denominator, 0.0, dtype),
    )


def _ravel(index: Array, extent: Array) -> Array:
    """Row-major keys of multi-indices ``(..., d)`` in extents ``(..., d)``."""
    key = index[..., 0]
    for axis in range(1, index.shape[-1]):
        key = key * extent[..., axis] + index[..., axis]
    return key


def _leaves(packed: PackedSpline, x: Array) -> tuple[Array, Array, Array]:
    """``(level, cell, unit)``: each point's leaf (as ``locate_leaves``) and its
    coordinates in the unit box."""
    unit = (x - packed.lower) / (packed.upper - packed.lower)
    level = jnp.zeros(x.shape[0], jnp.int32)
    cell = jnp.zeros(x.shape, jnp.int32)
    for lev in range(packed.cells.shape[0]):
        cells = packed.cells[lev]
        here = jnp.clip(jnp.floor(unit * cells.astype(unit.dtype)), 0, cells - 1).astype(jnp.int32)
        shift = packed.leaf_shift[lev]
        # A padding level's queries are -1, below every key: never found.
        key = jnp.where(shift < 0, -1, _ravel(here, cells) + shift)
        at = jnp.clip(jnp.searchsorted(packed.leaf_keys, key), 0, packed.leaf_keys.shape[0] - 1)
        found = packed.leaf_keys[at] == key
        level = jnp.where(found, lev, level)
        cell = jnp.where(found[:, None], here, cell)
    return level, cell, unit


def _terms(packed: PackedSpline, x: Array):
    """The ``4^d`` cascaded numerator and denominator coefficients over each point's leaf,
    its local coordinates ``t`` and its leaf's cell widths."""
    level, cell, unit = _leaves(packed, x)
    cells = packed.cells[level]
    offsets = jnp.asarray(cube_offsets(x.shape[1], 4), jnp.int32)
    key = _ravel(cell[:, None, :] + offsets[None], (cells + 3)[:, None, :])
    key = key + packed.function_shift[level][:, None]
    keys = packed.function_keys
    positions = jnp.clip(jnp.searchsorted(keys, key), 0, keys.shape[0] - 1)
    t = unit * cells.astype(unit.dtype) - cell.astype(unit.dtype)
    widths = (packed.upper - packed.lower) / cells.astype(unit.dtype)
    return packed.numerator[positions], packed.denominator[positions], t, widths


def packed_values(packed: PackedSpline, x: Float[Array, "n d"]) -> Float[Array, " n"]:
    """g at ``x (n, d)`` (eq. 14 on the hierarchy)."""
    numerator, denominator, t, _ = _terms(packed, x)
    basis = hierarchy_basis(t)
    return jnp.sum(numerator * basis, axis=-1) / jnp.sum(denominator * basis, axis=-1)


def packed_values_and_gradients(
    packed: PackedSpline, x: Float[Array, "n d"]
) -> tuple[Float[Array, " n"], Float[Array, "n d"]]:
    """g and its spatial gradient at ``x (n, d)``: the quotient rule on eq. 14, each
    factor from the leaf's local pieces."""
    numerator, denominator, t, widths = _terms(packed, x)
    both, slopes = local_values_and_gradients(jnp.stack([numerator, denominator]), t, widths)
    return rational_values_and_gradients(both, slopes)


_packed_values = jax.jit(packed_values)
_packed_values_and_gradients = jax.jit(packed_values_and_gradients)
# (hierarchy, control, weights) by their ids -> (the three, kept so that the ids stay
# theirs, and the packed spline or None).
_cache: OrderedDict = OrderedDict()


def _concrete(*arrays) -> bool:
    """Whether ``arrays`` hold no tracer and no transformation is being traced: inside
    ``jax.jit`` a spline and points closed over are concrete, but every array the packed
    path makes (``device_put`` of its host arrays) would be a tracer, which it neither
    reads back on the host nor may keep in its cache."""
    leaves = jax.tree_util.tree_leaves(arrays)
    if any(isinstance(leaf, Tracer) for leaf in leaves):
        return False
    return not isinstance(jax.device_put(np.zeros((), np.float32)), Tracer)


def _packed(hierarchy: Hierarchy, control, weights) -> PackedSpline | None:
    if not all(isinstance(a, jax.Array) for a in (control, weights)):
        return pack(hierarchy, control, weights)  # NumPy arrays change in place: no cache
    key = (id(hierarchy), id(control), id(weights))
    if key in _cache:
        _cache.move_to_end(key)
        return _cache[key][-1]
    packed = pack(hierarchy, control, weights)
    _cache[key] = (hierarchy, control, weights, packed)
    while len(_cache) > CACHE_SIZE:
        _cache.popitem(last=False)
    return packed


def packed_values_at(hierarchy: Hierarchy, control, weights, x) -> Array | None:
    """g at ``x`` (``(n, d)`` or one point ``(d,)``) by the packed program, or None where
    the spline or ``x`` is traced, ``x`` is of another shape or empty, or the hierarchy
    does not pack (then the caller evaluates through the hierarchy)."""
    found = _evaluate(hierarchy, control, weights, x, False)
    return None if found is None else found[0]


def packed_gradients_at(hierarchy: Hierarchy, control, weights, x) -> Array | None:
    """The spatial gradient of g at ``x`` by the packed program, or None as
    ``packed_values_at``."""
    found = _evaluate(hierarchy, control, weights, x, True)
    return None if found is None else found[1]


def _evaluate(hierarchy: Hierarchy, control, weights, x, gradient: bool):
    """``(g, gradient or None)`` at ``x`` by the packed program, or None."""
    if not _concrete(hierarchy, control, weights, x):
        return None
    x = np.asarray(x)
    if x.ndim == 1 and x.shape == (hierarchy.ndim,):  # one point: unbatched results
        one = _evaluate(hierarchy, control, weights, x[None], gradient)
        return None if one is None else tuple(None if a is None else a[0] for a in one)
    if x.ndim != 2 or x.shape[1] != hierarchy.ndim or len(x) == 0:
        return None
    packed = _packed(hierarchy, control, weights)
    if packed is None:
        return None
    n = len(x)
    size = max(MIN_POINTS, 1 << (n - 1).bit_length())
    padded = np.concatenate([x, np.repeat(x[:1], size - n, axis=0)]).astype(
        np.result_type(x.dtype, np.asarray(control).dtype), copy=False
    )
    # Cut back on the host: slicing a JAX array compiles a small program per new length.
    if gradient:
        value, slope = _packed_values_and_gradients(packed, on_device(padded))
        return on_device(np.asarray(value)[:n]), on_device(np.asarray(slope)[:n])
    return on_device(np.asarray(_packed_values(packed, on_device(padded)))[:n]), None
