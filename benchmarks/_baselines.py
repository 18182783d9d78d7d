"""What a Python user would run instead of jurs, measured on the same samples.

``rbf_fit`` is ``scipy.interpolate.RBFInterpolator`` with the thin-plate-spline kernel on the
same 3m offset samples and targets as jurs (eq. 4-5: ``[P, P + d n, P - d n] -> [0, +eps,
-eps]``): a global dense solve of size 3m (+3 polynomial terms), O(m^3) time and O(m^2)
memory. ``smoothing > 0`` turns interpolation into a smoothing fit (for noisy data).

``rbf_report`` measures the RBF's zero set with the same level-set analysis as jurs fits, on
the same box and grid, so Chamfer distances and supplementary counts compare like for like;
``rbf_grid_values`` evaluates the RBF on that grid adaptively, exactly wherever the zero set
can pass.

``orient_mst`` is the plain spanning-tree orientation of normals (Hoppe et al. 1992), the
baseline ``benchmarks/normals.py`` measures beside ``jurs.estimate_normals``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import sparse
from scipy.interpolate import RBFInterpolator
from scipy.ndimage import binary_dilation, maximum_filter
from scipy.sparse import csgraph
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

import jurs
import jurs.levelset
from jurs._cloud.signs import forest_signs  # the library's one sign routine


def offset_samples(points, normals, offset: float, eps: float):
    """jurs's own samples and targets (eq. 4-5) as NumPy arrays, normals normalised first."""
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    samples, targets = jurs.internal.offset_samples(points, normals, offset, eps)
    return np.asarray(samples, float), np.asarray(targets, float)


def rbf_fit(points, normals, *, offset: float, eps: float, smoothing: float = 0.0):
    """Thin-plate RBF through the offset samples. Returns ``(interpolator, seconds)``; the
    time is the fit (the dense solve), not the evaluation."""
    samples, targets = offset_samples(points, normals, offset, eps)
    t0 = time.perf_counter()
    rbf = RBFInterpolator(samples, targets, kernel="thin_plate_spline", smoothing=smoothing)
    return rbf, time.perf_counter() - t0


