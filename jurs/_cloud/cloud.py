"""The ``Cloud``: a point cloud checked once, with what the host measures on it kept
for every fit that reads it."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

import jax
import numpy as np
from jaxtyping import Float

from .._problem.validate import _is_concrete, unit_normals, validate_points
from .measure import PROBES, kd_tree, strided_probes
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

    Raises:
        ValueError: NaN or Inf, wrong shapes, zero normals, fewer than 3 points (or a
            mask selecting fewer), or points that all coincide.
        TypeError: points or normals that are not numbers.
    """

    def __init__(self, points: Any, normals: Any = None, mask: Any = None):
        if not _is_concrete(points, normals, mask):
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
        self._problems: dict = {}

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


def _kept(x):
    """A JAX array as it is (immutable, on its devices), anything else as a NumPy copy."""
    return x if isinstance(x, jax.Array) else np.array(x)
