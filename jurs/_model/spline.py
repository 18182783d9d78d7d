"""The rational implicit function g (eq. 14) as an equinox Module, and the two linear maps
every solver is built from.

``g(x) = sum_ij C_ij w_ij B_i(x) B_j(y) / W(x)`` with ``W(x) = sum_kl w_kl B_k(x) B_l(y)``;
with all weights 1, ``W = 1`` (partition of unity) and g is the B-spline f of eq. 2.

So g is two plain B-spline evaluations, ``F(w C) / F(w)``, where ``F`` maps a coefficient
grid to values at the samples ([`bspline_values`][jurs.internal.bspline_values]). Its transpose
``T`` ([`bspline_transpose`][jurs.internal.bspline_transpose]) gives everything else: the
collocation transpose of eq. 23 is ``D^T v = w * T(v / W)``, and the gradients of
docs/design.md section 2 are ``T`` of per-sample scalars times a grid. No (samples x 16) array
of rows is ever needed on the fast path.

Samples are stored in *buckets*: runs of ``bucket_size`` samples that share one cell, so a
bucket reads its 4 x 4 coefficient patch once and its sums over samples are dense
reductions instead of scatters. ``bucket_size = 1`` (one sample a bucket, any order) is the
generic layout that works under any JAX transformation.

Two ways to run F and T, chosen by what the [`LocalBasis`][jurs.internal.LocalBasis] holds:

* *power form* (large problems): each cell's piece is taken to powers of the centred local
  coordinates once, a sample costs a Horner scheme, and T sums power moments per bucket
  (one variadic reduction) before going back to the B-spline basis per cell. Per sample
  only its two local coordinates are read.
* *table form* (small problems, ``TABLE_MAX_SLOTS``): the samples keep their order (one
  a slot, no padding), and a table of their own groups them into buckets of one cell: the
  16 basis products of every table position (0 at its padding), the grid corner of every
  bucket's 4 x 4 coefficient patch and the flat grid index of its 16 coefficients are
  stored, with the permutation between slots and table positions. F gathers the patches
  from the grid (one 4 x 4 window a bucket, cheaper than 16 indices: docs/performance.md,
  "Spline kernels") and T scatters onto it directly; a step then runs as a handful of
  small kernels, which is what counts with a few thousand samples. Table position ``p``
  is entry ``p % K`` of bucket ``p // K``. The products are stored twice,
  term-major (for F, which broadcasts a bucket's coefficient along its entries) and
  term-minor (for T, which broadcasts an entry's value along its 16 terms): XLA vectorises
  a loop only along contiguous memory.
"""

from __future__ import annotations

from functools import partial
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .basis import (
    NUM_LOCAL,
    cubic_weights,
    flat_cell,
    grid_to_patches,
    locate,
    num_cells,
    patch_to_power,
    patches_to_grid,
    power_moments,
    power_values,
)
from .function import AbstractSpline
from .groups import grouped_values
from .lattice import HostGrid, grid_lattice_values, grid_values_and_gradients, spline_fields
from .local import LocalBasis
from .precision import full_precision

#: Up to this many samples [`jurs.make_problem`][] builds the table form (16 stored
#: products a sample, 8 MB in float64 at the limit).
TABLE_MAX_SLOTS = 1 << 16


