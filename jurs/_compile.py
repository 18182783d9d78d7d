"""XLA options that vectorise the per-bucket sums of large problems."""

from __future__ import annotations

#: XLA options for ``jax.jit(..., compiler_options=jurs.COMPILER_OPTIONS)``.
#:
#: What they do: allow floating-point reassociation, so that LLVM vectorises sums that
#: XLA's CPU backend otherwise runs as scalar accumulator chains: the per-bucket moment
#: sums of the power form (:func:`jurs._basis.power_moments`). NaN and Inf, division and
#: library functions keep their IEEE semantics (the ``honor`` options), so the non-finite
#: checks of the solver driver still work. Measured effect in
#: ``benchmarks/results/speed.md`` (1e6 points, 128 x 128).
#:
#: Who uses them: :func:`jurs.fit` compiles with them the solvers that declare
#: ``reassociation_safe`` (IURS, IPIA, NormalIPIA, LeastSquares) on problems in the bucketed
#: power form (the large ones), when no JAX transformation is tracing: XLA takes compiler
#: options only on an outermost jit. For your own jit of a solver's step or of
#: :func:`jurs.solve`, pass them to the outermost ``jax.jit``.
#:
#: Why not everywhere: sums round differently. jurs's own solvers move at the level of the
#: last digits, but an optimiser that wanders near its minimum can end elsewhere (optax's
#: Adam through ``OptimistixMinimiser``): ``benchmarks/results/solvers.md`` compiles every
#: solver both ways. The names are those of XLA's debug options; other backends ignore the
#: CPU ones.
COMPILER_OPTIONS = {
    "xla_cpu_enable_fast_math": True,
    "xla_cpu_fast_math_honor_nans": True,
    "xla_cpu_fast_math_honor_infs": True,
    "xla_cpu_fast_math_honor_division": True,
    "xla_cpu_fast_math_honor_functions": True,
}
