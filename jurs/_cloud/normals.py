"""Normals for clouds given without them: local PCA, then a globally consistent outward sign.

[`estimate_normals`][jurs.estimate_normals] runs on the host (NumPy and SciPy), before a fit:

1. **Unsigned normals** by principal component analysis of each point's ``k`` nearest
   neighbours (``scipy.spatial.cKDTree``). ``k`` is chosen from the data: the smallest ``k``
   of a ladder whose normals have a small expected angle error, ``sqrt(noise^2 /
   (k lambda_tangent))`` (median over a subsample; ``noise`` measured on the smallest
   neighbourhoods for curves, at each k's own scale for surfaces), so clean clouds get
   few neighbours and noisy ones as many as their noise needs.
2. **Propagation** of a sign along a minimum spanning tree (after Hoppe et al. 1992) of a
   *tangential* neighbour graph: pairs whose displacement runs along the normal by more
   than the local noise explains (the two sides of a thin part, close components, nested
   rings) are not edges, so no sign is carried across them.
3. **Patches.** The tree's heaviest edges (where neighbouring normals disagree most, where a
   propagation error happens) are cut: the forest falls into patches, each with one sign.
4. **Outward, globally.** Each patch's contribution to the regularised generalised winding
   number (a dipole field: 1 inside, 0 outside, 1/2 on the surface for outward normals) is
   evaluated at the points; the patch signs bring the field at the points to 1/2 in least
   squares (a binary quadratic problem: enumerated when small, else greedy moves from two
   starts). Nested rings, holes and components inside components come out right because
   the field counts enclosure. In 2D the sources are weighted so that noise shrinks the
   field less (a field biased below 1/2 makes the solve flip patches to raise it).
   **Open surfaces** (scans seen from one side) have no inside: a component whose own
   field on its points stays far below 1/2 keeps its propagated signs, with the one
   global sign that makes its own field positive (``_open_parts``); the objective would
   otherwise read pieces under another piece's concave side as enclosed.
5. **Per-point check** against the near field: a point whose field rises outward flips;
   the probes sit outside the noise band (at least three local noise levels away).

What is left wrong at 0.5 % noise in 2D is where the noise is as wide as the gaps (the
horse's legs, the necks of blobs): the tree crosses between the two sides inside a patch,
and the on-surface objective is too noisy to split such patches finer (docs/normals.md).

docs/normals.md gives the reasoning and the measurements; the plain spanning-tree
orientation the benchmark measures beside this method lives with the benchmarks
(``benchmarks/_baselines.py``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import numpy as np
from jaxtyping import ArrayLike, Float
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

from .measure import (
    PROBES,
    check_encloses,
    check_narrow_type,
    check_rounding,
    kd_tree,
    principal_widths,
    query_all,
)
from .parts import agree, gathered_probes, local_rows, spans_processes
from .signs import forest_signs
from .winding import (
    DENSE_PAIRS,
    dipole_kernel,
    patch_fields_clustered,
    patch_fields_dense,
    solve_signs,
)

#: Candidate neighbour counts for PCA, per dimension (the smallest good one is taken).
K_LADDER = {2: (6, 8, 11, 16, 22, 32, 45, 64), 3: (10, 14, 20, 28, 40, 56, 80)}
#: Target for the median expected normal angle error (radians) that picks k.
ANGLE_TARGET = 0.08
#: Whether the choice of k reads the noise at each candidate k (corrected for the
#: neighbourhood cutting the noise's tails off, ``_slab_noise``), per dimension, or
#: on the smallest neighbourhoods. In 3D the smallest neighbourhoods read too little
#: noise where it is as wide as the spacing, and k came out too small; in 2D reading it
#: at each k chose larger k, whose neighbourhoods reach across thin parts and close
#: rings, and lost more than it gained (docs/normals.md, "Method", step 1).
NOISE_AT_SCALE = {2: False, 3: True}
#: Neighbours per point in the orientation graph (at most k).
GRAPH_NEIGHBOURS = {2: 8, 3: 12}
#: A graph edge is dropped when its displacement leans out of the tangent plane by more
#: than this (sine), after the local noise is allowed for.
MAX_NORMAL_LEAN = 0.5
#: Spanning-forest edges cut into patches: at most this many patches...
MAX_PATCHES = 256
#: ... and about one patch per this many points.
POINTS_PER_PATCH = 15
#: Pieces of fewer points are joined to one neighbour (see _rejoin_tiny).
MIN_PATCH = 5
#: Rounds of rejoining, per dimension. In 2D the tree is a path per curve and its heavy
#: edges cluster at corners; in 3D the tiny pieces are leaves all over the tree, and
#: rejoining them left too few patches to undo propagation errors (docs/normals.md,
#: "Method", step 3).
REJOIN_ROUNDS = {2: 6, 3: 0}
#: Width of the field's regularisation, in sample spacings (at least twice the noise).
FIELD_WIDTH = 1.5
#: Points where the field is evaluated (a seeded subsample above this).
MAX_QUERIES = 2000
#: Nearest points whose field enters each point's final sign check.
CHECK_NEIGHBOURS = {2: 96, 3: 64}
#: A point flips only when its field rises outward by more than this (0 to 1 across a
#: surface), per dimension. On noisy surfaces the unguarded check flipped correct points
#: on the noise; on noisy curves a margin cost more correct signs than it saved
#: (docs/performance.md, "Measurements behind the defaults").
CHECK_MARGIN = {2: 0.0, 3: 0.1}
#: Probes of the per-point check sit this many local noise levels from the point at least
#: (else half a field width): probes inside the noise band read the noise, not the side.
#: Clean clouds (noise about 0) are unchanged (docs/normals.md, "Method", step 5).
CHECK_NOISE_OFFSET = 3.0
#: Source weight per dimension: the geometric mean of the confidence and of
#: ``min(1, confidence / median confidence)`` (True), or the raw confidence (False). In
#: 2D noise lowers the raw confidence, which shrank the field of a correctly oriented
#: noisy cloud below 1/2 on its points, and the sign solve then preferred patch flips
#: that raised it. Fully relative weights (``min(1, c / median)``) went further but lost
#: a noisy, unevenly sampled cloud whose sparse stretches have poor normals, which the
#: raw confidence discounts; the geometric mean kept both. In 3D the raw weights did
#: slightly better (docs/normals.md, "Method", step 4, "Weights").
NORMALISED_SOURCES = {2: True, 3: False}
#: A surface component whose own winding field on its points, with its propagated signs,
#: averages under this (relative to its mean source weight; 1/2 on a closed surface) is
#: an open sheet: it keeps the propagated signs with one global sign (``_open_parts``).
OPEN_FIELD = 0.3


class NormalsInfo(NamedTuple):
    """What [`estimate_normals`][jurs.estimate_normals] decided, for ``sol.stats`` and
    diagnostics.

    Attributes:
        k: neighbours per PCA fit.
        components: connected components of the tangential neighbour graph.
        patches: patches whose signs the winding-number field decided.
        flipped: patches whose propagated sign the field reversed.
        corrected: points flipped afterwards by the per-point field check.
        residual: RMS of (winding number - 1/2) at the query points after orientation
            (about 0 on a clean closed surface; larger on noisy or open data).
        confidence: ``(m,)`` per point in [0, 1]: the planarity of its neighbourhood,
            ``1 - lambda_min / lambda_next`` (near 0 where the normal is ill-defined).
        open_components: components read as open sheets (surfaces only): oriented by
            the spanning tree with one sign each, not by the closed-surface objective.
    """

    k: int
    components: int
    patches: int
    flipped: int
    corrected: int
    residual: float
    confidence: np.ndarray
    open_components: int = 0


# --------------------------------------------------------------------------- input


def _check_points(points) -> np.ndarray:
    try:
        array = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"points must be a numeric (m, d) array: {err}") from None
    if array.ndim != 2 or array.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (m, 2) or (m, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError("points contain NaN or infinite coordinates")
    return array


def _minimum_points(d: int) -> int:
    return 2 * d + 1


# --------------------------------------------------------------------------- PCA


def _pca(points: np.ndarray, neighbours: np.ndarray, chunk: int = 20000):
    """Eigen-decomposition of each neighbourhood's covariance: ``(values (m, d) ascending,
    vectors (m, d, d) in columns)``, in chunks to bound memory."""
    m, d = len(neighbours), points.shape[1]
    values, vectors = np.empty((m, d)), np.empty((m, d, d))
    for start in range(0, m, chunk):
        nb = points[neighbours[start : start + chunk]]
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred) / nb.shape[1]
        values[start : start + chunk], vectors[start : start + chunk] = np.linalg.eigh(cov)
    return np.maximum(values, 0.0), vectors


def _expected_angle_error(noise2: np.ndarray, values: np.ndarray, k: int) -> np.ndarray:
    """Standard error (radians) of a PCA normal from ``k`` points: the noise across the
    surface over the tangential spread, over sqrt(k) (a least-squares slope's error)."""
    tangent = values[:, 1:].mean(axis=1) if values.shape[1] == 3 else values[:, 1]
    return np.sqrt(noise2 / (k * np.maximum(tangent, 1e-300)))


@functools.cache
def _slab_table(d: int) -> tuple[np.ndarray, np.ndarray]:
    """``(observed / r, sigma / r)``, ascending: the spread across a flat sheet blurred by
    Gaussian noise ``sigma`` as seen by a ball of radius ``r`` around a point on it (the
    ball's cross-section at height z weighs z by ``(r^2 - z^2)^((d-1)/2)``)."""
    z = np.linspace(-1.0, 1.0, 2001)
    ratio = np.geomspace(1e-3, 30.0, 300)  # sigma / r
    weight = np.exp(-0.5 * (z[None, :] / ratio[:, None]) ** 2) * (1.0 - z**2) ** ((d - 1) / 2)
    observed = np.sqrt(np.sum(weight * z**2, axis=1) / np.sum(weight, axis=1))
    return observed, ratio


def _slab_noise(residual2: np.ndarray, radius: np.ndarray, k: int, d: int) -> np.ndarray:
    """The noise level that explains a PCA residual variance ``residual2`` over ``k``
    points within ``radius``: corrected for the ``d`` degrees of freedom of the fitted
    line/plane and for the ball cutting the noise's tails off (nearest neighbours in a
    cloud whose noise is as wide as its spacing come mostly from near the point's own
    height, so the plain residual reads 2-3x less noise than there is)."""
    observed, ratio = _slab_table(d)
    residual = np.sqrt(residual2 * k / max(k - d, 1))
    return radius * np.interp(residual / np.maximum(radius, 1e-300), observed, ratio)


def _choose_k(points: np.ndarray, tree: cKDTree, rng: np.random.Generator) -> int:
    """The smallest ``k`` of ``K_LADDER`` whose median expected angle error is at most
    ``ANGLE_TARGET`` (if none is, the one of least error), measured on a subsample.

    The noise in the error is, per ``NOISE_AT_SCALE``, the one measured at each ``k``
    (``_slab_noise`` of the residual over those ``k`` neighbours) or the residual over
    the ladder's smallest ``k`` (``_local_noise``), where the other side of a thin part
    is rarely inside. Where a second sheet enters a neighbourhood its residual jumps, and
    so does the error: the least-error fallback does not reach across."""
    m, d = points.shape
    ladder = [k for k in K_LADDER[d] if k < m] or [m - 1]
    sample = rng.choice(m, size=min(m, 2000), replace=False)
    distance, neighbours = tree.query(points[sample], k=ladder[-1] + 1, workers=-1)
    small_noise2 = None if NOISE_AT_SCALE[d] else _local_noise(points, neighbours) ** 2
    errors = []
    for k in ladder:
        values, _ = _pca(points, neighbours[:, : k + 1])
        noise2 = (
            _slab_noise(values[:, 0], distance[:, k], k + 1, d) ** 2
            if small_noise2 is None
            else small_noise2
        )
        errors.append(float(np.median(_expected_angle_error(noise2, values, k + 1))))
        if errors[-1] <= ANGLE_TARGET:
            return k
    return ladder[int(np.argmin(errors))]


def _local_noise(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Each point's RMS residual across its best-fit line/plane through its nearest
    ``K_LADDER[d][0]`` neighbours: the noise (plus curvature) on the smallest scale, where
    the other side of a thin part or a nearby component is rarely inside."""
    small = K_LADDER[points.shape[1]][0]
    values, _ = _pca(points, neighbours[:, : min(small, neighbours.shape[1] - 1) + 1])
    return np.sqrt(values[:, 0])


# --------------------------------------------------------------------------- graph


def _tangential_graph(points, normals, noise, neighbours) -> sparse.csr_matrix:
    """Symmetric neighbour graph with edge weight ``1 - |n_i . n_j| + lean``; ``lean`` is
    how far the displacement leans out of the two tangent planes (sine). Edges leaning more
    than ``MAX_NORMAL_LEAN`` beyond what the local noise explains are dropped: they join
    the two sides of a thin part, or two close components, whose normals are parallel but
    opposed."""
    m, kg = neighbours.shape
    i = np.repeat(np.arange(m), kg)
    j = neighbours.ravel()
    keep = i != j
    i, j = i[keep], j[keep]
    e = points[j] - points[i]
    length = np.linalg.norm(e, axis=1)
    across = 0.5 * (np.abs(np.sum(e * normals[i], 1)) + np.abs(np.sum(e * normals[j], 1)))
    allowed = 2.0 * (noise[i] + noise[j])
    length = np.maximum(length, 1e-300)
    keep = np.maximum(across - allowed, 0.0) / length <= MAX_NORMAL_LEAN
    # The weight counts the whole lean: the tree prefers tangential edges wherever it can.
    align = 1.0 - np.abs(np.sum(normals[i] * normals[j], axis=1))
    weight = (align + across / length)[keep] + 1e-9  # csgraph reads 0 as "no edge"
    graph = sparse.coo_matrix((weight, (i[keep], j[keep])), shape=(m, m)).tocsr()
    return graph.maximum(graph.T)  # pyright: ignore[reportReturnType]  # SciPy is unannotated


def _rejoin_tiny(forest, keep, patch) -> bool:
    """Restore, for every piece of fewer than ``MIN_PATCH`` points, its lightest cut
    edge (in place in ``keep``): heavy edges cluster at corners, and the one-point pieces
    between them give the field no grip. One edge per tiny piece and none for the others,
    so two large pieces are never joined through a chain of tiny ones. Returns whether
    any edge was restored."""
    size = np.bincount(patch)
    cut = np.flatnonzero(~keep)
    ends = np.concatenate([patch[forest.row[cut]], patch[forest.col[cut]]])
    edge = np.concatenate([cut, cut])
    tiny = size[ends] < MIN_PATCH
    ends, edge = ends[tiny], edge[tiny]
    if len(edge) == 0:
        return False
    order = np.lexsort((forest.data[edge], ends))  # by piece, lightest first
    first = np.unique(ends[order], return_index=True)[1]
    keep[edge[order][first]] = True
    return True


def _spanning_patches(graph: sparse.csr_matrix, m: int, d: int):
    """Minimum spanning forest of ``graph``, cut at its heaviest edges into about
    ``m / POINTS_PER_PATCH`` patches (at most ``MAX_PATCHES``), tiny pieces rejoined
    as ``REJOIN_ROUNDS`` says for dimension ``d``. Returns ``(forest,
    component (m,), patch (m,), patch_tree)``: labels, and the forest the cut edges make
    between patches."""
    forest = csgraph.minimum_spanning_tree(graph).tocoo()
    n_comp, component = csgraph.connected_components(forest, directed=False)
    wanted = int(np.clip(m // POINTS_PER_PATCH, n_comp, max(MAX_PATCHES, n_comp)))
    cuts = min(wanted - n_comp, len(forest.data))
    keep = np.ones(len(forest.data), bool)
    if cuts > 0:
        keep[np.argpartition(forest.data, -cuts)[-cuts:]] = False
    rounds = REJOIN_ROUNDS[d]
    for _ in range(rounds + 1):
        pieces = sparse.coo_matrix(
            (forest.data[keep], (forest.row[keep], forest.col[keep])), shape=(m, m)
        )
        n_patch, patch = csgraph.connected_components(pieces, directed=False)
        if _ == rounds or not _rejoin_tiny(forest, keep, patch):
            break
    cut = ~keep
    patch_tree = sparse.coo_matrix(
        (np.ones(int(cut.sum())), (patch[forest.row[cut]], patch[forest.col[cut]])),
        shape=(n_patch, n_patch),
    ).tocsr()
    return forest.tocsr(), component, patch, patch_tree


# --------------------------------------------------------------------------- API
# (the patches' signs are chosen in jurs._cloud.winding)


def estimate_normals(
    points: Float[ArrayLike, "m d"],
    *,
    k: int | None = None,
    orient: bool = True,
    return_info: bool = False,
    seed: int = 0,
) -> Float[np.ndarray, "m d"] | tuple[Float[np.ndarray, "m d"], NormalsInfo]:
    """Outward unit normals of a point cloud sampling closed curves (2D) or surfaces (3D),
    or open surfaces (scans seen from one side: one consistent side each, pointing away
    from the side their curvature encloses).

    Local PCA over ``k`` nearest neighbours, a sign propagated along a minimum spanning tree
    of a tangential neighbour graph (no edges across thin parts), then patch signs chosen
    so the generalised winding number is 1 inside and 0 outside (see the module
    docstring and docs/normals.md). Host-side NumPy/SciPy; deterministic for a given
    ``seed`` (used only to subsample large clouds).

    Args:
        points: ``(m, 2)`` or ``(m, 3)`` coordinates, finite.
        k: neighbours per PCA fit (default: chosen from the data's noise, 6-64 in 2D,
            10-80 in 3D). Must be at least ``d`` and below the number of distinct points.
        orient: ``False`` returns the unsigned PCA normals (arbitrary sign per point).
        return_info: also return a ``NormalsInfo``.
        seed: seed of the subsampling (choice of k; field query points above 2000 points).

    Returns:
        ``normals`` ``(m, d)`` float64 unit vectors pointing out of the enclosed region
        (into the hole on the boundary of a hole), or ``(normals, info)``. Repeated points
        get the same normal.

    Raises:
        TypeError: ``points`` is not numeric.
        ValueError: wrong shape, NaN/inf, fewer than ``2 d + 1`` distinct points, points
            on a line or in a plane (no side of them is outward), float32 points whose
            rounding exceeds 1e-4 of their extent or made them repeat, or a bad ``k``.

    Points held by several processes (a global ``jax.Array`` no process holds whole):
    every process calls this and gets a global array of the normals, split like the
    points (``normals_across_processes``, below, docs/sharding.md); no
    ``return_info`` there.
    """
    if spans_processes(points):
        if return_info:
            raise ValueError("return_info: not over several processes (docs/sharding.md)")
        return normals_across_processes(points, k, orient, seed)  # pyright: ignore[reportReturnType]
    array = _check_points(points)
    check_narrow_type(array, getattr(points, "dtype", np.float64))
    d = array.shape[1]
    unique, inverse = np.unique(array, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    m = len(unique)
    if m < len(array):  # repeats made by the rounding of a narrow float type are refused
        check_rounding(array, getattr(points, "dtype", np.float64), len(array) - m)
    if m < _minimum_points(d):
        raise ValueError(
            f"points must hold at least {_minimum_points(d)} distinct points "
            f"in {d}D, got {m} (of {len(array)})"
        )
    widths = principal_widths(unique)
    if widths[0] < 0.25 * widths[-1]:  # on a line or in a plane: no outward side
        spacing = float(np.median(cKDTree(unique).query(unique, k=2, workers=-1)[0][:, 1]))
        check_encloses(unique, widths, spacing)
    # Normals do not change with a translation or a uniform scaling: the cloud is moved
    # to its box's centre and to unit size, so that far from the origin (1e7) the
    # winding field's sums keep their precision (they lost it: 16 % of a circle's
    # normals came out flipped there).
    lower, upper = unique.min(axis=0), unique.max(axis=0)
    unique = (unique - 0.5 * (lower + upper)) / float(np.max(upper - lower))
    if k is not None and (int(k) != k or not d <= int(k) < m):
        raise ValueError(f"k must be an integer in [{d}, {m - 1}] here, got {k}")
    rng = np.random.default_rng(seed)
    tree = cKDTree(unique)
    k = _choose_k(unique, tree, rng) if k is None else int(k)
    _, neighbours = query_all(tree, unique, k + 1)
    values, vectors = _pca(unique, neighbours)
    normals = vectors[:, :, 0]
    noise = _local_noise(unique, neighbours)
    # At a thin part the smallest neighbourhood may still hold both sides: no point's noise
    # is taken above twice the cloud's median.
    noise = np.minimum(noise, 2.0 * np.median(noise))
    confidence = 1.0 - values[:, 0] / np.maximum(values[:, 1], 1e-300)
    info = NormalsInfo(k, 0, 0, 0, 0, float("nan"), confidence[inverse])
    if orient:
        normals, stats = _orient(unique, normals, values, noise, neighbours, tree, rng, confidence)
        info = info._replace(**stats)
    return (normals[inverse], info) if return_info else normals[inverse]


def _source_weight(confidence: np.ndarray, d: int) -> np.ndarray:
    """Weight of each point's dipole in the field (``NORMALISED_SOURCES``): in 2D
    ``sqrt(confidence min(1, confidence / median confidence))``, which discounts points
    less planar than the cloud's typical one but shrinks the field of a noisy cloud much
    less than the confidence itself; in 3D the confidence."""
    if not NORMALISED_SOURCES[d]:
        return confidence
    relative = np.minimum(1.0, confidence / max(float(np.median(confidence)), 1e-12))
    return np.sqrt(confidence * relative)


def _orient(points, normals, values, noise, neighbours, tree, rng, confidence):
    """Steps 2-5 of the module docstring: ``(outward normals, stats for NormalsInfo)``.

    Weights: a query counts by its ``confidence`` (planarity), a source by
    ``_source_weight``."""
    m, d = points.shape
    graph_k = min(GRAPH_NEIGHBOURS[d], neighbours.shape[1] - 1)
    graph = _tangential_graph(points, normals, noise, neighbours[:, : graph_k + 1])
    forest, component, patch, patch_tree = _spanning_patches(graph, m, d)
    normals = normals * forest_signs(forest, normals)[:, None]
    # Start each component pointing away from its centroid (a guess the field corrects).
    n_comp, n_patch = int(component.max()) + 1, int(patch.max()) + 1
    centroid = np.stack([np.bincount(component, points[:, a]) for a in range(d)], 1)
    centroid /= np.bincount(component)[:, None]
    away = np.bincount(component, np.sum((points - centroid[component]) * normals, 1), n_comp)
    normals = normals * np.where(away[component] < 0, -1.0, 1.0)[:, None]
    # Length per point (2D) from the tangential spread of its PCA neighbourhood, which
    # noise across the curve does not shrink; area per point (3D) from the k-th neighbour
    # distance. Field width from the spacing and the noise.
    k = neighbours.shape[1]
    if d == 2:
        area = 2.0 * np.sqrt(3.0 * values[:, 1]) / k
    else:  # pi r_k^2 / k: unbiased for uniform random samples (the PCA spread is not)
        r_k = np.linalg.norm(points[neighbours[:, -1]] - points, axis=1)
        area = np.pi * r_k**2 / (k - 1)
    spacing = query_all(tree, points, min(d + 1, m))[0][:, -1]  # ~ sample spacing
    eps = np.maximum(FIELD_WIDTH * spacing, 2.0 * noise)
    weight = confidence  # as a query
    source = _source_weight(confidence, d)
    dipoles = normals * (area * source)[:, None]
    queries = (
        np.arange(m) if m <= MAX_QUERIES else np.sort(rng.choice(m, MAX_QUERIES, replace=False))
    )
    if len(queries) * m <= DENSE_PAIRS:
        fields = patch_fields_dense(points[queries], points, dipoles, eps, patch, n_patch)
    else:
        fields = patch_fields_clustered(points[queries], points, dipoles, eps, patch, n_patch, tree)
    centre = np.stack([np.bincount(patch, points[:, a], n_patch) for a in range(d)], 1)
    centre /= np.bincount(patch, minlength=n_patch)[:, None]
    signs = solve_signs(fields, weight[queries], patch_tree, centre)
    signs, open_parts = _open_parts(
        fields, weight[queries], signs, patch, component, source, queries, d
    )
    residual = float(
        np.sqrt(np.average((fields @ signs - 0.5) ** 2, weights=weight[queries] + 1e-300))
    )
    normals = normals * signs[patch][:, None]
    offset = np.maximum(0.5 * eps, CHECK_NOISE_OFFSET * noise)
    normals, corrected = _point_corrections(
        points, normals, area * weight, eps, offset, tree, neighbours
    )
    return normals, dict(
        corrected=corrected,
        components=n_comp,
        patches=n_patch,
        flipped=int(np.sum(signs < 0)),
        residual=residual,
        open_components=open_parts,
    )


def _open_parts(fields, weight, signs, patch, component, source, queries, d):
    """Components that are open sheets (scans seen from one side), and their signs:
    ``(patch signs, number of open components)``.

    The winding-number objective assumes closed surfaces: a closed one's own field is 1/2
    on its points, whatever else is around. An open sheet's own field there is well
    below 1/2 (0 on a flat sheet, about 0.15 on the top of a scanned body), and another
    open piece's field adds to it: a piece lying under the concave side of a larger one
    (legs under a body scanned from above) reads as enclosed and comes out flipped, and
    within a sheet patches flip to pull the field towards 1/2. So a component whose own
    field, with its propagated (consistent) signs, averages under ``OPEN_FIELD`` of its
    mean source weight (the weights shrink the field of a noisy cloud; relative to them
    closed surfaces read 0.44-0.51 and open scans 0.01-0.2, docs/normals.md) keeps the
    propagated signs, with the one global sign that makes its own field positive:
    outward on the side its curvature turns away from (the dipoles of a cap point away
    from its centre). A flat sheet's field is about 0 either way and its sign arbitrary.
    Curves (``d`` = 2) are left to the closed objective. ``fields`` ``(Q, P)``: each
    patch's field at the ``queries``; ``weight``: the queries'; ``signs``: the closed
    solve's; ``source``: each point's source weight."""
    n_comp, n_patch = int(component.max()) + 1, int(patch.max()) + 1
    if d != 3:
        return signs, 0
    comp_of_patch = np.zeros(n_patch, np.int64)
    comp_of_patch[patch] = component
    at = component[queries]
    own = np.sum(np.where(comp_of_patch[None, :] == at[:, None], fields, 0.0), axis=1)
    total = np.bincount(at, weight, n_comp)
    mean_field = np.bincount(at, weight * own, n_comp) / np.maximum(total, 1e-300)
    strength = np.bincount(component, source, n_comp) / np.bincount(component, minlength=n_comp)
    level = np.abs(mean_field) / np.maximum(strength, 1e-300)
    is_open = (level < OPEN_FIELD) & (total > 0)
    outward = np.where(mean_field < 0, -1.0, 1.0)
    signs = np.where(is_open[comp_of_patch], outward[comp_of_patch], signs)
    return signs, int(is_open.sum())


def _point_corrections(points, normals, area, eps, offset, tree, neighbours, rounds: int = 6):
    """Per-point sign check against the field (as WNNC iterates): the winding number (width
    ``eps``) must fall outward, ``w(p + delta n) < w(p - delta n)`` with delta = ``offset``
    (half the field width, or ``CHECK_NOISE_OFFSET`` local noise levels where that is
    more); points where it rises are flipped. Only the nearest ``CHECK_NEIGHBOURS``
    points enter the difference: far sources add almost the same to both sides. Repairs
    the stretches a patch's propagation got wrong, from their ends inward over the rounds.
    ``neighbours`` (each point's nearest, itself first, as the PCA's) serve where they
    are enough (noisy 3D clouds: k + 1 = 81), which saves a second neighbour query
    (docs/normals.md, "Measurements").
    Returns ``(normals, points flipped)``."""
    m, d = points.shape
    count = min(CHECK_NEIGHBOURS[d], m)
    flipped = np.zeros(m, bool)
    normals = normals.copy()
    if neighbours.shape[1] >= count:
        near_all = neighbours[:, :count]
    else:
        near_all = query_all(tree, points, count)[1]
    check = np.arange(m)
    for _ in range(rounds):
        dipoles = normals * area[:, None]
        rising = np.zeros(m, bool)
        for s in range(0, len(check), MAX_QUERIES):
            idx = check[s : s + MAX_QUERIES]
            near = near_all[idx]
            delta = (offset[idx, None] * normals[idx])[:, None, :]
            src, dip, e = points[near], dipoles[near], eps[near]
            outside = dipole_kernel(points[idx, None, :] + delta, src, dip, e).sum(1)
            inside = dipole_kernel(points[idx, None, :] - delta, src, dip, e).sum(1)
            rising[idx] = outside - inside > CHECK_MARGIN[d]
        if not rising.any():
            break
        normals[rising] *= -1.0
        flipped ^= rising
        check = np.flatnonzero(rising[near_all].any(axis=1))  # only where something moved
    return normals, int(flipped.sum())


def normals_across_processes(points, k=None, orient=True, seed=0, most: int = PROBES):
    """[`jurs.estimate_normals`][] of a cloud whose rows the global array ``points``
    spreads over several processes: a global array of outward unit normals, split like
    the points. Every process calls it.

    At most ``most`` (``PROBES``) points: the cloud is all-gathered and every process estimates its
    normals as one process does (the same normals exactly), keeping its own rows'.
    More: ``most`` strided points are gathered and their normals estimated and
    oriented there (the whole shape, sparser); each process estimates the unsigned
    normals of its own rows (local PCA over its own points: at the edge of its part a
    neighbourhood holds only the points on its side, no halo) and takes each point's
    sign from its nearest gathered point's oriented normal."""
    rows, p = local_rows(points)
    p = np.asarray(p, float)
    total = int(points.shape[0])
    held, sample = gathered_probes(rows, p, total, most)
    oriented = estimate_normals(sample, k=k, orient=orient, seed=seed)
    assert isinstance(oriented, np.ndarray)
    if len(held) == total:  # the whole cloud: this process's rows of its normals
        mine = oriented[np.searchsorted(held, rows)]
    else:
        failure, mine = None, None
        try:  # this process's own rows: an error here is raised in every process
            mine = estimate_normals(p, k=k, orient=False, seed=seed)
        except (TypeError, ValueError) as error:
            failure = type(error)(f"process {jax.process_index()}, its own part: {error}")
        agree(failure, "estimating its normals")
        assert isinstance(mine, np.ndarray)
        if orient:
            nearest = kd_tree(sample).query(p)[1]
            flip = np.sum(mine * oriented[nearest], axis=1) < 0
            mine = np.where(flip[:, None], -mine, mine)
    mine = np.ascontiguousarray(mine.astype(points.dtype))
    return jax.make_array_from_process_local_data(points.sharding, mine, tuple(points.shape))