def local_basis(
    xy: Float[Array, "S d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    shape: tuple[int, ...],
    bucket_size: int = 1,
    xp=jnp,
) -> LocalBasis:
    """The local basis of the ``shape`` grid (``(N, M)``, or ``(N, M, K)`` in 3D) on
    ``[lower, upper]`` at ``xy (S, d)``, in the power form (2D) or the generic form.

    With ``bucket_size > 1`` the caller guarantees that each run of ``bucket_size``
    consecutive points lies in one cell (see [`jurs.internal.bucket_layout`][]).
    ``xp=numpy`` computes on the host (its fields are then NumPy arrays).
    """
    cell, t = locate(xy, lower, upper, shape, xp)
    # Stored centred, one row a coordinate: every evaluation works in s = t - 1/2 (see the
    # module notes), and a subtraction shared by many kernels would be stored once more by
    # XLA. On the host, rows made contiguous: the layouts slice them.
    s = (t - 0.5).T
    return LocalBasis(
        cell=flat_cell(cell, shape),
        s=np.ascontiguousarray(s) if xp is np else s,  # pyright: ignore[reportArgumentType]
        bucket_size=bucket_size,
    )


def with_table(
    local: LocalBasis, order: np.ndarray, valid: np.ndarray, shape: tuple[int, int]
) -> LocalBasis:
    """``local`` (one sample a slot, concrete) with the table form added, built on the host.

    ``order`` and ``valid``, both ``(B, K)``: the sample at entry ``i`` of table bucket
    ``b`` (all of a bucket's samples in one cell; padding entries repeat one of them) and
    whether it is real.
    """
    num_buckets, k = order.shape
    order, valid = order.reshape(-1), valid.reshape(-1)  # position p = b * K + i
    s = np.asarray(local.s)[:, order]
    dtype = s.dtype
    b = cubic_weights(s + 0.5, xp=np)  # (2, P, 4)
    # Padding positions repeat a sample of their bucket: their values stay finite, and the
    # transposes weigh them by ``filled`` (0).
    terms = (b[0][:, :, None] * b[1][:, None, :]).reshape(-1, NUM_LOCAL)  # (P, 16)
    position = np.zeros(local.cell.shape[0], np.int32)
    position[order[valid]] = np.nonzero(valid)[0]
    cell = np.asarray(local.cell)[order[::k]]  # one sample of every bucket
    corner = np.stack([cell // (shape[1] - 3), cell % (shape[1] - 3)], axis=1)
    first = corner[:, 0] * shape[1] + corner[:, 1]
    offsets = (np.arange(4)[:, None] * shape[1] + np.arange(4)[None, :]).reshape(NUM_LOCAL)
    return eqx.tree_at(
        lambda x: (x.terms, x.terms_t, x.index, x.corner, x.order, x.position, x.filled),
        local,
        # device_put: host arrays of the right dtype, transferred without compiling anything,
        # all in one call.
        jax.device_put(
            (
                np.ascontiguousarray(terms.T.reshape(NUM_LOCAL, num_buckets, k)),
                terms.reshape(num_buckets, k, NUM_LOCAL),
                (first[:, None] + offsets[None, :]).astype(np.int32),
                corner.astype(np.int32),
                order.astype(np.int32),
                position,
                valid.astype(dtype),
            )
        ),
        is_leaf=lambda x: x is None,
    )


def _take(x: Array, i: int, axis: int) -> Array:
    """``x`` at index ``i`` of ``axis``, that axis dropped (a static slice)."""
    return jax.lax.index_in_dim(x, i, axis, keepdims=False)


def computed_apart(fn, *args, shapes=None):
    """``fn(*args)``, evaluated in a kernel of its own and stored.

    XLA fuses an elementwise producer into the kernels that consume it: into a reduction,
    where the per-sample Horner schemes run several times slower than in an elementwise
    kernel (docs/performance.md, "Spline kernels"), or into several consumers at once, each
    then evaluating the spline again. A conditional is a fusion boundary, and a cheap one. Its
    predicate is always true but opaque to the compiler (the first integer input, a cell
    or grid index, is never negative), so the other branch, zeros, never runs; without an
    integer input both branches are ``fn``. ``shapes``: the output's shape-dtype structure
    when the caller knows it (otherwise ``fn`` is traced once more to find it).
    """
    leaves = jax.tree_util.tree_leaves(args)
    index = next((x for x in leaves if jnp.issubdtype(x.dtype, jnp.integer)), None)
    if index is None:
        leaf = next(x for x in leaves if jnp.issubdtype(x.dtype, jnp.floating))
        return jax.lax.cond(jnp.isnan(leaf.ravel()[0]), fn, fn, *args)
    if shapes is None:
        shapes = jax.eval_shape(fn, *args)
    zeros = lambda *_: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    return jax.lax.cond(index.ravel()[0] >= 0, fn, zeros, *args)


def gather_patches(grids: Array, corner: Array) -> Array:
    """``(C, N, M)`` coefficient grids -> ``(B, C, 16)``: the 4 x 4 patch whose first
    coefficient sits at each ``corner (B, 2)`` (row, column), every grid at once.

    One windowed gather: an index pair a patch, its 4 rows read as contiguous runs.
    """
    dims = jax.lax.GatherDimensionNumbers(
        offset_dims=(1, 2, 3), collapsed_slice_dims=(), start_index_map=(1, 2)
    )
    patches = jax.lax.gather(
        grids,
        corner,
        dims,
        slice_sizes=(grids.shape[0], 4, 4),
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )
    return patches.reshape(corner.shape[0], grids.shape[0], NUM_LOCAL)


def power_coefficients(grids: Array) -> Array:
    """``(C, N, M)`` coefficient grids -> ``(C, cells, 16)``: each cell's bicubic piece in
    powers of its centred local coordinates (see ``jurs._model.basis.patch_to_power``).

    One 4 x 4 convolution with 16 output channels: the patch gather and the change of
    basis in a single kernel.
    """
    kernel = jnp.asarray(patch_to_power().reshape(4, 4, 1, NUM_LOCAL), grids.dtype)  # HWIO
    out = jax.lax.conv_general_dilated(
        grids[..., None],
        kernel,
        (1, 1),
        "VALID",
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
        precision=jax.lax.Precision.HIGHEST,
    )
    return out.reshape(grids.shape[0], -1, NUM_LOCAL)


def bspline_values(
    local: LocalBasis,
    grids: Float[Array, "*batch N M"] | Float[Array, "*batch N M K"],
    *,
    layout: bool = False,
) -> Float[Array, "*batch S"]:
    """F: the B-spline ``sum_ij G_ij B_i B_j`` of coefficient grid(s) at the samples.

    ``grids`` is ``(..., N, M)``; returns ``(..., S)``. Several grids share one pass over
    the samples. Power form: each bucket's cell piece is taken to powers once, and each
    sample costs a Horner scheme (15 multiply-adds a grid); table form: 16 stored products
    a sample against the gathered patch. ``layout=True`` returns the values in the
    kernels' layout ([`LocalBasis.to_layout`][jurs.internal.LocalBasis.to_layout]) instead
    of per slot.
    """
    ndim = local.ndim
    if ndim != 2:
        return _gathered_values(local, grids)
    lead = grids.shape[:-2]
    flat = grids.reshape((-1,) + grids.shape[-2:])
    if local.terms is not None:
        assert local.corner is not None  # the table fields are set together
        # (C, buckets, 1) per term, broadcast along each bucket's entries. lax slicing:
        # these unrolled loops are traced in every solver, and jnp indexing traces slowly.
        patches = jnp.transpose(gather_patches(flat, local.corner), (1, 0, 2))[..., None]
        values = cast(
            Array, sum(_take(local.terms, j, 0) * _take(patches, j, 2) for j in range(NUM_LOCAL))
        )  # a sum of 16 arrays, never its start 0
        values = values.reshape(flat.shape[0], -1)
        if layout:
            return values.reshape(lead + values.shape[-1:])
        values = values[:, local.position]
    else:
        coeffs = power_coefficients(flat)[:, local.bucket_cell]  # (C, buckets, 16)
        sx, sy = local.centred()
        values = power_values([coeffs[:, :, j, None] for j in range(16)], sx, sy)
    return values.reshape(lead + (local.cell.shape[0],))


#: Samples a block of the generic (3D) evaluation: each block gathers ``(block, 64)``
#: coefficients and basis products, so the whole cloud's never exist at once. Unblocked,
#: the objective of 1e6 surface points (3e6 samples) held 3.6 GB of such temporaries
#: (XLA's memory analysis), most of a 1e6-point fit's peak.
GATHER_BLOCK = 1 << 16


def _gathered_values(local: LocalBasis, grids: Array) -> Array:
    """F in the generic form (any d, one sample a slot): each sample's ``4 ** d``
    coefficients gathered from the flat grid against its basis products, a block of
    ``GATHER_BLOCK`` samples at a time (within each of the ``local.parts`` parts of a
    split sample axis, so that no device reads another's samples). This is the path of 3D
    grids, whose samples are not bucketed (see [`jurs.make_problem`][])."""
    shape = grids.shape[grids.ndim - local.ndim :]
    lead = grids.shape[: grids.ndim - local.ndim]
    flat = grids.reshape(lead + (-1,))

    if local.group_position is not None:
        return grouped_values(local, flat, shape)

    def values(cell, s):  # (n,) cells and (d, n) coordinates -> (..., n)
        block = LocalBasis(cell=cell, s=s)
        coeffs = jnp.take(flat, block.patch_index(shape), axis=-1)  # (..., n, 4 ** d)
        return jnp.sum(coeffs * block.products, axis=-1)

    count = local.cell.shape[0]
    parts = local.parts if local.parts > 1 and count % local.parts == 0 else 1
    per_part = count // parts
    if per_part <= GATHER_BLOCK:
        return values(local.cell, local.s)
    pad = (-per_part) % GATHER_BLOCK
    blocks = (per_part + pad) // GATHER_BLOCK

    def split(x):  # (..., count) -> (blocks, ..., parts, GATHER_BLOCK); padding in cell 0
        x = x.reshape(x.shape[:-1] + (parts, per_part))
        x = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)])
        return jnp.moveaxis(x.reshape(x.shape[:-1] + (blocks, GATHER_BLOCK)), -2, 0)

    by_part = jax.vmap(values, in_axes=(0, 1), out_axes=-2)  # over the parts
    out = jax.lax.map(lambda block: by_part(*block), (split(local.cell), split(local.s)))
    out = jnp.moveaxis(out, 0, -2)  # (..., parts, blocks, GATHER_BLOCK)
    return out.reshape(lead + (parts, -1))[..., :per_part].reshape(lead + (count,))


