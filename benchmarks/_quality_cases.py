"""The 2D cases of ``benchmarks/quality.py``, shared with ``benchmarks/smoothing.py``: the
shapes, how many points each gets, the dense reference samples of its clean outline and the
resolution of the zero-set analysis."""

from __future__ import annotations

import numpy as np

import jurs.levelset
import jurs.shapes

#: Base cases: key -> (shape name, sampling keyword arguments, what it tests).
CASES = {
    "example1": ("example1", {}, "the paper's Example 1 curve (concave dent)"),
    "ellipse": ("ellipse", {}, "ellipse (the paper's Example 10 curve)"),
    "rose": ("rose", {}, "five-petal rose, five concave bays"),
    "lobes": ("lobes", {}, "lopsided three-lobed curve"),
    "annulus": ("annulus", {}, "disc with an off-centre hole (2 components)"),
    "glyph_B": ("glyph_B", {}, "DejaVu Sans 'B': corners, two holes"),
    "glyph_a": ("glyph_a", {}, "DejaVu Sans 'a': one hole, thin strokes"),
    "glyph_8": ("glyph_8", {}, "DejaVu Sans '8': two holes"),
    "glyph_g": ("glyph_g", {}, "DejaVu Sans 'g': hole, descender"),
    "horse": ("horse", {}, "scikit-image horse: legs, tail, ears (thin parts)"),
    "coins": ("coins", {}, "scikit-image coins: 24 separate components"),
    "lobes_nonuniform": (
        "lobes",
        {"nonuniform": 0.6},
        "lobes, sampling density varying 0.4x-1.6x along the curve",
    ),
    "rose_gap": ("rose", {"gap": 0.08}, "rose with 8 % of its length unsampled"),
}
#: m = clip(round(M_PER_LENGTH * L / diag, -2), M_MIN, M_MAX), L the outline's total length:
#: longer, more detailed outlines get more points, within a range of 1000 to 2000 points.
M_PER_LENGTH, M_MIN, M_MAX = 250, 1000, 2000
#: Reference samples of the clean outline: spacing diag / REFERENCE_DIVISOR.
REFERENCE_DIVISOR = 2000
#: Zero-set analysis grid (nodes along the longer side), the same for jurs and the RBF.
RESOLUTION = jurs.levelset.DEFAULT_RESOLUTION


def clean_outline(shape: str):
    """Components, reference samples, bounding-box diagonal and total length of the clean
    outline of ``shape`` (as [`jurs.shapes.get`][] samples it)."""
    comps = jurs.shapes.outline(shape)
    allp = np.concatenate(comps)
    diag = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    length = float(sum(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1).sum() for c in comps))
    ref = np.concatenate(
        [jurs.levelset.resample(np.vstack([c, c[:1]]), diag / REFERENCE_DIVISOR) for c in comps]
    )
    return comps, ref, diag, length


def choose_m(length: float, diag: float) -> int:
    return int(np.clip(round(M_PER_LENGTH * length / diag, -2), M_MIN, M_MAX))
