"""Host-side evaluation of g on tensor lattices and at scattered points, for any dimension.

g is a tensor-product rational spline, ``g = F(w C) / F(w)`` with ``F`` a plain B-spline
evaluation (see ``jurs._model.spline``). On a lattice ``xs x ys (x zs)`` a node sees four
basis functions along each axis, so ``F`` is one contraction per axis, four terms a node:
``(N, M, K) -> (X, M, K) -> (X, M, Z) -> (X, Y, Z)``. That costs ``4 (X M K + X M Z +
X Y Z)`` multiply-adds instead of ``64 X Y Z`` for per-point evaluation, and needs no array
of per-point patches.

Everything here reads only the fields ``control``, ``weights``, ``lower`` and ``upper`` of
the spline it is given (any object with them works) and computes in float64 NumPy, so
meshing and mesh metrics run without compiling anything. An adaptive spline
([`jurs.AdaptiveSpline`][]) is read as the uniform spline of its finest level, with
coefficients computed only where a lattice or a point needs them (``FinestSpline``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._threads import in_threads
from .basis import CENTRED_POWER, cubic_weights
from .function import AbstractSpline
from .hierarchy import cascade


def adaptive_lattice_values(spline, axes) -> np.ndarray:
    """[`lattice_values`][jurs._model.lattice.lattice_values] of an adaptive spline: g at
    every node, ``(len(xs), len(ys)(, len(zs)))``, through
    ``FinestSpline.lattice``."""
    if len(axes) != spline.ndim:
        raise ValueError(
            f"a {spline.ndim}D spline needs {spline.ndim} lattice axes, got {len(axes)}"
        )
    return spline.on_host().lattice(axes)


#: Finest-level coefficients a window of ``FinestSpline.lattice`` holds at most: about
#: 32 MiB of float64 numerator and denominator.
WINDOW_FUNCTIONS = 1 << 21


class FinestSpline:
    """An adaptive spline read as the rational spline of its finest level's uniform grid,
    evaluated on the host in float64 NumPy.

    The levels' spaces nest, so numerator and denominator of eq. 14 are splines of the
    finest level over the whole box; their coefficients on any set of finest functions
    come from ``jurs._model.finest.finest_coefficients``, computed only
    where asked. A lattice is then contracted axis by axis as a uniform spline's
    (``lattice_values``), at ``4 (W^d n + ...)`` operations for ``W`` functions and ``n``
    nodes a side instead of one leaf search and ``4^d`` key searches per node.

    **Bitwise agreement.** A node's value depends only on its coordinates and on the
    coefficients of the ``4^d`` functions over its finest cell, each computed by the same
    element-wise operations whatever window it is asked in; the per-axis contractions are
    element-wise too (four products added in a fixed order, no BLAS). So two windows that
    share a node give it bitwise the same value: blocks of a lattice meshed apart stitch
    exactly (``jurs._model.band``).
    """

    def __init__(self, spline):
        """``spline``: a [`jurs.AdaptiveSpline`][] (its ``hierarchy``, ``control`` and
        ``weights`` are read)."""
        hierarchy = spline.hierarchy
        self.hierarchy = hierarchy
        self.ndim = hierarchy.ndim
        finest = hierarchy.num_levels - 1
        self.cells = np.asarray(hierarchy.cells(finest), np.int64)
        self.lower = np.asarray(hierarchy.lower, np.float64)
        self.upper = np.asarray(hierarchy.upper, np.float64)
        self.width = (self.upper - self.lower) / self.cells
        weights = np.asarray(spline.weights, np.float64)
        stacked = np.stack([weights * np.asarray(spline.control, np.float64), weights])
        # The cascade on the host: no program to compile for a new hierarchy.
        self.cascaded = np.asarray(cascade(hierarchy, stacked, np))

    def axis(self, coords, axis: int):
        """``(cell, weights (n, 4), slopes (n, 4))`` of 1D ``coords`` along ``axis`` at
        the finest level: the arithmetic of ``locate_leaves`` (clamped cells; outside the
        box the border pieces extrapolate). ``slopes`` are d/dx."""
        unit = (np.asarray(coords, np.float64) - self.lower[axis]) / (
            self.upper[axis] - self.lower[axis]
        )
        u = unit * float(self.cells[axis])
        cell = np.clip(np.floor(u), 0, self.cells[axis] - 1).astype(np.int64)
        t = u - cell
        return cell, cubic_weights(t, xp=np), cubic_slopes(t) / self.width[axis]

    def coefficients(self, functions) -> np.ndarray:
        """Numerator and denominator coefficients of finest functions ``(n, d)``; ``(2,
        n)``. Each distinct function is computed once."""
        from .finest import finest_coefficients

        functions = np.asarray(functions, np.int64).reshape(-1, self.ndim)
        functions = np.clip(functions, 0, self.cells + 2)
        key = functions[:, 0]
        for a in range(1, self.ndim):
            key = key * (self.cells[a] + 3) + functions[:, a]
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        unique = functions[first]
        return finest_coefficients(self.hierarchy, self.cascaded, unique)[:, inverse.reshape(-1)]

    def windows(self, starts, sizes) -> np.ndarray:
        """Coefficients of the windows of finest functions ``starts[b] + [0, sizes)`` per
        axis (``starts (b, d)``); ``(2, b, *sizes)``. Functions past the grid's end are
        clamped onto it (a window padded to a common size; the padding is never read by
        nodes inside it)."""
        starts = np.asarray(starts, np.int64).reshape(-1, self.ndim)
        offsets = np.stack(np.meshgrid(*[np.arange(n) for n in sizes], indexing="ij"), -1)
        functions = starts[:, None, :] + offsets.reshape(1, -1, self.ndim)
        functions = np.minimum(functions, self.cells + 2)
        return self.coefficients(functions).reshape((2, len(starts)) + tuple(sizes))

    @staticmethod
    def contract(windows, relative, factors) -> np.ndarray:
        """Splines on lattices from their windows of coefficients: ``windows (k, b, W_1..W_d)``,
        per axis ``relative[a] (b, n_a)`` (each node's cell, relative to its window's
        start) and ``factors[a] (b, n_a, 4)`` (basis values or slopes); ``(k, b, n_1 ..
        n_d)``. Element-wise, four terms added in order (see the class docstring)."""
        out = windows
        blocks = np.arange(windows.shape[1])[:, None]
        for a in range(len(relative)):
            # Axis a moved next to the blocks' axis: a block's nodes then gather their
            # window's rows by one advanced index of two adjacent axes (take_along_axis
            # would broadcast an index over every axis).
            moved = np.moveaxis(out, 2 + a, 2)
            shape = [1] * out.ndim
            shape[1], shape[2] = relative[a].shape
            total = moved[:, blocks, relative[a]] * factors[a][:, :, 0].reshape(shape)
            for m in range(1, 4):
                term = moved[:, blocks, relative[a] + m] * factors[a][:, :, m].reshape(shape)
                total = total + term
            out = np.moveaxis(total, 2, 2 + a)
        return out

    def lattice(self, axes) -> np.ndarray:
        """g on the lattice ``axes`` (``len(axes) == d``); ``(len(axes[0]), ...)``, in
        windows of at most about ``WINDOW_FUNCTIONS`` coefficients along the first axis."""
        located = [self.axis(a, k) for k, a in enumerate(axes)]
        cells = [c for c, _, _ in located]
        across = int(np.prod([c[-1] - c[0] + 4 for c in cells[1:]])) if self.ndim > 1 else 1
        rows = max(1, WINDOW_FUNCTIONS // max(across, 1) - 3)
        first = cells[0]
        parts = []
        start = 0
        while start < len(first):
            # nodes start .. stop - 1: their cells span at most `rows` cells
            stop = int(np.searchsorted(first, first[start] + rows, side="left"))
            stop = max(stop, start + 1)
            chosen = [slice(start, stop)] + [slice(None)] * (self.ndim - 1)
            chunk_cells = [c[s] for c, s in zip(cells, chosen)]
            starts = np.array([[c[0] for c in chunk_cells]])
            sizes = tuple(int(c[-1] - c[0] + 4) for c in chunk_cells)
            window = self.windows(starts, sizes)
            relative = [(c - c[0])[None] for c in chunk_cells]
            factors = [w[s][None] for (_, w, _), s in zip(located, chosen)]
            both = self.contract(window, relative, factors)[:, 0]
            parts.append(both[0] / both[1])
            start = stop
        return np.concatenate(parts, axis=0)

    def values(self, points) -> np.ndarray:
        """g at scattered ``points (n, d)``, each from its leaf (``values_and_gradients``)."""
        return finest_values_and_gradients(self, points, gradients=False)[0]

    def values_and_gradients(
        self, points, gradients: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """g and its gradient (None unless ``gradients``) at scattered ``points (n, d)``:
        each point's leaf is found (``locate_leaves`` in NumPy, the traced evaluation's
        own search), its ``4^d`` cascaded coefficients read, and contracted axis by axis,
        last axis first: the leaf's own piece, with no subdivision to the finest level."""
        from .leaves import leaf_terms, locate_leaves

        points = np.asarray(points, np.float64)
        n, d = points.shape
        hierarchy = self.hierarchy
        level, cell = locate_leaves(hierarchy, points, xp=np)
        positions, t = leaf_terms(hierarchy, points, level, cell, xp=np)
        # Points on the last axis: each of the contractions below then multiplies and
        # adds whole rows of points (a point's own four terms along an axis stand a row
        # apart), not four neighbouring numbers at a time.
        coeffs = self.cascaded[:, positions.T].reshape((2,) + (4,) * d + (n,))
        # Each level's cell on the host (NumPy: a jitted caller's trace reaches no array).
        cells = np.asarray([hierarchy.cells(lev) for lev in range(hierarchy.num_levels)], float)
        widths = ((self.upper - self.lower) / cells)[level]
        located = [
            (
                np.asarray(cubic_weights(t[:, a], xp=np)).T,
                (cubic_slopes(t[:, a]) / widths[:, a, None]).T if gradients else None,
            )
            for a in range(d)
        ]
        # Contract the last axis, then the others; `parts[k]` holds the contraction with
        # the slope along axis k (and values along the rest), `parts[d]` values only.
        parts: list = [None] * d + [coeffs]
        for a in range(d - 1, -1, -1):
            weights, slopes = located[a]
            if slopes is not None:  # gradients asked for
                parts[a] = _four_terms(parts[d], slopes)  # before parts[d] loses axis a
            for k in range(a + 1 if gradients else d, d + 1):
                parts[k] = _four_terms(parts[k], weights)
        numerator, denominator = parts[d]
        g = numerator / denominator
        if not gradients:
            return g, None
        gradient = np.stack([(p[0] - g * p[1]) / denominator for p in parts[:d]], axis=-1)
        return g, gradient


