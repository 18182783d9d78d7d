"""Saving and loading fitted splines, curves' (2D grids) and surfaces' (3D grids), as
``.npz`` files.

A file holds the arrays ``SPLINE_KEYS`` and ``format_version`` (``FORMAT_VERSION``, a
0-d integer). Files written before the format had a version hold the same four arrays
without it and read as version 0; their layout is the same. An adaptive spline
([`jurs.AdaptiveSpline`][]) is format version 2 (``ADAPTIVE_VERSION``): ``control`` and
``weights`` are the active functions' vectors, and ``base`` with ``refined_0``,
``refined_1``, ... (the cells split at each level) rebuild its hierarchy.
"""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np
from jaxtyping import DTypeLike

from .adaptive import AdaptiveSpline
from .hierarchy import build_hierarchy, refined_cells
from .spline import ImplicitSpline

SPLINE_KEYS = ("control", "weights", "lower", "upper")
#: The key of the format version in a spline file, and the version
#: [`save_spline`][jurs.save_spline] writes. Version 0 (no key: files written before the
#: format had a version) and version 1 hold the same arrays, ``SPLINE_KEYS``.
VERSION_KEY, FORMAT_VERSION = "format_version", 1
#: The format version of an adaptive spline's file.
ADAPTIVE_VERSION = 2
#: The versions [`load_spline`][jurs.load_spline] reads.
KNOWN_VERSIONS = (0, 1, ADAPTIVE_VERSION)


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


def save_spline(path: str | os.PathLike[str], spline: ImplicitSpline | AdaptiveSpline) -> None:
    """Write ``spline`` (an [`ImplicitSpline`][jurs.ImplicitSpline], or an
    [`AdaptiveSpline`][jurs.AdaptiveSpline] as format version 2) to exactly ``path``
    (``.npz`` format, whatever the name: NumPy's ``savez`` would append ``.npz`` to a name
    without it, and
    [`load_spline`][jurs.load_spline] of the same name would then not find it): arrays
    ``control``, ``weights``, ``lower``, ``upper``, and ``format_version`` (``FORMAT_VERSION``,
    which [`load_spline`][jurs.load_spline] checks). Raises ValueError for a spline that
    cannot be evaluated (see [`load_spline`][jurs.load_spline]), before anything is
    written."""
    if isinstance(spline, AdaptiveSpline):
        _save_adaptive(path, spline)
        return
    if not isinstance(spline, ImplicitSpline):
        raise TypeError(
            f"spline must be a jurs.ImplicitSpline or jurs.AdaptiveSpline, got "
            f"{type(spline).__name__}"
        )
    arrays = {k: np.asarray(getattr(spline, k)) for k in SPLINE_KEYS}
    check_spline_arrays(arrays, "spline: ")
    with open(os.fspath(path), "wb") as fh:
        np.savez(fh, **arrays, **{VERSION_KEY: np.int64(FORMAT_VERSION)})  # pyright: ignore[reportArgumentType]


def _save_adaptive(path, spline: AdaptiveSpline) -> None:
    arrays = {k: np.asarray(getattr(spline, k)) for k in SPLINE_KEYS}
    for k in ("control", "weights"):
        if not np.isfinite(arrays[k]).all():
            raise ValueError(f"spline: {k} contain NaN or Inf")
    if not (arrays["weights"] > 0).all():
        raise ValueError("spline: weights must all be positive (a zero weight makes g undefined)")
    refined = {f"refined_{i}": r for i, r in enumerate(refined_cells(spline.hierarchy))}
    arrays |= refined | {
        "base": np.asarray(spline.hierarchy.base, np.int64),
        VERSION_KEY: np.asarray(ADAPTIVE_VERSION, np.int64),
    }
    with open(os.fspath(path), "wb") as fh:
        np.savez(fh, **arrays)  # pyright: ignore[reportArgumentType]


def _load_adaptive(path: str, data, dtype) -> AdaptiveSpline:
    """The adaptive spline of a version-2 file; ValueError naming the file for arrays that
    do not make one."""
    names = set(data.files)
    levels = sum(1 for k in names if k.startswith("refined_"))
    expected = set(SPLINE_KEYS) | {"base", VERSION_KEY} | {f"refined_{i}" for i in range(levels)}
    if names != expected:
        raise ValueError(
            f"{path}: an adaptive spline file holds {sorted(expected)}, got {sorted(names)}"
        )
    base = np.asarray(data["base"])
    lower, upper = np.asarray(data["lower"], float), np.asarray(data["upper"], float)
    if base.dtype.kind not in "iu" or base.ndim != 1 or base.size not in (2, 3) or (base < 1).any():
        raise ValueError(f"{path}: base must be 2 or 3 positive cell counts, got {base.tolist()}")
    if lower.shape != base.shape or upper.shape != base.shape or not (lower < upper).all():
        raise ValueError(f"{path}: lower and upper must bound a box of {base.size} axes")
    try:
        hierarchy = build_hierarchy(
            lower,
            upper,
            tuple(int(n) for n in base),
            [np.asarray(data[f"refined_{i}"], np.int64) for i in range(levels)],
            dtype=dtype,
        )
        return AdaptiveSpline(
            hierarchy,
            jnp.asarray(np.asarray(data["control"]), dtype),
            jnp.asarray(np.asarray(data["weights"]), dtype),
        )
    except (ValueError, IndexError) as exc:
        raise ValueError(f"{path}: not a valid adaptive spline ({exc})") from None


def load_spline(
    path: str | os.PathLike[str], dtype: DTypeLike | None = None
) -> ImplicitSpline | AdaptiveSpline:
    """Read an [`ImplicitSpline`][jurs.ImplicitSpline] written by
    [`save_spline`][jurs.save_spline]: a curve's (2D grids, box of shape (2,)) or a
    surface's (3D grids, box of shape (3,)); or an [`AdaptiveSpline`][jurs.AdaptiveSpline]
    (format version 2).

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
    dtype = dtype or jnp.result_type(float)
    try:
        with np.load(path, allow_pickle=False) as data:
            names = list(data.files)
            arrays = {k: np.asarray(data[k]) for k in SPLINE_KEYS if k in names}
            version = np.asarray(data[VERSION_KEY]) if VERSION_KEY in names else np.int64(0)
            if version.shape == () and int(version) == ADAPTIVE_VERSION:
                return _load_adaptive(path, data, dtype)
    except ValueError as exc:
        if str(exc).startswith(f"{path}:"):
            raise
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
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
    return ImplicitSpline(*(jnp.asarray(arrays[k], dtype) for k in SPLINE_KEYS))
