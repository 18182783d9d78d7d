"""Sizes: the margin of the automatic box, and the ladders that compiled shapes are rounded
to so that clouds of different sizes share one compiled fit (docs/design.md section 5,
"Compiled shapes")."""

from __future__ import annotations

#: Fewest points a fit is padded to (smaller clouds all share the size 32).
MIN_PADDED_POINTS = 32

#: Point counts up to this are padded to a power of two (one size an octave); larger
#: clouds to ``round_size``'s four sizes an octave, where the padded work of a warm fit
#: (up to twice the samples) would cost more than a compilation.
OCTAVE_PADDING_MAX = 1 << 18


def round_size(n: int) -> int:
    """``n`` rounded up to the size ladder 1, 2, ..., 8, then 4, 5, 6, 7 times a power of
    two (10, 12, 14, 16, 20, 24, 28, 32, 40, ...): four sizes an octave.

    Automatic grids' cell counts are rounded to it (``jurs._fit.settings.choose_grid``;
    a curve's longest side first to ``round_octave`` up to 64 cells, one size an octave,
    so that a shape gets one grid an octave of points; a surface's every side to this
    ladder, cells at most 25 % narrower, where a power of two would cost up to 8x the
    coefficients);
    and point counts above ``OCTAVE_PADDING_MAX``. A size in ``[4, 8) * 2^k`` on it is
    divisible by 2^k (a cell count halves k times), which multigrid coarsening likes.
    """
    n = int(n)
    if n <= 8:
        return max(n, 1)
    shift = n.bit_length() - 3  # n in [4, 8) * 2^shift
    step = 1 << shift
    return -(-n // step) * step


def round_octave(n: int) -> int:
    """``n`` rounded up to a power of two (1, 2, 4, 8, ...): one size an octave.

    Point counts and occupied cells, the counts a compiled fit's sample arrays are sized
    from, are rounded to it: a new shape costs a compilation, many times a small warm
    fit's time (docs/performance.md), while
    padding to a power of two costs at most twice the per-sample work (2 ln 2 = 1.39
    times on average over sizes), which in a default fit is a small share of the solve on
    its grid (docs/startup.md, "Shape-stable compiled fits")."""
    n = int(n)
    return 1 if n <= 1 else 1 << (n - 1).bit_length()


def padded_count(num_points: int) -> int:
    """The number of points [`jurs.fit`][] pads a cloud of ``num_points`` to (with
    masked-out copies of its first point): ``round_octave`` (``round_size`` above
    ``OCTAVE_PADDING_MAX``), at least ``MIN_PADDED_POINTS``."""
    if num_points > OCTAVE_PADDING_MAX:
        return round_size(num_points)
    return max(MIN_PADDED_POINTS, round_octave(num_points))


def padded_to(values, length: int, fill=0):
    """``values`` (a NumPy array) followed by ``fill`` up to ``length`` along its first
    axis: host arrays padded to a size class, so that one compiled program serves them."""
    import numpy as np

    out = np.full((length,) + values.shape[1:], fill, values.dtype)
    out[: values.shape[0]] = values
    return out


#: Default margin added around the samples' bounding box, as a fraction of its longest side.
DEFAULT_MARGIN = 0.1
