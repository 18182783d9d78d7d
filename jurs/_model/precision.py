"""The fit's precision: full float32 precision for jurs's matrix products on every device,
and host values handed to compiled calls in the dtype the fit runs in."""

from __future__ import annotations

import functools

import jax
import numpy as np


def full_precision(fn):
    """``fn`` traced with matrix products at full precision (``"highest"``).

    Why: JAX's default lets a GPU run float32 products as TF32, with a 10-bit mantissa. The
    normal equations of a fit and their block Cholesky do not survive that: with TF32 a
    float32 fit ended far above the minimum energy, which it reaches with full precision
    as on a CPU (docs/performance.md, "On a GPU"). It changes nothing in float64 or on a
    CPU. A caller's own ``jax.default_matmul_precision`` does not reach inside ``fn``."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


def on_device(array, dtype=None) -> jax.Array:
    """A host array (NumPy or a Python number) as a JAX array of ``dtype`` (its own when
    None), converted on the host and then transferred.

    Why: ``jnp.asarray`` of a NumPy array compiles a small program for every new shape
    (JAX 0.10), and a conversion to another dtype one more; an adaptive fit hands over
    some thirty arrays whose shapes change with every cloud. ``jax.device_put`` of a
    NumPy array compiles nothing."""
    return jax.device_put(np.asarray(array, dtype))


def scalar_array(value, dtype):
    """A hyperparameter passed to a compiled call on its own (lambda): a Python or NumPy
    number as a 0-d NumPy array of ``dtype``, the problem's, as ``jurs._jit.as_arrays``
    converts a solver's floats (a new value compiles nothing, and a float32 problem's
    lambda is float32); a JAX array, traced or not, as it is (a derivative in it stays
    one)."""
    if isinstance(value, jax.Array):
        return value
    return np.asarray(value, np.dtype(dtype))
