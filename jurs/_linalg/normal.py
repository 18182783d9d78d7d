"""The normal equations of the collocation least-squares problem, without forming D.

For fixed weights the data energy ``E_d = ||D C - b||^2`` is quadratic in C, and its
minimiser (with the regulariser of eq. 31) solves ``(D^T D + 2 lam L) C = D^T b``
(docs/design.md section 3). ``D^T D`` is banded: coefficient ``(i, j)`` couples only to
``(i + di, j + dj)`` with ``|di|, |dj| <= 3`` (two cubic basis functions overlap when
their supports share a cell), so it is stored as an ``(N, M, 7, 7)`` **stencil**:
``stencil[i, j, 3 + di, 3 + dj] = (D^T D)[(i, j), (i + di, j + dj)]``, 49 numbers a row.

Assembly is one pass over the samples, accumulated per cell and then folded onto the
stencil; its memory is independent of the number of samples:

* B-spline (w = 1): ``B_a(t) B_a'(t)`` is a degree-6 polynomial in the local coordinate
  ``t``, so every 16 x 16 cell Gram block follows from the 49 per-cell moments
  ``sum_k Bern6_p(tx_k) Bern6_q(ty_k)`` (degree-6 Bernstein basis: all terms positive, no
  cancellation in float32). ``D^T b`` likewise from 16 cubic Bernstein moments.
* rational (fixed w): the 256 products of each row ``w_ij B_ij / W`` (eq. 23), accumulated
  in blocks of ``chunk_size`` samples (``lax.scan``) so that no ``(3m, 256)`` array exists.

The stencil is reusable (``jurs._linalg.stencil``): it applies in O(NM) (an I-PIA step
in normal-equation form costs nothing per sample), and
[`NormalEquations.regularised`][jurs.internal.NormalEquations.regularised] gives the system
``D^T D + 2 lam L`` as a lineax operator for the exact solve.
"""

from __future__ import annotations

from math import comb, prod

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax

from .._model.basis import (
    NUM_LOCAL,
    cell_shape,
    grid_to_patches,
    num_cells,
    patches_to_grid,
    tensor_basis,
)
from .._model.groups import map_groups
from .._model.precision import full_precision
from .._problem.problem import Problem
from .stencil import (
    HALF,
    SIDE,
    StencilOperator,
    plus_laplacian,
    stencil_matvec,
    stencil_to_dense,
)

#: Default number of samples accumulated at once on the rational path (``chunk x 256``
#: floats: 32 MB in float64).
DEFAULT_CHUNK = 2**14


def _cubic_bernstein() -> np.ndarray:
    """Coefficients of the four uniform cubic B-spline pieces
    ([`jurs.internal.cubic_weights`][]) in the cubic Bernstein basis
    ``comb(3, p) t^p (1 - t)^(3 - p)``; ``(4, 4)``."""
    return np.array([[1, 0, 0, 0], [4, 4, 2, 1], [1, 2, 4, 4], [0, 0, 0, 1]], float) / 6.0


def _product_bernstein() -> np.ndarray:
    """``B_a(t) B_{a + d - 3}(t)`` in the degree-6 Bernstein basis; ``(4, 7, 7)`` indexed
    ``[a, d, p]``, zero where ``a + d - 3`` is not a piece. Products of Bernstein forms:
    ``Bern3_i Bern3_j = comb(3, i) comb(3, j) / comb(6, i + j) Bern6_{i + j}``."""
    cubic = _cubic_bernstein()
    out = np.zeros((4, SIDE, SIDE))
    for a in range(4):
        for d in range(SIDE):
            b = a + d - HALF
            if not 0 <= b < 4:
                continue
            for i in range(4):
                for j in range(4):
                    out[a, d, i + j] += (
                        cubic[a, i] * cubic[b, j] * comb(3, i) * comb(3, j) / comb(6, i + j)
                    )
    return out


def _bernstein(t: Array, degree: int) -> Array:
    """Bernstein basis of ``degree`` at ``t``; ``(..., degree + 1)``, from products only
    (``_bernstein_terms``: a power would cost the assembly more than the rest of it)."""
    return jnp.stack(_bernstein_terms(t, degree), axis=-1)


