"""Distances between a zero set and reference curves beyond the sampling floor: a point's
distance to a polyline, Newton projection onto the zero set, and the refined Chamfer and
Hausdorff distances (see the module docstring of ``jurs.levelset``)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from jaxtyping import Bool, Float
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from .._model.adaptive import AdaptiveSpline
from .._model.lattice import values_and_gradients
from .._model.spline import ImplicitSpline
from ._curves import evaluate_spline, spline_gradient


def distance_to_polyline(
    points: Float[npt.ArrayLike, "k 2"],
    polyline: Float[npt.ArrayLike, "l 2"],
    *,
    closed: bool = False,
) -> Float[np.ndarray, " k"]:
    """Distance from each of ``points (k, 2)`` to the polyline ``(l, 2)``: to its segments,
    not only its vertices, so the polyline's spacing sets no floor (only its chords' own
    distance to the curve they sample, ``spacing^2 * curvature / 8``). ``closed`` adds the
    segment from the last vertex back to the first. ``inf`` for an empty polyline."""
    p = np.asarray(points, float).reshape(-1, 2)
    v = np.asarray(polyline, float).reshape(-1, 2)
    if closed and len(v) > 1:
        v = np.concatenate([v, v[:1]])
    if len(v) == 0 or len(p) == 0:
        return np.full(len(p), np.inf)
    if len(v) == 1:
        return np.linalg.norm(p - v[0], axis=1)
    start, end = v[:-1], v[1:]
    longest = float(np.max(np.linalg.norm(end - start, axis=1)))
    tree = cKDTree(v)
    nearest = tree.query(p)[0]
    # The closest point of the polyline lies on a segment with an end within that point's
    # distance plus the segment's length, which is at most the nearest vertex's distance
    # plus the longest segment: only the segments at those vertices are candidates.
    near = tree.query_ball_point(p, nearest + longest * (1 + 1e-9) + 1e-300)
    counts = np.fromiter(map(len, near), int, len(p))
    vertex = np.concatenate([np.asarray(n, int) for n in near])
    owner = np.repeat(np.arange(len(p)), counts)
    segment = np.concatenate([vertex - 1, vertex])  # the segments ending and starting there
    owner = np.concatenate([owner, owner])
    keep = (segment >= 0) & (segment < len(start))
    segment, owner = segment[keep], owner[keep]
    a, ab, q = start[segment], end[segment] - start[segment], p[owner]
    length2 = np.sum(ab * ab, axis=1)
    t = np.clip(np.sum((q - a) * ab, axis=1) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    out = np.full(len(p), np.inf)
    np.minimum.at(out, owner, np.linalg.norm(a + t[:, None] * ab - q, axis=1))
    return out


def _central_gradient(fn, xy: np.ndarray, step: float) -> np.ndarray:
    """Central differences of ``fn`` at ``xy (k, 2)``: four evaluations, error ``O(step^2)``."""
    e = np.array([[step, 0.0], [0.0, step]])
    values = np.asarray(
        fn(np.concatenate([xy + e[0], xy - e[0], xy + e[1], xy - e[1]])), float
    ).reshape(4, -1)
    return np.stack([values[0] - values[1], values[2] - values[3]], axis=1) / (2 * step)


def _both_at_once(spline: AdaptiveSpline):
    """``(value_of, gradient)`` of an adaptive spline that evaluate both in one pass: the
    loop below asks for the value, then the gradient, at the same points."""
    last: dict = {}

    def both(xy):
        xy = np.asarray(xy, float).reshape(-1, 2)
        if "x" not in last or not np.array_equal(last["x"], xy):
            last["x"], last["out"] = xy.copy(), values_and_gradients(spline, xy)
        return last["out"]

    return (lambda xy: both(xy)[0]), (lambda xy: both(xy)[1])


def project_to_zero_set(
    fn,
    points: Float[npt.ArrayLike, "k 2"],
    *,
    grad=None,
    steps: int = 3,
    tol: float | None = None,
    step: float | None = None,
) -> tuple[Float[np.ndarray, "k 2"], Bool[np.ndarray, " k"]]:
    """Move each of ``points (k, 2)`` onto ``{fn = 0}`` by Newton steps along the gradient,
    ``x <- x - f(x) grad f(x) / |grad f(x)|^2``; from a point near the zero set this lands
    on it near the point's foot, with the error squared every step.

    ``fn`` maps ``(n, 2)`` points to ``(n,)`` values (an
    [`ImplicitSpline`][jurs.ImplicitSpline], an RBF interpolator, ...). ``grad`` maps them
    to ``(n, 2)`` gradients; by default a spline's own (``ImplicitSpline.grad``; a spline
    and its gradient run jitted), for other functions central differences with ``step``
    (default 1e-7 of the points' extent), four more evaluations each. A point has converged
    when its first-order distance ``|f| / |grad f|`` is at most ``tol`` (default 1e-11 of
    the extent) after the steps; points with a zero or non-finite gradient stay put.

    Returns ``(projected (k, 2), converged (k,) bool)``.
    """
    x = np.array(points, float).reshape(-1, 2)
    if int(steps) < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    extent = float(np.max(np.ptp(x, axis=0))) if len(x) > 1 else 1.0
    extent = extent if extent > 0 else 1.0
    tol = 1e-11 * extent if tol is None else float(tol)
    step = 1e-7 * extent if step is None else float(step)
    spline = isinstance(fn, ImplicitSpline)
    value_of = (lambda xy: evaluate_spline(fn, xy)) if spline else fn
    if grad is not None:
        gradient = grad
    elif spline:
        gradient = lambda xy: spline_gradient(fn, xy)  # noqa: E731
    elif isinstance(fn, AdaptiveSpline):  # on the host (FinestSpline): nothing compiled
        value_of, gradient = _both_at_once(fn)
    else:
        gradient = lambda xy: _central_gradient(value_of, xy, step)  # noqa: E731
    for k in range(int(steps) + 1):  # the last round only checks
        value = np.asarray(value_of(x), float).reshape(-1)
        g = np.asarray(gradient(x), float).reshape(-1, 2)
        norm2 = np.sum(g * g, axis=1)
        usable = np.isfinite(value) & np.isfinite(norm2) & (norm2 > 0)
        converged = usable & (np.abs(value) <= tol * np.sqrt(np.where(usable, norm2, 1.0)))
        if k == int(steps):
            break
        move = usable & ~converged
        x[move] -= (value[move] / norm2[move])[:, None] * g[move]
    return x, converged


def refined_chamfer_hausdorff(
    fn,
    zero_points: Float[npt.ArrayLike, "k 2"],
    reference: Float[npt.ArrayLike, "l 2"],
    *,
    grad=None,
    closed: bool = True,
    reference_samples: int | None = None,
    steps: int = 3,
) -> dict:
    """Chamfer and Hausdorff distances (as in
    [`chamfer_hausdorff`][jurs.levelset.chamfer_hausdorff]) between the zero set Z of ``fn``
    and a reference curve, without the floor that sampling puts under them.

    * Z -> reference: ``zero_points`` (samples of Z, e.g. resampled contour polylines) are
      moved onto Z by [`project_to_zero_set`][jurs.levelset.project_to_zero_set] (the
      contouring error goes) and measured to the ``reference`` polyline's segments
      ([`distance_to_polyline`][jurs.levelset.distance_to_polyline]; ``closed`` for a closed
      curve given without its first point repeated).
    * reference -> Z: ``reference_samples`` evenly spread vertices of ``reference`` (default
      all) are projected onto Z too; the distance is the smaller of the way to where they
      land and the distance to the nearest projected zero-set sample, both distances to
      points of Z, so never below the true one.

    Returns ``{"chamfer", "hausdorff", "unconverged_zero", "unconverged_reference"}``; the
    counts are points whose projection did not converge (a zero-set sample that did not is
    measured where it ended). ``inf`` distances if Z is empty.
    """
    reference = np.asarray(reference, float).reshape(-1, 2)
    zero_points = np.asarray(zero_points, float).reshape(-1, 2)
    if reference_samples is not None and int(reference_samples) < 1:
        raise ValueError(f"reference_samples must be >= 1, got {reference_samples}")
    count = len(reference) if reference_samples is None else int(reference_samples)
    if len(zero_points) == 0 or len(reference) == 0:
        return {
            "chamfer": float("inf"),
            "hausdorff": float("inf"),
            "unconverged_zero": 0,
            "unconverged_reference": 0,
        }
    zero, zero_ok = project_to_zero_set(fn, zero_points, grad=grad, steps=steps)
    z_to_ref = distance_to_polyline(zero, reference, closed=closed)
    ref = reference[np.unique(np.linspace(0, len(reference) - 1, count).astype(int))]
    landed, ref_ok = project_to_zero_set(fn, ref, grad=grad, steps=steps)
    on_zero = zero[zero_ok] if zero_ok.any() else zero
    ref_to_z = np.minimum(
        cKDTree(on_zero).query(ref)[0],
        np.where(ref_ok, np.linalg.norm(landed - ref, axis=1), np.inf),
    )
    return {
        "chamfer": float(0.5 * (z_to_ref.mean() + ref_to_z.mean())),
        "hausdorff": float(max(z_to_ref.max(), ref_to_z.max())),
        "unconverged_zero": int(np.sum(~zero_ok)),
        "unconverged_reference": int(np.sum(~ref_ok)),
    }
