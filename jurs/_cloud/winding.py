"""The global step of normal orientation: each patch's sign chosen so that the generalised
winding number of the oriented dipoles is 1 inside and 0 outside (docs/normals.md). The
fields of the patches' dipoles at query points, and the sign search over them."""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.sparse.linalg import eigsh
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # no stub

#: Patch signs are found by enumeration up to this many patches.
EXHAUSTIVE_PATCHES = 14


#: Exact near field over this many nearest points; clustered far field beyond.
NEAR_NEIGHBOURS = 48


#: At most this many query-source pairs are evaluated exactly (dense path).
DENSE_PAIRS = 1.5e7


def dipole_kernel(queries, sources, dipoles, eps):
    """Regularised generalised winding number of dipoles at ``queries``, pairwise
    (broadcast): ``D . (p - x) / (omega_d (|p - x|^2 + eps^2)^(d/2))``, omega_2 = 2 pi,
    omega_3 = 4 pi. Outward dipoles (area x unit normal) on a closed surface sum to 1
    inside, 0 outside, 1/2 on the surface."""
    d = queries.shape[-1]
    diff = sources - queries
    r2 = np.sum(diff * diff, axis=-1) + eps * eps
    omega = 2.0 * np.pi if d == 2 else 4.0 * np.pi
    return np.sum(dipoles * diff, axis=-1) / (omega * r2 ** (0.5 * d))


def _dipole_matrix(queries, sources, dipoles, eps):
    """``dipole_kernel`` for every query-source pair, ``(Q, S)``, written with matrix
    products (``D . (p - x) = D . p - D . x``, ``|p - x|^2 = |p|^2 + |x|^2 - 2 p . x``)
    so that no ``(Q, S, d)`` temporary is built."""
    d = queries.shape[1]
    r2 = (
        np.sum(queries**2, 1)[:, None]
        - 2.0 * queries @ sources.T
        + (np.sum(sources**2, 1) + eps * eps)[None, :]
    )
    np.maximum(r2, (eps * eps)[None, :], out=r2)
    flux = np.sum(dipoles * sources, 1)[None, :] - queries @ dipoles.T
    if d == 2:
        flux /= 2.0 * np.pi * r2
    else:
        flux /= 4.0 * np.pi * r2 * np.sqrt(r2)
    return flux


