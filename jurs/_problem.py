"""From points and outward normals to the sampled fitting problem (eq. 4-5, 9).

Each data point P_i with unit outward normal n_i gives three samples: P_i (target 0),
P_i + d n_i (target +eps, outside) and P_i - d n_i (target -eps, inside), stacked in that
order as in eq. 9, so the first m samples are the data points. The fitted function is
negative inside and positive outside.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ._spline import LocalBasis, local_basis

#: Default margin added around the samples' bounding box, as a fraction of its longest side.
DEFAULT_MARGIN = 0.05


class Problem(eqx.Module):
    """A fitting problem: samples, targets, the box and the grid, and their local basis.

    Build it with :func:`make_problem`. ``shape`` is static (it fixes array sizes); all
    other fields are arrays, so a Problem can be traced, differentiated and batched.
    """

    points: Array  # (m, 2) data points P
    normals: Array  # (m, 2) unit outward normals
    samples: Array  # (3m, 2): P, P + d n, P - d n  (eq. 4)
    targets: Array  # (3m,): 0, +eps, -eps  (eq. 5, 9)
    lower: Array  # (2,) box corner
    upper: Array  # (2,) box corner
    offset: Array  # d
    eps: Array  # epsilon
    mask: Array  # (3m,) 1.0 for real samples, 0.0 for padding (batched fits)
    local: LocalBasis  # basis of the 3m samples on the grid
    shape: tuple[int, int] = eqx.field(static=True)

    @property
    def num_points(self) -> int:
        """m, the number of data points (padding included, see ``mask``)."""
        return self.points.shape[0]


def offset_samples(points: Array, normals: Array, offset, eps):
    """Samples and targets of eq. 4-5 and 9: ``[P, P + d n, P - d n]`` and ``[0, +eps, -eps]``."""
    m = points.shape[0]
    samples = jnp.concatenate([points, points + offset * normals, points - offset * normals])
    ones = jnp.ones((m,), dtype=points.dtype)
    targets = jnp.concatenate([0.0 * ones, eps * ones, -eps * ones])
    return samples, targets


def auto_domain(samples: Array, margin: float = DEFAULT_MARGIN, mask: Array | None = None):
    """Bounding box of ``samples`` (those with ``mask`` 1, if given) grown on every side by
    ``margin`` x its longest side."""
    if mask is None:
        lo = jnp.min(samples, axis=0)
        hi = jnp.max(samples, axis=0)
    else:
        keep = mask[:, None] > 0
        lo = jnp.min(jnp.where(keep, samples, jnp.inf), axis=0)
        hi = jnp.max(jnp.where(keep, samples, -jnp.inf), axis=0)
    pad = margin * jnp.max(hi - lo)
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
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            raise ValueError(f"{name} contain NaN or Inf (first at row {int(np.argmax(bad))})")
    short = np.linalg.norm(n, axis=1) < 1e-12
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
        dtype: floating dtype; default float64 when ``jax_enable_x64`` is on, else float32.

    Raises:
        ValueError: for NaN/Inf, wrong shapes, zero normals, fewer than 3 points, a grid
            below 4 x 4, non-positive offset/eps, or samples outside a given domain. Values
            that are traced (inside jit/grad/vmap) cannot be inspected and are not checked.
    """
    shape = normalise_grid(grid)
    validate_inputs(points, normals, offset=offset, eps=eps, domain=domain)
    dtype = dtype or jnp.result_type(float)
    points = jnp.asarray(points, dtype=dtype)
    normals = jnp.asarray(normals, dtype=dtype)
    normals = normals / jnp.linalg.norm(normals, axis=1, keepdims=True)
    samples, targets = offset_samples(points, normals, offset, eps)
    if mask is None:
        sample_mask = jnp.ones(samples.shape[0], dtype=dtype)
    else:
        sample_mask = jnp.tile(jnp.asarray(mask).astype(dtype), 3)
    if domain is None:
        lower, upper = auto_domain(samples, margin, None if mask is None else sample_mask)
    else:
        lower = jnp.asarray(domain[0], dtype=dtype)
        upper = jnp.asarray(domain[1], dtype=dtype)
    return Problem(
        points=points,
        normals=normals,
        samples=samples,
        targets=targets,
        lower=lower,
        upper=upper,
        offset=jnp.asarray(offset, dtype=dtype),
        eps=jnp.asarray(eps, dtype=dtype),
        mask=sample_mask,
        local=local_basis(samples, lower, upper, shape),
        shape=shape,
    )
