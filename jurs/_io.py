"""Saving and loading fitted splines as ``.npz`` files."""

from __future__ import annotations

import os

import jax.numpy as jnp
import numpy as np

from ._spline import ImplicitSpline

_KEYS = ("control", "weights", "lower", "upper")


def save_spline(path, spline: ImplicitSpline) -> None:
    """Write ``spline`` to ``path`` (``.npz``): arrays ``control``, ``weights``, ``lower``,
    ``upper``. :func:`load_spline` reads it back."""
    np.savez(os.fspath(path), **{k: np.asarray(getattr(spline, k)) for k in _KEYS})


def load_spline(path, dtype=None) -> ImplicitSpline:
    """Read an :class:`ImplicitSpline` written by :func:`save_spline`.

    ``dtype`` defaults to JAX's default float (float64 with ``jax_enable_x64``).
    Raises FileNotFoundError, or ValueError naming the file for missing or ill-shaped arrays.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in _KEYS if k in data.files}
    except Exception as exc:
        raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    missing = [k for k in _KEYS if k not in arrays]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing} (expected {list(_KEYS)})")
    if arrays["lower"].shape != (2,) or arrays["upper"].shape != (2,):
        raise ValueError(f"{path}: lower and upper must have shape (2,)")
    if arrays["control"].ndim != 2 or arrays["control"].shape != arrays["weights"].shape:
        raise ValueError(f"{path}: control and weights must be matching 2D grids")
    dtype = dtype or jnp.result_type(float)
    return ImplicitSpline(*(jnp.asarray(arrays[k], dtype) for k in _KEYS))
