"""From points and outward normals to the sampled fitting problem (eq. 4-5, 9).

Each data point P_i with unit outward normal n_i gives three samples: P_i (target 0),
P_i + d n_i (target +eps, outside) and P_i - d n_i (target -eps, inside), stacked in that
order as in eq. 9, so the first m samples are the data points. The fitted function is
negative inside and positive outside.
"""

from __future__ import annotations

import os
from collections import namedtuple
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.core import Tracer

from .._model.basis import flat_cell, locate, num_cells
from .._model.spline import TABLE_MAX_SLOTS, LocalBasis, local_basis, with_table
from .sizes import padded_count, round_size

#: Default margin added around the samples' bounding box, as a fraction of its longest side.
DEFAULT_MARGIN = 0.1


class Problem(eqx.Module):
    """A fitting problem: samples, targets, the box and the grid, and their local basis.

    Build it with :func:`make_problem`. Every per-sample array (``samples``, ``targets``,
    ``mask``, ``is_data``, ``local``) is indexed the same way, by *slot*: the 3m samples of
    eq. 4 regrouped into buckets that share a cell (see :mod:`jurs._model.spline`), plus padding
    slots with ``mask`` 0. ``sample_index`` maps each slot to the paper's order (eq. 9: the
    m data points, then the outer, then the inner offsets). With ``bucket_size`` 1 the slots
    are exactly the paper's order. ``shape`` is static; all other fields are arrays, so a
    Problem can be traced, differentiated and batched.
    """

    points: Array  # (m, d) data points P (d = 2: a curve, 3: a surface)
    normals: Array  # (m, d) unit outward normals
    samples: Array  # (S, d) sample positions, P or P +/- d n (eq. 4)
    targets: Array  # (S,) b: 0, +eps or -eps (eq. 5, 9)
    mask: Array  # (S,) 1.0 for real samples, 0.0 for padding (layout or batched fits)
    is_data: Array  # (S,) 1.0 where the slot holds a real data point P_i (target 0)
    sample_index: Array  # (S,) int32 position in the paper's order [P, P + d n, P - d n]
    lower: Array  # (d,) box corner
    upper: Array  # (d,) box corner
    offset: Array  # d
    eps: Array  # epsilon
    local: LocalBasis  # basis at the samples
    shape: tuple[int, ...] = eqx.field(static=True)

    @property
    def ndim(self) -> int:
        """2 for curves, 3 for surfaces."""
        return len(self.shape)

    @property
    def num_points(self) -> int:
        """m, the number of data points (padding points included)."""
        return self.points.shape[0]


#: Largest automatic bucket size.
MAX_BUCKET_SIZE = 64
#: Largest automatic bucket size of the table form of small problems (their per-bucket
#: sums are unrolled in one kernel).
SMALL_MAX_BUCKET_SIZE = 16


def choose_bucket_size(cells: np.ndarray, count: int, small: bool = False) -> int:
    """Automatic bucket size, a power of two: the largest not above the median number of
    samples per occupied cell (at most ``MAX_BUCKET_SIZE``), so that most buckets are full
    and padding stays below about half the slots. ``small`` (the table form of small
    problems): the largest not above half that median (at most ``SMALL_MAX_BUCKET_SIZE``),
    where padding costs as much as extra buckets (measured on 640-point outlines at
    15 x 15, median 51 and 25 samples a cell: 16 and 8 were fastest)."""
    counts = np.bincount(cells, minlength=count)
    median = float(np.median(counts[counts > 0]))
    if not small:
        cap = MAX_BUCKET_SIZE
    else:
        cap, median = SMALL_MAX_BUCKET_SIZE, median / 2.0
    return int(min(cap, 2 ** int(np.floor(np.log2(max(median, 1.0))))))


