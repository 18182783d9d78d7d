"""XLA options for compiling jurs's large problems faster: opt-in, for users' own jits."""

from __future__ import annotations

#: XLA options for ``jax.jit(..., compiler_options=jurs.COMPILER_OPTIONS)`` of a solver's
#: step or of :func:`jurs.solve` on a large problem. Opt-in: :func:`jurs.fit` does not use
#: them.
#:
#: What they do: allow floating-point reassociation, so that LLVM vectorises sums that
#: XLA's CPU backend otherwise runs as scalar accumulator chains. The per-bucket moment sums
#: of an IURS step at 3e6 samples (32 a sample) took 6.2 ms instead of 13.5 ms, and the
#: whole step at 1e6 points on a 128 x 128 grid 58 ms instead of 75 ms (2-core x86_64 CPU,
#: float64; ``benchmarks/results/speed.md``). NaN and Inf, division and library functions
#: keep their IEEE semantics (the ``honor`` options), so the non-finite checks of the
#: solver driver still work.
#:
#: Why opt-in: sums round differently. jurs's own solvers move at the level of the last
#: digits (an IURS fit of 300 points: the same steps, coefficients within 1e-11), but an
#: optimiser that wanders near its minimum can end elsewhere: optax's Adam through
#: ``OptimistixMinimiser`` ended 1.8e-4 above the minimum energy after 5000 steps with
#: these options, 3.5e-8 without (and 1.9e-6 without, from a start moved by 1e-15). The
#: names are those of XLA's debug options; other backends ignore the CPU ones. They cannot
#: be given to a jit nested inside another: pass them to the outermost one.
COMPILER_OPTIONS = {
    "xla_cpu_enable_fast_math": True,
    "xla_cpu_fast_math_honor_nans": True,
    "xla_cpu_fast_math_honor_infs": True,
    "xla_cpu_fast_math_honor_division": True,
    "xla_cpu_fast_math_honor_functions": True,
}