def _bernstein_terms(t: Array, degree: int) -> list:
    """The Bernstein basis of ``degree`` at ``t`` as a list of arrays shaped like ``t``,
    from products only (no ``pow``: inside a reduction every operand would evaluate it)."""
    s = 1.0 - t
    tp, sp = [jnp.ones_like(t)], [jnp.ones_like(t)]
    for _ in range(degree):
        tp.append(tp[-1] * t)
        sp.append(sp[-1] * s)
    return [comb(degree, p) * tp[p] * sp[degree - p] for p in range(degree + 1)]


def chunked_segment_sum(
    rows_fn,
    inputs,
    segments: Array,
    num_segments: int,
    chunk_size: int = DEFAULT_CHUNK,
    parts: int = 1,
) -> Array:
    """``segment_sum(rows_fn(*inputs), segments)`` computed ``chunk_size`` rows at a time.

    ``rows_fn`` maps a block of the ``inputs`` (arrays sharing a leading axis) to
    ``(block, ...)`` rows; it must return 0 rows for zero-padded inputs whose weight
    (the caller's mask) is 0. Peak memory is one block of rows, whatever the number of
    samples.

    ``parts``: the leading axis is taken as that many equal parts (the devices of a sharded
    fit, ``jurs.LocalBasis.parts``), each summed a chunk at a time on its own, then
    the parts' sums added. Why: a scan over chunks of an axis split over devices walks
    across the devices, and the partitioner gathers every chunk to every device; chunks
    taken within each part stay where they are, and only the grid-sized sums are reduced.
    """
    n = segments.shape[0]
    parts = parts if parts > 1 and n % parts == 0 else 1
    per_part = n // parts
    if per_part <= chunk_size:
        return jax.ops.segment_sum(rows_fn(*inputs), segments, num_segments=num_segments)
    pad = (-per_part) % chunk_size
    blocks = (per_part + pad) // chunk_size

    def split(x):  # (n, ...) -> (blocks, parts, chunk, ...), each part padded on its own
        x = x.reshape((parts, per_part) + x.shape[1:])
        x = jnp.pad(x, [(0, 0), (0, pad)] + [(0, 0)] * (x.ndim - 2))
        return jnp.moveaxis(x.reshape((parts, blocks, chunk_size) + x.shape[2:]), 1, 0)

    split_inputs = [split(x) for x in inputs]
    split_segments = split(segments)
    out_struct = jax.eval_shape(rows_fn, *[x[0, 0] for x in split_inputs])

    def part_sum(seg, *xs):
        return jax.ops.segment_sum(rows_fn(*xs), seg, num_segments=num_segments)

    def body(total, block):
        return total + jax.vmap(part_sum)(*block), None

    total0 = jnp.zeros((parts, num_segments) + out_struct.shape[1:], out_struct.dtype)
    total, _ = jax.lax.scan(body, total0, [split_segments, *split_inputs])
    return total.sum(axis=0)


def _cells_to_stencil(blocks: Array, shape: tuple[int, ...]) -> Array:
    """Fold per-cell couplings onto the stencil.

    ``blocks`` is ``(cells, 16, 7, 7)``: for local term ``(a, b)`` of a cell, its coupling
    to the term at offset ``(da, db)`` (stored at ``[3 + da, 3 + db]``). Term ``(a, b)`` of
    cell ``(cx, cy)`` is coefficient ``(cx + a, cy + b)``, so this is the adjoint of the
    patch gather (``jurs._model.basis.patches_to_grid``) with 49 channels.
    """
    n, m = shape[0] - 3, shape[1] - 3
    per_cell = blocks.reshape(n, m, NUM_LOCAL, SIDE, SIDE)
    stencil = jnp.zeros(shape + (SIDE, SIDE), blocks.dtype)
    for a in range(4):
        for b in range(4):
            stencil = stencil.at[a : a + n, b : b + m].add(per_cell[:, :, a * 4 + b])
    return stencil


def _gram_to_blocks(gram: Array) -> Array:
    """``(cells, 16, 16)`` Gram blocks -> ``(cells, 16, 7, 7)`` couplings by offset."""
    a = np.arange(4)[:, None, None, None]
    b = np.arange(4)[None, :, None, None]
    da = np.arange(SIDE)[None, None, :, None] - HALF
    db = np.arange(SIDE)[None, None, None, :] - HALF
    a2, b2 = a + da, b + db
    valid = (a2 >= 0) & (a2 < 4) & (b2 >= 0) & (b2 < 4)
    col = np.where(valid, a2 * 4 + b2, NUM_LOCAL)  # out of the cell -> a zero column
    col = np.broadcast_to(col, (4, 4, SIDE, SIDE)).reshape(NUM_LOCAL, SIDE * SIDE)
    padded = jnp.concatenate([gram, jnp.zeros(gram.shape[:2] + (1,), gram.dtype)], axis=-1)
    picked = jnp.take_along_axis(padded, jnp.asarray(col)[None], axis=-1)
    return picked.reshape(gram.shape[0], NUM_LOCAL, SIDE, SIDE)


