"""What a Python user would run instead of jurs, measured on the same samples.

``rbf_fit`` is ``scipy.interpolate.RBFInterpolator`` with the thin-plate-spline kernel on the
same 3m offset samples and targets as jurs (eq. 4-5: ``[P, P + d n, P - d n] -> [0, +eps,
-eps]``): a global dense solve of size 3m (+3 polynomial terms), O(m^3) time and O(m^2)
memory. ``smoothing > 0`` turns interpolation into a smoothing fit (for noisy data).

``rbf_report`` measures the RBF's zero set with the same level-set analysis as jurs fits, on
the same box and grid, so Chamfer distances and supplementary counts compare like for like.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.interpolate import RBFInterpolator

import jurs
import jurs.levelset


def offset_samples(points, normals, offset: float, eps: float):
    """jurs's own samples and targets (eq. 4-5) as NumPy arrays, normals normalised first."""
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    samples, targets = jurs.internal.offset_samples(points, normals, offset, eps)
    return np.asarray(samples, float), np.asarray(targets, float)


def rbf_fit(points, normals, *, offset: float, eps: float, smoothing: float = 0.0):
    """Thin-plate RBF through the offset samples. Returns ``(interpolator, seconds)``; the
    time is the fit (the dense solve), not the evaluation."""
    samples, targets = offset_samples(points, normals, offset, eps)
    t0 = time.perf_counter()
    rbf = RBFInterpolator(samples, targets, kernel="thin_plate_spline", smoothing=smoothing)
    return rbf, time.perf_counter() - t0


def evaluate_rbf(rbf, xy, chunk: int = 4096) -> np.ndarray:
    """``rbf`` at ``xy (n, 2)`` in chunks (the kernel matrix of a chunk is chunk x 3m, so
    memory stays bounded)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) == 0:
        return np.empty(0)
    return np.concatenate([rbf(xy[k : k + chunk]) for k in range(0, len(xy), chunk)])


def evaluate_rbf_grid(rbf, xs, ys, chunk: int = 4096) -> np.ndarray:
    """``values[j, i] = rbf(xs[i], ys[j])`` (:func:`evaluate_rbf` on the grid's nodes)."""
    gx, gy = np.meshgrid(xs, ys)
    return evaluate_rbf(rbf, np.stack([gx.ravel(), gy.ravel()], axis=1), chunk).reshape(gx.shape)


def rbf_report(
    rbf,
    points,
    box,
    *,
    offset: float,
    reference=None,
    resolution: int = jurs.levelset.DEFAULT_RESOLUTION,
):
    """:func:`jurs.levelset.analyze_grid` of the RBF on ``box`` (use the jurs fit's box)."""
    xs, ys, _ = jurs.levelset.sampling_grid(*box, resolution)
    values = evaluate_rbf_grid(rbf, xs, ys)
    return jurs.levelset.analyze_grid(xs, ys, values, points, offset=offset, reference=reference)
