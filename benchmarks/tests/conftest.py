"""Setup of the benchmarks' own tests (renderers, baselines, smoke runs), apart from the
library's tests in ``tests/``: the benchmark scripts and their shared modules import each
other as top-level modules (``import speed``, ``from _common import ...``), so the
``benchmarks`` folder goes on ``sys.path``, and the repository root too, for ``jurs``
itself. As in ``tests/``: float64 (the NumPy port agrees with jurs to 1e-10), no
persistent compilation cache, matplotlib without a display."""

import os
import sys

import jax
import matplotlib

BENCHMARKS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(BENCHMARKS)
for path in (ROOT, BENCHMARKS):
    if path not in sys.path:
        sys.path.insert(0, path)

jax.config.update("jax_enable_x64", True)
os.environ["JURS_NO_COMPILATION_CACHE"] = "1"
matplotlib.use("Agg")