def round_buckets(count: int) -> int:
    """``count`` buckets rounded up to one of eight sizes an octave (at most 1/8 more),
    so that clouds of similar size share one compiled fit."""
    if count <= 32:
        return count
    step = 1 << (int(count).bit_length() - 4)
    return -(-count // step) * step


def bucket_layout(cells: np.ndarray, bucket_size: int, count: int, num_buckets: int | None = None):
    """Group sample indices into buckets of ``bucket_size`` samples sharing a cell.

    ``cells`` (S,) is each sample's flat cell, ``count`` the number of cells. Returns
    ``(slot_sample, valid)``, both ``(num_buckets * bucket_size,)``: the sample in each slot
    and whether it is real. Padding slots repeat their bucket's first sample (so the basis
    stays well defined) and have ``valid`` False. A cell with more samples than a bucket
    holds gets several buckets. Buckets are in cell order; ``num_buckets`` (at least the
    number needed) appends empty buckets in the last cell.
    """
    k = bucket_size
    # A stable sort by cell; 16-bit keys sort by radix, several times faster.
    keys = cells.astype(np.uint16) if count <= 1 << 16 else cells
    order = np.argsort(keys, kind="stable").astype(np.int32)
    sorted_cells = cells[order]
    counts = np.bincount(cells, minlength=count)
    buckets_per_cell = -(-counts // k)
    first_slot = (np.cumsum(buckets_per_cell) - buckets_per_cell) * k
    cell_start = np.cumsum(counts) - counts
    # Position within its cell (rank) plus the cell's first slot: consecutive buckets of a
    # cell are consecutive slots.
    slot = (first_slot - cell_start)[sorted_cells] + np.arange(cells.shape[0])
    needed = int(buckets_per_cell.sum())
    slot_sample = np.full(max(needed, num_buckets or 0) * k, -1, dtype=np.int32)
    slot_sample[slot] = order
    slot_sample[needed * k :] = order[-1]
    slot_sample = slot_sample.reshape(-1, k)
    valid = slot_sample >= 0
    valid[needed:] = False
    slot_sample = np.where(valid, slot_sample, slot_sample[:, :1])
    return slot_sample.reshape(-1), valid.reshape(-1)


def stable_layout(
    cells: np.ndarray,
    sample_mask: np.ndarray,
    count: int,
    bucket_size: int | None = None,
    small: bool = False,
):
    """:func:`bucket_layout` of the real samples (``sample_mask`` > 0), sized from the
    number of slots (padding included) and the occupied cells rounded up by
    :func:`jurs._problem.sizes.round_size`, not from the exact counts: clouds padded to one size
    (:func:`jurs.fit`) whose samples occupy about as many cells get the same shapes, so one
    compiled fit. Padding samples take no bucket.

    The bucket size (None chooses) is the power of two :func:`choose_bucket_size` would take
    with the mean count per rounded occupied cell in place of the median. The number of
    buckets, ``ceil(S / K) + occupied``, bounds ``sum_cells ceil(count / K)`` for any
    placement of the real samples. Returns ``(slot_sample, valid, bucket_size)``.
    """
    real = np.flatnonzero(np.asarray(sample_mask) > 0)
    cells = np.asarray(cells)
    num_slots = cells.shape[0]
    occupied = min(
        count, round_size(int(np.count_nonzero(np.bincount(cells[real], minlength=count))))
    )
    if bucket_size is None:
        cap, per_cell = (
            (SMALL_MAX_BUCKET_SIZE, num_slots / occupied / 2.0)
            if small
            else (MAX_BUCKET_SIZE, num_slots / occupied)
        )
        bucket_size = int(min(cap, 2 ** int(np.floor(np.log2(max(per_cell, 1.0))))))
    num_buckets = -(-num_slots // bucket_size) + occupied
    slot, valid = bucket_layout(cells[real], bucket_size, count, num_buckets)
    return real[slot].astype(np.int32), valid, bucket_size


def offset_samples(points: Array, normals: Array, offset, eps, xp=jnp):
    """Samples and targets of eq. 4-5 and 9: ``[P, P + d n, P - d n]`` and ``[0, +eps, -eps]``.

    ``xp=numpy`` computes on the host (NumPy inputs and results)."""
    m = points.shape[0]
    samples = xp.concatenate([points, points + offset * normals, points - offset * normals])
    ones = xp.ones((m,), dtype=points.dtype)
    targets = xp.concatenate([0.0 * ones, eps * ones, -eps * ones])
    return samples, targets


def auto_domain(samples: Array, margin: float = DEFAULT_MARGIN, mask: Array | None = None, xp=jnp):
    """Bounding box of ``samples`` (those with ``mask`` 1, if given) grown on every side by
    ``margin`` x its longest side. ``xp=numpy`` computes on the host."""
    if mask is None:
        lo = xp.min(samples, axis=0)
        hi = xp.max(samples, axis=0)
    else:
        keep = mask[:, None] > 0
        lo = xp.min(xp.where(keep, samples, xp.inf), axis=0)
        hi = xp.max(xp.where(keep, samples, -xp.inf), axis=0)
    pad = margin * xp.max(hi - lo)
    return lo - pad, hi + pad


def normalise_grid(grid, ndim: int = 2) -> tuple[int, ...]:
    """``9`` or ``(9, 9)`` -> ``(9, 9)`` (``ndim`` 3: ``9`` or ``(9, 9, 9)`` -> ``(9, 9,
    9)``); raises ValueError for anything below 4 functions an axis."""
    kind = "a pair" if ndim == 2 else "a triple"
    if isinstance(grid, (int, np.integer)):
        grid = (grid,) * ndim
    try:
        shape = tuple(int(g) for g in grid)
        if any(int(g) != g for g in grid):
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(f"grid must be an int or {kind} of ints, got {grid!r}") from None
    if len(shape) != ndim:
        raise ValueError(f"grid must be {kind} of ints for {ndim}D points, got {grid!r}")
    if min(shape) < 4:
        raise ValueError(
            f"grid must be at least {' x '.join('4' * ndim)} for cubic B-splines, got {shape}"
        )
    return shape


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, Tracer) for x in jax.tree_util.tree_leaves(xs))


def _as_array(x, dtype=None):
    """``jnp.asarray(x, dtype)``; concrete values are converted on the host and transferred,
    which compiles nothing (an eager conversion compiles a small kernel on first use)."""
    if isinstance(x, jax.Array) or not _is_concrete(x):
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))


def check_nonnegative(name: str, value, *, strict: bool = False) -> None:
    """Raise ValueError unless ``value`` is a finite number >= 0 (> 0 when ``strict``);
    TypeError for something that is not a number (a string, None, ...).

    Traced values are not checked (their value is unknown at trace time).
    """
    if not _is_concrete(value):
        return
    if isinstance(value, (str, bytes)):  # NumPy would parse "1" as a number
        raise TypeError(f"{name} must be a number, got {value!r}")
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if v.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {float(v)}")
    if v < 0 or (strict and v == 0):
        raise ValueError(
            f"{name} must be {'positive' if strict else 'non-negative'}, got {float(v)}"
        )


