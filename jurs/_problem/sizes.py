"""Sizes: the margin of the automatic box, and the ladder that compiled shapes are rounded
to so that similar clouds share one compiled fit."""

from __future__ import annotations

#: Fewest points a fit is padded to (smaller clouds all share the size 32).
MIN_PADDED_POINTS = 32


def round_size(n: int) -> int:
    """``n`` rounded up to the size ladder 1, 2, ..., 8, then 4, 5, 6, 7 times a power of
    two (10, 12, 14, 16, 20, 24, 28, 32, 40, ...): four sizes an octave.

    Shapes that XLA compiles for (point counts, grid cells, occupied cells) are rounded to
    it, so that clouds of similar size share one compiled fit. Why four an octave: a new
    shape costs a compilation, seconds against a warm fit's fraction of a second
    (``benchmarks/results/startup.md``), while a size rounded up by at most 25 % (10 % on
    average over sizes) costs at most that much more work; eight an octave
    would halve the waste and double the compilations. A size in ``[4, 8) * 2^k`` on it is
    divisible by 2^k (a cell count halves k times), which multigrid coarsening likes.
    """
    n = int(n)
    if n <= 8:
        return max(n, 1)
    shift = n.bit_length() - 3  # n in [4, 8) * 2^shift
    step = 1 << shift
    return -(-n // step) * step


def padded_count(num_points: int) -> int:
    """The number of points [`jurs.fit`][] pads a cloud of ``num_points`` to (with
    masked-out copies of its first point): ``round_size``, at least
    ``MIN_PADDED_POINTS``."""
    return max(MIN_PADDED_POINTS, round_size(num_points))


#: Default margin added around the samples' bounding box, as a fraction of its longest side.
DEFAULT_MARGIN = 0.1
