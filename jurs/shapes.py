"""Closed test outlines with outward unit normals, for benchmarks and experiments.

The paper's Examples 2-7 use "figures" whose outlines are not published. This module
offers stand-ins with a clear origin, each with several of the features that make implicit
fitting hard (concavities, several components, holes, thin parts):

* **analytic curves** (exact, no external data): the paper's Example 1 curve, an ellipse,
  a rounded five-petal rose, a lopsided three-lobed curve, an annulus with an off-centre
  hole;
* **glyph outlines** of DejaVu Sans, the font that ships with matplotlib, read with
  ``matplotlib.textpath.TextPath`` (the quadratic/cubic Bezier pieces are evaluated
  exactly): letters with holes, i.e. several components;
* **outlines traced from images that ship with scikit-image** (``skimage.data.horse``,
  ``skimage.data.coins``) with ``skimage.measure.find_contours`` after a small Gaussian
  blur, which smooths the pixel staircase.

Every shape is a list of closed polylines (*components*) in data units, scaled so the
longest side of its bounding box is ``size`` (default 8, about Example 1's 8 x 8.45, so
that the paper's d = 0.1 and eps = 0.01 keep their meaning) and centred on ``center``.
Components are oriented with the filled region on their left (outer boundaries
anticlockwise, holes clockwise; the filled region follows the even-odd rule), so the
normal ``(t_y, -t_x)`` of the unit tangent ``t`` points **out of the filled region**: away
from the shape on outer boundaries, into the hole on holes (the convention of
[`jurs.datasets`][] and docs/design.md section 1).

    points, normals = jurs.shapes.get("glyph_B", 639, size=8.0)

matplotlib and scikit-image are imported inside the functions that need them, so
``import jurs.shapes`` stays light. scikit-image is needed only for the image shapes.
"""

from __future__ import annotations

import functools
from typing import Sequence

import numpy as np
import numpy.typing as npt
from jaxtyping import Bool, Float

#: Vertices per analytic curve before arc-length resampling.
_ANALYTIC_VERTICES = 8192
#: Bezier evaluations per glyph curve piece.
_BEZIER_SAMPLES = 64


# --------------------------------------------------------------------------- geometry


def signed_area(polyline: Float[npt.ArrayLike, "k 2"]) -> float:
    """Shoelace area of a closed polyline (first vertex not repeated): > 0 anticlockwise."""
    x, y = np.asarray(polyline, float).T
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _drop_closing_vertex(polyline: np.ndarray) -> np.ndarray:
    if len(polyline) > 1 and np.allclose(polyline[0], polyline[-1]):
        return polyline[:-1]
    return polyline


def _dedupe(polyline: np.ndarray) -> np.ndarray:
    """Remove consecutive repeated vertices (zero-length segments break arc length)."""
    keep = np.ones(len(polyline), bool)
    keep[1:] = np.linalg.norm(np.diff(polyline, axis=0), axis=1) > 1e-12
    return polyline[keep]


def contains(
    components: Sequence[Float[npt.ArrayLike, "k 2"]], xy: Float[npt.ArrayLike, "n 2"]
) -> Bool[np.ndarray, " n"]:
    """Whether each point of ``xy (n, 2)`` lies in the filled region of ``components``
    under the even-odd rule (inside an odd number of the closed polylines)."""
    from matplotlib.path import Path

    xy = np.asarray(xy, float).reshape(-1, 2)
    count = np.zeros(len(xy), int)
    for comp in components:
        count += Path(np.asarray(comp, float)).contains_points(xy)
    return count % 2 == 1


def orient(components: Sequence[Float[npt.ArrayLike, "k 2"]]) -> list[Float[np.ndarray, "k 2"]]:
    """Orient closed polylines so the even-odd filled region lies on their left.

    A component's nesting depth is the number of other components that contain it (tested
    at its first vertex; components must not cross). Even depth: an outer boundary, made
    anticlockwise. Odd depth: a hole, made clockwise.
    """
    from matplotlib.path import Path

    comps = [_dedupe(_drop_closing_vertex(np.asarray(c, float))) for c in components]
    out = []
    for i, comp in enumerate(comps):
        depth = sum(
            bool(Path(other).contains_point(comp[0])) for j, other in enumerate(comps) if j != i
        )
        want_anticlockwise = depth % 2 == 0
        if (signed_area(comp) > 0) != want_anticlockwise:
            comp = comp[::-1]
        out.append(np.ascontiguousarray(comp))
    return out


