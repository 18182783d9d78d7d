"""Clouds padded to the size ladder (``jurs._problem.sizes``) with masked-out points, so
that clouds of similar size share one compiled fit."""

from __future__ import annotations

import numpy as np

from .problem import build_problem
from .sizes import padded_count
from .validate import is_concrete


def padded_cloud(points, normals):
    """``(points, normals, mask)`` padded to ``jurs._problem.sizes.padded_count`` points with
    masked-out copies of the first point (inside any box the cloud fits in), or None where
    the inputs are traced or malformed (make_problem then reports them as given).

    Why: a compiled fit is specialised to its array shapes; clouds padded to one of a few
    sizes, with a layout sized from that (``make_problem(stable_shapes=True)``), reuse one
    compilation. Masked points take no part in the fit, so the result is the unpadded one
    up to rounding (the per-bucket sums group the samples differently).
    """
    if not is_concrete(points, normals):
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
    points,
    normals,
    mask,
    shape,
    offset,
    eps,
    domain,
    margin,
    bucket_size,
    dtype,
    support=None,
    on_host: bool = False,
):
    """The problem of a checked cloud (``jurs._problem.problem.build_problem``) on the
    normalised grid ``shape``, padded (``padded_cloud``) when it has no mask.

    ``support``: optional ``(m,)`` weights of the caller's points (0 sets a point aside,
    ``jurs._fit.settings.isolated_points``), multiplied into the mask. ``on_host``: laid
    out on the host, one sample a slot (``build_problem``'s)."""
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
    return build_problem(
        points,
        normals,
        shape,
        offset,
        eps,
        domain,
        margin,
        mask,
        bucket_size,
        dtype,
        stable_shapes=padded is not None,
        on_host=on_host,
    )
