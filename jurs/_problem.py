"""From points and outward normals to the sampled fitting problem (eq. 4-5, 9).

Each data point P_i with unit outward normal n_i gives three samples: P_i (target 0),
P_i + d n_i (target +eps, outside) and P_i - d n_i (target -eps, inside), stacked in that
order as in eq. 9, so the first m samples are the data points. The fitted function is
negative inside and positive outside.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._basis import flat_cell, locate, num_cells
from ._spline import TABLE_MAX_SLOTS, LocalBasis, local_basis, with_table

#: Default margin added around the samples' bounding box, as a fraction of its longest side.
DEFAULT_MARGIN = 0.1


class Problem(eqx.Module):
    """A fitting problem: samples, targets, the box and the grid, and their local basis.

    Build it with :func:`make_problem`. Every per-sample array (``samples``, ``targets``,
    ``mask``, ``is_data``, ``local``) is indexed the same way, by *slot*: the 3m samples of
    eq. 4 regrouped into buckets that share a cell (see :mod:`jurs._spline`), plus padding
    slots with ``mask`` 0. ``sample_index`` maps each slot to the paper's order (eq. 9: the
    m data points, then the outer, then the inner offsets). With ``bucket_size`` 1 the slots
    are exactly the paper's order. ``shape`` is static; all other fields are arrays, so a
    Problem can be traced, differentiated and batched.
    """

    points: Array  # (m, 2) data points P
    normals: Array  # (m, 2) unit outward normals
    samples: Array  # (S, 2) sample positions, P or P +/- d n (eq. 4)
    targets: Array  # (S,) b: 0, +eps or -eps (eq. 5, 9)
    mask: Array  # (S,) 1.0 for real samples, 0.0 for padding (layout or batched fits)
    is_data: Array  # (S,) 1.0 where the slot holds a real data point P_i (target 0)
    sample_index: Array  # (S,) int32 position in the paper's order [P, P + d n, P - d n]
    lower: Array  # (2,) box corner
    upper: Array  # (2,) box corner
    offset: Array  # d
    eps: Array  # epsilon
    local: LocalBasis  # basis at the samples
    shape: tuple[int, int] = eqx.field(static=True)

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


def bucket_layout(cells: np.ndarray, bucket_size: int, count: int,
                  num_buckets: int | None = None):
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
    slot_sample[needed * k:] = order[-1]
    slot_sample = slot_sample.reshape(-1, k)
    valid = slot_sample >= 0
    valid[needed:] = False
    slot_sample = np.where(valid, slot_sample, slot_sample[:, :1])
    return slot_sample.reshape(-1), valid.reshape(-1)


def offset_samples(points: Array, normals: Array, offset, eps, xp=jnp):
    """Samples and targets of eq. 4-5 and 9: ``[P, P + d n, P - d n]`` and ``[0, +eps, -eps]``.

    ``xp=numpy`` computes on the host (NumPy inputs and results)."""
    m = points.shape[0]
    samples = xp.concatenate([points, points + offset * normals, points - offset * normals])
    ones = xp.ones((m,), dtype=points.dtype)
    targets = xp.concatenate([0.0 * ones, eps * ones, -eps * ones])
    return samples, targets


def auto_domain(samples: Array, margin: float = DEFAULT_MARGIN, mask: Array | None = None,
                xp=jnp):
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


def normalise_grid(grid) -> tuple[int, int]:
    """``9`` or ``(9, 9)`` -> ``(9, 9)``; raises ValueError for anything below 4 x 4."""
    if isinstance(grid, (int, np.integer)):
        grid = (grid, grid)
    try:
        shape = tuple(int(g) for g in grid)
        if any(int(g) != g for g in grid):
            raise TypeError
    except (TypeError, ValueError):
        raise ValueError(f"grid must be an int or a pair of ints, got {grid!r}") from None
    if len(shape) != 2:
        raise ValueError(f"grid must be a pair (N, M), got {grid!r}")
    if min(shape) < 4:
        raise ValueError(f"grid must be at least 4 x 4 for cubic B-splines, got {shape}")
    return shape


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(xs))


def _as_array(x, dtype=None):
    """``jnp.asarray(x, dtype)``; concrete values are converted on the host and transferred,
    which compiles nothing (an eager conversion compiles a small kernel on first use)."""
    if isinstance(x, jax.Array) or not _is_concrete(x):
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))


def check_nonnegative(name: str, value, *, strict: bool = False) -> None:
    """Raise ValueError unless ``value`` is a finite number >= 0 (> 0 when ``strict``).

    Traced values are not checked (their value is unknown at trace time).
    """
    if not _is_concrete(value):
        return
    v = np.asarray(value, dtype=float)
    if v.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {v.shape}")
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {float(v)}")
    if v < 0 or (strict and v == 0):
        raise ValueError(f"{name} must be {'positive' if strict else 'non-negative'}, got {float(v)}")


def _validate_points(points, normals) -> None:
    p = np.asarray(points)
    n = np.asarray(normals)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must have shape (m, 2), got {p.shape}")
    if n.shape != p.shape:
        raise ValueError(f"normals must have the same shape as points {p.shape}, got {n.shape}")
    if p.shape[0] < 3:
        raise ValueError(f"need at least 3 points, got {p.shape[0]}")
    for name, a in (("points", p), ("normals", n)):
        if not np.isfinite(a).all():  # one pass; rows only to name the first bad one
            bad = ~np.isfinite(a).all(axis=1)
            raise ValueError(f"{name} contain NaN or Inf (first at row {int(np.argmax(bad))})")
    short = np.einsum("ij,ij->i", n, n) < 1e-24  # |n| < 1e-12
    if short.any():
        raise ValueError(f"normals must be non-zero (zero-length normal at row {int(np.argmax(short))})")


def _validate_domain(domain, samples, m: int):
    d = np.asarray(domain, dtype=float)
    if d.shape != (2, 2):
        raise ValueError(f"domain must be ((x_min, y_min), (x_max, y_max)), got shape {d.shape}")
    if not np.isfinite(d).all() or not (d[0] < d[1]).all():
        raise ValueError(f"domain must be finite with min < max on both axes, got {d.tolist()}")
    s = np.asarray(samples)
    outside = ((s < d[0]) | (s > d[1])).any(axis=1)
    if outside[:m].any():
        raise ValueError(f"points outside the given domain (first at row {int(np.argmax(outside[:m]))})")
    if outside.any():
        row = int(np.argmax(outside)) % m
        raise ValueError(
            f"offset samples P +/- d*n fall outside the given domain (point row {row}): "
            "enlarge the domain or reduce the offset"
        )


def validate_inputs(points, normals, *, offset, eps, domain=None) -> None:
    """All input checks of :func:`make_problem`, on concrete values (traced ones are skipped).

    Raises ValueError naming the problem; see :func:`make_problem`.
    """
    check_nonnegative("offset", offset, strict=True)
    check_nonnegative("eps", eps, strict=True)
    if not _is_concrete(points, normals):
        return
    _validate_points(points, normals)
    if domain is not None and _is_concrete(domain, offset):
        p = np.asarray(points, dtype=float)
        n = np.asarray(normals, dtype=float)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        d = float(offset)
        _validate_domain(domain, np.concatenate([p, p + d * n, p - d * n]), p.shape[0])


def _slot_arrays(samples, targets, sample_mask, lower, upper, slot_sample, valid, shape,
                 bucket_size, xp=jnp):
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


def _geometry_arrays(points, normals, offset, eps, domain, margin, mask, shape, with_slots,
                     xp=jnp):
    """Samples, targets, mask, box and the flat cell of every sample, and with
    ``with_slots`` the arrays of the one-sample-a-slot layout. ``xp=numpy``: on the host,
    for concrete inputs (compiles nothing); jitted as :func:`_geometry` otherwise."""
    dtype = points.dtype
    normals = normals / xp.linalg.norm(normals, axis=1, keepdims=True)
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
        slots = _slot_arrays(samples, targets, sample_mask, lower, upper, index,
                             xp.ones(samples.shape[0], dtype=bool), shape, 1, xp)
    return normals, samples, targets, sample_mask, lower, upper, cells, slots


_geometry = eqx.filter_jit(_geometry_arrays)
_slots = eqx.filter_jit(_slot_arrays)


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
) -> Problem:
    """Build the fitting :class:`Problem` of eq. 4-5 and 9.

    Args:
        points: ``(m, 2)`` data points, m >= 3.
        normals: ``(m, 2)`` outward normals; normalised here (zero length is an error).
        grid: ``N`` or ``(N, M)``, basis functions along x and y, each >= 4.
        offset: d > 0, distance of the offset samples along the normals.
        eps: epsilon > 0, target value at the outer offsets (-eps at the inner ones).
        domain: ``((x_min, y_min), (x_max, y_max))``; ``None`` takes the samples' bounding
            box plus ``margin`` times its longest side on every side.
        mask: optional ``(m,)`` booleans; points with False are padding and take no part in
            the fit, the box or the metrics. Lets clouds of different sizes share one shape
            so that a fit can be ``jax.vmap``-ed over a padded batch.
        bucket_size: samples per bucket of the slot layout. ``None`` chooses: up to
            :data:`jurs._spline.TABLE_MAX_SLOTS` samples the paper's order, one sample a
            slot, with the table form of :mod:`jurs._spline` (its own buckets, built on the
            host); above, buckets of :func:`choose_bucket_size`. 1 keeps the paper's order
            (with the table form when small and concrete). Sizes above 1 need concrete
            (untraced) inputs: the layout is computed on the host.
        dtype: floating dtype; default float64 when ``jax_enable_x64`` is on, else float32.

    Raises:
        ValueError: for NaN/Inf, wrong shapes, zero normals, fewer than 3 points, a grid
            below 4 x 4, non-positive offset/eps, or samples outside a given domain. Values
            that are traced (inside jit/grad/vmap) cannot be inspected and are not checked.
    """
    shape = normalise_grid(grid)
    validate_inputs(points, normals, offset=offset, eps=eps, domain=domain)
    if bucket_size is not None and (int(bucket_size) != bucket_size or bucket_size < 1):
        raise ValueError(f"bucket_size must be a positive int, got {bucket_size!r}")
    dtype = dtype or jnp.result_type(float)
    concrete = _is_concrete(points, normals, offset, eps, domain, mask)
    small = 3 * jnp.shape(points)[0] <= TABLE_MAX_SLOTS
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
    if mask is not None and tuple(jnp.shape(mask)) != (points.shape[0],):
        raise ValueError(f"mask must have shape ({points.shape[0]},), got {jnp.shape(mask)}")
    # One sample a slot unless a concrete problem gets the bucketed layout (built on the
    # host between two compiled calls); otherwise the geometry builds the slots too.
    identity = bucket_size == 1 or not concrete or (bucket_size is None and small)
    normals, samples, targets, sample_mask, lower, upper, cells, slots = geometry(
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
    if bucket_size is not None and bucket_size > 1 and not concrete:
        raise ValueError("bucket_size > 1 needs concrete inputs (the layout is built on the host)")
    count = num_cells(shape)
    table = None
    if concrete and bucket_size in (None, 1) and small:
        # Small problems keep the paper's order, one sample a slot; the table form groups
        # them into buckets of its own (see jurs._spline).
        k = choose_bucket_size(cells, count, small=True)
        needed = int((-(-np.bincount(cells, minlength=count) // k)).sum())
        order, real = bucket_layout(cells, k, count, round_buckets(needed))
        table = (order.reshape(-1, k), real.reshape(-1, k))
        bucket_size = 1
    elif concrete and bucket_size != 1:
        cells = np.asarray(cells)
        bucket_size = bucket_size or choose_bucket_size(cells, count)
    else:
        bucket_size = 1
    if bucket_size == 1:  # the geometry built the one-sample-a-slot arrays (identity above)
        slot_sample = (np if concrete else jnp).arange(samples.shape[0], dtype=np.int32)
        slot_xy, local, slot_targets, slot_mask, slot_data = slots
    else:
        slot_sample, valid = bucket_layout(cells, bucket_size, count)
        slot_xy, local, slot_targets, slot_mask, slot_data = _slots(
            samples, targets, sample_mask, lower, upper, slot_sample, valid, shape, bucket_size)
    if table is not None:
        local = with_table(local, *table, shape)
    problem = Problem(
        points=points,
        normals=normals,
        samples=slot_xy,
        targets=slot_targets,
        mask=slot_mask,
        is_data=slot_data,
        sample_index=slot_sample,
        lower=lower,
        upper=upper,
        offset=convert(offset),
        eps=convert(eps),
        local=local,
        shape=shape,
    )
    # Host arrays to the device in one transfer.
    return jax.device_put(problem) if concrete else problem