def normalise(
    components: Sequence[Float[np.ndarray, "k 2"]],
    size: float = 8.0,
    center: Float[npt.ArrayLike, " 2"] = (0.0, 0.0),
) -> list[Float[np.ndarray, "k 2"]]:
    """Scale and translate components together so the longest side of their joint bounding
    box is ``size`` and its centre is ``center``."""
    if not size > 0:
        raise ValueError(f"size must be positive, got {size}")
    allv = np.concatenate(components)
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    scale = size / float(np.max(hi - lo))
    mid = 0.5 * (lo + hi)
    return [(c - mid) * scale + np.asarray(center, float) for c in components]


def sample_outline(
    components: Sequence[Float[npt.ArrayLike, "k 2"]],
    num_points: int,
    *,
    nonuniform: float = 0.0,
    gap: float = 0.0,
    gap_at: float = 0.0,
    tangent_window: float | None = None,
) -> tuple[Float[np.ndarray, "n 2"], Float[np.ndarray, "n 2"]]:
    """Sample closed polylines by arc length: ``(points, normals)``, each ``(num_points, 2)``.

    The components are laid end to end on one arc-length axis, so the spacing is the same
    on every component and each gets points in proportion to its length. Normals are
    ``(t_y, -t_x)`` of the unit chord tangent ``p(s + delta) - p(s - delta)``: outward
    for components oriented as [`orient`][jurs.shapes.orient] leaves them. At a corner the
    chord gives the bisector of the two sides, so corners get a well-defined normal.

    Args:
        components: closed polylines (first vertex not repeated), filled region on the left.
        num_points: number of points returned (>= 3).
        nonuniform: ``a`` in [0, 1): the sampling density varies smoothly along the outline
            between ``1 - a`` and ``1 + a`` times the mean (0: uniform arc-length spacing).
        gap: fraction in [0, 1) of the total outline length left unsampled (a hole in the
            data), starting at ``gap_at`` (a fraction of the total length, measured along
            the components in order). All ``num_points`` go to the rest.
        tangent_window: ``delta`` in data units (default 1e-4 x the total length).
    """
    num_points = int(num_points)
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    if not 0.0 <= nonuniform < 1.0:
        raise ValueError(f"nonuniform must be in [0, 1), got {nonuniform}")
    if not 0.0 <= gap < 1.0:
        raise ValueError(f"gap must be in [0, 1), got {gap}")
    comps = [np.asarray(c, float) for c in components]
    seg_lengths = [np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1) for c in comps]
    cum = [np.concatenate([[0.0], np.cumsum(s)]) for s in seg_lengths]  # per component
    lengths = np.array([c[-1] for c in cum])
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    total = float(starts[-1])
    delta = 1e-4 * total if tangent_window is None else float(tangent_window)

    # Parameter v on the sampled part [0, usable), uniform (mid-cell) then warped.
    usable = total * (1.0 - gap)
    v = (np.arange(num_points) + 0.5) * usable / num_points
    if nonuniform:
        # v -> v - a L/(2 pi) sin(2 pi v / L): derivative 1 - a cos(.), so the spacing
        # varies between (1 - a) and (1 + a) times the mean.
        v = v - nonuniform * usable / (2 * np.pi) * np.sin(2 * np.pi * v / usable)
    u = np.mod(v + (gap_at + gap) * total, total)  # skip [gap_at, gap_at + gap) x total

    def position(k, s):
        s = np.mod(s, lengths[k])
        c = comps[k]
        closed = np.vstack([c, c[:1]])
        return np.stack(
            [np.interp(s, cum[k], closed[:, 0]), np.interp(s, cum[k], closed[:, 1])], axis=-1
        )

    points = np.empty((num_points, 2))
    normals = np.empty((num_points, 2))
    which = np.clip(np.searchsorted(starts, u, side="right") - 1, 0, len(comps) - 1)
    for k in range(len(comps)):
        sel = which == k
        if not sel.any():
            continue
        s = u[sel] - starts[k]
        points[sel] = position(k, s)
        chord = position(k, s + delta) - position(k, s - delta)
        chord /= np.linalg.norm(chord, axis=1, keepdims=True)
        normals[sel] = np.stack([chord[:, 1], -chord[:, 0]], axis=1)
    return points, normals


# --------------------------------------------------------------------------- sources


def _closed_curve(fn, vertices: int = _ANALYTIC_VERTICES) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, vertices, endpoint=False)
    return np.stack(fn(t), axis=1)