def values_apart(local: LocalBasis, grids: Array) -> Array:
    """[`bspline_values`][jurs.internal.bspline_values] in the kernels' layout, in a
    kernel of its own (``computed_apart``), as the solver steps call it: ``(..., N, M)``
    -> ``(..., P)`` with ``P`` the layout's length."""
    count = local.cell.shape[0] if local.terms is None else local.terms[0].size
    shapes = jax.ShapeDtypeStruct(
        grids.shape[: grids.ndim - local.ndim] + (count,), jnp.result_type(grids, local.s)
    )
    return computed_apart(partial(bspline_values, layout=True), local, grids, shapes=shapes)


@full_precision
def transpose_and_sum(
    local: LocalBasis, values: Array, shape: tuple[int, ...], extra=(), *, layout: bool = False
):
    """[`bspline_transpose`][jurs.internal.bspline_transpose] of ``values (C, S)``, and the
    totals of the ``extra`` per-sample arrays ``(S,)`` computed in the same pass over the
    samples. ``layout=True``: ``values`` and ``extra`` are in the kernels' layout
    ([`LocalBasis.to_layout`][jurs.internal.LocalBasis.to_layout])."""
    k = local.bucket_size
    if local.terms is not None:
        assert local.index is not None  # the table fields are set together
        num_buckets = local.index.shape[0]
        if not layout:
            values = local.to_layout(values)
            extra = [local.to_layout(x) for x in extra]
        v = values.reshape(values.shape[0], num_buckets, -1)

        def bucket_sums(v, terms):  # (C, table buckets, 16)
            v = v[..., None]
            return sum(_take(terms, i, 1) * _take(v, i, 2) for i in range(terms.shape[1]))

        # In a kernel of its own: fused into the scatter, the sums are laid out as the
        # scatter's (updates, 1) operand and lose vectorisation (docs/performance.md,
        # "Spline kernels").
        per_bucket = computed_apart(
            lambda index, v, terms: bucket_sums(v, terms),
            local.index,
            v,
            local.terms_t,
            shapes=jax.ShapeDtypeStruct(
                v.shape[:2] + (NUM_LOCAL,), jnp.result_type(v, local.terms_t)
            ),
        )
        size = shape[0] * shape[1]
        index = (
            local.index[None]
            + size * jnp.arange(v.shape[0], dtype=local.index.dtype)[:, None, None]
        )
        grid = jnp.zeros(v.shape[0] * size, values.dtype).at[index].add(per_bucket)
        return grid.reshape((v.shape[0],) + tuple(shape)), tuple(jnp.sum(x) for x in extra)
    if local.ndim != 2:
        # The generic form (3D): each sample's 4 ** d products scattered onto the grid.
        size = int(np.prod(shape))
        updates = values[:, :, None] * local.products  # (C, S, 4 ** d)
        grid = jnp.zeros((values.shape[0], size), values.dtype)
        grid = grid.at[:, local.patch_index(shape)].add(updates)
        return grid.reshape((values.shape[0],) + tuple(shape)), tuple(jnp.sum(x) for x in extra)
    if k == 1:
        # One sample a bucket (the generic layout): nothing to sum per bucket, so each
        # sample's 16 B-spline products go to its cell directly (the power detour would
        # only add work).
        per_sample = local.products[:, None, :] * values.T[:, :, None]  # (S, C, 16)
        per_cell = jax.ops.segment_sum(per_sample, local.cell, num_segments=num_cells(shape))
        grid = patches_to_grid(jnp.moveaxis(per_cell, 0, -2), shape)
        return grid, tuple(jnp.sum(x) for x in extra)
    v = values.reshape((-1, local.num_buckets, k))
    sx, sy = local.centred()
    moments, sums = power_moments(sx, sy, v, [e.reshape(-1, k) for e in extra])
    per_cell = jax.ops.segment_sum(
        moments, local.bucket_cell, num_segments=num_cells(shape), indices_are_sorted=k > 1
    )  # (cells, C, 16)
    patches = per_cell @ jnp.asarray(patch_to_power().T, values.dtype)
    grid = patches_to_grid(jnp.moveaxis(patches, 0, -2), shape)
    return grid, tuple(jnp.sum(x) for x in sums)


