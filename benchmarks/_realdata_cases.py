"""Real outlines for ``benchmarks/realdata.py``: traced from images and data files that ship
with installed packages (scikit-image, matplotlib), or set in fonts that matplotlib ships.

Every image case is segmented with a plain threshold (Otsu, a local threshold, a colour
range or a fixed level, after at most a crop or a 2x downscale of the image), keeps its
largest few connected regions, fills holes smaller than a few pixels, and is traced the way
a new user would trace it: ``skimage.measure.find_contours`` at 0.5 on the padded 0/1
mask, **without** the Gaussian blur that [`jurs.shapes.mask_outline`][] applies. The
outline therefore runs along pixel edges: its vertices lie on half-pixel positions and it
carries the pixel staircase. Font cases are exact glyph outlines
([`jurs.shapes.glyph_outline`][]). None of these data are in the project's suite
(``jurs.shapes`` uses ``horse``, ``coins`` and DejaVu Sans).

Each case is oriented ([`jurs.shapes.orient`][]), scaled to size 8
([`jurs.shapes.normalise`][]) and given a point count m: ``clip(round(POINTS_PER_PIXEL *
L, -2), M_MIN, M_MAX)`` with L the outline's length in pixels (fonts: in units of
1/``FONT_PIXELS`` of the longest side, as if set that many pixels wide), so the spacing is
finer than a pixel; the multi-ring ``page`` case has m = ``MULTI_RING_M``. Everything is
deterministic and cached.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

import jurs.shapes

#: Sample points per pixel of outline length, and the range m is clipped to.
POINTS_PER_PIXEL, M_MIN, M_MAX = 1.75, 1500, 5000
#: Point count of the multi-ring case.
MULTI_RING_M = 20000
#: Font cases count as if set this many pixels along their longest side.
FONT_PIXELS = 400
#: Regions (and holes) below this many square pixels are dropped (filled).
MIN_AREA = 20
#: Longest side after [`jurs.shapes.normalise`][].
SIZE = 8.0


# --------------------------------------------------------------------------- helpers


def trace(mask, min_area: float = MIN_AREA) -> list[np.ndarray]:
    """Closed outlines of the True pixels of ``mask`` in pixel units (x = column, y = -row),
    by plain marching squares (``skimage.measure.find_contours`` at 0.5 on the 0/1 mask
    padded with False, no blur): vertices on half-pixel positions, the pixel staircase kept.
    Outlines enclosing less than ``min_area`` square pixels are dropped."""
    from skimage import measure

    pad = 2
    image = np.pad(np.asarray(mask, bool), pad).astype(float)
    out = []
    for contour in measure.find_contours(image, 0.5):
        comp = np.stack([contour[:, 1] - pad, -(contour[:, 0] - pad)], axis=1)
        if np.allclose(comp[0], comp[-1]):
            comp = comp[:-1]
        if len(comp) > 2 and abs(jurs.shapes.signed_area(comp)) >= min_area:
            out.append(comp)
    return out


def largest(mask, count: int, min_hole: float = MIN_AREA) -> np.ndarray:
    """The ``count`` largest 4-connected regions of ``mask`` (the regions that marching
    squares at 0.5 traces apart), with holes smaller than ``min_hole`` pixels filled."""
    from scipy import ndimage

    mask = np.asarray(mask, bool)
    labels, sizes = _regions(mask)
    if len(sizes) > count:
        mask = np.isin(labels, np.argsort(sizes)[::-1][:count] + 1)
    holes = np.asarray(ndimage.binary_fill_holes(mask)) & ~mask
    labels, sizes = _regions(holes)
    return mask | np.isin(labels, np.nonzero(sizes < min_hole)[0] + 1)


def drop_small(mask, min_size: float = MIN_AREA) -> np.ndarray:
    """``mask`` without its 4-connected regions smaller than ``min_size`` pixels."""
    labels, sizes = _regions(mask)
    return np.isin(labels, np.nonzero(sizes >= min_size)[0] + 1)


def _regions(mask):
    """4-connected regions of ``mask``: ``(labels (0: background), sizes of regions 1..)``."""
    from skimage import measure

    labels = np.asarray(measure.label(np.asarray(mask, bool), connectivity=1))
    return labels, np.bincount(labels.ravel())[1:]


def _grey(image) -> np.ndarray:
    from skimage import color

    image = np.asarray(image)
    return color.rgb2gray(image[..., :3]) if image.ndim == 3 else image / 255.0


def _half(image) -> np.ndarray:
    """A greyscale image at half size (anti-aliased), as a user shrinks a large photo."""
    from skimage import transform

    return transform.rescale(np.asarray(image, float), 0.5, anti_aliasing=True)


def _hsv(image) -> np.ndarray:
    from skimage import color

    return color.rgb2hsv(np.asarray(image)[..., :3])


# --------------------------------------------------------------------------- sources
# Each returns a boolean mask (image cases) or closed polylines (font cases).


def camera():
    """``skimage.data.camera()`` at half size, dark pixels (Otsu): the cameraman's silhouette
    with the camera and its holes; thin handle and tripod parts."""
    from skimage import data, filters

    g = _half(data.camera() / 255.0)
    return largest(g < filters.threshold_otsu(g), 1)


def coffee():
    """``skimage.data.coffee()``, white pixels (saturation < 0.25, value > 0.7): the cup's
    rim, a thin elliptic band (outer and inner ring, about 12 px apart)."""
    from skimage import data

    hsv = _hsv(data.coffee())
    return largest((hsv[..., 1] < 0.25) & (hsv[..., 2] > 0.7), 1)


def rocket():
    """``skimage.data.rocket()``, columns 270-350 and rows 150-380, grey > 0.5: the rocket's
    lit body, elongated (about 15:1) with fins and gantry stubs."""
    from skimage import data

    g = _grey(data.rocket()[150:380, 270:350])
    return largest(g > 0.5, 1)


def astronaut():
    """``skimage.data.astronaut()`` at half size, orange pixels (hue < 0.1, saturation >
    0.55, value > 0.45): the space suit with the helmet ring and badges as holes."""
    from skimage import data

    hsv = _hsv(data.astronaut())
    orange = (hsv[..., 0] < 0.1) & (hsv[..., 1] > 0.55) & (hsv[..., 2] > 0.45)
    return largest(_half(orange.astype(float)) > 0.5, 1)


def logo():
    """``skimage.data.logo()`` at half size, green opaque pixels: one half of the disc, cut
    by the snake's S curve (smooth curves, staircase outline)."""
    from skimage import data

    image = data.logo()
    hsv = _hsv(image)
    green = (hsv[..., 0] > 0.15) & (hsv[..., 0] < 0.4) & (hsv[..., 1] > 0.3) & (image[..., 3] > 128)
    return largest(_half(green.astype(float)) > 0.5, 1)


