"""Full float32 precision for jurs's matrix products on every device."""

from __future__ import annotations

import functools

import jax


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