def evaluate_rbf(rbf, xy, chunk: int = 4096) -> np.ndarray:
    """``rbf`` at ``xy (n, 2)`` in chunks (the kernel matrix of a chunk is chunk x 3m, so
    memory stays bounded)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) == 0:
        return np.empty(0)
    return np.concatenate([rbf(xy[k : k + chunk]) for k in range(0, len(xy), chunk)])


def evaluate_rbf_grid(rbf, xs, ys, chunk: int = 4096) -> np.ndarray:
    """``values[j, i] = rbf(xs[i], ys[j])`` (``evaluate_rbf`` on the grid's nodes)."""
    gx, gy = np.meshgrid(xs, ys)
    return evaluate_rbf(rbf, np.stack([gx.ravel(), gy.ravel()], axis=1), chunk).reshape(gx.shape)


def rbf_grid_values(fn, xs, ys, coarse: int = 8, safety: float = 1.0, chunk: int = 4096):
    """Values of ``fn`` on the analysis grid ``xs x ys``, exact wherever the zero set can pass.

    A full 512-node grid costs 2.6e5 RBF evaluations of 3m kernel terms each, and the
    smoothing ladder of ``benchmarks/quality.py`` needs several fits per case, so the grid is
    refined adaptively, quadtree-style: exact values on every
    ``coarse``-th node; a cell is split (exact values on the half-step lattice inside it) when
    its corners change sign or the smallest corner |value| is at most ``safety`` times the
    largest corner-to-corner variation among it and its 8 neighbours, and then its 8
    neighbours are split too; down to single grid cells. Cells never split have all corners
    of one sign and far from 0 relative to the local variation; their inner nodes get the
    bilinear interpolant of their corners (same sign, so no zero crossing is lost). Every
    grid cell the zero set crosses therefore has exact corner values, and the contour is the
    one ``rbf_report`` draws from the full grid: ``benchmarks/quality.py`` checks this on
    the runs in its ``CHECKS_*`` (signs at every grid node, component counts, Chamfer and
    Hausdorff distances).

    Returns ``(values (len(ys), len(xs)), number of exact evaluations)``.
    """
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    nx, ny = len(xs), len(ys)
    big_x = -(-(nx - 1) // coarse) * coarse + 1  # grid extended to a multiple of coarse
    big_y = -(-(ny - 1) // coarse) * coarse + 1
    gx = xs[0] + (xs[1] - xs[0]) * np.arange(big_x)
    gy = ys[0] + (ys[1] - ys[0]) * np.arange(big_y)
    gx[:nx], gy[:ny] = xs, ys
    vals = np.zeros((big_y, big_x))
    known = np.zeros((big_y, big_x), bool)
    count = 0

    def evaluate(jj, ii):
        nonlocal count
        keep = ~known[jj, ii]
        jj, ii = jj[keep], ii[keep]
        if len(jj):
            pts = np.stack([gx[ii], gy[jj]], axis=1)
            vals[jj, ii] = np.concatenate(
                [
                    np.asarray(fn(pts[k : k + chunk]), float).reshape(-1)
                    for k in range(0, len(pts), chunk)
                ]
            )
            known[jj, ii] = True
            count += len(jj)

    jj, ii = np.meshgrid(np.arange(0, big_y, coarse), np.arange(0, big_x, coarse), indexing="ij")
    evaluate(jj.ravel(), ii.ravel())
    active = np.ones(((big_y - 1) // coarse, (big_x - 1) // coarse), bool)
    step = coarse
    while step >= 2:
        cj, ci = np.nonzero(active)
        j0, i0 = cj * step, ci * step
        corners = np.stack(
            [vals[j0, i0], vals[j0, i0 + step], vals[j0 + step, i0], vals[j0 + step, i0 + step]]
        )
        var = np.zeros(active.shape)
        var[cj, ci] = corners.max(0) - corners.min(0)
        var = maximum_filter(var, size=3, mode="nearest")[cj, ci]
        split = np.zeros(active.shape, bool)
        split[cj, ci] = ((corners.min(0) <= 0) & (corners.max(0) >= 0)) | (
            np.abs(corners).min(0) <= safety * var
        )
        split = binary_dilation(split, np.ones((3, 3), bool)) & active
        # cells kept whole: bilinear fill of the nodes not evaluated exactly
        fj, fi = np.nonzero(active & ~split)
        u = np.arange(step + 1) / step
        c00, c01 = vals[fj * step, fi * step], vals[fj * step, fi * step + step]
        c10, c11 = vals[fj * step + step, fi * step], vals[fj * step + step, fi * step + step]
        for a in range(step + 1):
            for b in range(step + 1):
                jj, ii = fj * step + a, fi * step + b
                w = (1 - u[a]) * ((1 - u[b]) * c00 + u[b] * c01) + u[a] * (
                    (1 - u[b]) * c10 + u[b] * c11
                )
                free = ~known[jj, ii]
                vals[jj[free], ii[free]] = w[free]
        # split cells: exact values on the half-step lattice inside them
        sj, si = np.nonzero(split)
        half = step // 2
        off = np.array([0, half, step])
        jj = (sj[:, None, None] * step + off[None, :, None] + 0 * off[None, None, :]).ravel()
        ii = (si[:, None, None] * step + 0 * off[None, :, None] + off[None, None, :]).ravel()
        flat = np.unique(jj * big_x + ii)
        evaluate(flat // big_x, flat % big_x)
        nxt = np.zeros((2 * active.shape[0], 2 * active.shape[1]), bool)
        for a in (0, 1):
            for b in (0, 1):
                nxt[2 * sj + a, 2 * si + b] = True
        active, step = nxt, half
    return vals[:ny, :nx], count


def rbf_report(
    rbf,
    points,
    box,
    *,
    offset: float,
    reference=None,
    resolution: int = jurs.levelset.DEFAULT_RESOLUTION,
):
    """[`jurs.levelset.analyze_grid`][] of the RBF on ``box`` (use the jurs fit's box)."""
    xs, ys, _ = jurs.levelset.sampling_grid(*box, resolution)
    values = evaluate_rbf_grid(rbf, xs, ys)
    return jurs.levelset.analyze_grid(xs, ys, values, points, offset=offset, reference=reference)


def orient_mst(points, normals, k: int = 15) -> np.ndarray:
    """Baseline: Hoppe et al. (1992) orientation. Minimum spanning tree of the symmetric
    ``k``-nearest-neighbour graph with weight ``1 - |n_i . n_j|``, signs propagated along
    it, each tree's topmost point (largest last coordinate) made to point up."""
    points = np.asarray(points, dtype=np.float64)  # checked by jurs.estimate_normals before
    normals = np.asarray(normals, float)
    m = len(points)
    _, neighbours = cKDTree(points).query(points, k=min(k + 1, m))
    i = np.repeat(np.arange(m), neighbours.shape[1])
    j = neighbours.ravel()
    keep = i != j
    i, j = i[keep], j[keep]
    weight = 1.0 - np.abs(np.sum(normals[i] * normals[j], axis=1)) + 1e-9
    graph = sparse.coo_matrix((weight, (i, j)), shape=(m, m)).tocsr()
    forest = csgraph.minimum_spanning_tree(graph.maximum(graph.T))
    signed = normals * forest_signs(forest, normals)[:, None]
    _, component = csgraph.connected_components(forest, directed=False)
    top = np.zeros(component.max() + 1, np.int64)
    order = np.argsort(points[:, -1])  # ascending: the last write per component is its top
    top[component[order]] = order
    flip = np.where(signed[top, -1] < 0, -1.0, 1.0)
    return signed * flip[component][:, None]