def mri():
    """matplotlib's sample ``s1045.ima.gz`` (a 256 x 256 sagittal MRI slice, 16-bit
    big-endian), pixels > 25 with holes filled: the head's profile."""
    import matplotlib.cbook as cbook
    from scipy import ndimage

    with cbook.get_sample_data("s1045.ima.gz") as fh:  # pyright: ignore[reportGeneralTypeIssues]
        image = np.frombuffer(fh.read(), ">u2").reshape(256, 256).astype(float)
    return largest(ndimage.binary_fill_holes(image > 25), 1)


def terrain():
    """matplotlib's sample ``jacksboro_fault_dem.npz`` (a terrain elevation model) at half
    size, above its 80th percentile: ridges with dendritic valleys (3 regions)."""
    import matplotlib.cbook as cbook

    dem = _half(cbook.get_sample_data("jacksboro_fault_dem.npz")["elevation"])  # pyright: ignore[reportIndexIssue]  # an NpzFile
    return largest(dem > np.percentile(dem, 80), 3)


def blobs():
    """``skimage.data.binary_blobs(192, 0.2, volume_fraction=0.3, rng=3)``: several smooth
    blobs, some touching the border."""
    from skimage import data

    return drop_small(data.binary_blobs(192, 0.2, volume_fraction=0.3, rng=3))


def blobs_small():
    """``skimage.data.binary_blobs(192, 0.06, volume_fraction=0.1, rng=5)``, regions of at
    least 40 px: many small rings."""
    from skimage import data

    return drop_small(data.binary_blobs(192, 0.06, volume_fraction=0.1, rng=5), 40)


def hubble():
    """``skimage.data.hubble_deep_field()``, rows and columns 200-600, grey > 0.3, regions of
    at least 25 px: galaxies and stars, many small irregular rings."""
    from skimage import data

    g = _grey(data.hubble_deep_field()[200:600, 200:600])
    return drop_small(g > 0.3, 25)


