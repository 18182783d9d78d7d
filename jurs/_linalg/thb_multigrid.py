"""A multilevel solve of a THB hierarchy's normal equations on its own nested spaces.

**Nested spaces.** Let ``V_l`` be the THB space of the hierarchy cut after level ``l``: the
domains ``Omega_0 .. Omega_l`` kept, nothing refined below level ``l``. Its basis is the
hierarchy's active functions of the levels below ``l`` and every level-``l`` function
whose support lies in ``Omega_l`` (``keep[l] == 0``); ``V_0`` is the level-0 tensor
space, ``V_L`` the hierarchy's own, and ``V_l`` is a subspace of ``V_{l+1}``.

**Prolongation, exact and sparse.** A THB coefficient of an active function of level
``k`` is the level-``k`` B-spline coefficient of the spline on that level's leaves (its
cascaded coefficient ``a^k``, where truncation zeroes every coarser term). A spline of
``V_l`` is, on all of ``Omega_l``, the level-``l`` spline of its cascaded ``a^l``; so its
coefficients in ``V_{l+1}``'s basis are its own on the functions of levels below ``l``
and on the level-``l`` functions ``V_{l+1}`` keeps active (``keep[l] == 0`` there, so
``a^l`` is the coefficient itself), and ``R_{l+1} a^l`` on the level-``l + 1`` functions
(cubic subdivision, untruncated: their supports lie in ``Omega_{l+1}``, inside
``Omega_l``). ``a^l`` comes from the hierarchy's cascade matrix: the level-``l - 1``
block refined and truncated, plus the level-``l`` coefficients. No hierarchy is built
again; the cut spaces are read off the full one.

**Cycle.** Galerkin coarse operators ``A_l = P_l^T A_{l+1} P_l``; a symmetric V-cycle
with a Chebyshev smoother on the Jacobi-scaled operator (the same polynomial before and
after, so the cycle is a symmetric positive definite preconditioner) and an exact solve
of the coarsest space; conjugate gradients on the full system, preconditioned by one
cycle (docs/multigrid.md, "The multilevel solve of the hierarchy").

**Two places to run it.** ``ThbMultigrid`` sets the cycle up on the host (Galerkin
products, patch blocks, eigenvalue estimates: SciPy and NumPy) and applies it there;
``ThbMultigrid.on_device`` hands the same cycle to JAX as a ``VCycle``, a pure function of
arrays, so that conjugate gradients preconditioned by it run in one compiled loop on any
device and ``jax.grad`` passes through the solve (``lax.custom_linear_solve``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from .._model.hierarchy import Hierarchy, cascade_matrix, refinement_matrix
from .._problem.sizes import padded_to
from .sparse import PaddedCoo

#: Chebyshev smoothing steps before and after the coarse correction of each level, and
#: the smoother's patches: boxes of ``PATCH_SIDE`` functions a side, one every
#: ``PATCH_STRIDE`` per axis, in each level's function grid; by dimension (curve,
#: surface). A surface takes boxes of 3: its set-up (27 x 27 blocks instead of 64 x 64)
#: costs far less for a few more steps (docs/multigrid.md, "The multilevel solve of the
#: hierarchy").
DEFAULT_DEGREE = {2: 2, 3: 3}
PATCH_SIDE = {2: 4, 3: 3}
PATCH_STRIDE = 2
#: The Chebyshev smoother damps the Jacobi-scaled spectrum in ``[rho / RATIO, rho]``.
DEFAULT_RATIO = 8.0
#: Power steps that estimate each level's largest Jacobi-scaled eigenvalue ``rho``.
POWER_STEPS = 12
#: Margin on the estimated ``rho`` (a power estimate is from below).
RHO_MARGIN = 1.1


def nested_prolongations(hierarchy: Hierarchy) -> list:
    """``[P_0, ..., P_{L-1}]``: ``P_l`` (SciPy CSR) maps coefficients of ``V_l`` to those of
    ``V_{l+1}`` (module docstring), exactly. ``V_L`` is the hierarchy's basis in its own
    order (active functions level by level); ``V_l`` for ``l < L`` orders the active
    functions of the levels below ``l`` first, then the level-``l`` functions whose
    support lies in ``Omega_l``, by position. Empty for a hierarchy of one level."""
    from scipy import sparse

    levels = hierarchy.num_levels
    counts = hierarchy.active_counts
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    sizes = hierarchy.level_sizes
    row_starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    cascaded = cascade_matrix(hierarchy)
    inside = [np.flatnonzero(np.asarray(hierarchy.keep[k]) == 0) for k in range(levels)]
    out = []
    for level in range(levels - 1):
        below = int(starts[level])  # active functions of the levels below ``level``
        own = inside[level]
        coarse = below + own.size
        # a^level of V_level: the coarser block refined and truncated, plus its own.
        placed = sparse.csr_matrix(
            (np.ones(own.size), (own, below + np.arange(own.size))), shape=(sizes[level], coarse)
        )
        if level:
            previous = cascaded[row_starts[level - 1] : row_starts[level], :below]
            truncated = refinement_matrix(hierarchy, level) @ previous
            cascade_level = sparse.csr_matrix(
                sparse.hstack([truncated, sparse.csr_matrix((sizes[level], own.size))]) + placed
            )
        else:
            cascade_level = placed
        finer = inside[level + 1]
        refined = (refinement_matrix(hierarchy, level + 1, truncated=False) @ cascade_level)[finer]
        # The level's functions V_{level+1} keeps active: their place among ``own``.
        active = np.asarray(hierarchy.active[level])
        kept = np.searchsorted(own, active)
        identity = sparse.csr_matrix(
            (
                np.ones(below + active.size),
                (np.arange(below + active.size), np.concatenate([np.arange(below), below + kept])),
            ),
            shape=(below + active.size, coarse),
        )
        prolongation = sparse.csr_matrix(sparse.vstack([identity, refined]))
        prolongation.eliminate_zeros()
        out.append(prolongation)
    return out


def _chebyshev_coefficients(degree: int, low: float, high: float) -> list[tuple[float, float]]:
    """The three-term recurrence's ``(alpha, beta)`` per step of the Chebyshev smoother on
    ``[low, high]`` (Saad, Iterative Methods, algorithm 12.1)."""
    theta, delta = 0.5 * (high + low), 0.5 * (high - low)
    sigma = theta / delta
    rho = 1.0 / sigma
    out = [(1.0 / theta, 0.0)]
    for _ in range(degree - 1):
        rho_new = 1.0 / (2.0 * sigma - rho)
        out.append((2.0 * rho_new / delta, rho_new * rho))
        rho = rho_new
    return out


@dataclass
class _Level:
    matrix: object  # SciPy CSR
    inverse: np.ndarray  # Jacobi scaling, 0 on zero rows
    steps: list[tuple[float, float]] = field(default_factory=list)
    patches: _Patches | None = None

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """The smoother's ``M^-1 r``: Jacobi, or additive Schwarz over the patches."""
        return self.inverse * r if self.patches is None else self.patches.apply(r)


