"""Checks of what a user passes in: numbers, shapes, grids, boxes, and whether the chosen
float type can resolve the cloud. Each raises a ValueError (TypeError for what is not a
number) that names the argument, before anything is computed from it. Traced values
(inside jit, grad or vmap) cannot be inspected and pass unchecked."""

from __future__ import annotations

import math

import jax
import numpy as np
from jax.core import Tracer

from .sizes import DEFAULT_MARGIN


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


def is_concrete(*xs) -> bool:
    """Whether no leaf of ``xs`` is traced."""
    if all(type(x) in _PLAIN for x in xs):  # the common case, without a flatten
        return True
    return not any(isinstance(x, Tracer) for x in jax.tree_util.tree_leaves(xs))


#: Types that are never traced and hold nothing that is.
_PLAIN = frozenset({np.ndarray, float, int, bool, type(None), str})


def check_nonnegative(name: str, value, *, strict: bool = False) -> None:
    """Raise ValueError unless ``value`` is a finite number >= 0 (> 0 when ``strict``);
    TypeError for something that is not a number (a string, None, ...).

    Traced values are not checked (their value is unknown at trace time).
    """
    if type(value) is float and math.isfinite(value) and (value > 0 or not strict and value == 0):
        return  # the common case, without NumPy
    if not is_concrete(value):
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


def shape_of(x) -> tuple:
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


def validate_points(points, normals, mask=None) -> None:
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


def check_offset_scale(points, offset, mask=None, extent: float | None = None) -> None:
    """ValueError when the offset d exceeds the cloud's extent (its bounding-box diagonal):
    the offset samples P +/- d n then lie beyond the whole shape, on every side of every
    other point, and no fit can read inside from outside (offset=1e6 on a unit cloud ran
    for a minute into 203 loops). Concrete values only. ``extent``: that diagonal, where
    the caller knows it (``jurs.Cloud.extent``)."""
    if not is_concrete(points, offset, mask):
        return
    if extent is None:
        extent = bounding_diagonal(points, mask)
    if float(offset) > extent:
        raise ValueError(
            f"offset d = {float(offset):.4g} exceeds the cloud's extent (its "
            f"bounding-box diagonal, {extent:.4g}): the offset samples would lie "
            "beyond the whole shape; choose d below the point spacing or leave "
            "it to the automatic choice"
        )


def bounding_diagonal(points, mask=None) -> float:
    """The diagonal of the bounding box of ``points`` (those of ``mask``, where given)."""
    p = np.asarray(points, float)
    if mask is not None:
        p = p[np.asarray(mask).astype(bool)]
    return float(np.linalg.norm(np.ptp(p, axis=0)))


#: Largest ratio of the floating-point resolution at the cloud's coordinates to the offset
#: d (a step of d / 8): beyond it a translated float32 fit first loses accuracy, then grows
#: loops, then loses its zero set (docs/robustness.md, "Precision threshold").
MAX_RESOLUTION_TO_OFFSET = 0.125


def check_precision(points, offset, dtype, domain=None, eps=None) -> None:
    """ValueError when ``dtype`` cannot resolve the offset d at the cloud's coordinates:
    float32 at |x| = 1e7 steps by 1, so offsets of 0.01 collapse onto the points and the
    fit silently loses its zero set; or when the energy, a sum of 3m squares of about
    ``eps``, would overflow it (eps = 1e153 in float64). Concrete values only."""
    if not is_concrete(points, offset, domain, eps):
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
    """All input checks of [`jurs.make_problem`][], on concrete values (traced ones are
    skipped): ``validate_points``, then ``validate_settings``.

    Raises ValueError (TypeError for non-numbers) naming the problem; see
    [`jurs.make_problem`][]. ``offset`` or ``eps`` None (to be chosen from the data)
    skips their checks.
    """
    check_values(offset=offset, eps=eps, margin=margin, domain=domain)
    if not is_concrete(points, normals, mask):
        return
    validate_points(points, normals, mask)
    validate_settings(points, normals, mask, offset=offset, domain=domain)


def check_values(*, offset, eps, margin, domain) -> None:
    """The checks of the settings alone: offset and eps positive (None: to be chosen),
    margin non-negative, the domain a finite box."""
    for name, value in (("offset", offset), ("eps", eps)):
        if value is not None:
            check_nonnegative(name, value, strict=True)
    # A negative margin shrinks the box until it leaves out the data (below -1/2 the box
    # turns inside out); the fit then "succeeded" on samples the basis does not cover.
    check_nonnegative("margin", margin)
    if domain is not None and is_concrete(domain):
        check_domain(domain)


def validate_settings(points, normals, mask, *, offset, domain, extent=None) -> None:
    """The checks of the settings against points already validated
    (``validate_points``): the offset within the cloud's extent (``extent``, where the
    caller knows it), the samples inside a given domain. ``offset`` None (to be chosen)
    skips them."""
    if offset is None:
        return
    check_offset_scale(points, offset, mask, extent)
    if domain is not None and is_concrete(domain, offset):
        p = np.asarray(points, dtype=float)
        n = unit_normals(np.asarray(normals, dtype=float))
        d = float(offset)
        _validate_domain(domain, np.concatenate([p, p + d * n, p - d * n]), p.shape[0])