def text():
    """``skimage.data.text()``, columns 0-220, dark pixels (local threshold, block 41,
    offset 15), regions of at least 40 px: handwritten strokes and ruled lines, 2-4 px
    wide, crossing each other."""
    from skimage import data, filters

    g = data.text()[:, :220].astype(float)
    return drop_small(g < filters.threshold_local(g, 41, offset=15), 40)


def page():
    """``skimage.data.page()``, rows 0-150, dark pixels (local threshold, block 35, offset
    10), regions of at least 8 px: a title and six lines of printed text, letters and
    their holes (about 190 rings, 1-3 px apart)."""
    from skimage import data, filters

    g = data.page()[:150].astype(float)
    return drop_small(g < filters.threshold_local(g, 35, offset=10), 8)


def serif():
    """'Rag&' set in DejaVu Serif (ships with matplotlib): serifs, hairlines, holes."""
    return jurs.shapes.glyph_outline("Rag&", family="DejaVu Serif")


def mono():
    """'il1|' set in DejaVu Sans Mono (ships with matplotlib): thin straight strokes, the
    dot of the i, slab serifs."""
    return jurs.shapes.glyph_outline("il1|", family="DejaVu Sans Mono")


#: Case name -> (source function, what it tests).
CASES = {
    "camera": (camera, "photo silhouette, thin parts"),
    "coffee": (coffee, "thin elliptic band (2 close rings)"),
    "rocket": (rocket, "elongated (15:1), fins"),
    "astronaut": (astronaut, "colour segment with holes"),
    "logo": (logo, "smooth S curve, staircase"),
    "mri": (mri, "medical slice, head profile"),
    "terrain": (terrain, "terrain mask, dendritic valleys"),
    "blobs": (blobs, "smooth blobs"),
    "blobs_small": (blobs_small, "many small rings"),
    "hubble": (hubble, "many small irregular rings (photo)"),
    "text": (text, "thin crossing strokes"),
    "page": (page, "2e4 points, ~190 rings of printed text"),
    "serif": (serif, "font: serifs and hairlines"),
    "mono": (mono, "font: thin strokes"),
}


# --------------------------------------------------------------------------- cases


@dataclasses.dataclass(frozen=True)
class Case:
    """One real outline, ready to sample.

    Attributes:
        name: key of ``CASES``.
        source: where it comes from and how it was segmented (the source's docstring).
        traced: True for outlines traced from a pixel mask (staircase), False for fonts.
        raw: the oriented components in pixel units (fonts: their own units).
        components: the same, scaled to size 8 and centred (dense closed polylines).
        pixel: one pixel in the scaled units (fonts: 1/``FONT_PIXELS`` of the size).
        image_shape: the mask's shape (rows, columns), None for fonts.
        length_px: total outline length in pixels.
        m: the number of points sampled.
    """

    name: str
    source: str
    traced: bool
    raw: tuple
    components: tuple
    pixel: float
    image_shape: tuple | None
    length_px: float
    m: int

    @property
    def diag(self) -> float:
        """The bounding-box diagonal of the scaled outline."""
        allp = np.concatenate(self.components)
        return float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))


def outline_length(components) -> float:
    """Total length of closed polylines (first vertex not repeated)."""
    return float(sum(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1).sum() for c in components))


@functools.lru_cache(maxsize=None)
def build(name: str) -> Case:
    """The ``Case`` ``name`` (deterministic; cached)."""
    if name not in CASES:
        raise ValueError(f"unknown case {name!r}; known: {', '.join(CASES)}")
    fn = CASES[name][0]
    data = fn()
    traced = isinstance(data, np.ndarray)
    raw = jurs.shapes.orient(trace(data) if traced else data)
    allp = np.concatenate(raw)
    extent = float(np.max(allp.max(axis=0) - allp.min(axis=0)))
    components = jurs.shapes.normalise(raw, SIZE)
    pixel = SIZE / extent if traced else SIZE / FONT_PIXELS
    length_px = outline_length(components) / pixel
    if name == "page":
        m = MULTI_RING_M
    else:
        m = int(np.clip(round(POINTS_PER_PIXEL * length_px, -2), M_MIN, M_MAX))
    return Case(
        name=name,
        source=" ".join((fn.__doc__ or "").split()),
        traced=traced,
        raw=tuple(raw),
        components=tuple(components),
        pixel=pixel,
        image_shape=tuple(data.shape) if traced else None,
        length_px=length_px,
        m=m,
    )
