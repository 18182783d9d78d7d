"""Host-side evaluation of g on tensor lattices and at scattered points, for any dimension.

g is a tensor-product rational spline, ``g = F(w C) / F(w)`` with ``F`` a plain B-spline
evaluation (see ``jurs._model.spline``). On a lattice ``xs x ys (x zs)`` every axis sees its
own ``(len(xs), N)`` matrix of basis values (four non-zero entries a row), so ``F`` is one
contraction per axis: ``(N, M, K) -> (M, K, X) -> (K, X, Y) -> (X, Y, Z)``. That costs
``N M K X + M K X Y + K X Y Z`` multiply-adds instead of ``64 X Y Z`` for per-point
evaluation, and needs no array of per-point patches.

Everything here reads only the fields ``control``, ``weights``, ``lower`` and ``upper`` of
the spline it is given (any object with them works) and computes in float64 NumPy, so
meshing and mesh metrics run without compiling anything. An adaptive spline
([`jurs.AdaptiveSpline`][]) has no tensor grid: it is evaluated point by point through its
own jitted evaluation (``adaptive_lattice_values``), in chunks of one size.
"""

from __future__ import annotations

import numpy as np

from .adaptive import AdaptiveSpline
from .basis import CENTRED_POWER, cubic_weights

#: Points per call of an adaptive spline's jitted evaluation (the last chunk padded, so
#: one compiled program serves every lattice).
ADAPTIVE_CHUNK = 1 << 15


def _values(spline: AdaptiveSpline, x):
    return spline(x)


def _values_and_gradients(spline: AdaptiveSpline, x):
    return spline(x), spline.grad(x)


_jitted: dict = {}


def _packed(fn):
    """The packed evaluation doing what ``fn`` does (``_values`` or
    ``_values_and_gradients``)."""
    from .packed import packed_values, packed_values_and_gradients

    return packed_values if fn is _values else packed_values_and_gradients


def _adaptive_evaluate(spline: AdaptiveSpline, points: np.ndarray, fn=_values) -> list:
    """``fn(spline, chunk)`` over ``points`` in chunks of ``ADAPTIVE_CHUNK`` (the last one
    padded); the parts as float64 NumPy arrays cut to ``len(points)``, one list entry per
    output of ``fn``. The spline is packed first (``jurs._model.packed``), so one compiled
    program serves every fit of a size class; a spline too large to pack is evaluated
    through its own methods, compiled per hierarchy."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from .packed import pack

    packed = pack(spline)
    if packed is None:
        jitted, argument = _jitted.setdefault(fn, eqx.filter_jit(fn)), spline
    else:
        jitted, argument = _jitted.setdefault(_packed(fn), eqx.filter_jit(_packed(fn))), packed
    dtype = np.asarray(spline.control).dtype
    n = len(points)
    padded = np.concatenate([points, np.repeat(points[-1:], -n % ADAPTIVE_CHUNK, axis=0)])
    parts = [
        jax.tree.leaves(jitted(argument, jnp.asarray(padded[k : k + ADAPTIVE_CHUNK], dtype)))
        for k in range(0, len(padded), ADAPTIVE_CHUNK)
    ]
    return [
        np.concatenate([np.asarray(p[i], np.float64) for p in parts])[:n]
        for i in range(len(parts[0]))
    ]


def adaptive_values(spline: AdaptiveSpline, points) -> np.ndarray:
    """g of an adaptive spline at ``points (n, d)``, float64 NumPy ``(n,)``."""
    return _adaptive_evaluate(spline, np.asarray(points, np.float64))[0]


def adaptive_lattice_values(spline: AdaptiveSpline, axes) -> np.ndarray:
    """[`lattice_values`][jurs._model.lattice.lattice_values] of an adaptive spline: g at
    every node, ``(len(xs), len(ys)(, len(zs)))``."""
    if len(axes) != spline.ndim:
        raise ValueError(
            f"a {spline.ndim}D spline needs {spline.ndim} lattice axes, got {len(axes)}"
        )
    grids = np.meshgrid(*[np.asarray(a, np.float64) for a in axes], indexing="ij")
    points = np.stack([g.ravel() for g in grids], axis=1)
    return _adaptive_evaluate(spline, points)[0].reshape(grids[0].shape)


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
    # d/ds sum_p a_p s^p = sum_{p >= 1} p a_p s^(p - 1)
    return (powers * s ** (powers - 1)) @ CENTRED_POWER[:, 1:].T


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
    denominator ``F(w)`` are each contracted with one band matrix per axis
    (``axis_basis``), then divided. ``xp=numpy`` (default) computes in float64;
    ``xp=jax.numpy`` runs the same contractions in JAX (float64 when x64 is enabled).
    Memory: the lattice values and the intermediates of the contractions, at most about
    ``16 * max(N M K, M K X, K X Y, X Y Z)`` bytes for an ``(N, M, K)`` grid.
    """
    if isinstance(spline, AdaptiveSpline):
        values = adaptive_lattice_values(spline, axes)
        return values if xp is np else xp.asarray(values)
    control, weights, lower, upper = spline_fields(spline)
    d = control.ndim
    if len(axes) != d:
        raise ValueError(f"a {d}D spline needs {d} lattice axes, got {len(axes)}")
    numerator, denominator = weights * control, weights
    for k, coords in enumerate(axes):
        basis = axis_basis(coords, lower[k], upper[k], control.shape[k])
        # Only the coefficients under the coordinates' cells take part: a thin slab of a
        # large grid reads a few planes of it, not all (docs/performance.md, "Measurements
        # behind the defaults").
        used = np.flatnonzero(basis.any(axis=0))
        window = slice(used[0], used[-1] + 1) if len(used) else slice(0, 0)
        basis = xp.asarray(basis[:, window])
        # Contract the leading (grid) axis; the lattice axis comes out last, so after d
        # steps the axes are in lattice order.
        numerator = xp.tensordot(xp.asarray(numerator[window]), basis, axes=([0], [1]))
        denominator = xp.tensordot(xp.asarray(denominator[window]), basis, axes=([0], [1]))
    return numerator / denominator


