"""Measurements of a point cloud on the host, in data units: the spacing of its points, the
noise about a smooth curve or surface, which side of the tangent the offsets land, and the
width of thin parts and narrow gaps. [`jurs.auto_settings`][] chooses from them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # SciPy's spatial module loads on the first fit, not on import
    # SciPy ships no stub for its compiled cKDTree, so a type checker sees no such class;
    # KDTree, its pure-Python subclass with the same query(), stands in for it here.
    from scipy.spatial import KDTree as cKDTree

#: Clouds above this many points are measured and checked at this many of them, evenly
#: strided over their order (the same points wherever the cloud is placed): the settings'
#: measurements, the orientation check and the doubt checks all read one such subsample.
#: Their medians and fractions settle well below it; neighbour searches past it cost time
#: that grows with the cloud and buys nothing.
PROBES = 20_000


#: Neighbours used for the noise estimate (the point itself included).
NOISE_NEIGHBOURS = 16


def kd_tree(points: np.ndarray) -> cKDTree:
    """``scipy.spatial.cKDTree(points)``, with SciPy's spatial module imported on first use."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]

    return cKDTree(points)


def query_all(tree: cKDTree, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(points, k, workers=-1)`` (``(dist, index)``, each ``(m, k)``) of the
    tree's own ``points``, queried in the tree's leaf order and returned in theirs.

    Why: queries in a cloud's own order (random on a scan) walk the whole tree for each
    point; in leaf order consecutive queries read the same nodes: more than twice as fast
    on a large scan, the same results (docs/performance.md). Any order gives the same
    answers, so ``points`` other than the tree's (of its size) are queried correctly too."""
    order = tree.indices if len(points) == tree.n else np.arange(len(points))
    dist, index = tree.query(points[order], k=k, workers=-1)
    dist, index = (
        np.asarray(dist).reshape(len(points), -1),
        np.asarray(index).reshape(len(points), -1),
    )
    out_dist, out_index = np.empty_like(dist), np.empty_like(index)
    out_dist[order], out_index[order] = dist, index
    return out_dist, out_index


def strided_probes(count: int, most: int) -> np.ndarray | None:
    """Indices of at most ``most`` of ``count`` points, evenly strided over their order (the
    same points wherever the cloud is placed); None where all ``count`` fit."""
    return None if count <= most else np.linspace(0, count - 1, most).round().astype(int)


def _probe(points: np.ndarray, at) -> np.ndarray:
    return np.arange(len(points)) if at is None else np.asarray(at)


def point_spacing(points: np.ndarray, tree: cKDTree | None = None, at=None) -> float:
    """Median distance from a point to its nearest other point (duplicates skipped),
    over the points indexed by ``at`` (default all)."""
    tree = kd_tree(points) if tree is None else tree
    dist = tree.query(points[_probe(points, at)], k=min(len(points), 4))[0][:, 1:]
    dist = np.where(dist > 0, dist, np.inf).min(axis=1)
    finite = dist[np.isfinite(dist)]
    if finite.size == 0:
        raise ValueError("all points coincide; the cloud has no extent")
    return float(np.median(finite))


def _tangent_frame(rel: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``(probes, d, d)`` principal frames of the kept neighbours ``rel (probes, k, d)``
    (centred): the rows are the covariance's eigenvectors, largest first, so the last row
    is the direction across the curve or surface."""
    cov = np.matmul((keep[:, :, None] * rel).transpose(0, 2, 1), rel)
    return np.linalg.eigh(cov)[1][:, :, ::-1].transpose(0, 2, 1)


def _quadratic_terms(u: np.ndarray) -> np.ndarray:
    """``1``, the tangent coordinates ``u (probes, k, d - 1)`` and their products of degree
    two: the terms of a quadratic height function; ``(probes, k, terms)``."""
    dims = u.shape[-1]
    products = [u[..., i] * u[..., j] for i in range(dims) for j in range(i, dims)]
    return np.concatenate([np.ones(u.shape[:-1] + (1,)), u, np.stack(products, -1)], axis=-1)


def estimate_noise(
    points: np.ndarray,
    normals: np.ndarray,
    tree: cKDTree | None = None,
    neighbours: int = NOISE_NEIGHBOURS,
    at=None,
) -> float:
    """Positional noise sigma: the median over points of the RMS residual of a quadratic
    height ``v = q(u)`` fitted, in the principal frame of the point's ``neighbours``
    nearest same-facing neighbours (normals within 60 degrees), to those neighbours: ``u``
    the coordinate along the curve (the two tangent coordinates on a surface), ``v`` the
    one across. The quadratic absorbs the curvature, so clean samples of a smooth curve or
    surface give about 0; the residual divides by the neighbours less the quadratic's
    terms (3 in 2D, 6 in 3D), so it is unbiased for independent noise. The median ignores
    corners and the ends of a gap. Measured at the points indexed by ``at`` (default all),
    with neighbours from the whole cloud."""
    rms = noise_residuals(points, normals, tree, neighbours, at)
    return float(np.median(rms)) if rms.size else 0.0


def noise_residuals(
    points: np.ndarray,
    normals: np.ndarray,
    tree: cKDTree | None = None,
    neighbours: int = NOISE_NEIGHBOURS,
    at=None,
) -> np.ndarray:
    """``estimate_noise``'s RMS residual at every probe with enough same-facing
    neighbours (twice the quadratic's terms), before the median: a fit over several
    processes takes the median of all processes' residuals."""
    at = _probe(points, at)
    k = min(len(points), neighbours)
    tree = kd_tree(points) if tree is None else tree
    idx = tree.query(points[at], k=k)[1]
    nb = points[idx]  # (probes, k, d)
    # Plain broadcasts and sums below: NumPy's einsum runs these small contractions
    # several times slower (docs/performance.md, "Measurements behind the defaults").
    keep = ((normals[idx] * normals[at][:, None, :]).sum(axis=2) > 0.5).astype(float)
    count = keep.sum(axis=1)
    centre = (keep[:, :, None] * nb).sum(axis=1) / np.maximum(count, 1)[:, None]
    rel = nb - centre[:, None, :]
    frame = _tangent_frame(rel, keep)
    local = np.matmul(rel, frame.transpose(0, 2, 1))  # (probes, k, d): tangent..., across
    u, v = local[..., :-1], local[..., -1]
    # Scale u to unit RMS so the powers stay conditioned (and finite where all coincide).
    scale = np.sqrt((keep[:, :, None] * u * u).sum(axis=(1, 2)) / np.maximum(count, 1))
    scale = np.where(scale > 0, scale, 1.0)
    basis = _quadratic_terms(u / scale[:, None, None])  # (probes, k, terms)
    terms = basis.shape[-1]
    weighted = keep[:, :, None] * basis
    gram = np.matmul(weighted.transpose(0, 2, 1), basis)  # (probes, terms, terms)
    rhs = (weighted * v[:, :, None]).sum(axis=1)
    ok = count >= 2 * terms
    gram[~ok] = np.eye(terms)
    coef = np.linalg.solve(gram + 1e-12 * np.eye(terms), rhs[..., None])[..., 0]
    resid = v - (basis * coef[:, None, :]).sum(axis=2)
    rms = np.sqrt((keep * resid * resid).sum(axis=1) / np.maximum(count - terms, 1))
    return rms[ok]


def offset_agreement(
    points: np.ndarray, normals: np.ndarray, offset, tree: cKDTree | None = None, at=None
):
    """Fraction of the 2m offset samples ``P_i +/- d n_i`` that lie on their intended side
    (outside for ``+``, inside for ``-``) of the tangent line of their nearest data point
    other than ``P_i``.

    It is low for small d on noisy data (a neighbour's noise is larger than d) and for large
    d where the offsets cross a thin part of the shape or the gap between two parts (they
    land nearer the far side and read the wrong side there); in between it is near 1.
    Measured for the points indexed by ``at`` (default all). ``offset`` may be a 1-D array
    of offsets (one KD-tree query for all of them); then so is the result.
    """
    tree = kd_tree(points) if tree is None else tree
    own = _probe(points, at)
    offsets = np.asarray(offset, float)
    # (offsets, sign, probes): +d then -d for every offset.
    signed = offsets.reshape(-1, 1, 1) * np.array([1.0, -1.0]).reshape(1, 2, 1)
    q = points[own] + signed[..., None] * normals[own]
    idx = tree.query(q.reshape(-1, points.shape[1]), k=2)[1].reshape(q.shape[:3] + (2,))
    j = np.where(idx[..., 0] == own, idx[..., 1], idx[..., 0])
    side = ((q - points[j]) * normals[j]).sum(axis=-1)
    agreement = (signed * side > 0).mean(axis=(1, 2))
    return agreement.reshape(offsets.shape) if offsets.ndim else float(agreement[0])


def feature_width(
    points: np.ndarray,
    normals: np.ndarray,
    radius: float,
    spacing: float,
    at=None,
    tree: cKDTree | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(width, partner)`` per probe point (``at``, default all): the distance to the
    nearest point whose normal faces the other way (more than 120 degrees apart), within
    ``radius`` (inf where there is none), and that point's index (-1 where none).

    On a thin part of the shape it is the part's width at that point, on the far side of a
    narrow gap the gap's: the features a grid must resolve. Clouds much denser than the
    radius are thinned to about 16 points a radius first (by stride: only the nearest
    opposite point matters, and 64 neighbours must reach across). ``tree``: one of
    ``points`` the caller has, used where none are thinned out."""
    own = _probe(points, at)
    stride = max(1, min(int(radius / (16.0 * spacing)), len(points) // 64))
    keep = np.arange(0, len(points), stride)
    if stride > 1 or tree is None:
        tree = kd_tree(points[keep])
    k = min(len(keep), 64)
    # k as a list: 2-D results even for k = 1 (SciPy's stub types k as an int only).
    ks = list(range(1, k + 1))
    dist, idx = tree.query(points[own], k=ks, distance_upper_bound=radius)  # pyright: ignore[reportArgumentType]
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    facing = (normals[keep][idx] * normals[own][:, None, :]).sum(axis=-1)
    dist = np.where(found & (facing < -0.5), dist, np.inf)
    nearest = np.argmin(dist, axis=1)
    width = np.take_along_axis(dist, nearest[:, None], axis=1)[:, 0]
    partner = np.where(
        np.isfinite(width), keep[np.take_along_axis(idx, nearest[:, None], 1)[:, 0]], -1
    )
    return width, partner


def repeated_points(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(first, group)`` for a cloud with exact repeats, None where every point is
    distinct: ``first`` the index of each distinct point's first occurrence, in the
    cloud's order, and ``group (m,)`` the position in ``first`` of each point's copy.

    One sort of the first coordinate rules repeats out for most clouds (any repeated
    point repeats its x); only a cloud with repeated x values pays for the sort of its
    rows."""
    x = np.sort(points[:, 0])
    if not (x[1:] == x[:-1]).any():
        return None
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(points):
        return None
    order = np.argsort(first)  # the distinct points in the order they first occur
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[np.ravel(inverse)]


#: A cloud narrower than this many point spacings across a principal direction (its
#: central 98 %: a few stray points do not give it a thickness) samples no closed
#: surface (in 2D no closed curve) there: it lies in a plane or on a line. Two sheets
#: of a thin part closer than a spacing make the spacing that close too, so a real
#: closed shape is never this flat.
FLAT_SPACINGS = 0.5


def principal_widths(points: np.ndarray, at=None) -> np.ndarray:
    """``(d,)`` widths of the cloud along its principal directions, narrowest first:
    the spread of the central 98 % of the points (those indexed by ``at``, default all)
    along each eigenvector of their covariance."""
    p = points[_probe(points, at)]
    centred = p - p.mean(axis=0)  # differences first: exact far from the origin too
    vectors = np.linalg.eigh(centred.T @ centred)[1]  # ascending variance
    lo, hi = np.percentile(centred @ vectors, [1.0, 99.0], axis=0)
    return hi - lo


def check_encloses(points: np.ndarray, widths: np.ndarray, spacing: float) -> None:
    """ValueError naming the cause when the cloud, of principal ``widths`` (narrowest
    first, ``principal_widths``) and point ``spacing``, lies on a line or in a plane
    (``FLAT_SPACINGS``): it encloses no area (2D) or volume (3D), and a fit or an
    orientation of its normals would invent one."""
    d = points.shape[1]
    flat = int(np.sum(widths < FLAT_SPACINGS * spacing))
    if flat == 0:
        return
    where = "on a line" if d - flat <= 1 else "in a plane"
    encloses = "a closed curve encloses an area" if d == 2 else "a closed surface encloses a volume"
    hint = (
        "; for the outline of a planar shape pass its two in-plane coordinates (a 2D curve)"
        if where == "in a plane"
        else ""
    )
    raise ValueError(
        f"points lie {where}: they spread {widths[flat - 1]:.3g} across it, under "
        f"{FLAT_SPACINGS} x their spacing {spacing:.3g}, and {encloses}{hint}"
    )


#: Points given in a float type narrower than float64 are refused where the type's step
#: at their largest coordinate exceeds this share of the cloud's bounding-box diagonal
#: (the rule of ``jurs.datasets.FLOAT32_RESOLUTION`` for files): a fit's cells are a few
#: hundredths of the diagonal, and rounding of 1e-4 is far below them.
NARROW_RESOLUTION = 1e-4


def check_narrow_type(points: np.ndarray, dtype) -> None:
    """ValueError where ``points`` (as float64) were given in a float type narrower than
    float64 (``dtype``) whose step at their largest coordinate exceeds
    ``NARROW_RESOLUTION`` of their extent: a georeferenced cloud (coordinates about 1e6 m)
    in float32 is rounded to 0.06-0.5 m steps, which moves its points by a share of a
    fit's cells that no later check can tell from the data (a 2 m sphere at [6.5e5, 5.4e6,
    300] came back "inconsistent_normals"; other clouds fit silently wrong)."""
    dtype = np.dtype(dtype)
    if dtype.kind != "f" or dtype.itemsize >= 8 or len(points) == 0:
        return
    big = float(np.max(np.abs(points)))
    step = float(np.spacing(np.asarray(big, dtype)))
    extent = float(np.linalg.norm(np.ptp(points, axis=0)))
    if step > NARROW_RESOLUTION * extent:
        raise ValueError(
            f"points are {dtype.name}, which at |x| = {big:.3g} resolves only steps of "
            f"{step:.3g}, more than {NARROW_RESOLUTION:g} of the cloud's extent "
            f"{extent:.3g}: the rounding has already moved the points. Pass them in "
            "float64 (read the file as float64), or translate the cloud near the origin "
            "in float64 before converting"
        )


def check_rounding(points: np.ndarray, dtype, repeated: int) -> None:
    """ValueError where ``points`` given in a float type narrower than float64 repeat
    each other because of its rounding: the type's step at the cloud's largest
    coordinate is more than 1e-4 of its extent (float32 at 1e7 steps by 1), so the
    repeats are the type's, not the data's."""
    dtype = np.dtype(dtype)
    if dtype.kind != "f" or dtype.itemsize >= 8:
        return
    big = float(np.max(np.abs(points)))
    step = float(np.spacing(np.asarray(big, dtype)))
    extent = float(np.linalg.norm(np.ptp(points, axis=0)))
    if step > 1e-4 * extent:
        raise ValueError(
            f"points are {dtype.name}, which at |x| = {big:.3g} resolves only steps of "
            f"{step:.3g}: its rounding made {repeated} of the {len(points)} points repeat "
            "others. Pass them in float64 (read the file as float64, or translate the "
            "cloud near the origin before converting)"
        )
