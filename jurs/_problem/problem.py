"""From points and outward normals to the sampled fitting problem (eq. 4-5, 9).

Each data point P_i with unit outward normal n_i gives three samples: P_i (target 0),
P_i + d n_i (target +eps, outside) and P_i - d n_i (target -eps, inside), stacked in that
order as in eq. 9, so the first m samples are the data points. The fitted function is
negative inside and positive outside.
"""

from __future__ import annotations

from collections import namedtuple
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .._model.basis import flat_cell, locate, num_cells
from .._model.groups import with_groups
from .._model.local import LocalBasis
from .._model.spline import TABLE_MAX_SLOTS, local_basis, with_table
from .layout import (
    bucket_layout,
    cell_groups,
    choose_bucket_size,
    round_buckets,
    stable_layout,
)
from .sizes import DEFAULT_MARGIN
from .validate import (
    check_precision,
    is_concrete,
    normalise_grid,
    shape_of,
    unit_normals,
    validate_inputs,
)


class Problem(eqx.Module):
    """A fitting problem: samples, targets, the box and the grid, and their local basis.

    Build it with [`make_problem`][jurs.make_problem]. Every per-sample array (``samples``,
    ``targets``, ``mask``, ``is_data``, ``local``) is indexed the same way, by *slot*: the 3m
    samples of eq. 4 regrouped into buckets that share a cell (see ``jurs._model.spline``), plus
    padding slots with ``mask`` 0. ``sample_index`` maps each slot to the paper's order (eq. 9:
    the m data points, then the outer, then the inner offsets). With ``bucket_size`` 1 the slots
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


def _as_array(x, dtype=None):
    """``jnp.asarray(x, dtype)``; concrete values are converted on the host and transferred,
    which compiles nothing (an eager conversion compiles a small kernel on first use)."""
    if isinstance(x, jax.Array) or not is_concrete(x):
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))


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
    for concrete inputs (compiles nothing); jitted as ``_geometry`` otherwise."""
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


def surface_bucket_size(bucket_size) -> int:
    """1, the one sample layout of 3D points; ValueError for any other ``bucket_size``."""
    # The buckets, the table and the power form are 2D kernels; a surface's samples
    # take the generic form, one sample a slot.
    if bucket_size not in (None, 1):
        raise ValueError(f"bucket_size must be 1 for 3D points, got {bucket_size!r}")
    return 1


#: The results of ``_geometry_arrays``, by name.
_Geometry = namedtuple("_Geometry", "normals samples targets sample_mask lower upper cells slots")


def _converted_geometry(
    points, normals, offset, eps, domain, margin, mask, shape, dtype, bucket_size, concrete, small
):
    """``(convert, points, geometry)``: the cast to ``dtype``, the cast points, a _Geometry."""
    # Small concrete problems are laid out on the host in NumPy and transferred once at the
    # end: nothing to compile, where compiling the geometry would cost a first call more
    # than computing it. Larger and traced ones take the same arithmetic jitted, faster
    # than NumPy there (docs/performance.md, "Measurements behind the defaults").
    on_host = concrete and small
    if on_host:
        convert, geometry = (lambda x: np.asarray(x, dtype)), partial(_geometry_arrays, xp=np)
        mask = None if mask is None else np.asarray(mask)
    else:
        convert, geometry = (lambda x: _as_array(x, dtype)), _geometry
    points = convert(points)
    if mask is not None and shape_of(mask) != (points.shape[0],):
        raise ValueError(f"mask must have shape ({points.shape[0]},), got {shape_of(mask)}")
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
    """The [`Problem`][jurs.Problem] fields of the slots: the samples laid out, their basis and
    masks."""
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
    if concrete and stable_shapes and len(shape) != 2 and layout is None:
        # A surface's slots, gathered by cell for the assembly (jurs._linalg.normal).
        groups = cell_groups(np.asarray(cells), num_cells(shape))
        local = local if groups is None else with_groups(local, *groups)
    return dict(
        samples=slot_xy,
        targets=slot_targets,
        mask=slot_mask,
        is_data=slot_data,
        sample_index=slot_sample,
        local=local,
    )