def _polar(radius):
    return lambda t: (radius(t) * np.cos(t), radius(t) * np.sin(t))


def example1_outline() -> list[Float[np.ndarray, "k 2"]]:
    """The paper's Example 1 curve x = 4 cos t, y = sin t (3 - 5 sin t): one component with
    a concave dent at the top (analytic)."""
    return [_closed_curve(lambda t: (4.0 * np.cos(t), np.sin(t) * (3.0 - 5.0 * np.sin(t))))]


def ellipse_outline() -> list[Float[np.ndarray, "k 2"]]:
    """The ellipse x = 4 cos t, y = 5 sin t of the paper's Example 10 (analytic)."""
    return [_closed_curve(lambda t: (4.0 * np.cos(t), 5.0 * np.sin(t)))]


def rose_outline() -> list[Float[np.ndarray, "k 2"]]:
    """A rounded five-petal rose r(t) = 1 + 0.4 cos 5t: five concave bays (analytic; this
    library's choice, in the style of the paper's star-like figures)."""
    return [_closed_curve(_polar(lambda t: 1.0 + 0.4 * np.cos(5.0 * t)))]


def lobes_outline() -> list[Float[np.ndarray, "k 2"]]:
    """A lopsided three-lobed curve r(t) = 1 + 0.35 cos 3t + 0.2 sin 2t: concavities of
    different depths, no symmetry (analytic; this library's choice)."""
    return [_closed_curve(_polar(lambda t: 1.0 + 0.35 * np.cos(3.0 * t) + 0.2 * np.sin(2.0 * t)))]


def annulus_outline() -> list[Float[np.ndarray, "k 2"]]:
    """A disc of radius 1 with an off-centre elliptical hole (semi-axes 0.45, 0.3, centre
    (0.2, 0.1)): two components, the inner one a hole (analytic)."""
    outer = _closed_curve(lambda t: (np.cos(t), np.sin(t)))
    hole = _closed_curve(lambda t: (0.2 + 0.45 * np.cos(t), 0.1 + 0.3 * np.sin(t)))
    return [outer, hole]


def glyph_outline(text: str, family: str = "DejaVu Sans") -> list[Float[np.ndarray, "k 2"]]:
    """Outlines of ``text`` set in ``family`` (default DejaVu Sans, which ships with
    matplotlib), one closed polyline per contour of the glyphs.

    Read with ``matplotlib.textpath.TextPath``; its line, quadratic and cubic Bezier
    pieces are evaluated at ``_BEZIER_SAMPLES`` parameters each (no flattening
    tolerance involved).
    """
    from matplotlib.font_manager import FontProperties
    from matplotlib.path import Path
    from matplotlib.textpath import TextPath

    path = TextPath((0.0, 0.0), text, size=1.0, prop=FontProperties(family=family))
    components, current = [], []
    t = np.linspace(0.0, 1.0, _BEZIER_SAMPLES, endpoint=False)
    # matplotlib's stub says iter_bezier yields segments; it yields (segment, code) pairs.
    for segment, code in path.iter_bezier():  # pyright: ignore[reportGeneralTypeIssues]
        if code == Path.MOVETO:
            if len(current) > 2:
                components.append(np.concatenate(current))
            current = []
        elif code == Path.CLOSEPOLY:
            # iter_bezier yields the closing line as a degree-1 segment.
            current.append(segment.control_points[:1])
        elif segment.degree == 1:
            current.append(segment.control_points[:1])  # a line: its start vertex suffices
        else:
            current.append(segment(t))
    if len(current) > 2:
        components.append(np.concatenate(current))
    components = [_dedupe(_drop_closing_vertex(c)) for c in components]
    return [c for c in components if len(c) > 2 and abs(signed_area(c)) > 1e-9]


def mask_outline(
    mask: Bool[npt.ArrayLike, "h w"], *, blur: float = 1.5, min_area: float = 50.0
) -> list[Float[np.ndarray, "k 2"]]:
    """Closed outlines of the True region of a 2-D boolean image (scikit-image).

    The mask is padded with False (so every contour closes), blurred with a Gaussian of
    ``blur`` pixels (rounds the pixel staircase) and contoured at 0.5 with
    ``skimage.measure.find_contours``. Components enclosing fewer than ``min_area``
    square pixels are dropped. Coordinates: x = column, y = -row (image upright).
    """
    from scipy import ndimage
    from skimage import measure

    image = np.pad(np.asarray(mask, bool), 4).astype(float)
    if blur > 0:
        image = ndimage.gaussian_filter(image, blur)
    comps = []
    for contour in measure.find_contours(image, 0.5):
        comp = _dedupe(_drop_closing_vertex(np.stack([contour[:, 1], -contour[:, 0]], axis=1)))
        if len(comp) > 2 and abs(signed_area(comp)) >= min_area:
            comps.append(comp)
    return comps


