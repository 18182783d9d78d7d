"""Setup of the benchmarks' own tests (renderers, baselines, smoke runs), apart from the
library's tests in ``tests/``. The scripts are modules of the ``benchmarks`` package and
the tests import them relatively (``from .. import speed``, ``from .._common import ...``):
pytest puts the repository root, the first folder above ``benchmarks/tests`` without an
``__init__.py``, on ``sys.path``, so ``benchmarks`` and ``jurs`` import from this checkout.
As in ``tests/``: float64 (the NumPy port agrees with jurs to 1e-10), no persistent
compilation cache, matplotlib without a display."""

import os

import jax
import matplotlib

jax.config.update("jax_enable_x64", True)
os.environ["JURS_NO_COMPILATION_CACHE"] = "1"
matplotlib.use("Agg")