def bspline_transpose(
    local: LocalBasis, values: Float[Array, "*batch S"], shape: tuple[int, ...]
) -> Float[Array, "*batch N M"] | Float[Array, "*batch N M K"]:
    """T, the transpose of [`bspline_values`][jurs.internal.bspline_values]:
    ``sum_k v_k B_i B_j(x_k)`` on the grid.

    ``values`` is ``(..., S)``; returns ``(..., N, M)``. Several value vectors share one
    pass over the samples. Power form: per bucket the power moments ``sum_k v_k sx^p sy^q``
    (one reduction), then per cell, then back to the B-spline basis and onto the grid;
    table form: per table bucket the 16 sums against the stored products, scattered onto
    the grid.
    """
    lead = values.shape[:-1]
    grid, _ = transpose_and_sum(local, values.reshape((-1, values.shape[-1])), shape)
    return grid.reshape(lead + tuple(shape))


def rational_values(
    local: LocalBasis, control: Float[Array, "*grid"], weights: Float[Array, "*grid"]
) -> tuple[Float[Array, " S"], Float[Array, " S"]]:
    """``(W, g)`` at the samples: ``W = F(w)`` and ``g = F(w C) / W`` (eq. 14)."""
    both = bspline_values(local, jnp.stack([weights, weights * control]))
    return both[0], both[1] / both[0]