def check_count(name: str, value, minimum: int = 0) -> None:
    """TypeError unless ``value`` is an int (not a bool, not a float: a step count of 2.5
    or NaN has no meaning), ValueError if it is below ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")


def _shape(x) -> tuple:
    """The shape of an array, or of a nested list on the host (``jnp.shape`` of a list is
    deprecated by JAX)."""
    return tuple(x.shape) if hasattr(x, "shape") else np.shape(x)


def numeric_array(name: str, x) -> np.ndarray:
    """``x`` as a NumPy array of numbers: TypeError naming ``name`` for strings, objects or
    booleans, ValueError for ragged nested lists (NumPy's own errors name nothing)."""
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers ({exc})") from None
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be an array of numbers, got dtype {a.dtype}")
    return a


def unit_normals(normals, xp=np):
    """``normals`` scaled to unit length, robustly: divided by their largest component
    first, so that lengths beyond the float range (1e200: the squares overflow) or below it
    (1e-200: they underflow) normalise as well as unit ones."""
    scale = xp.max(xp.abs(normals), axis=1, keepdims=True)
    n = normals / scale
    return n / xp.linalg.norm(n, axis=1, keepdims=True)


def _validate_points(points, normals, mask=None) -> None:
    p = numeric_array("points", points)
    n = numeric_array("normals", normals)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (m, 2) or (m, 3), got {p.shape}")
    if n.shape != p.shape:
        raise ValueError(f"normals must have the same shape as points {p.shape}, got {n.shape}")
    if p.shape[0] < 3:
        raise ValueError(f"need at least 3 points, got {p.shape[0]}")
    for name, a in (("points", p), ("normals", n)):
        if not np.isfinite(a).all():  # one pass; rows only to name the first bad one
            bad = ~np.isfinite(a).all(axis=1)
            raise ValueError(f"{name} contain NaN or Inf (first at row {int(np.argmax(bad))})")
    # Any non-zero length normalises (unit_normals divides by the largest component first).
    short = np.abs(n).max(axis=1) == 0
    if short.any():
        raise ValueError(
            f"normals must be non-zero (zero-length normal at row {int(np.argmax(short))})"
        )
    if mask is not None:
        keep = np.asarray(mask)
        if keep.shape != (p.shape[0],):
            raise ValueError(f"mask must have shape ({p.shape[0]},), got {keep.shape}")
        keep = keep.astype(bool)
        if keep.sum() < 3:
            raise ValueError(f"mask must select at least 3 points, got {int(keep.sum())}")
        p = p[keep]
    # The automatic path refused these in point_spacing; the explicit one fitted them
    # "successfully" (a degenerate box). Both paths check here.
    if not np.ptp(p, axis=0).max() > 0:
        raise ValueError("points: all points coincide; the cloud has no extent")


def check_domain(domain, ndim: int | None = None) -> np.ndarray:
    """``domain`` as a ``(2, d)`` float array; ValueError naming it unless it is
    ``((x_min, y_min), (x_max, y_max))`` (or with z in 3D; ``ndim`` None takes either),
    finite, with min < max on every axis."""
    try:
        d = np.asarray(domain, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(
            f"domain must be ((x_min, y_min), (x_max, y_max)) numbers, got {domain!r}"
        ) from None
    if d.ndim != 2 or d.shape[0] != 2 or d.shape[1] not in ((2, 3) if ndim is None else (ndim,)):
        raise ValueError(
            f"domain must be ((x_min, y_min), (x_max, y_max)) (with z_min, z_max "
            f"for 3D points), got shape {d.shape}"
        )
    if not np.isfinite(d).all() or not (d[0] < d[1]).all():
        raise ValueError(f"domain must be finite with min < max on both axes, got {d.tolist()}")
    return d


def _validate_domain(domain, samples, m: int):
    d = check_domain(domain, np.shape(samples)[1])
    s = np.asarray(samples)
    outside = ((s < d[0]) | (s > d[1])).any(axis=1)
    if outside[:m].any():
        raise ValueError(
            f"points outside the given domain (first at row {int(np.argmax(outside[:m]))})"
        )
    if outside.any():
        row = int(np.argmax(outside)) % m
        raise ValueError(
            f"offset samples P +/- d*n fall outside the given domain (point row {row}): "
            "enlarge the domain or reduce the offset"
        )


def check_offset_scale(points, offset, mask=None) -> None:
    """ValueError when the offset d exceeds the cloud's extent (its bounding-box diagonal):
    the offset samples P +/- d n then lie beyond the whole shape, on every side of every
    other point, and no fit can read inside from outside (offset=1e6 on a unit cloud ran
    for a minute into 203 loops). Concrete values only."""
    if not _is_concrete(points, offset, mask):
        return
    p = np.asarray(points, float)
    if mask is not None:
        p = p[np.asarray(mask).astype(bool)]
    extent = float(np.linalg.norm(np.ptp(p, axis=0)))
    if float(offset) > extent:
        raise ValueError(
            f"offset d = {float(offset):.4g} exceeds the cloud's extent (its "
            f"bounding-box diagonal, {extent:.4g}): the offset samples would lie "
            "beyond the whole shape; choose d below the point spacing or leave "
            "it to the automatic choice"
        )


#: Largest ratio of the floating-point resolution at the cloud's coordinates to the offset
#: d: a circle of radius 1 (d = 0.016) fitted in float32 kept its Chamfer distance within
#: 2 % up to a translation of 3e4 (ratio 0.12), lost 13 % at 1e5 (0.5), grew 11 loops at
#: 1e6 (4) and had no zero set at 1e7 (64).
MAX_RESOLUTION_TO_OFFSET = 0.125


def check_precision(points, offset, dtype, domain=None, eps=None) -> None:
    """ValueError when ``dtype`` cannot resolve the offset d at the cloud's coordinates:
    float32 at |x| = 1e7 steps by 1, so offsets of 0.01 collapse onto the points and the
    fit silently loses its zero set; or when the energy, a sum of 3m squares of about
    ``eps``, would overflow it (eps = 1e153 in float64). Concrete values only."""
    if not _is_concrete(points, offset, domain, eps):
        return
    info = np.finfo(np.dtype(dtype))
    if eps is not None:
        terms = 3.0 * len(points)
        if float(eps) > np.sqrt(float(info.max) / (1e4 * terms)):
            raise ValueError(
                f"eps = {float(eps):.3g} is too large for {np.dtype(dtype).name}: "
                "the energy (a sum of squares of about eps) would overflow; "
                "eps only scales g, so take eps about the offset d"
            )
    big = float(np.max(np.abs(np.asarray(points, float))))
    if domain is not None:
        big = max(big, float(np.max(np.abs(np.asarray(domain, float)))))
    if big > float(info.max) / 4:
        raise ValueError(
            f"points reach |x| = {big:.3g}, beyond the range of {np.dtype(dtype).name}"
        )
    resolution = float(np.spacing(np.asarray(big, dtype)))
    if resolution > MAX_RESOLUTION_TO_OFFSET * float(offset):
        raise ValueError(
            f"points reach |x| = {big:.3g}, where {np.dtype(dtype).name} resolves only steps "
            f"of {resolution:.3g}, more than {MAX_RESOLUTION_TO_OFFSET} x the offset d = "
            f"{float(offset):.3g}: translate the cloud near the origin or enable float64 "
            "(jax.config.update('jax_enable_x64', True))"
        )


def validate_inputs(
    points, normals, *, offset, eps, domain=None, margin=DEFAULT_MARGIN, mask=None
) -> None:
    """All input checks of :func:`make_problem`, on concrete values (traced ones are skipped).

    Raises ValueError (TypeError for non-numbers) naming the problem; see
    :func:`make_problem`. ``offset`` or ``eps`` None (to be chosen from the data) skips
    their checks.
    """
    for name, value in (("offset", offset), ("eps", eps)):
        if value is not None:
            check_nonnegative(name, value, strict=True)
    # A negative margin shrinks the box until it leaves out the data (below -1/2 the box
    # turns inside out); the fit then "succeeded" on samples the basis does not cover.
    check_nonnegative("margin", margin)
    if domain is not None and _is_concrete(domain):
        check_domain(domain)
    if not _is_concrete(points, normals, mask):
        return
    _validate_points(points, normals, mask)
    if offset is None:
        return
    check_offset_scale(points, offset, mask)
    if domain is not None and _is_concrete(domain, offset):
        p = np.asarray(points, dtype=float)
        n = unit_normals(np.asarray(normals, dtype=float))
        d = float(offset)
        _validate_domain(domain, np.concatenate([p, p + d * n, p - d * n]), p.shape[0])


def _slot_arrays(
    samples, targets, sample_mask, lower, upper, slot_sample, valid, shape, bucket_size, xp=jnp
):
    """Per-slot positions, basis, targets and masks."""
    m = samples.shape[0] // 3
    xy = samples[slot_sample]
    slot_mask = sample_mask[slot_sample] * valid
    return (
        xy,
        local_basis(xy, lower, upper, shape, bucket_size, xp),
        targets[slot_sample],
        slot_mask,
        slot_mask * (slot_sample < m),
    )


def _geometry_arrays(points, normals, offset, eps, domain, margin, mask, shape, with_slots, xp=jnp):
    """Samples, targets, mask, box and the flat cell of every sample, and with
    ``with_slots`` the arrays of the one-sample-a-slot layout. ``xp=numpy``: on the host,
    for concrete inputs (compiles nothing); jitted as :func:`_geometry` otherwise."""
    dtype = points.dtype
    normals = unit_normals(normals, xp)
    samples, targets = offset_samples(points, normals, offset, eps, xp)
    if mask is None:
        sample_mask = xp.ones(samples.shape[0], dtype=dtype)
    else:
        sample_mask = xp.tile(xp.asarray(mask).astype(dtype), 3)
    if domain is None:
        lower, upper = auto_domain(samples, margin, None if mask is None else sample_mask, xp)
    else:
        lower, upper = domain[0], domain[1]
    cells = flat_cell(locate(samples, lower, upper, shape, xp)[0], shape)
    slots = None
    if with_slots:
        index = xp.arange(samples.shape[0], dtype=xp.int32)
        slots = _slot_arrays(
            samples,
            targets,
            sample_mask,
            lower,
            upper,
            index,
            xp.ones(samples.shape[0], dtype=bool),
            shape,
            1,
            xp,
        )
    return normals, samples, targets, sample_mask, lower, upper, cells, slots


_geometry = eqx.filter_jit(_geometry_arrays)
_slots = eqx.filter_jit(_slot_arrays)


def _surface_bucket_size(bucket_size) -> int:
    """1, the one sample layout of 3D points; ValueError for any other ``bucket_size``."""
    # The buckets, the table and the power form are 2D kernels; a surface's samples
    # take the generic form, one sample a slot.
    if bucket_size not in (None, 1):
        raise ValueError(f"bucket_size must be 1 for 3D points, got {bucket_size!r}")
    return 1


#: The results of :func:`_geometry_arrays`, by name.
_Geometry = namedtuple("_Geometry", "normals samples targets sample_mask lower upper cells slots")


def _converted_geometry(
    points, normals, offset, eps, domain, margin, mask, shape, dtype, bucket_size, concrete, small
):
    """``(convert, points, geometry)``: the cast to ``dtype``, the cast points, a _Geometry."""
    # Small concrete problems are laid out on the host in NumPy and transferred once at the
    # end: nothing to compile (a first call would otherwise spend about 0.3 s compiling
    # the geometry). Larger and traced ones take the same arithmetic jitted (at 1e6 points
    # 0.17 s against 0.52 s in NumPy).
    on_host = concrete and small
    if on_host:
        convert, geometry = (lambda x: np.asarray(x, dtype)), partial(_geometry_arrays, xp=np)
        mask = None if mask is None else np.asarray(mask)
    else:
        convert, geometry = (lambda x: _as_array(x, dtype)), _geometry
    points = convert(points)
    if mask is not None and _shape(mask) != (points.shape[0],):
        raise ValueError(f"mask must have shape ({points.shape[0]},), got {_shape(mask)}")
    # One sample a slot unless a concrete problem gets the bucketed layout (built on the
    # host between two compiled calls); otherwise the geometry builds the slots too.
    identity = bucket_size == 1 or not concrete or (bucket_size is None and small)
    arrays = geometry(
        points,
        convert(normals),
        convert(offset),
        convert(eps),
        None if domain is None else convert(domain),
        margin,
        mask,
        shape,
        identity,
    )
    return convert, points, _Geometry(*arrays)


def _choose_layout(cells, sample_mask, count, bucket_size, concrete, small, stable_shapes):
    """``(table, layout, bucket_size)``; ``layout`` None where one sample takes each slot."""
    if bucket_size is not None and bucket_size > 1 and not concrete:
        raise ValueError("bucket_size > 1 needs concrete inputs (the layout is built on the host)")
    table = layout = None
    if concrete and bucket_size in (None, 1) and small:
        # Small problems keep the paper's order, one sample a slot; the table form groups
        # them into buckets of its own (see jurs._model.spline).
        if stable_shapes:
            order, real, k = stable_layout(cells, sample_mask, count, small=True)
        else:
            k = choose_bucket_size(cells, count, small=True)
            needed = int((-(-np.bincount(cells, minlength=count) // k)).sum())
            order, real = bucket_layout(cells, k, count, round_buckets(needed))
        table = (order.reshape(-1, k), real.reshape(-1, k))
        bucket_size = 1
    elif concrete and bucket_size != 1:
        cells = np.asarray(cells)
        if stable_shapes:
            *layout, bucket_size = stable_layout(cells, sample_mask, count, bucket_size)
        bucket_size = bucket_size or choose_bucket_size(cells, count)
    else:
        bucket_size = 1
    if bucket_size != 1 and layout is None:
        layout = bucket_layout(cells, bucket_size, count)
    return table, layout, bucket_size


def _laid_out_slots(geometry, shape, bucket_size, concrete, small, stable_shapes) -> dict[str, Any]:
    """The :class:`Problem` fields of the slots: the samples laid out, their basis and masks."""
    _, samples, targets, sample_mask, lower, upper, cells, slots = geometry
    table, layout, bucket_size = _choose_layout(
        cells, sample_mask, num_cells(shape), bucket_size, concrete, small, stable_shapes
    )
    if layout is None and slots is None:
        # An automatic bucket size of 1 (a sparse cloud: under 2 samples an occupied cell)
        # on a problem whose geometry expected buckets: lay the samples out by cell.
        layout = bucket_layout(np.asarray(cells), bucket_size, num_cells(shape))
    if layout is None:  # the geometry built one sample a slot
        assert slots is not None
        slot_sample = (np if concrete else jnp).arange(samples.shape[0], dtype=np.int32)
        slot_xy, local, slot_targets, slot_mask, slot_data = slots
    else:
        slot_sample, valid = layout
        slot_xy, local, slot_targets, slot_mask, slot_data = _slots(
            samples, targets, sample_mask, lower, upper, slot_sample, valid, shape, bucket_size
        )
    if table is not None:
        local = with_table(local, *table, shape)
    return dict(
        samples=slot_xy,
        targets=slot_targets,
        mask=slot_mask,
        is_data=slot_data,
        sample_index=slot_sample,
        local=local,
    )


def make_problem(
    points,
    normals,
    *,
    grid,
    offset=0.1,
    eps=0.01,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    mask=None,
    bucket_size: int | None = None,
    dtype=None,
    stable_shapes: bool = False,
) -> Problem:
    """Build the fitting :class:`Problem` of eq. 4-5 and 9.

    Args:
        points: ``(m, 2)`` data points of a curve, or ``(m, 3)`` of a surface; m >= 3.
        normals: outward normals, the shape of ``points``; normalised here (zero length
            is an error).
        grid: ``N`` or ``(N, M)``, basis functions along x and y, each >= 4 (``N`` or
            ``(N, M, K)`` in 3D).
        offset: d > 0, distance of the offset samples along the normals.
        eps: epsilon > 0, target value at the outer offsets (-eps at the inner ones).
        domain: ``((x_min, y_min), (x_max, y_max))`` (with z in 3D); ``None`` takes the
            samples' bounding
            box plus ``margin`` times its longest side on every side.
        mask: optional ``(m,)`` booleans; points with False are padding and take no part in
            the fit, the box or the metrics. Lets clouds of different sizes share one shape
            so that a fit can be ``jax.vmap``-ed over a padded batch.
        bucket_size: samples per bucket of the slot layout. ``None`` chooses: up to
            :data:`jurs._model.spline.TABLE_MAX_SLOTS` samples the paper's order, one sample a
            slot, with the table form of :mod:`jurs._model.spline` (its own buckets, built on the
            host); above, buckets of :func:`choose_bucket_size`. 1 keeps the paper's order
            (with the table form when small and concrete). Sizes above 1 need concrete
            (untraced) inputs: the layout is computed on the host. 3D problems always
            take one sample a slot (the generic form of :mod:`jurs._model.spline`).
        dtype: floating dtype; default float64 when ``jax_enable_x64`` is on, else float32.
        stable_shapes: size a concrete problem's sample layout from the number of points
            and the rounded number of occupied cells (:func:`stable_layout`), so that
            clouds padded to one size share one compiled fit; masked samples then take no
            bucket. :func:`jurs.fit` sets it for the clouds it pads.

    Raises:
        ValueError: for NaN/Inf, wrong shapes, zero normals, fewer than 3 points (or a mask
            selecting fewer), points that all coincide, a grid below 4 x 4, non-positive
            offset/eps, an offset beyond the cloud's extent, a negative margin, samples
            outside a given domain, or coordinates that ``dtype`` cannot resolve at the
            scale of the offset (float32 far from the origin). Values that are traced
            (inside jit/grad/vmap) cannot be inspected and are not checked.
        TypeError: for points or normals that are not numbers.
    """
    validate_inputs(
        points, normals, offset=offset, eps=eps, domain=domain, margin=margin, mask=mask
    )
    ndim = _shape(points)[1]
    shape = normalise_grid(grid, ndim)
    if bucket_size is not None and (int(bucket_size) != bucket_size or bucket_size < 1):
        raise ValueError(f"bucket_size must be a positive int, got {bucket_size!r}")
    dtype = dtype or jnp.result_type(float)
    concrete = _is_concrete(points, normals, offset, eps, domain, mask)
    check_precision(points, offset, dtype, domain, eps)
    if concrete:
        # Unit length in float64 before any cast: 1e200-long normals overflow float32.
        normals = unit_normals(np.asarray(normals, float))
    small = 3 * _shape(points)[0] <= TABLE_MAX_SLOTS
    if ndim != 2:
        bucket_size, small = _surface_bucket_size(bucket_size), False
    convert, points, geometry = _converted_geometry(
        points,
        normals,
        offset,
        eps,
        domain,
        margin,
        mask,
        shape,
        dtype,
        bucket_size,
        concrete,
        small,
    )
    slots = _laid_out_slots(geometry, shape, bucket_size, concrete, small, stable_shapes)
    # On the host the fields hold NumPy arrays until the device_put below.
    problem = Problem(
        points=points,  # pyright: ignore[reportArgumentType]
        normals=geometry.normals,
        lower=geometry.lower,
        upper=geometry.upper,
        offset=convert(offset),  # pyright: ignore[reportArgumentType]
        eps=convert(eps),  # pyright: ignore[reportArgumentType]
        shape=shape,
        **slots,
    )
    # Host arrays to the device in one transfer.
    return jax.device_put(problem) if concrete else problem


def _join_roots(tree, roots, m):
    """The ``(m + 1, m + 1)`` graph of ``tree`` with node ``m`` joined to ``roots``."""
    from scipy.sparse import bmat, coo_matrix

    link = coo_matrix((np.ones(len(roots)), (np.zeros(len(roots), int), roots)), shape=(1, m))
    return bmat([[tree, link.T], [link, None]]).tocsr()


#: Neighbours per point in :func:`flipped_normal_fraction`'s graph.
ORIENTATION_NEIGHBOURS = 8
#: Clouds above this many points are checked at this many, evenly strided.
ORIENTATION_MAX_POINTS = 20_000


def orientation_sample(points, normals):
    """``(p, n, dist, idx)`` that :func:`flipped_normal_fraction` and
    :func:`tangential_normal_fraction` read: the points (at most
    :data:`ORIENTATION_MAX_POINTS`, evenly strided), their unit normals, and each point's
    :data:`ORIENTATION_NEIGHBOURS` + 1 nearest (itself first) from one KD-tree query, so a
    caller of both builds the tree once."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

    p = np.asarray(points, float)
    n = unit_normals(np.asarray(normals, float))
    if len(p) > ORIENTATION_MAX_POINTS:
        keep = np.linspace(0, len(p) - 1, ORIENTATION_MAX_POINTS).round().astype(int)
        p, n = p[keep], n[keep]
    dist, idx = cKDTree(p).query(p, k=min(ORIENTATION_NEIGHBOURS + 1, len(p)))
    return p, n, dist, idx


def flipped_normal_fraction(points, normals, sample=None) -> float:
    """Fraction of the points whose normal is flipped against its neighbours along the
    curve, after Hoppe et al. (1992): the sign is carried along a minimum spanning tree of
    the neighbour graph (weights ``1 - |n_i . n_j|``) and, in each connected part, the
    smaller of the two sign classes counts. 0 for consistently oriented normals; about 1/2
    when half the cloud is flipped, however large the cloud.

    Only *tangential* neighbours are edges (the displacement within 72.5 degrees of both
    tangents, within two median spacings): the two sides of a thin part, or a ring and its
    hole, face opposite ways legitimately, and lie across, not along, each other. Where
    noise scrambles the displacement's direction the graph falls apart into small parts
    and the check turns blind, not wrong. Measured: 0 on Examples 1, 9, 10, the rose,
    lobes, annulus, horse, coins and glyphs B, a, g, W at 300-20000 points, also with
    0.1 rad normal noise and with 10 % positional outliers; 0.12 on the horse at 100 points
    (legs thinner than the spacing); 0.5 with half or every other normal flipped.
    Runs on the host (SciPy), on concrete inputs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import (
        breadth_first_order,
        connected_components,
        minimum_spanning_tree,
    )

    p, n, dist, idx = orientation_sample(points, normals) if sample is None else sample
    m = len(p)
    k = dist.shape[1] - 1
    dist, idx = dist[:, 1:], idx[:, 1:]
    nearest = dist[:, 0][dist[:, 0] > 0]
    if nearest.size == 0:
        return 0.0
    spacing = float(np.median(nearest))
    i, j, d = np.repeat(np.arange(m), k), idx.ravel(), dist.ravel()
    u = (p[j] - p[i]) / np.where(d > 0, d, 1.0)[:, None]
    dot = np.sum(n[i] * n[j], axis=1)
    edge = (
        (d > 0)
        & (d <= 2.0 * spacing)
        & (np.abs(np.sum(u * n[i], axis=1)) < 0.3)
        & (np.abs(np.sum(u * n[j], axis=1)) < 0.3)
    )
    graph = coo_matrix((1.0 - np.abs(dot[edge]) + 1e-3, (i[edge], j[edge])), shape=(m, m))
    tree = minimum_spanning_tree(graph.tocsr().maximum(graph.T.tocsr()))
    tree = tree + tree.T
    count, labels = connected_components(tree, directed=False)
    # Parent of every point in one breadth-first forest: a virtual node m joined to each
    # part's first point is searched from (roots are their own parent). Whether a normal
    # opposes its parent's, then the parity of flips up to the root by pointer jumping.
    roots = np.unique(labels, return_index=True)[1]
    joined = _join_roots(tree, roots, m)
    pred = breadth_first_order(joined, m, directed=False)[1][:m]
    parent = np.where(pred == m, np.arange(m), pred)
    flip = np.sum(n * n[parent], axis=1) < 0
    while np.any(parent != parent[parent]):
        flip = flip ^ flip[parent]
        parent = parent[parent]
    flipped = np.bincount(labels, weights=flip, minlength=count)
    size = np.bincount(labels, minlength=count)
    return float(np.minimum(flipped, size - flipped).sum() / m)


def available_memory(device: bool = True) -> int | None:
    """Bytes a new allocation can take: with ``device`` on an accelerator its free memory,
    else the host's available memory (``MemAvailable`` of /proc/meminfo, else the physical
    memory); None where neither is known."""
    stats = {}
    if device:
        try:
            stats = jax.devices()[0].memory_stats() or {}
        except Exception:  # backends without memory statistics
            stats = {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(
    setting: str, estimate: float, available: int | None = None, device: bool = True
) -> None:
    """MemoryError-free refusal: ValueError naming ``setting`` when ``estimate`` bytes
    exceed the memory available (:func:`available_memory`, on the device or with
    ``device=False`` on the host), before anything is allocated
    (grid=10000 otherwise asked XLA for 248 GB after 20 s, and a level-set resolution of
    30000 ended in a MemoryError traceback)."""
    available = available_memory(device) if available is None else available
    if available is not None and estimate > available:
        raise ValueError(
            f"{setting} needs about {estimate / 2**30:.3g} GiB of memory, more "
            f"than the {available / 2**30:.3g} GiB available; choose a smaller "
            f"{setting.split(' ')[0].split('=')[0]}"
        )


def tangential_normal_fraction(points, normals, sample=None) -> float:
    """Fraction of the points whose normal lies within 45 degrees of the curve's tangent
    (of a surface's tangent plane), spanned by the principal directions of the point and
    its :data:`ORIENTATION_NEIGHBOURS` nearest neighbours (counted only where the direction
    across is clear, the variance along each tangent direction at least 4 times its: not
    at corners, not in clouds sampled coarser than their features).
    About 1/2 for random normals, which :func:`flipped_normal_fraction` cannot see (its
    graph falls apart) and a fine grid fits "successfully"; measured at most 0.03 on the
    consistent clouds listed there, also with 10 % of the normals random. Host side."""
    p, n, _, idx = orientation_sample(points, normals) if sample is None else sample
    near = p[idx] - p[idx].mean(axis=1, keepdims=True)
    variance, axes = np.linalg.eigh(np.einsum("mki,mkj->mij", near, near))
    clear = variance[:, 1] > 4.0 * variance[:, 0]
    # Within 45 degrees of the tangent: at most cos 45 degrees along the direction across
    # (the smallest variance's).
    along = np.abs(np.sum(axes[:, :, 0] * n, axis=1)) < np.sqrt(0.5)
    return float(np.mean(clear & along))


#: Peak bytes a fit holds per coefficient: the exact solve and the normal-equation form
#: assemble the 49-point stencil of D^T D and solve with it (LeastSquares measured 0.8 GB,
#: 3.1 KB a coefficient, at 512 x 512, peak resident memory above the process' baseline
#: on this 2-core CPU; XLA asked for 2.5 KB a coefficient at 10000 x 10000); the
#: per-sample iterations hold a few grids (IURS: 0.19 GB at 64 x 64 and at 256 x 256,
#: compilation included). At 2000 x 2000 it held 10 GB (2.5 KB a coefficient) after 8
#: minutes and was still growing: the limit is twice the largest rate measured, so that a
#: fit it lets through does not run the machine out of memory.
BYTES_PER_COEFFICIENT = 8192
BYTES_PER_COEFFICIENT_ITERATIVE = 1024
#: Peak bytes per sample (positions, basis values, residuals).
BYTES_PER_SAMPLE = 256
#: The same for surfaces (3D), from peak resident sets on this 2-core CPU: the 343-point
#: stencil, the per-cell moments it is folded from and the fold's intermediates (a 64^3 fit
#: of 2e4 points peaked at 4.8 GB, 18 KB a coefficient), and each sample's 64 gathered
#: coefficients and basis products (1e6 points at 48^3 peaked at 10 GB: 2.9 KB a sample
#: after the grid's share).
BYTES_PER_COEFFICIENT_3D = 20480
BYTES_PER_SAMPLE_3D = 3072


def fit_memory(shape, num_samples: int, solver) -> float:
    """Estimated peak bytes of a fit on an ``(N, M)`` (or ``(N, M, K)``) grid with
    ``num_samples`` samples (:data:`BYTES_PER_COEFFICIENT`, :data:`BYTES_PER_SAMPLE` and
    their 3D counterparts)."""
    surface = len(shape) == 3
    if getattr(solver, "per_sample_iterations", False):
        per_coefficient = BYTES_PER_COEFFICIENT_ITERATIVE
    else:
        per_coefficient = BYTES_PER_COEFFICIENT_3D if surface else BYTES_PER_COEFFICIENT
    per_sample = BYTES_PER_SAMPLE_3D if surface else BYTES_PER_SAMPLE
    return float(per_coefficient * np.prod(shape) + per_sample * num_samples)


def values_by_point(values: Array, sample_index: Array, real: Array, num_points: int):
    """``(g(P_i), g(P_i + d n_i), g(P_i - d n_i))``, three ``(m,)`` arrays, from per-slot
    ``values`` (``sample_index`` the slots' positions in the paper's order, eq. 9); a sample
    that is not ``real`` (padding) counts 0."""
    point, kind = sample_index % num_points, sample_index // num_points
    return tuple(
        jax.ops.segment_sum(jnp.where(real & (kind == k), values, 0.0), point, num_points)
        for k in range(3)
    )


def padded_cloud(points, normals):
    """``(points, normals, mask)`` padded to :func:`jurs._problem.sizes.padded_count` points with
    masked-out copies of the first point (inside any box the cloud fits in), or None where
    the inputs are traced or malformed (make_problem then reports them as given).

    Why: a compiled fit is specialised to its array shapes; clouds padded to one of a few
    sizes, with a layout sized from that (``make_problem(stable_shapes=True)``), reuse one
    compilation. Masked points take no part in the fit, so the result is the unpadded one
    up to rounding (the per-bucket sums group the samples differently).
    """
    if not _is_concrete(points, normals):
        return None
    try:  # ragged lists: make_problem names them
        p, n = np.asarray(points), np.asarray(normals)
    except (TypeError, ValueError):
        return None
    if p.ndim != 2 or p.shape[1] not in (2, 3) or n.shape != p.shape or p.shape[0] < 3:
        return None
    m = p.shape[0]
    extra = padded_count(m) - m
    mask = np.arange(m + extra) < m
    return (
        np.concatenate([p, np.repeat(p[:1], extra, axis=0)]),
        np.concatenate([n, np.repeat(n[:1], extra, axis=0)]),
        mask,
    )


def padded_problem(
    points, normals, mask, shape, offset, eps, domain, margin, bucket_size, dtype, support=None
):
    """:func:`make_problem` of the cloud, padded (:func:`padded_cloud`) when it has no mask.

    ``support``: optional ``(m,)`` weights of the caller's points (0 sets a point aside,
    :func:`jurs._fit.settings.isolated_points`), multiplied into the mask."""
    # The problem is built outside the solver's jit: its sample layout is chosen on the
    # host from concrete data (see make_problem); under a caller's jit/grad/vmap it is traced.
    padded = padded_cloud(points, normals) if mask is None else None
    if padded is not None:  # shape-stable: clouds of similar size share one compiled fit
        points, normals, mask = padded
    if support is not None:
        count = len(points)
        base = np.ones(count) if mask is None else np.asarray(mask, float)
        weights = np.asarray(support, float)
        mask = base * np.concatenate([weights, np.zeros(count - len(weights))])
    return make_problem(
        points,
        normals,
        grid=shape,
        offset=offset,
        eps=eps,
        domain=domain,
        margin=margin,
        mask=mask,
        bucket_size=bucket_size,
        dtype=dtype,
        stable_shapes=padded is not None,
    )