def horse_outline() -> list[Float[np.ndarray, "k 2"]]:
    """The horse silhouette of ``skimage.data.horse()`` (a 328 x 400 binary image shipped
    with scikit-image): one component with legs, tail and ears, i.e. thin parts and deep
    concavities."""
    from skimage import data

    return mask_outline(~data.horse(), blur=1.5)  # pyright: ignore[reportOperatorIssue]  # bool


def coins_outline() -> list[Float[np.ndarray, "k 2"]]:
    """The 24 coins of ``skimage.data.coins()`` (a greyscale photo shipped with
    scikit-image), segmented as in scikit-image's own tutorial: Sobel edges, watershed
    from markers (grey < 30 background, > 150 coin), holes filled. 24 components."""
    from scipy import ndimage
    from skimage import data, filters, segmentation

    image = data.coins()
    markers = np.zeros(image.shape, int)
    markers[image < 30] = 1
    markers[image > 150] = 2
    coins = segmentation.watershed(filters.sobel(image), markers) == 2
    # binary_fill_holes returns an array for an array; its stubs say "or None".
    return mask_outline(ndimage.binary_fill_holes(coins), blur=2.0, min_area=200.0)  # pyright: ignore[reportArgumentType]


def _glyph(char):
    def source():
        return glyph_outline(char)

    source.__doc__ = (
        f"The glyph {char!r} of DejaVu Sans (ships with matplotlib), read with "
        "matplotlib.textpath.TextPath."
    )
    return source


#: Shape name -> function returning its raw (unscaled, unoriented) components.
SOURCES = {
    "example1": example1_outline,
    "ellipse": ellipse_outline,
    "rose": rose_outline,
    "lobes": lobes_outline,
    "annulus": annulus_outline,
    "glyph_B": _glyph("B"),
    "glyph_a": _glyph("a"),
    "glyph_8": _glyph("8"),
    "glyph_g": _glyph("g"),
    "horse": horse_outline,
    "coins": coins_outline,
}
#: The shapes
#: [`get`][jurs.shapes.get]
#: knows.
NAMES = tuple(SOURCES)


def origin(name: str) -> str:
    """One line saying where shape ``name`` comes from (its source's docstring)."""
    _check(name)
    return " ".join((SOURCES[name].__doc__ or "").split())


def _check(name):
    if name not in SOURCES:
        raise ValueError(f"unknown shape {name!r}; known: {', '.join(NAMES)}")


@functools.lru_cache(maxsize=None)
def _raw(name: str):
    return tuple(orient(SOURCES[name]()))


def outline(
    name: str, size: float = 8.0, center: Float[npt.ArrayLike, " 2"] = (0.0, 0.0)
) -> list[Float[np.ndarray, "k 2"]]:
    """The components of shape ``name`` as dense closed polylines (first vertex not
    repeated), oriented with the filled region on the left, scaled so the longest side of
    the bounding box is ``size`` and centred on ``center``."""
    _check(name)
    return normalise([c.copy() for c in _raw(name)], size, center)


def get(
    name: str,
    num_points: int,
    size: float = 8.0,
    *,
    center: Float[npt.ArrayLike, " 2"] = (0.0, 0.0),
    nonuniform: float = 0.0,
    gap: float = 0.0,
    gap_at: float = 0.0,
) -> tuple[Float[np.ndarray, "n 2"], Float[np.ndarray, "n 2"]]:
    """``num_points`` points of shape ``name`` with outward unit normals.

    Sampled by arc length across all components (same spacing everywhere; see
    [`sample_outline`][jurs.shapes.sample_outline] for ``nonuniform``, ``gap`` and
    ``gap_at``). The shape is scaled so the longest side of its bounding box is ``size``
    (default 8.0) and centred on ``center``.

    Returns:
        ``(points, normals)``, float64 arrays of shape ``(num_points, 2)``.
    """
    return sample_outline(
        outline(name, size, center), num_points, nonuniform=nonuniform, gap=gap, gap_at=gap_at
    )