def values_and_gradients(spline, points, *, chunk: int = 1 << 14):
    """g and its spatial gradient at scattered ``points (n, d)``; ``((n,), (n, d))``.

    Each point reads the ``4^d`` coefficients of its cell, in chunks of ``chunk`` points
    (peak memory about ``chunk * 4^d * 48`` bytes: 50 MB in 3D at the default). By the
    quotient rule ``grad g = (grad F(w C) - g grad F(w)) / F(w)``.
    """
    if isinstance(spline, AdaptiveSpline):
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != spline.ndim:
            raise ValueError(f"points must have shape (n, {spline.ndim}), got {points.shape}")
        if len(points) == 0:
            return np.empty(0), np.empty((0, spline.ndim))
        value, gradient = _adaptive_evaluate(spline, points, _values_and_gradients)
        return value, gradient
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
    for start in range(0, len(points), int(chunk)):
        p = points[start : start + int(chunk)]
        index, factors, slopes = [], [], []
        for k in range(d):
            cell, t, h = locate_axis(p[:, k], lower[k], upper[k], control.shape[k])
            shape = (len(p),) + (1,) * k + (4,) + (1,) * (d - k - 1)
            index.append((cell[:, None] + np.arange(4)).reshape(shape))
            factors.append(cubic_weights(t, xp=np))
            slopes.append(cubic_slopes(t) / h)
        index = tuple(index)
        num_patch, den_patch = weighted[index], weights[index]
        num = np.einsum(contract, num_patch, *factors, optimize=True)
        den = np.einsum(contract, den_patch, *factors, optimize=True)
        g = num / den
        value[start : start + len(p)] = g
        for k in range(d):
            along = factors[:k] + [slopes[k]] + factors[k + 1 :]
            d_num = np.einsum(contract, num_patch, *along, optimize=True)
            d_den = np.einsum(contract, den_patch, *along, optimize=True)
            gradient[start : start + len(p), k] = (d_num - g * d_den) / den
    return value, gradient