def _local_coordinates(problem: Problem) -> Array:
    """``t (S, 2)`` of every sample in its cell (as stored in ``problem.local``)."""
    return problem.local.t.T


def bernstein_moments(problem: Problem, chunk_size: int = DEFAULT_CHUNK) -> Array:
    """Per-cell sums ``(cells, 7 ** d + 4 ** d)``: ``sum_k mask Bern6_p(tx) Bern6_q(ty)`` and
    ``sum_k b_k Bern3_p(tx) Bern3_q(ty)`` over the samples of each cell (with a third
    factor per term in 3D). Sums: the moments of several sets of samples add up."""
    local = problem.local
    count = num_cells(problem.shape)
    if local.group_slot is not None:
        return _grouped_moments(problem, count)
    if local.bucket_size > 1:
        # Bucketed layout: the 65 sums of each bucket are one variadic reduction over its
        # slots (no (samples x 65) array, no scatter), then a sorted sum per cell.
        k = local.bucket_size
        t = local.t.reshape(2, -1, k)
        mask = problem.mask.reshape(-1, k)
        target = (problem.mask * problem.targets).reshape(-1, k)
        b6x, b6y = _bernstein_terms(t[0], 6), _bernstein_terms(t[1], 6)
        b3x, b3y = _bernstein_terms(t[0], 3), _bernstein_terms(t[1], 3)
        terms = [mask * b6x[p] * b6y[q] for p in range(7) for q in range(7)]
        terms += [target * b3x[p] * b3y[q] for p in range(4) for q in range(4)]
        zeros = tuple(jnp.zeros((), t.dtype) for _ in terms)
        sums = jax.lax.reduce(
            tuple(terms), zeros, lambda a, b: tuple(x + y for x, y in zip(a, b)), (1,)
        )
        return jax.ops.segment_sum(
            jnp.stack(sums, axis=-1), local.bucket_cell, num_segments=count, indices_are_sorted=True
        )
    t = _local_coordinates(problem)

    def moments(t, mask, target):
        axes = range(t.shape[1])
        gram = tensor_basis(*[_bernstein(t[:, a], 6) for a in axes])
        rhs = tensor_basis(*[_bernstein(t[:, a], 3) for a in axes]) * target[:, None]
        return jnp.concatenate([gram, rhs], axis=1) * mask[:, None]

    inputs = [t, problem.mask, problem.targets]
    return chunked_segment_sum(moments, inputs, local.cell, count, chunk_size, local.parts)


def _group_tensor_sums(t: Array, weight: Array, degree: int) -> Array:
    """``sum_k weight_k Bern_p(t_k[0]) Bern_q(t_k[1]) ...`` over the ``K`` entries of each
    group: ``t (d, G, K)``, ``weight (G, K)`` -> ``(G, (degree + 1) ** d)``, row-major in
    the axes as ``tensor_basis``. The first axis's values meet the other axes' products
    in one batched matrix product a group, never a ``(samples, (degree + 1) ** d)``
    array."""
    first = jnp.stack(_bernstein_terms(t[0], degree), -1) * weight[..., None]
    rest = jnp.stack(_bernstein_terms(t[1], degree), -1)
    for axis in range(2, t.shape[0]):
        more = jnp.stack(_bernstein_terms(t[axis], degree), -1)
        rest = (rest[..., :, None] * more[..., None, :]).reshape(rest.shape[:2] + (-1,))
    sums = jnp.einsum("gkp,gkq->gpq", first, rest, precision=jax.lax.Precision.HIGHEST)
    return sums.reshape(sums.shape[0], -1)