def patch_fields_dense(queries, points, dipoles, eps, patch, n_patches):
    """Field of every patch at every query, exactly: ``(Q, P)``."""
    owner = sparse.csr_matrix(
        (np.ones(len(points)), (np.arange(len(points)), patch)), shape=(len(points), n_patches)
    )
    out = np.empty((len(queries), n_patches))
    step = max(1, int(DENSE_PAIRS // (4 * len(points))))
    for s in range(0, len(queries), step):
        kernel = _dipole_matrix(queries[s : s + step], points, dipoles, eps)
        out[s : s + step] = (owner.T @ kernel.T).T
    return out


def patch_fields_clustered(queries, points, dipoles, eps, patch, n_patches, tree):
    """Field of every patch at every query: exact over each query's
    ``NEAR_NEIGHBOURS`` nearest points, the rest from clusters (a voxel of half the
    near radius, within one patch) summed into one dipole at their centroid."""
    m, d = points.shape
    dist, near = tree.query(queries, k=NEAR_NEIGHBOURS, workers=-1)
    voxel = max(0.5 * float(np.median(dist[:, -1])), 1e-12)
    cells = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    key = np.concatenate([cells, patch[:, None]], axis=1)
    _, cluster = np.unique(key, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    n_cl = int(cluster.max()) + 1
    size = np.bincount(cluster, minlength=n_cl)
    centre = np.stack([np.bincount(cluster, points[:, a], n_cl) for a in range(d)], 1)
    centre /= size[:, None]
    c_dip = np.stack([np.bincount(cluster, dipoles[:, a], n_cl) for a in range(d)], 1)
    c_eps = np.bincount(cluster, eps, n_cl) / size
    c_patch = np.zeros(n_cl, np.int64)
    c_patch[cluster] = patch
    owner = sparse.csr_matrix((np.ones(n_cl), (np.arange(n_cl), c_patch)), shape=(n_cl, n_patches))
    out = np.empty((len(queries), n_patches))
    step = max(1, int(DENSE_PAIRS // (4 * n_cl)))
    for s in range(0, len(queries), step):
        kernel = _dipole_matrix(queries[s : s + step], centre, c_dip, c_eps)
        out[s : s + step] = (owner.T @ kernel.T).T
    # Near points: exact minus their share of their cluster's centroid approximation.
    q = queries[:, None, :]
    exact = dipole_kernel(q, points[near], dipoles[near], eps[near])
    approx = dipole_kernel(q, centre[cluster[near]], dipoles[near], c_eps[cluster[near]])
    rows = np.repeat(np.arange(len(queries)), near.shape[1])
    np.add.at(out, (rows, patch[near].ravel()), (exact - approx).ravel())
    return out


def _subtree_moves(patch_tree: sparse.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """Two ``(moves, P)`` 0/1 matrices of sign moves. Fine: every subtree of the patch
    forest (rooted at its lowest patch; the whole tree is one, a component's global flip),
    which undoes one propagation error at a cut edge, and every single patch. Coarse: whole
    components and single patches only (greedy descent is path dependent: the smaller set
    sometimes ends lower)."""
    n = patch_tree.shape[0]  # pyright: ignore[reportOptionalSubscript]  # SciPy is unannotated
    n_trees, tree_of = csgraph.connected_components(patch_tree, directed=False)
    below = np.eye(n, dtype=bool)
    roots = []
    for t in range(n_trees):
        roots.append(int(np.flatnonzero(tree_of == t)[0]))
        order, parent = csgraph.breadth_first_order(patch_tree, roots[-1], directed=False)
        for p in order[:0:-1]:  # leaves first: a patch's subtree joins its parent's
            below[parent[p]] |= below[p]
    single = np.eye(n, dtype=bool)
    coarse = np.concatenate([below[roots], single])  # whole components, single patches
    return (np.unique(np.concatenate([below, single]), axis=0).astype(float), coarse.astype(float))


def _greedy_flips(gram, target, moves, s):
    """Greedy descent of ``s^T G s - 2 t^T s`` (``t`` = ``target``): apply the move (a row
    of ``moves``: the patches whose signs change together) that lowers it most, while one
    does."""
    s = s.copy()
    tol = 1e-12 * max(1.0, float(target @ target))
    for _ in range(4 * len(s) + 8):
        flip = moves * s  # each move's patches, with their current signs
        gains = 4.0 * flip @ (gram @ s - target) - 4.0 * np.sum((flip @ gram) * flip, axis=1)
        best = int(np.argmax(gains))
        if gains[best] <= tol:
            break
        s = np.where(moves[best] > 0, -s, s)
    return s


def _pair_moves(centre: np.ndarray, count: int = 4) -> np.ndarray:
    """``(moves, P)`` 0/1 rows flipping a patch together with one of its ``count`` nearest
    patches (by centroid), in any component: the two facing sides of a thin part or of a
    narrow gap come out flipped together (each alone is worse), e.g. the bar of a B."""
    n = len(centre)
    if n < 2:
        return np.zeros((0, n))
    near = cKDTree(centre).query(centre, k=min(count + 1, n))[1][:, 1:]
    rows = np.repeat(np.arange(n), near.shape[1])
    moves = np.zeros((len(rows), n))
    moves[np.arange(len(rows)), rows] = 1.0
    moves[np.arange(len(rows)), near.ravel()] = 1.0
    return np.unique(moves, axis=0)


def solve_signs(fields, weight, patch_tree, centre):
    """Patch signs ``s`` (+1/-1) minimising ``sum_q weight_q (fields_q . s - 1/2)^2``.

    A binary quadratic problem, solved exactly by enumeration up to
    ``EXHAUSTIVE_PATCHES`` patches (greedy moves end in local minima where the facing
    sides of a B's bar and a patch at its notch must flip together). Above that, two
    starts: the propagated signs (all +1) and the spectral relaxation (the lowest
    eigenvector of the problem homogenised with one extra sign, rounded). Each descends by
    greedy moves of each set of ``_subtree_moves`` (a subtree of the patch forest,
    which undoes one propagation error or flips a whole component, or a single patch; the
    fine set adds ``_pair_moves`` of patches near each other, ``centre`` their
    centroids) and by phases of component moves then single moves; the lowest objective
    of the six wins."""
    wf = fields * np.sqrt(weight)[:, None]
    gram = wf.T @ wf
    target = wf.T @ (0.5 * np.sqrt(weight))
    n = len(target)
    if n <= EXHAUSTIVE_PATCHES:  # every sign vector: the exact optimum
        every = 1.0 - 2.0 * ((np.arange(2**n)[:, None] >> np.arange(n)) & 1)
        value = np.sum((every @ gram) * every, axis=1) - 2.0 * every @ target
        return every[int(np.argmin(value))]
    homogeneous = np.block([[gram, -target[:, None]], [-target[None, :], np.zeros((1, 1))]])
    if n < 64:
        vector = np.linalg.eigh(homogeneous)[1][:, 0]
    else:  # Lanczos: a dense LAPACK solve is slow when BLAS threads contend for cores
        vector = eigsh(homogeneous, k=1, which="SA", v0=np.ones(n + 1))[1][:, 0]
    spectral = np.where(vector[:n] * vector[n] >= 0, 1.0, -1.0)
    fine, coarse = _subtree_moves(patch_tree)
    fine = np.concatenate([fine, _pair_moves(centre)])
    starts = (np.ones(n), spectral)
    results = [
        _greedy_flips(gram, target, moves, start) for moves in (fine, coarse) for start in starts
    ]
    for s in starts:  # phased: whole components until none helps, then single patches
        for _ in range(8):
            before = s
            s = _greedy_flips(gram, target, coarse[: len(coarse) - n], s)
            s = _greedy_flips(gram, target, coarse[len(coarse) - n :], s)
            if np.array_equal(s, before):
                break
        results.append(s)
    return min(results, key=lambda s: float(s @ gram @ s - 2.0 * target @ s))