def _four_terms(x: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """``x (..., 4, n)`` contracted with ``factors (4, n)`` over its axis of four: four
    products added in order, row by row of the ``n`` points."""
    total = x[..., 0, :] * factors[0]
    for m in range(1, 4):
        total = total + x[..., m, :] * factors[m]
    return total


def spline_fields(spline, dims=(2, 3)):
    """``(control, weights, lower, upper)`` of ``spline`` as float64 NumPy arrays, checked:
    matching grids of a dimension in ``dims``, at least 4 coefficients along every axis,
    a box with ``lower < upper`` of that dimension. Raises ValueError otherwise."""
    control = np.asarray(spline.control, dtype=np.float64)
    weights = np.asarray(spline.weights, dtype=np.float64)
    lower = np.asarray(spline.lower, dtype=np.float64)
    upper = np.asarray(spline.upper, dtype=np.float64)
    d = control.ndim
    if d not in dims:
        raise ValueError(
            f"expected a spline on a grid of dimension {' or '.join(map(str, dims))}"
            f", got a control grid of shape {control.shape}"
        )
    if weights.shape != control.shape:
        raise ValueError(
            f"control and weights must have the same shape, got {control.shape} and {weights.shape}"
        )
    if min(control.shape) < 4:
        raise ValueError(
            f"a cubic spline needs at least 4 coefficients along every axis, got {control.shape}"
        )
    if lower.shape != (d,) or upper.shape != (d,):
        raise ValueError(
            f"lower and upper must have shape ({d},), got {lower.shape} and {upper.shape}"
        )
    if not (np.isfinite(lower).all() and np.isfinite(upper).all() and (upper > lower).all()):
        raise ValueError(f"box must be finite with lower < upper, got {lower}, {upper}")
    return control, weights, lower, upper


def locate_axis(coords, lower: float, upper: float, n: int):
    """Cell and local coordinate along one axis of ``n`` basis functions on ``[lower, upper]``.

    Returns ``(cell, t, h)``: ``cell`` int64 in ``[0, n - 4]`` (coordinates outside the box
    are clamped to the border cell, so ``t`` leaves ``[0, 1]`` there and the border
    polynomial pieces extend the spline), ``t`` float64, ``h`` the cell width. The same
    arithmetic as ``jurs._model.basis.locate``.
    """
    if n < 4:
        raise ValueError(f"a cubic spline needs at least 4 basis functions, got {n}")
    coords = np.asarray(coords, dtype=np.float64).reshape(-1)
    h = (float(upper) - float(lower)) / (n - 3)
    u = (coords - float(lower)) / h
    cell = np.clip(np.floor(u), 0, n - 4).astype(np.int64)
    return cell, u - cell, h


def cubic_slopes(t) -> np.ndarray:
    """d/dt of the four pieces of [`jurs.internal.cubic_weights`][], in NumPy float64;
    ``(..., 4)``. Differentiates the pieces' centred power form (``CENTRED_POWER``), so it
    follows the basis module's own definition of the pieces."""
    s = np.asarray(t, dtype=np.float64)[..., None] - 0.5
    powers = np.arange(1, 4)
    # d/ds sum_p a_p s^p = sum_{p >= 1} p a_p s^(p - 1). s^2 as s * s: correctly rounded,
    # where NumPy's power is off by an ulp in a few per cent of the squares, and without
    # a call of pow an entry.
    return (powers * np.concatenate([np.ones_like(s), s, s * s], axis=-1)) @ CENTRED_POWER[:, 1:].T


def axis_basis(coords, lower: float, upper: float, n: int, *, derivative: bool = False):
    """All ``n`` cubic B-spline values of one axis at the 1D ``coords``; ``(len(coords), n)``.

    Row ``k`` holds ``cubic_weights(t_k)`` in columns ``cell_k .. cell_k + 3`` and zeros
    elsewhere. Outside the box the border pieces continue as polynomials (as
    ``cubic_weights`` does). ``derivative=True`` gives d/dx instead (slopes over the cell
    width).
    """
    cell, t, h = locate_axis(coords, lower, upper, n)
    values = cubic_slopes(t) / h if derivative else cubic_weights(t, xp=np)
    out = np.zeros((len(cell), n))
    out[np.arange(len(cell))[:, None], cell[:, None] + np.arange(4)] = values
    return out


def lattice_values(spline, axes, *, xp=np):
    """g on the tensor lattice ``axes = (xs, ys[, zs])``: ``out[i, j(, k)] = g(xs[i], ys[j]
    (, zs[k]))``, shape ``(len(xs), len(ys)(, len(zs)))`` ("ij" indexing).

    For a 2D or 3D spline; ``len(axes)`` must match its dimension. Numerator ``F(w C)`` and
    denominator ``F(w)`` are contracted axis by axis, then divided. ``xp=numpy`` (default)
    computes in float64, four products a node and axis added in a fixed order, so a node's
    value is bitwise the same in every lattice that holds it (``grid_lattice_values``);
    ``xp=jax.numpy`` runs band-matrix contractions in JAX (float64 when x64 is enabled; a
    uniform grid's only). A [`jurs.AdaptiveSpline`][] is read through its finest level
    (``AbstractSpline.lattice``). Memory: the lattice values, 8 bytes a node, and
    intermediates of about ``16 M Z`` bytes a node of ``xs`` in 3D (``M``: the
    coefficients along y; ``Z = len(zs)``).
    """
    if xp is np and isinstance(spline, AbstractSpline):
        return spline.lattice(axes)
    return grid_lattice_values(spline, axes, xp=xp)


#: Order of the per-axis contractions of ``grid_lattice_values``. Each but the last reads
#: a small array; the last writes the lattice and gathers whole contiguous rows (never
#: single elements along the last axis). In 3D the first axis goes first, so the
#: intermediates of a thin slab of [`mesh`][jurs.levelset.mesh] stay as thin as it.
CONTRACTION_ORDER = {2: (1, 0), 3: (0, 2, 1)}
#: Lattice nodes whose numerator and denominator the last contraction holds at once.
CONTRACTION_BLOCK = 1 << 15


def grid_lattice_values(spline, axes, *, xp=np):
    """[`lattice_values`][jurs._model.lattice.lattice_values] of a spline on a uniform
    grid: any object with the fields ``control``, ``weights``, ``lower`` and ``upper``.

    In NumPy each axis is contracted element-wise: a node's partial sum is the four
    products of its cell's coefficients with its basis values, added in order
    (``CONTRACTION_ORDER``), the same arithmetic whatever the other nodes of the lattice.
    A node's value is therefore bitwise the same in any lattice that holds it: the slabs
    of [`mesh`][jurs.levelset.mesh] give the values of the whole lattice whatever their
    size, as ``FinestSpline`` does for an adaptive spline's blocks. (A band-matrix product
    by BLAS does not: its summation order changes with the matrix's shape, and a slab of
    one plane is a matrix-vector product.)"""
    control, weights, lower, upper = spline_fields(spline)
    d = control.ndim
    if len(axes) != d:
        raise ValueError(f"a {d}D spline needs {d} lattice axes, got {len(axes)}")
    if xp is not np:
        return _band_matrix_values(control, weights, lower, upper, axes, xp)
    located = [
        locate_axis(coords, lower[k], upper[k], control.shape[k]) for k, coords in enumerate(axes)
    ]
    counts = tuple(len(cell) for cell, _, _ in located)
    if 0 in counts:
        return np.empty(counts)
    # Only the coefficients under the nodes' cells take part: a thin slab of a large grid
    # reads a few planes of it, not all (docs/performance.md, "Measurements behind the
    # defaults").
    first = [int(cell.min()) for cell, _, _ in located]
    window = tuple(slice(f, int(cell.max()) + 4) for f, (cell, _, _) in zip(first, located))
    both = np.stack([(weights * control)[window], weights[window]])
    cells = [cell - f for f, (cell, _, _) in zip(first, located)]
    factors = [cubic_weights(t, xp=np) for _, t, _ in located]
    *early, last = CONTRACTION_ORDER[d]
    for k in early:
        both = _contract_axis(both, k + 1, cells[k], factors[k])
    out = np.empty(counts)
    rows = max(1, CONTRACTION_BLOCK // (int(np.prod(counts)) // counts[last]))
    for start in range(0, counts[last], rows):
        part = _contract_axis(
            both, last + 1, cells[last][start : start + rows], factors[last][start : start + rows]
        )
        where = [slice(None)] * d
        where[last] = slice(start, start + rows)
        np.divide(part[0], part[1], out=out[tuple(where)])
    return out


def _contract_axis(values, axis: int, cell, factors) -> np.ndarray:
    """``sum_m factors[:, m] values[cell + m]`` along ``axis``: ``values`` with that axis
    (coefficients) replaced by the nodes' (``cell (n,)``, ``factors (n, 4)``). Element-wise,
    the four terms added in order."""
    shape = [1] * values.ndim
    shape[axis] = len(cell)
    total = np.take(values, cell, axis=axis)
    total *= factors[:, 0].reshape(shape)
    for m in range(1, 4):
        term = np.take(values, cell + m, axis=axis)
        term *= factors[:, m].reshape(shape)
        total += term
    return total


def _band_matrix_values(control, weights, lower, upper, axes, xp):
    """``grid_lattice_values`` in ``xp`` (JAX): one band matrix of basis values per axis."""
    numerator, denominator = weights * control, weights
    for k, coords in enumerate(axes):
        basis = axis_basis(coords, lower[k], upper[k], control.shape[k])
        used = np.flatnonzero(basis.any(axis=0))
        window = slice(used[0], used[-1] + 1) if len(used) else slice(0, 0)
        basis = xp.asarray(basis[:, window])
        # Contract the leading (grid) axis; the lattice axis comes out last, so after d
        # steps the axes are in lattice order.
        numerator = xp.tensordot(xp.asarray(numerator[window]), basis, axes=([0], [1]))
        denominator = xp.tensordot(xp.asarray(denominator[window]), basis, axes=([0], [1]))
    return numerator / denominator


class HostGrid(NamedTuple):
    """A uniform grid's spline as float64 NumPy fields, read by the host evaluations here
    without a JAX array's conversion or a Module's attribute lookup on every call
    (``ImplicitSpline.on_host``)."""

    control: np.ndarray
    weights: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def lattice(self, axes) -> np.ndarray:
        """``grid_lattice_values`` of these fields."""
        return grid_lattice_values(self, axes)

    def values(self, points) -> np.ndarray:
        """g at scattered ``points (n, d)`` (``grid_values_and_gradients``)."""
        return grid_values_and_gradients(self, points, gradients=False)[0]


def values_and_gradients(spline, points, *, chunk: int = 1 << 14):
    """g and its spatial gradient at scattered ``points (n, d)``; ``((n,), (n, d))``.

    Each point reads the ``4^d`` coefficients of its cell, in chunks of ``chunk`` points
    (peak memory about ``chunk * 4^d * 48`` bytes: 50 MB in 3D at the default). By the
    quotient rule ``grad g = (grad F(w C) - g grad F(w)) / F(w)``.
    """
    if isinstance(spline, AbstractSpline):
        return spline.values_and_gradients(points, chunk=chunk)
    return grid_values_and_gradients(spline, points, chunk=chunk)


def finest_values_and_gradients(
    evaluator: FinestSpline, points, *, chunk: int = 1 << 14, gradients: bool = True
):
    """[`values_and_gradients`][jurs._model.lattice.values_and_gradients] of an adaptive
    spline by its host ``evaluator``: its finest level's coefficients under the points,
    in chunks of ``chunk`` points; the gradients None unless ``gradients``."""
    d = evaluator.ndim
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != d:
        raise ValueError(f"points must have shape (n, {d}), got {points.shape}")
    if len(points) == 0:
        return np.empty(0), (np.empty((0, d)) if gradients else None)
    # The chunks are independent: shared out over the host's threads, the same values.
    starts = range(0, len(points), int(chunk))
    parts = in_threads(
        lambda start: evaluator.values_and_gradients(points[start : start + int(chunk)], gradients),
        starts,
    )
    value = np.concatenate([v for v, _ in parts])
    if not gradients:
        return value, None
    return value, np.concatenate([g for _, g in parts if g is not None])


def grid_values_and_gradients(spline, points, *, chunk: int = 1 << 14, gradients: bool = True):
    """[`values_and_gradients`][jurs._model.lattice.values_and_gradients] of a spline on a
    uniform grid (any object with ``control``, ``weights``, ``lower`` and ``upper``); the
    gradients None unless ``gradients``."""
    control, weights, lower, upper = spline_fields(spline)
    d = control.ndim
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != d:
        raise ValueError(f"points must have shape (n, {d}) for a {d}D spline, got {points.shape}")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    weighted = weights * control
    value = np.empty(len(points))
    gradient = np.empty((len(points), d))
    letters = "abc"[:d]
    # "nabc,na,nb,nc->n": a cell's coefficient patch against the per-axis factors.
    contract = f"n{letters}," + ",".join(f"n{c}" for c in letters) + "->n"
    # The patch against one axis's factors at a time, the running result kept last: the
    # order NumPy's greedy search picks for every chunk size, given instead of searched
    # for on every call (the search took longer than the contraction of a small chunk).
    path = ["einsum_path", (0, 1)] + [(0, d - 1 - j) for j in range(d - 1)]
    for start in range(0, len(points), int(chunk)):
        p = points[start : start + int(chunk)]
        index, factors, slopes = [], [], []
        for k in range(d):
            cell, t, h = locate_axis(p[:, k], lower[k], upper[k], control.shape[k])
            shape = (len(p),) + (1,) * k + (4,) + (1,) * (d - k - 1)
            index.append((cell[:, None] + np.arange(4)).reshape(shape))
            factors.append(cubic_weights(t, xp=np))
            if gradients:
                slopes.append(cubic_slopes(t) / h)
        index = tuple(index)
        num_patch, den_patch = weighted[index], weights[index]
        num = np.einsum(contract, num_patch, *factors, optimize=path)
        den = np.einsum(contract, den_patch, *factors, optimize=path)
        g = num / den
        value[start : start + len(p)] = g
        for k in range(d if gradients else 0):
            along = factors[:k] + [slopes[k]] + factors[k + 1 :]
            d_num = np.einsum(contract, num_patch, *along, optimize=path)
            d_den = np.einsum(contract, den_patch, *along, optimize=path)
            gradient[start : start + len(p), k] = (d_num - g * d_den) / den
    return value, (gradient if gradients else None)