def _grouped_moments(problem: Problem, count: int) -> Array:
    """``bernstein_moments`` from the slots gathered by cell
    ([`jurs.internal.with_groups`][]): each group's moments in one batched product
    (``_group_tensor_sums``), ``GROUP_CHUNK`` groups at a time, then one sorted scatter
    of a row a group. A slot's mask and target are read here, so a mask changed after
    the layout (the robust fit's weights) counts."""
    local = problem.local

    def sums(slot, filled):  # (c, K) -> (c, 7 ** d + 4 ** d)
        t = local.t[:, slot]  # (d, c, K)
        weight = problem.mask[slot] * filled
        gram = _group_tensor_sums(t, weight, 6)
        rhs = _group_tensor_sums(t, weight * problem.targets[slot], 3)
        return jnp.concatenate([gram, rhs], axis=1)

    per_group = map_groups(sums, local)
    assert local.group_slot is not None  # map_groups ran
    group_cell = local.cell[local.group_slot[:, 0]]
    return jax.ops.segment_sum(per_group, group_cell, num_segments=count, indices_are_sorted=True)


def _fold_axes(cells: Array, kernel: Array) -> Array:
    """The moment-to-stencil fold over every axis: ``cells`` is ``cell_grid + (channels,) *
    d`` (channel axis ``d + a`` the moment degree along axis ``a``), the result
    ``grid + (offsets,) * d`` (``kernel`` is ``(4, offsets, channels)``: 7 offsets for
    the Gram moments, 1 for the right-hand side's).

    Along axis ``a``, ``out[i] = sum_b kernel[b] . cells[i - b]`` (cells outside the range
    are 0): a one-dimensional convolution of width 4 from the degree channels to the
    offset channels, with the other channel axes as its batch. One convolution an axis
    writes one array, where four shifted products summed kept four grid-sized arrays
    alive at once, the largest buffers of a surface's fit. The first channel axis is
    the one folded, and the new offset axis goes last, so after ``d`` folds the offsets
    are in axis order."""
    d = cells.ndim // 2
    grid = tuple(range(d))
    taps = jnp.flip(kernel, 0).transpose(1, 2, 0)  # (offsets, channels, 4): correlation
    for axis in range(d):
        rest = cells.shape[d + 1 :]
        merged = cells.reshape(cells.shape[: d + 1] + (prod(rest),))
        width = tuple(4 if a == axis else 1 for a in grid)
        numbers = lax.ConvDimensionNumbers(
            lhs_spec=(d + 1, d) + grid, rhs_spec=(0, 1) + tuple(range(2, 2 + d)),
            out_spec=(d, d + 1) + grid,
        )  # fmt: skip
        folded = lax.conv_general_dilated(
            merged,
            taps.reshape(taps.shape[:2] + width),
            (1,) * d,
            [(3, 3) if a == axis else (0, 0) for a in grid],
            dimension_numbers=numbers,
            precision=lax.Precision.HIGHEST,
        )
        cells = folded.reshape(folded.shape[:d] + rest + (kernel.shape[1],))
    return cells