def make_problem(
    points: Float[ArrayLike, "m d"],
    normals: Float[ArrayLike, "m d"],
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
    """Build the fitting [`Problem`][jurs.Problem] of eq. 4-5 and 9.

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
            ``jurs._model.spline.TABLE_MAX_SLOTS`` samples the paper's order, one sample a
            slot, with the table form of ``jurs._model.spline`` (its own buckets, built on the
            host); above, buckets of ``choose_bucket_size``. 1 keeps the paper's order
            (with the table form when small and concrete). Sizes above 1 need concrete
            (untraced) inputs: the layout is computed on the host. 3D problems always
            take one sample a slot (the generic form of ``jurs._model.spline``); with
            ``stable_shapes`` a concrete one also holds its slots gathered by cell, for
            the assembly of the normal equations ([`jurs.internal.with_groups`][]).
        dtype: floating dtype; default float64 when ``jax_enable_x64`` is on, else float32.
        stable_shapes: size a concrete problem's sample layout from the number of points
            and the rounded number of occupied cells (``stable_layout``), so that
            clouds padded to one size share one compiled fit; masked samples then take no
            bucket. [`jurs.fit`][] sets it for the clouds it pads.

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
    shape = normalise_grid(grid, shape_of(points)[1])
    return build_problem(
        points, normals, shape, offset, eps, domain, margin, mask, bucket_size, dtype, stable_shapes
    )


def build_problem(
    points,
    normals,
    shape: tuple[int, ...],
    offset,
    eps,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    mask=None,
    bucket_size: int | None = None,
    dtype=None,
    stable_shapes: bool = False,
    on_host: bool = False,
) -> Problem:
    """[`make_problem`][jurs.make_problem] of inputs already checked
    (``jurs._problem.validate.validate_inputs``) on a normalised grid ``shape``: what
    [`jurs.fit`][] calls, having checked its cloud once.

    ``on_host``: concrete inputs laid out on the host in NumPy whatever their size, one
    sample a slot in the paper's order (``bucket_size`` 1, no table or groups): what the
    exact solve in parts reads (``jurs.solvers._parts``), built without compiling the
    geometry for each new count of points."""
    ndim = len(shape)
    if bucket_size is not None and (int(bucket_size) != bucket_size or bucket_size < 1):
        raise ValueError(f"bucket_size must be a positive int, got {bucket_size!r}")
    dtype = dtype or jnp.result_type(float)
    concrete = is_concrete(points, normals, offset, eps, domain, mask)
    check_precision(points, offset, dtype, domain, eps)
    if concrete:
        # Unit length in float64 before any cast: 1e200-long normals overflow float32.
        normals = unit_normals(np.asarray(normals, float))
    small = 3 * shape_of(points)[0] <= TABLE_MAX_SLOTS
    if ndim != 2:
        bucket_size, small = surface_bucket_size(bucket_size), False
    on_host = on_host and concrete
    if on_host:
        bucket_size, stable_shapes = 1, False
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
        small or on_host,
    )
    slots = _laid_out_slots(
        geometry, shape, bucket_size, concrete, small and not on_host, stable_shapes
    )
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


def values_by_point(values: Array, sample_index: Array, real: Array, num_points: int):
    """``(g(P_i), g(P_i + d n_i), g(P_i - d n_i))``, three ``(m,)`` arrays, from per-slot
    ``values`` (``sample_index`` the slots' positions in the paper's order, eq. 9); a sample
    that is not ``real`` (padding) counts 0."""
    point, kind = sample_index % num_points, sample_index // num_points
    return tuple(
        jax.ops.segment_sum(jnp.where(real & (kind == k), values, 0.0), point, num_points)
        for k in range(3)
    )