class _Patches:
    """Additive Schwarz over overlapping patches of functions: ``sum_p E_p A_p^-1 E_p^T``,
    each patch's principal submatrix inverted exactly (dense, batched). A patch is a box
    of ``side^d`` functions of one level's grid; its slots are the box's positions, so a
    matrix entry finds its slot by subtraction, with no search."""

    def __init__(self, matrix, homes: np.ndarray, multi: np.ndarray, stride: int, side: int):
        n, ndim = multi.shape
        starts = [(multi - offset) // stride for offset in range(0, side, stride)]
        # Each function's patches: per axis the starts c with c stride <= i < c stride + side.
        choices = list(itertools.product(range(len(starts)), repeat=ndim))
        corner = np.stack(
            [np.stack([starts[c][:, axis] for axis, c in enumerate(ch)], -1) for ch in choices], 1
        )  # (n, M, d) patch corners (in strides)
        origin = corner * stride
        inside = np.all((multi[:, None] >= origin) & (multi[:, None] < origin + side), -1)
        inside &= np.all(corner >= 0, -1)
        span = int(corner.max()) + 1
        key = np.broadcast_to(homes[:, None], inside.shape).astype(np.int64)
        for axis in range(ndim):
            key = key * span + corner[..., axis]
        key = np.where(inside, key, -1)
        unique, patch = np.unique(key, return_inverse=True)
        patch = patch.reshape(key.shape) - (unique[0] < 0)  # -1 where not a member
        count = unique.size - int(unique[0] < 0)
        local = multi[:, None] - origin
        slot = np.zeros(inside.shape, np.int64)
        for axis in range(ndim):
            slot = slot * side + local[..., axis]
        size = side**ndim
        members = np.full((count, size), -1, np.int64)
        members[patch[inside], slot[inside]] = np.broadcast_to(np.arange(n)[:, None], inside.shape)[
            inside
        ]
        # The blocks from the matrix's entries: row i's slot in each of its patches, the
        # column's by the entry's offset from the row (same level, within a patch's side).
        matrix = matrix.tocsr()
        rows = np.repeat(np.arange(n), np.diff(matrix.indptr))
        cols, values = matrix.indices, matrix.data
        # An entry's offset (column less row, per axis) in -side < o < side, coded in
        # base 2 side - 1; the column's slot is the row's plus a linear code of it, valid
        # where the row's slot plus the offset stays in the box (a small table).
        width = 2 * side - 1
        near = homes[rows] == homes[cols]
        code = np.zeros(rows.size, np.int64)
        shift = np.zeros(rows.size, np.int64)
        for axis in range(ndim):
            delta = multi[cols, axis] - np.repeat(multi[:, axis], np.diff(matrix.indptr))
            near &= np.abs(delta) < side
            code = code * width + delta + side - 1
            shift = shift * side + delta
        counts = np.bincount(rows[near], minlength=n)  # rows stay sorted
        code, shift, values = code[near], shift[near], values[near]
        box = np.stack(np.unravel_index(np.arange(size), (side,) * ndim), -1)
        offsets = np.stack(np.unravel_index(np.arange(width**ndim), (width,) * ndim), -1)
        moved = box[:, None] + offsets[None] - (side - 1)
        fits = np.all((moved >= 0) & (moved < side), -1).ravel()  # (slot, code)
        blocks = np.zeros((count, size, size))
        flat = blocks.reshape(-1)
        for m in range(inside.shape[1]):
            member = np.repeat(np.where(inside[:, m], slot[:, m], -1), counts)
            ok = (member >= 0) & fits[np.maximum(member, 0) * width**ndim + code]
            start = np.repeat((patch[:, m] * size + slot[:, m]) * size + slot[:, m], counts)
            flat[start[ok] + shift[ok]] = values[ok]
        diagonal = np.einsum("pii->pi", blocks)
        # Empty slots and functions nothing reaches: a unit diagonal (their residual is 0).
        # Each block is scaled to a unit diagonal and given a ridge of k eps, so that a
        # singular block (lam = 0) still inverts, its inverse below the exact one.
        scale = 1.0 / np.sqrt(np.where(diagonal > 0, diagonal, 1.0))
        blocks *= scale[:, :, None] * scale[:, None, :]
        ridge = 1.0 + size * np.finfo(float).eps
        blocks[:, np.arange(size), np.arange(size)] = np.where(diagonal > 0, ridge, 1.0)
        self.inverses = np.linalg.inv(blocks)
        del blocks
        self.inverses *= scale[:, :, None] * scale[:, None, :]
        self.valid = members >= 0
        self.index = np.where(self.valid, members, 0)
        self.n = n

    def apply(self, r: np.ndarray) -> np.ndarray:
        local = np.where(self.valid, r[self.index], 0.0)
        solved = np.einsum("pab,pb->pa", self.inverses, local)
        return np.bincount(
            self.index.ravel(), weights=np.where(self.valid, solved, 0.0).ravel(), minlength=self.n
        )


def _largest_eigenvalue(level: _Level, seed: int = 0) -> float:
    """A power estimate of the largest eigenvalue of the smoother's ``M^-1 A``."""
    x = np.random.default_rng(seed).standard_normal(level.inverse.shape[0]) * (level.inverse > 0)
    estimate = 1.0
    for _ in range(POWER_STEPS):
        norm = float(np.linalg.norm(x))
        if norm == 0.0:
            return 1.0
        x = x / norm
        x = level.precondition(level.matrix @ x)  # pyright: ignore[reportOperatorIssue]
        estimate = float(np.linalg.norm(x))
    return estimate


def space_functions(hierarchy: Hierarchy, level: int) -> tuple[np.ndarray, np.ndarray]:
    """``(home level (n,), multi-index (n, d))`` of the basis of ``V_level`` in the order of
    ``nested_prolongations``: each function's own level and its index in that level's
    function grid."""
    homes, multis = [], []
    for k in range(level + 1):
        keys = np.asarray(hierarchy.function_keys[k], np.int64)
        if k < level:
            chosen = np.asarray(hierarchy.active[k])
        else:
            chosen = np.flatnonzero(np.asarray(hierarchy.keep[k]) == 0)
        extent = tuple(n + 3 for n in hierarchy.cells(k))
        multis.append(np.stack(np.unravel_index(keys[chosen], extent), -1).astype(np.int64))
        homes.append(np.full(chosen.size, k, np.int64))
    return np.concatenate(homes), np.concatenate(multis).reshape(-1, hierarchy.ndim)


class ThbMultigrid:
    """A symmetric V-cycle over a THB hierarchy's nested spaces (module docstring), for the
    normal matrix ``matrix`` (SciPy sparse, symmetric positive semi-definite, over the
    hierarchy's active functions). Call ``cycle(r)`` (or use ``operator()`` as CG's
    preconditioner). Functions with a zero row keep 0, as under Jacobi.

    Args:
        hierarchy: the THB structure whose active functions ``matrix`` is over.
        matrix: the normal matrix ``D^T D + lam 2 G^T W G``.
        degree: Chebyshev steps before and after each coarse correction; None takes
            ``DEFAULT_DEGREE``.
        ratio: the smoother damps ``M^-1 A``'s spectrum in ``[rho / ratio, rho]``.
        prolongations: ``nested_prolongations(hierarchy)``, built here when None.
        smoother: ``"schwarz"`` (Chebyshev on additive Schwarz over patches) or
            ``"chebyshev"`` (Chebyshev on Jacobi: cheaper cycles, several times the steps).
        stride, side: the patches (``PATCH_STRIDE``; None takes ``PATCH_SIDE``).
    """

    def __init__(
        self,
        hierarchy: Hierarchy,
        matrix,
        degree: int | None = None,
        ratio: float = DEFAULT_RATIO,
        prolongations: list | None = None,
        smoother: str = "schwarz",
        stride: int = PATCH_STRIDE,
        side: int | None = None,
    ):
        from scipy import sparse

        if smoother not in ("schwarz", "chebyshev"):
            raise ValueError(f"smoother must be 'schwarz' or 'chebyshev', got {smoother!r}")
        degree = DEFAULT_DEGREE[hierarchy.ndim] if degree is None else degree
        side = PATCH_SIDE[hierarchy.ndim] if side is None else side
        if prolongations is None:
            prolongations = nested_prolongations(hierarchy)
        self.prolongations = prolongations
        self.restrictions = [p.T.tocsr() for p in prolongations]
        matrices = [sparse.csr_matrix(matrix)]
        for p, restriction in zip(reversed(prolongations), reversed(self.restrictions)):
            matrices.append(sparse.csr_matrix(restriction @ matrices[-1] @ p))
        matrices.reverse()  # coarsest first
        self.levels = []
        for index, a in enumerate(matrices):
            diagonal = a.diagonal()
            inverse = np.where(diagonal > 0, 1.0 / np.where(diagonal > 0, diagonal, 1.0), 0.0)
            level = _Level(a, inverse)
            if index and smoother == "schwarz":
                homes, multi = space_functions(hierarchy, index)
                level.patches = _Patches(a, homes, multi, stride, side)
            if index:
                rho = RHO_MARGIN * _largest_eigenvalue(level)
                level.steps = _chebyshev_coefficients(degree, rho / ratio, rho)
            self.levels.append(level)
        self.mask = self.levels[-1].inverse > 0
        self._coarse = _factorise(matrices[0])

    @property
    def sizes(self) -> tuple[int, ...]:
        """Unknowns per space, coarsest first."""
        return tuple(level.matrix.shape[0] for level in self.levels)  # pyright: ignore[reportAttributeAccessIssue]

    def _smooth(self, level: _Level, rhs: np.ndarray, x: np.ndarray | None) -> np.ndarray:
        a = level.matrix
        r = rhs if x is None else rhs - a @ x  # pyright: ignore[reportOperatorIssue]
        d = np.zeros_like(rhs)
        for alpha, beta in level.steps:
            d = alpha * level.precondition(r) + beta * d
            x = d.copy() if x is None else x + d
            r = r - a @ d  # pyright: ignore[reportOperatorIssue]
        assert x is not None
        return x

    def _cycle(self, index: int, rhs: np.ndarray) -> np.ndarray:
        if index == 0:
            return self._coarse(rhs)
        level = self.levels[index]
        x = self._smooth(level, rhs, None)
        residual = rhs - level.matrix @ x  # pyright: ignore[reportOperatorIssue]
        coarse = self._cycle(index - 1, self.restrictions[index - 1] @ residual)
        x = x + self.prolongations[index - 1] @ coarse
        return self._smooth(level, rhs, x)

    def cycle(self, residual: Float[np.ndarray, " n"]) -> Float[np.ndarray, " n"]:
        """One symmetric V-cycle from 0 for ``matrix x = residual``."""
        return np.where(self.mask, self._cycle(len(self.levels) - 1, residual), 0.0)

    def on_device(self, dtype, pad: Callable[[int], int] | None = None) -> VCycle:
        """The same cycle as a ``VCycle`` of JAX arrays in ``dtype``: every level's matrix,
        Jacobi scaling, patch blocks and Chebyshev steps, the prolongations, and the
        coarsest space's inverse (dense: it has at most ``(BASE_CELLS + 3)^d``
        functions). ``pad(n)``: the length each level's vectors are padded to (None: none),
        with zero rows that stay 0, so that a compiled solve serves every hierarchy whose
        levels fall in the same padded sizes."""
        pad = pad or (lambda n: n)
        lengths = [pad(size) for size in self.sizes]

        def entries(matrix, rows: int, cols: int) -> PaddedCoo:
            count = pad(max(matrix.nnz, 1))
            return PaddedCoo.from_scipy(matrix, count, (rows, cols), dtype)

        levels = []
        for level, length in zip(self.levels, lengths):
            patches = level.patches
            blocks = None
            if patches is not None:
                count = pad(patches.index.shape[0])
                blocks = _Blocks(
                    jnp.asarray(padded_to(patches.index.astype(np.int32), count)),
                    jnp.asarray(padded_to(patches.valid, count, False)),
                    jnp.asarray(padded_to(patches.inverses, count), dtype),
                )
            steps = np.asarray(level.steps, float).reshape(-1, 2)
            levels.append(
                _DeviceLevel(
                    entries(level.matrix, length, length),
                    jnp.asarray(padded_to(level.inverse, length), dtype),
                    jnp.asarray(steps, dtype),
                    blocks,
                )
            )
        prolongations = tuple(
            entries(p, lengths[k + 1], lengths[k]) for k, p in enumerate(self.prolongations)
        )
        coarse = np.zeros((lengths[0], lengths[0]))
        size = self.sizes[0]
        coarse[:size, :size] = _dense_inverse(self.levels[0].matrix)
        mask = padded_to(self.mask, lengths[-1], False)
        return VCycle(tuple(levels), prolongations, jnp.asarray(coarse, dtype), jnp.asarray(mask))

    def operator(self):
        """The cycle as a SciPy ``LinearOperator`` (CG's ``M``)."""
        from scipy.sparse.linalg import LinearOperator

        n = self.levels[-1].matrix.shape[0]  # pyright: ignore[reportAttributeAccessIssue]
        return LinearOperator((n, n), matvec=self.cycle, dtype=float)  # pyright: ignore[reportCallIssue]


def _dense_inverse(matrix) -> np.ndarray:
    """The inverse of the coarsest space's matrix as a dense array, its zero rows and
    columns (functions nothing reaches) kept at 0: ``_factorise``'s solve as a matrix,
    with the same ridge where the matrix is exactly singular."""
    dense = np.asarray(matrix.todense())
    diagonal = np.diag(dense).copy()
    live = np.flatnonzero(diagonal > 0)
    kept = dense[np.ix_(live, live)]
    out = np.zeros_like(dense)
    try:
        inverse = np.linalg.inv(kept)
        if not np.all(np.isfinite(inverse)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:  # exactly singular (lam = 0): a relative ridge
        ridge = diagonal[live] * live.size * np.finfo(float).eps
        inverse = np.linalg.inv(kept + np.diag(ridge))
    out[np.ix_(live, live)] = inverse
    return out


class _Blocks(eqx.Module):
    """Additive Schwarz over patches (``_Patches.apply``) on the device."""

    index: Array  # (patches, size) functions of each patch's slots
    valid: Array  # (patches, size) slots that hold a function
    inverses: Array  # (patches, size, size) the patches' inverse blocks

    def __call__(self, r: Array) -> Array:
        local = jnp.where(self.valid, r[self.index], 0.0)
        solved = jnp.einsum("pab,pb->pa", self.inverses, local)
        return jax.ops.segment_sum(
            jnp.where(self.valid, solved, 0.0).ravel(), self.index.ravel(), r.shape[0]
        )


class _DeviceLevel(eqx.Module):
    matrix: PaddedCoo
    inverse: Array  # Jacobi scaling, 0 on zero and padded rows
    steps: Array  # (degree, 2) the Chebyshev recurrence's (alpha, beta)
    patches: _Blocks | None

    def precondition(self, r: Array) -> Array:
        return self.inverse * r if self.patches is None else self.patches(r)

    def smooth(self, rhs: Array, x: Array | None) -> Array:
        """``ThbMultigrid._smooth``: the Chebyshev steps on the scaled residual."""
        r = rhs if x is None else rhs - self.matrix @ x
        d = jnp.zeros_like(rhs)
        for step in range(self.steps.shape[0]):
            alpha, beta = self.steps[step, 0], self.steps[step, 1]
            d = alpha * self.precondition(r) + beta * d
            x = d if x is None else x + d
            r = r - self.matrix @ d
        assert x is not None
        return x


class VCycle(eqx.Module):
    """``ThbMultigrid``'s symmetric V-cycle in JAX (``ThbMultigrid.on_device``): call it on
    a residual for the cycle's correction from 0. A pure function of its arrays, so it
    runs inside ``jax.jit``, on any device, as the preconditioner of
    ``jurs._linalg.pcg.conjugate_gradients``."""

    levels: tuple[_DeviceLevel, ...]  # coarsest first
    prolongations: tuple[PaddedCoo, ...]  # V_l -> V_{l+1}
    coarse: Array  # the coarsest space's inverse, dense
    mask: Array  # functions of the finest space with a nonzero row

    def _cycle(self, index: int, rhs: Array) -> Array:
        if index == 0:
            return self.coarse @ rhs
        level = self.levels[index]
        x = level.smooth(rhs, None)
        residual = rhs - level.matrix @ x
        prolongation = self.prolongations[index - 1]
        coarse = self._cycle(index - 1, prolongation.transpose_apply(residual))
        return level.smooth(rhs, x + prolongation @ coarse)

    def __call__(self, residual: Float[Array, " n"]) -> Float[Array, " n"]:
        return jnp.where(self.mask, self._cycle(len(self.levels) - 1, residual), 0.0)


def _factorise(matrix):
    """A solve with the coarsest space's matrix: LU of it, with the zero rows (functions
    nothing reaches) kept at 0."""
    from scipy import sparse
    from scipy.sparse.linalg import splu

    diagonal = matrix.diagonal()
    live = np.flatnonzero(diagonal > 0)
    kept = matrix[live][:, live].tocsc()
    try:
        lu = splu(kept, permc_spec="COLAMD")
    except RuntimeError:  # exactly singular (lam = 0): a relative ridge
        ridge = sparse.diags(diagonal[live] * live.size * np.finfo(float).eps)
        lu = splu(sparse.csc_matrix(kept + ridge), permc_spec="COLAMD")

    def solve(rhs):
        out = np.zeros_like(rhs)
        out[live] = lu.solve(rhs[live])
        return out

    return solve


def multigrid_cg(
    hierarchy: Hierarchy,
    matrix,
    rhs: Float[np.ndarray, " n"],
    rtol: float,
    max_steps: int,
    start: Float[np.ndarray, " n"] | None = None,
    **options,
) -> tuple[np.ndarray, int, float]:
    """``(x, steps, relative residual)``: SciPy's CG on ``matrix x = rhs`` from ``start``
    (None: 0) preconditioned by one ``ThbMultigrid`` V-cycle a step, stopping at
    ``|r| <= rtol |rhs|``. ``options`` go to ``ThbMultigrid``."""
    from scipy.sparse.linalg import cg

    multigrid = ThbMultigrid(hierarchy, matrix, **options)
    steps = 0

    def count(_):
        nonlocal steps
        steps += 1

    x, _ = cg(
        matrix,
        rhs,
        x0=start,
        rtol=rtol,
        atol=0.0,
        maxiter=max_steps,
        M=multigrid.operator(),
        callback=count,
    )
    scale = max(float(np.linalg.norm(rhs)), np.finfo(float).tiny)
    return x, steps, float(np.linalg.norm(matrix @ x - rhs)) / scale