def bspline_normal_equations(problem: Problem, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the B-spline collocation (w = 1) from per-cell Bernstein
    moments (``bernstein_moments``, folded by ``moments_to_stencil``). Any grid dimension
    d."""
    return moments_to_stencil(bernstein_moments(problem, chunk_size), problem.shape)


def moments_to_stencil(sums: Array, shape: tuple[int, ...]):
    """``(stencil, D^T b)`` from per-cell Bernstein moments ``(cells, 7 ** d + 4 ** d)``
    (``bernstein_moments``; the moments of several sets of samples are their sums):
    7 ** d + 4 ** d channels a cell, never the ``16 ** d`` products.

    Coefficient ``(i, j)`` couples to ``(i + da - 3, j + db - 3)`` through every cell
    ``(i - a, j - b)`` both touch, with ``sum_pq P[a, da, p] P[b, db, q] moment[p, q]``;
    that sum factorises by axis, so the fold runs as one pass over the grid an axis
    with 7 channels each, never a ``(cells, 16, 7, 7)`` array, which would dominate the
    assembly's time (docs/multigrid.md, "Measurements behind the constants")."""
    dtype = sums.dtype
    ndim = len(shape)
    cells = cell_shape(shape)
    gram_moments = sums[:, : 7**ndim].reshape(cells + (7,) * ndim)  # [cells..., p, q(, r)]
    rhs_moments = sums[:, 7**ndim :].reshape(cells + (4,) * ndim)
    stencil = _fold_axes(gram_moments, jnp.asarray(_product_bernstein(), dtype))  # [a, da, p]
    cubic = jnp.asarray(_cubic_bernstein(), dtype)[:, None, :]  # [a, 1, p]: B_a in Bern3
    rhs = _fold_axes(rhs_moments, cubic)
    return stencil, rhs.reshape(shape)


def rational_normal_equations(problem: Problem, weights: Array, chunk_size: int = DEFAULT_CHUNK):
    """``(stencil, D^T b)`` for the rational collocation rows ``w_ij B_ij / W`` (eq. 23) of
    fixed ``weights``: the 16 x 16 products of each row, accumulated ``chunk_size`` samples
    at a time. 2D only (NotImplementedError for a surface: its 64 x 64 row products are not
    written yet)."""
    if problem.ndim != 2:
        raise NotImplementedError(
            "the rational normal equations (fixed weights other than "
            "1) are 2D only; fit surfaces with the B-spline "
            "(LeastSquares(keep_weights=False), the default)"
        )
    w_patches = jnp.take(grid_to_patches(weights), problem.local.cell, axis=0)

    def products(bx, by, w_rows, mask, target):
        basis = (bx[:, :, None] * by[:, None, :]).reshape(-1, NUM_LOCAL)
        wb = basis * w_rows
        denom = jnp.sum(wb, axis=1)
        # Zero-padded blocks have W = 0: divide by 1 there (their mask is 0 anyway).
        rows = wb * (mask / jnp.where(denom > 0, denom, 1.0))[:, None]
        gram = (rows[:, :, None] * rows[:, None, :]).reshape(-1, NUM_LOCAL * NUM_LOCAL)
        return jnp.concatenate([gram, rows * target[:, None]], axis=1)

    inputs = [problem.local.bx, problem.local.by, w_patches, problem.mask, problem.targets]
    cells = num_cells(problem.shape)
    sums = chunked_segment_sum(
        products, inputs, problem.local.cell, cells, chunk_size, problem.local.parts
    )
    gram = sums[:, : NUM_LOCAL * NUM_LOCAL].reshape(-1, NUM_LOCAL, NUM_LOCAL)
    stencil = _cells_to_stencil(_gram_to_blocks(gram), problem.shape)
    return stencil, patches_to_grid(sums[:, NUM_LOCAL * NUM_LOCAL :], problem.shape)


class NormalEquations(eqx.Module):
    """``D^T D`` as an ``(N, M, 7, 7)`` stencil and ``D^T b`` as an ``(N, M)`` grid.

    Build with [`normal_equations`][jurs.internal.normal_equations]. ``matvec`` applies
    ``D^T D``; ``E_d(C)`` equals ``C.(D^T D) C - 2 C.(D^T b) + b.b`` (``b.b`` in
    ``target_norm2``).
    """

    stencil: Array
    rhs: Array
    target_norm2: Array

    def matvec(self, control: Array) -> Array:
        return stencil_matvec(self.stencil, control)

    def data_energy(self, control: Array, product: Array | None = None) -> Array:
        """E_d (eq. 16) from the normal equations, O(NM) whatever the number of samples;
        ``product``, ``matvec(control)``, where the caller has it already."""
        product = self.matvec(control) if product is None else product
        return jnp.vdot(control, product - 2.0 * self.rhs) + self.target_norm2

    def regularised(self, lam) -> StencilOperator:
        """``D^T D + 2 lam L``, the Hessian / 2 of ``E_d + lam R`` (docs/design.md section
        3), as a lineax operator holding its stencil."""
        return StencilOperator(plus_laplacian(self.stencil, 2.0 * lam))

    def to_dense(self) -> Array:
        return stencil_to_dense(self.stencil)


@full_precision
def normal_equations(
    problem: Problem, weights: Array | None = None, *, chunk_size: int = DEFAULT_CHUNK
) -> NormalEquations:
    """Assemble ``D^T D`` (stencil) and ``D^T b`` for ``problem`` in one pass over the samples.

    ``weights=None`` is the B-spline (w = 1, eq. 6), assembled from per-cell Bernstein
    moments; otherwise the rational rows of eq. 23 with those fixed ``(N, M)`` weights.
    Masked-out samples (padding) contribute nothing. Differentiable in the points,
    normals, targets and weights.
    """
    if weights is None:
        stencil, rhs = bspline_normal_equations(problem, chunk_size)
    else:
        stencil, rhs = rational_normal_equations(problem, weights, chunk_size)
    b = problem.mask * problem.targets
    return NormalEquations(stencil=stencil, rhs=rhs, target_norm2=jnp.sum(b * b))
