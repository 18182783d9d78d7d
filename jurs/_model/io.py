"""Saving and loading fitted splines, curves' (2D grids) and surfaces' (3D grids), as
``.npz`` files.

A file holds the arrays ``SPLINE_KEYS`` and ``format_version`` (``FORMAT_VERSION``, a
0-d integer). Files written before the format had a version hold the same four arrays
without it and read as version 0; their layout is the same.
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np
from jaxtyping import DTypeLike

from .spline import ImplicitSpline

SPLINE_KEYS = ("control", "weights", "lower", "upper")
#: The key of the format version in a spline file, and the version
#: [`save_spline`][jurs.save_spline] writes. Version 0 (no key: files written before the
#: format had a version) and version 1 hold the same arrays, ``SPLINE_KEYS``.
VERSION_KEY, FORMAT_VERSION = "format_version", 1
#: The versions [`load_spline`][jurs.load_spline] reads.
KNOWN_VERSIONS = (0, 1)


def check_spline_arrays(arrays: dict[str, np.ndarray], where: str) -> None:
    """ValueError (prefixed by ``where``) unless the arrays make a spline that can be
    evaluated: matching 2D grids of at least 4 x 4 with a box ``lower``, ``upper`` of shape
    (2,), or matching 3D grids of at least 4 x 4 x 4 with a box of shape (3,); finite
    numbers, positive weights (a zero or negative weight puts a pole, W = 0, where g is NaN:
    the fits keep every weight at or above ``min_weight > 0``) and lower < upper on every
    axis."""
    for k in SPLINE_KEYS:
        if arrays[k].dtype.kind not in "iuf":
            raise ValueError(f"{where}{k} must hold numbers, got dtype {arrays[k].dtype}")
    control, weights = arrays["control"], arrays["weights"]
    if control.ndim not in (2, 3) or control.shape != weights.shape:
        raise ValueError(
            f"{where}control and weights must be matching 2D or 3D grids, got "
            f"shapes {control.shape} and {weights.shape}"
        )
    d = control.ndim
    if arrays["lower"].shape != (d,) or arrays["upper"].shape != (d,):
        raise ValueError(
            f"{where}lower and upper must have shape ({d},) for a {d}D grid, got "
            f"{arrays['lower'].shape} and {arrays['upper'].shape}"
        )
    if min(control.shape) < 4:
        raise ValueError(
            f"{where}the grid must be at least {' x '.join('4' * d)}, got {control.shape}"
        )
    for k in SPLINE_KEYS:
        if not np.isfinite(arrays[k]).all():
            raise ValueError(f"{where}{k} contain NaN or Inf")
    if not (weights > 0).all():
        raise ValueError(
            f"{where}weights must all be positive (a zero weight makes g "
            f"undefined), got min {float(weights.min()):.3g}"
        )
    if not (arrays["lower"] < arrays["upper"]).all():
        axes = "both axes" if d == 2 else "every axis"
        raise ValueError(
            f"{where}lower must be below upper on {axes}, got "
            f"{arrays['lower'].tolist()} and {arrays['upper'].tolist()}"
        )


def save_spline(path: str | os.PathLike[str], spline: ImplicitSpline) -> None:
    """Write ``spline`` to exactly ``path`` (``.npz`` format, whatever the name: NumPy's
    ``savez`` would append ``.npz`` to a name without it, and
    [`load_spline`][jurs.load_spline] of the same name would then not find it): arrays
    ``control``, ``weights``, ``lower``, ``upper``, and ``format_version`` (``FORMAT_VERSION``,
    which [`load_spline`][jurs.load_spline] checks). Raises ValueError for a spline that
    cannot be evaluated (see [`load_spline`][jurs.load_spline]), before anything is
    written."""
    if not isinstance(spline, ImplicitSpline):
        raise TypeError(f"spline must be a jurs.ImplicitSpline, got {type(spline).__name__}")
    arrays = {k: np.asarray(getattr(spline, k)) for k in SPLINE_KEYS}
    check_spline_arrays(arrays, "spline: ")
    with open(os.fspath(path), "wb") as fh:
        np.savez(fh, **arrays, **{VERSION_KEY: np.int64(FORMAT_VERSION)})  # pyright: ignore[reportArgumentType]


def load_spline(path: str | os.PathLike[str], dtype: DTypeLike | None = None) -> ImplicitSpline:
    """Read an [`ImplicitSpline`][jurs.ImplicitSpline] written by
    [`save_spline`][jurs.save_spline]: a curve's (2D grids, box of shape (2,)) or a
    surface's (3D grids, box of shape (3,)).

    ``dtype`` defaults to JAX's default float (float64 with ``jax_enable_x64``). Files
    written before the format had a version (no ``format_version``) read as version 0.
    Raises FileNotFoundError, or ValueError naming the file for a format version this
    jurs does not know (a file from a newer jurs), arrays other than the format's,
    missing, ill-shaped or non-finite arrays, weights that are not all positive, or
    lower >= upper.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            names = list(data.files)
            arrays = {k: np.asarray(data[k]) for k in SPLINE_KEYS if k in names}
            version = np.asarray(data[VERSION_KEY]) if VERSION_KEY in names else np.int64(0)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if version.shape != () or version.dtype.kind not in "iu":
        raise ValueError(
            f"{path}: {VERSION_KEY} must be one integer, got dtype {version.dtype} and "
            f"shape {version.shape}"
        )
    if int(version) not in KNOWN_VERSIONS:
        raise ValueError(
            f"{path}: spline file format version {int(version)}; this jurs reads versions "
            f"{', '.join(map(str, KNOWN_VERSIONS))} (a newer jurs wrote it? upgrade jurs)"
        )
    extra = sorted(set(names) - set(SPLINE_KEYS) - {VERSION_KEY})
    if extra:
        raise ValueError(
            f"{path}: not a jurs spline file: unexpected arrays {extra} (expected "
            f"{list(SPLINE_KEYS)} and {VERSION_KEY})"
        )
    missing = [k for k in SPLINE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing} (expected {list(SPLINE_KEYS)})")
    check_spline_arrays(arrays, f"{path}: ")
    dtype = dtype or jnp.result_type(float)
    return ImplicitSpline(*(jnp.asarray(arrays[k], dtype) for k in SPLINE_KEYS))