def grid_rational_values(
    control: Float[Array, "*grid"],
    weights: Float[Array, "*grid"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    xy: Float[Array, "n d"],
) -> Float[Array, " n"]:
    """g at ``xy`` for a grid spline's fields (``rational_values`` on the grid's local
    basis): the evaluation of [`jurs.ImplicitSpline`][], one pure function of its arrays."""
    local = local_basis(xy, lower, upper, tuple(control.shape))
    return rational_values(local, control, weights)[1]


# Compiled once a shape: called outside a jit, the basis and the contraction would each
# compile op by op on a spline's first evaluation, many times the evaluation's own time.
# Inside a caller's jit, grad or vmap they are traced like any function.
_grid_values = jax.jit(grid_rational_values)
_grid_gradients = jax.jit(
    jax.vmap(
        jax.grad(lambda c, w, lo, up, p: grid_rational_values(c, w, lo, up, p[None])[0], 4),
        in_axes=(None, None, None, None, 0),
    )
)


def rational_terms(local: LocalBasis, control: Array, weights: Array):
    """Rational evaluation with explicit rows (eq. 14 and 23), for checks and row-based
    algorithms; the solvers use the cheaper
    [`rational_values`][jurs.internal.rational_values].

    Returns ``(wb, denom, g)``: ``wb = w_ij B_i B_j`` for the 16 local terms ``(S, 16)``
    (64 in 3D),
    ``denom = W(x)`` ``(S,)`` and ``g(x)`` ``(S,)``. The collocation row of eq. 23 is
    ``wb / denom``.
    """
    if local.ndim == 2:
        w_rows = grid_to_patches(weights)[local.cell]
        c_rows = grid_to_patches(control)[local.cell]
    else:  # one gather of each sample's coefficients, never a (cells, 64) patch array
        index = local.patch_index(weights.shape)
        w_rows, c_rows = weights.ravel()[index], control.ravel()[index]
    wb = local.products * w_rows
    denom = jnp.sum(wb, axis=-1)
    g = jnp.sum(wb * c_rows, axis=-1) / denom
    return wb, denom, g


class ImplicitSpline(AbstractSpline):
    """A uniform rational cubic spline function on the box ``[lower, upper]``: g of
    eq. 14 on the uniform tensor grid (a [`jurs.AbstractSpline`][]).

    Fields: ``control`` (N, M) coefficients C, ``weights`` (N, M) positive weights w, and the
    box corners ``lower``/``upper`` (2,), which fix the uniform knots; for a surface the
    grids are (N, M, K) and the corners (3,), g(x, y, z) the trivariate form of eq. 14.
    Calling it on an ``(n, d)`` array (or one ``(d,)`` point) returns g there (eq. 14). It
    is a pytree: jit, grad and vmap go through it. Outside the box the border polynomial
    pieces extend.
    """

    control: Float[Array, "*grid"]
    weights: Float[Array, "*grid"]
    lower: Float[Array, " d"]
    upper: Float[Array, " d"]

    def __check_init__(self):
        if self.control.ndim not in (2, 3) or self.control.shape != self.weights.shape:
            raise ValueError(
                f"control and weights must be matching 2D or 3D grids, got "
                f"{self.control.shape} and {self.weights.shape}"
            )
        if min(self.control.shape) < 4:
            raise ValueError(
                f"grid must be at least {' x '.join('4' * self.ndim)} for cubic "
                f"splines, got {self.control.shape}"
            )
        if jnp.shape(self.lower) != (self.ndim,) or jnp.shape(self.upper) != (self.ndim,):
            raise ValueError(
                f"lower and upper must have shape ({self.ndim},) for a "
                f"{self.ndim}D grid, got {jnp.shape(self.lower)} and "
                f"{jnp.shape(self.upper)}"
            )

    @property
    def shape(self) -> tuple[int, ...]:
        return self.control.shape

    @property
    def ndim(self) -> int:
        """2 for a curve's spline g(x, y), 3 for a surface's g(x, y, z)."""
        return self.control.ndim

    @property
    def cell_widths(self) -> np.ndarray:
        """The sides of a knot span (the box over ``N - 3`` spans per axis), on the host."""
        extent = np.asarray(self.upper, float) - np.asarray(self.lower, float)
        return extent / (np.asarray(self.shape) - 3)

    @property
    def finest_cells(self) -> tuple[int, ...]:
        """Knot spans per axis (``N - 3``): the uniform grid's cells, named as an
        adaptive spline names the cells of its finest level over the box."""
        return tuple(int(n) - 3 for n in self.shape)

    @classmethod
    def bspline(
        cls,
        control: Float[ArrayLike, "*grid"],
        lower: Float[ArrayLike, " d"],
        upper: Float[ArrayLike, " d"],
    ) -> ImplicitSpline:
        """A polynomial B-spline (all weights 1)."""
        control = jnp.asarray(control)
        return cls(
            control,
            jnp.ones_like(control),
            jnp.asarray(lower, control.dtype),
            jnp.asarray(upper, control.dtype),
        )

    def local_basis(self, xy: Float[Array, "S d"]) -> LocalBasis:
        return local_basis(xy, self.lower, self.upper, self.shape)

    def __call__(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n"]:
        xy = jnp.asarray(xy)
        single = xy.ndim == 1
        g = _grid_values(self.control, self.weights, self.lower, self.upper, jnp.atleast_2d(xy))
        return g[0] if single else g

    def grad(self, xy: Float[ArrayLike, "*n d"]) -> Float[Array, "*n d"]:
        """Spatial gradient of g at ``xy (n, d)``; ``(n, d)`` (or ``(d,)`` for one point)."""
        xy = jnp.asarray(xy)
        fields = (self.control, self.weights, self.lower, self.upper)
        gradients = _grid_gradients(*fields, jnp.atleast_2d(xy))
        return gradients[0] if xy.ndim == 1 else gradients

    def lattice(self, axes) -> np.ndarray:
        """g on the tensor lattice ``axes``, contracted axis by axis on the host
        (``jurs._model.lattice.grid_lattice_values``)."""
        return grid_lattice_values(self, axes)

    def on_host(self) -> HostGrid:
        """Its fields as float64 NumPy arrays, whose ``lattice`` is this spline's (see
        [`jurs.AbstractSpline`][])."""
        fields = (self.control, self.weights, self.lower, self.upper)
        return HostGrid(*(np.asarray(f, np.float64) for f in fields))

    def band_lattice(self, axes, level: float) -> tuple[np.ndarray, np.ndarray]:
        """``(values, evaluated)``: the grid evaluates every node (see
        [`jurs.AbstractSpline`][])."""
        values = self.lattice(axes)
        return values, np.ones(values.shape, bool)

    def values_and_gradients(
        self, points: Float[ArrayLike, "n d"], *, chunk: int = 1 << 14
    ) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, "n d"]]:
        """g and its gradient at ``points`` on the host, each point reading its cell's
        ``4^d`` coefficients (``jurs._model.lattice.values_and_gradients``)."""
        values, gradients = grid_values_and_gradients(self, points, chunk=chunk)
        assert gradients is not None
        return values, gradients

    def slope_bound(self) -> Float[np.ndarray, " d"]:
        """``(max w / min w) max |C_(i+1) - C_i| / h_a`` per axis a: for weights 1 a bound,
        the derivative being a quadratic spline with those coefficients."""
        control, weights = self.coefficients()
        steps = np.array([np.abs(np.diff(control, axis=a)).max() for a in range(self.ndim)])
        return weights.max() / weights.min() * steps / self.cell_widths


def grid_spline(spline, dims: tuple[int, ...] = (2, 3)) -> AbstractSpline:
    """``spline`` itself where it is a [`jurs.AbstractSpline`][], else an
    [`ImplicitSpline`][jurs.ImplicitSpline] of the fields ``control``, ``weights``,
    ``lower`` and ``upper`` of any object holding them, checked (``spline_fields``: a grid
    of a dimension in ``dims``); the level-set tools take either."""
    if isinstance(spline, AbstractSpline):
        if spline.ndim not in dims:
            raise ValueError(
                f"expected a spline of dimension {' or '.join(map(str, dims))}, got a "
                f"{spline.ndim}D {type(spline).__name__}"
            )
        return spline
    control, weights, lower, upper = spline_fields(spline, dims=dims)
    # NumPy float64 fields, as read: the host evaluations take them as they are.
    fields = (cast(Array, a) for a in (control, weights, lower, upper))
    return ImplicitSpline(*fields)
