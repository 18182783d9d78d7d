"""The ``Cloud``: a point cloud checked once, with what the host measures on it kept
for every fit that reads it."""

from __future__ import annotations

import functools
import warnings
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import jax
import numpy as np
from jaxtyping import Float

from .._problem.validate import bounding_diagonal, is_concrete, unit_normals, validate_points
from .measure import (
    PROBES,
    check_encloses,
    check_narrow_type,
    check_rounding,
    kd_tree,
    point_spacing,
    principal_widths,
    repeated_points,
    strided_probes,
)
from .orientation import flipped_normal_fraction, orientation_sample, tangential_normal_fraction

if TYPE_CHECKING:
    from scipy.spatial import KDTree as cKDTree


class Cloud:
    """Points, their outward normals and a mask, validated once, with one KD-tree and one
    probe subsample kept for every fit of the cloud.

    ``jurs.fit(points, normals)`` builds one; build it yourself to fit the same cloud
    several times (other grids, solvers, smoothings): ``jurs.fit(cloud, grid=...)`` then
    skips the input checks, the neighbour searches and the orientation check, which it
    has already made.

    Args:
        points: ``(m, 2)`` points of a curve or ``(m, 3)`` of a surface, m >= 3.
        normals: outward normals shaped like ``points`` (scaled to unit length here), or
            None for a cloud whose normals are to be estimated ([`jurs.fit`][] does).
        mask: optional ``(m,)`` booleans, False marking padding points that take no part.

    Exact repeats of a point (a cloud without a mask) are kept once, with the mean of
    their normals, and a warning says how many there were: repeats add no shape, and
    the measurements of spacing and orientation read them as a cloud of zero spacing.
    ``cloud.points`` and every per-point result of a fit (``sol.state``'s weights,
    ``Settings.set_aside``) then index the distinct points, in the order they first
    occur; ``cloud.repeated`` counts the copies dropped.

    Raises:
        ValueError: NaN or Inf, wrong shapes, zero normals, fewer than 3 points (or a
            mask selecting fewer), points that all coincide, points that lie on a line
            or in a plane (they enclose nothing: ``jurs._cloud.measure.check_encloses``),
            or points given in float32 (or float16) whose rounding at their distance
            from the origin exceeds 1e-4 of their extent (``check_narrow_type``) or made
            them repeat each other.
        TypeError: points or normals that are not numbers.
    """

    def __init__(self, points: Any, normals: Any = None, mask: Any = None):
        if not is_concrete(points, normals, mask):
            raise ValueError(
                "a Cloud holds concrete points (it is measured on the host); under jit, "
                "grad or vmap pass the arrays to jurs.fit with every setting given"
            )
        validate_points(points, points if normals is None else normals, mask)
        # JAX arrays as given, for their devices (a sharded cloud is solved where it lies);
        # host arrays as copies, so that a caller's later edit changes no kept measurement.
        self.given_points: Any = _kept(points)
        self.given_normals: Any = None if normals is None else _kept(normals)
        self.given_mask: Any = None if mask is None else _kept(mask)
        self.points: Float[np.ndarray, "m d"] = np.array(points, float)
        self.normals: Float[np.ndarray, "m d"] | None = (
            None if normals is None else unit_normals(np.asarray(normals, float))
        )
        self.mask: np.ndarray | None = None if mask is None else np.asarray(mask).astype(bool)
        #: Problems laid out on this cloud, by their settings, the latest last: ``jurs.fit``
        #: keeps a few there (``KEPT_PROBLEMS``) for fits that repeat their settings.
        self.kept_problems: OrderedDict = OrderedDict()
        #: Exact repeats dropped (see the class docstring).
        self.repeated: int = 0
        check_narrow_type(self.points, _given_dtype(points))
        if mask is None:  # a mask's padding repeats points on purpose
            self._drop_repeats(points)
        self._check_encloses()

    def _drop_repeats(self, given) -> None:
        """Keep each exactly repeated point once (class docstring), or raise where the
        repeats are float32 rounding."""
        found = repeated_points(self.points)
        if found is None:
            return
        first, group = found
        self.repeated = len(self.points) - len(first)
        check_rounding(self.points, _given_dtype(given), self.repeated)
        if len(first) < 3:
            raise ValueError(
                f"points: only {len(first)} distinct points (of {len(self.points)}); "
                "need at least 3"
            )
        self.points = self.points[first]
        self.given_points = self.points
        if self.normals is not None:
            summed = np.zeros_like(self.points)
            np.add.at(summed, group, self.normals)
            length = np.linalg.norm(summed, axis=1, keepdims=True)
            count = np.bincount(group)[:, None]
            # Repeats whose normals cancel (opposed): the first one's normal stands.
            cancel = length < 1e-6 * count
            mean = summed / np.maximum(length, 1e-300)
            self.normals = np.where(cancel, self.normals[first], mean)
            self.given_normals = self.normals
        warnings.warn(
            f"jurs: {self.repeated} of the {len(group)} points repeat others exactly; "
            f"each is kept once ({len(first)} distinct points"
            + (", normals averaged over the repeats)" if self.normals is not None else ")"),
            stacklevel=_caller_level(),
        )

    def _check_encloses(self) -> None:
        """Refuse a cloud on a line or in a plane (``check_encloses``); the spacing,
        which needs the KD-tree, is measured only for a cloud thin for its size."""
        points = self.points[self.kept]
        widths = principal_widths(points, self.probes)
        if widths[0] < 0.25 * widths[-1]:
            check_encloses(points, widths, self.spacing)

    @functools.cached_property
    def spacing(self) -> float:
        """The median distance between nearest points (``point_spacing``) of the points
        that take part, at the probes."""
        return point_spacing(self.points[self.kept], self.tree, self.probes)

    @functools.cached_property
    def extent(self) -> float:
        """The diagonal of the bounding box of the points that take part: the largest
        offset a fit of them may take (``check_offset_scale``)."""
        return bounding_diagonal(self.points, self.mask)

    @property
    def ndim(self) -> int:
        """2 for a curve's points, 3 for a surface's."""
        return self.points.shape[1]

    def __len__(self) -> int:
        return self.points.shape[0]

    def __repr__(self) -> str:
        kept = len(self) if self.mask is None else int(self.mask.sum())
        normals = "with normals" if self.normals is not None else "without normals"
        return f"Cloud({kept} points in {self.ndim}D, {normals})"

    @functools.cached_property
    def kept(self) -> np.ndarray:
        """Indices of the points that take part (all, unless masked)."""
        return np.arange(len(self)) if self.mask is None else np.flatnonzero(self.mask)

    @functools.cached_property
    def tree(self) -> cKDTree:
        """A KD-tree of the points that take part (built on first use)."""
        return kd_tree(self.points[self.kept])

    def tree_without(self, aside: tuple[int, ...] = ()) -> cKDTree:
        """A KD-tree of the points that take part less those at the indices ``aside``
        (into ``points``): [`tree`][jurs.Cloud.tree] where there are none. Built once per
        set and kept (the settings measure the shape on it, the verdicts judge the fit on
        it: a second tree of a large cloud is a noticeable cost; docs/performance.md)."""
        if not aside:
            return self.tree
        kept: dict = self.__dict__.setdefault("_trees_without", {})
        key = tuple(aside)
        if key not in kept:
            keep = np.zeros(len(self), bool)
            keep[self.kept] = True
            keep[list(key)] = False
            kept.clear()  # one set at a time: the latest settings'
            kept[key] = kd_tree(self.points[keep])
        return kept[key]

    @functools.cached_property
    def probes(self) -> np.ndarray | None:
        """Indices (into the points that take part) of at most ``PROBES`` of them,
        evenly strided; None where all are measured."""
        return strided_probes(len(self.kept), PROBES)

    @functools.cached_property
    def orientation(self) -> tuple[float, float]:
        """``(flipped, tangential)``: the fractions of the normals flipped against their
        neighbours (``jurs._cloud.orientation.flipped_normal_fraction``) and lying
        along the curve or surface (``tangential_normal_fraction``), measured once
        per cloud."""
        if self.normals is None:
            raise ValueError("the cloud has no normals to check")
        p, n = self.points[self.kept], self.normals[self.kept]
        sample = orientation_sample(p, n, self.tree if self.probes is None else None)
        return flipped_normal_fraction(p, n, sample), tangential_normal_fraction(p, n, sample)


def _caller_level() -> int:
    """The ``stacklevel`` of a warning raised here that names the first caller outside
    jurs (a warning from ``Cloud`` reached through ``jurs.fit`` or directly)."""
    import os
    import sys

    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


def _given_dtype(given) -> np.dtype:
    """The float type the points were given in (before the float64 copy)."""
    return given.dtype if isinstance(given, jax.Array) else np.asarray(given[:1]).dtype


def _kept(x):
    """A JAX array as it is (immutable, on its devices), anything else as a NumPy copy."""
    return x if isinstance(x, jax.Array) else np.array(x)
