"""The part of a lattice where an adaptive spline's level set can be: the blocks marching
cubes (3D) and contouring (2D) need, and g on them (``band_lattice``).

The lattice of [`mesh`][jurs.levelset.mesh] (of [`analyze`][jurs.levelset.analyze] and
[`zero_level_set`][jurs.levelset.zero_level_set] for a curve, ``band_lattice``) is cut
into blocks of ``BLOCK_CELLS`` lattice cells a side; the planning is the same in any
dimension. Only the blocks where g may reach the level are evaluated and marched; the
rest of the box costs a few comparisons per leaf of the hierarchy. A block is marched
when both tests below let it through (docs/design.md section 8, "Meshing the band"):

1. *Candidates* (per leaf, no evaluation): the blocks over a finest leaf (the band around
   the data, where the surface is expected), the blocks over a coarser leaf whose
   coefficients straddle the level (a surface piece far from the data, which must be
   meshed too), and the blocks with nodes outside the spline's box (where g
   extrapolates and no bound below holds).
2. *Window bound* (per candidate): the spline's coefficients in the finest level's
   uniform basis over the block's cells. With positive weights, g there is a convex
   combination of their ratios ``A_num / A_den`` (the B-splines are non-negative and the
   denominator's coefficients positive), so a block whose ratios all lie above the level
   (or all below it by more than the nudge of ``NUDGE``) has every node on one side, and
   marching cubes would find nothing in it.

Both bounds are exact (convex hulls, no sampling), so the blocks left out are exactly
blocks where marching the full lattice would put no triangle: the band's mesh is the full
lattice's mesh, surface far from the data included.

Neighbouring blocks share their boundary nodes, and ``jurs._model.lattice.FinestSpline``
gives a node bitwise the same value in every block that holds it; ``jurs.levelset._meshing``'s
``lattice_vertices`` puts each block's vertices where marching cubes over the whole
lattice puts them (it rounds them to float32 in the block's own index units), so the
vertices on shared lattice edges are bitwise equal and ``_weld`` stitches the blocks into
one watertight mesh.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from .._threads import ahead, in_threads
from .finest import level_offsets
from .hierarchy import cube_offsets, index_in, ravel_keys, unravel_keys
from .lattice import FinestSpline

#: Lattice cells along each side of a block. Smaller blocks hug the surface closer (fewer
#: nodes evaluated) but cost more calls of marching cubes and more shared boundary
#: planes: at 16 a block's 17^3 nodes hold 20 % boundary repeats.
BLOCK_CELLS = 16
#: Blocks evaluated and marched per batch: a batch's values take about ``BATCH_BLOCKS *
#: (BLOCK_CELLS + 1)^3 * 16`` bytes (20 MiB at 256 blocks of 16). Curves' blocks are
#: ``BLOCK_CELLS + 1`` times smaller, and as many times more of them make a batch.
BATCH_BLOCKS = 256
#: The convex-hull tests keep a block when the level is within this fraction of the
#: coefficients' magnitude of their range: rounding of the node values, which are
#: combinations of the coefficients, stays far below it.
HULL_TOLERANCE = 1e-9


@dataclasses.dataclass
class BandPlan:
    """Which blocks of a lattice are marched, with their nodes along each axis.

    ``blocks (b, 3)``: the marched blocks' indices in the block grid; ``nodes``: lattice
    nodes they evaluate (shared boundary nodes counted in each block); ``lattice_nodes``:
    the full lattice's; ``candidates``: blocks that passed the per-leaf test;
    ``total_blocks``: the block grid's size."""

    blocks: np.ndarray
    nodes: int
    lattice_nodes: int
    candidates: int
    total_blocks: int


class BlockGrid:
    """The block grid of a lattice: per axis, each block's first and last node and the
    finest cells of those nodes."""

    def __init__(self, evaluator: FinestSpline, axes, block: int):
        self.ndim = len(axes)
        self.block = int(block)
        self.batch = BATCH_BLOCKS * (self.block + 1) ** max(0, 3 - self.ndim)
        self.located = [evaluator.axis(a, k) for k, a in enumerate(axes)]
        self.counts = [len(a) for a in axes]
        self.grid = tuple(max(1, -(-(n - 1) // self.block)) for n in self.counts)
        self.first = [np.arange(g) * self.block for g in self.grid]
        self.last = [np.minimum(f + self.block, n - 1) for f, n in zip(self.first, self.counts)]
        cells = [c for c, _, _ in self.located]
        self.first_cell = [c[f] for c, f in zip(cells, self.first)]
        self.last_cell = [c[last] for c, last in zip(cells, self.last)]
        # Blocks holding nodes outside the spline's box, where g extrapolates.
        self.outside = []
        for k, coords in enumerate(axes):
            out = (coords < evaluator.lower[k]) | (coords > evaluator.upper[k])
            count = np.concatenate([[0], np.cumsum(out)])
            self.outside.append(count[self.last[k] + 1] - count[self.first[k]] > 0)

    def window_sizes(self) -> tuple[int, ...]:
        """Finest functions per axis of a block's window: those over its cells, at most."""
        pairs = zip(self.first_cell, self.last_cell)
        return tuple(int(np.max(last - first)) + 4 for first, last in pairs)

    def mark(self, marked: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
        """Mark in ``marked`` (the block grid) every block over a box of finest cells
        ``[low, high]`` (inclusive, ``(m, d)`` each)."""
        if len(low) == 0:
            return
        start, stop = [], []
        for k in range(self.ndim):
            start.append(np.searchsorted(self.last_cell[k], low[:, k], side="left"))
            stop.append(np.searchsorted(self.first_cell[k], high[:, k], side="right"))
        start = np.stack(start, -1)
        span = np.stack(stop, -1) - start  # blocks per axis (0 where none)
        keep = np.all(span > 0, axis=1)
        start, span = start[keep], span[keep]
        if len(start) == 0:
            return
        for offset in cube_offsets(self.ndim, int(span.max())):
            ok = np.all(offset < span, axis=1)
            if ok.any():
                marked[tuple((start[ok] + offset).T)] = True

    def outside_blocks(self) -> np.ndarray:
        """The block grid's blocks that hold nodes outside the spline's box."""
        out = np.zeros(self.grid, bool)
        for k in range(self.ndim):
            shape = [1] * self.ndim
            shape[k] = self.grid[k]
            out |= self.outside[k].reshape(shape)
        return out

    def corners(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First and last finest cells of the blocks ``batch (b, d)``; ``(b, d)`` each."""
        first = np.stack([self.first_cell[k][batch[:, k]] for k in range(self.ndim)], -1)
        last = np.stack([self.last_cell[k][batch[:, k]] for k in range(self.ndim)], -1)
        return first, last

    def values(self, evaluator: FinestSpline, batch: np.ndarray):
        """g on the nodes of the blocks ``batch (b, d)``: ``(values (b, B+1, .., B+1),
        nodes (b, d))``, block ``i``'s own nodes being ``values[i, :nodes[i, 0], ...]``
        (a block cut by the lattice's end repeats its last node past it). Each node gets
        bitwise the value of every other block holding it (``FinestSpline``)."""
        first_cell, _ = self.corners(batch)
        span = np.arange(self.block + 1)
        relative, factors, real = [], [], []
        for k in range(self.ndim):
            cells, weights, _ = self.located[k]
            start = self.first[k][batch[:, k]]
            index = np.minimum(start[:, None] + span[None], self.counts[k] - 1)
            relative.append(cells[index] - first_cell[:, k : k + 1])
            factors.append(weights[index])
            real.append(self.last[k][batch[:, k]] - start + 1)
        windows = evaluator.windows(first_cell, self.window_sizes())
        both = evaluator.contract(windows, relative, factors)
        return both[0] / both[1], np.stack(real, -1)

    def batches(self, blocks: np.ndarray):
        """``blocks (b, d)`` in batches of ``self.batch``, in order."""
        return [blocks[begin : begin + self.batch] for begin in range(0, len(blocks), self.batch)]

    def batch_values(self, evaluator: FinestSpline, blocks: np.ndarray):
        """``(batch, values, nodes)`` for each of ``batches(blocks)`` in order, ``values``
        and ``nodes`` as ``values`` gives them: the next batches' made by the host's
        threads while the caller works on this one (``jurs._threads.ahead``; the same
        values)."""
        return ahead(lambda batch: (batch, *self.values(evaluator, batch)), self.batches(blocks))


def _straddles(low, high, level: float, nudge: float, scale: float) -> np.ndarray:
    """Whether a range ``[low, high]`` of values may put a node's value, after the nudge,
    on both sides of the level (see the module docstring)."""
    tolerance = HULL_TOLERANCE * scale
    return (low <= level + tolerance) & (high >= level - nudge - tolerance)


def _ratios(both: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A_num / A_den`` and whether the denominator is positive (the hull holds)."""
    numerator, denominator = both
    positive = denominator > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(positive, numerator / np.where(positive, denominator, 1.0), 0.0), positive


def plan_band(
    evaluator: FinestSpline,
    axes,
    level: float,
    nudge: float,
    block: int = BLOCK_CELLS,
    near: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> BandPlan:
    """The blocks of the lattice ``axes`` (``d`` of them, the spline's dimension) where
    ``{g = level}`` may be (module docstring); host work, no lattice-sized array (the
    block grid is ``BLOCK_CELLS^d`` times smaller). ``near(lower, upper, step)``: of the
    blocks' corner nodes' coordinates ``(b, d)`` and the lattice's step ``(d,)``, which
    blocks to keep at all (None: every one), asked before their windows are read."""
    hierarchy = evaluator.hierarchy
    grid = BlockGrid(evaluator, axes, block)
    marked = np.zeros(grid.grid, bool)
    finest = hierarchy.num_levels - 1
    ratio_all, _ = _ratios(evaluator.cascaded)
    scale = float(np.max(np.abs(ratio_all), initial=0.0)) + abs(level)
    starts = level_offsets(hierarchy)
    for lev in range(finest + 1):
        leaves = unravel_keys(np.asarray(hierarchy.leaf_keys[lev], np.int64), hierarchy.cells(lev))
        if len(leaves) == 0:
            continue
        steps = finest - lev
        if lev < finest:
            keys = np.asarray(hierarchy.function_keys[lev], np.int64)
            corner = cube_offsets(grid.ndim, 4)[None]
            around = ravel_keys(leaves[:, None, :] + corner, hierarchy.functions(lev))
            both = evaluator.cascaded[:, starts[lev] + index_in(around.ravel(), keys)]
            ratio, positive = _ratios(both.reshape(2, len(leaves), -1))
            hull = _straddles(ratio.min(axis=1), ratio.max(axis=1), level, nudge, scale)
            leaves = leaves[hull | ~positive.all(axis=1)]
        grid.mark(marked, leaves << steps, ((leaves + 1) << steps) - 1)
    outside = grid.outside_blocks()
    marked |= outside
    candidates = np.argwhere(marked)
    if near is not None and len(candidates):
        first, last = (
            np.stack([np.asarray(axes[k])[ends[k][candidates[:, k]]] for k in range(grid.ndim)], 1)
            for ends in (grid.first, grid.last)
        )
        step = np.array([(a[-1] - a[0]) / max(len(a) - 1, 1) for a in axes], float)
        candidates = candidates[near(first, last, step)]
    sizes = grid.window_sizes()

    def kept(batch):
        """The blocks of ``batch`` whose window's ratios may reach the level."""
        first, last = grid.corners(batch)
        ratio, positive = _ratios(evaluator.windows(first, sizes))
        # Only the functions over the block's cells bound it (the window is padded).
        valid = np.ones(ratio.shape, bool)
        for k in range(grid.ndim):
            shape = [len(batch)] + [1] * grid.ndim
            shape[1 + k] = sizes[k]
            inside = np.arange(sizes[k])[None] <= (last[:, k] - first[:, k] + 3)[:, None]
            valid &= inside.reshape(shape)
        low = np.where(valid, ratio, np.inf).reshape(len(batch), -1).min(axis=1)
        high = np.where(valid, ratio, -np.inf).reshape(len(batch), -1).max(axis=1)
        bad = (valid & ~positive).reshape(len(batch), -1).any(axis=1)
        forced = outside[tuple(batch.T)]
        return batch[_straddles(low, high, level, nudge, scale) | bad | forced]

    # The batches are independent: shared out over the host's threads.
    chosen = in_threads(kept, grid.batches(candidates))
    blocks = np.concatenate(chosen) if chosen else np.zeros((0, grid.ndim), np.int64)
    per_axis = [last - first + 1 for first, last in zip(grid.first, grid.last)]
    nodes = int(sum(np.prod([per_axis[k][blocks[:, k]] for k in range(grid.ndim)], axis=0)))
    return BandPlan(
        blocks=blocks,
        nodes=nodes,
        lattice_nodes=int(np.prod(grid.counts)),
        candidates=len(candidates),
        total_blocks=int(np.prod(grid.grid)),
    )


def band_lattice(evaluator: FinestSpline, axes, level: float, block: int = BLOCK_CELLS):
    """g on the lattice ``axes`` where ``{g = level}`` may be: ``(values (len(axes[0]),
    ..), evaluated (same shape, bool), plan)``.

    The nodes of the blocks of ``plan_band`` (no nudge) hold g, bitwise the full
    lattice's values (``FinestSpline``). Every other node lies in a block whose nodes are
    all strictly on one side of the level, and holds instead g at one node of its
    connected region of such blocks (blocks sharing a side share nodes, so a region is on
    one side): contouring ``values`` crosses exactly the cells the full lattice's values
    cross, at the same points. ``evaluated`` marks the nodes that hold their own g."""
    from scipy import ndimage

    plan = plan_band(evaluator, axes, level, 0.0, block)
    grid = BlockGrid(evaluator, axes, block)
    skipped = np.ones(grid.grid, bool)
    skipped[tuple(plan.blocks.T)] = False
    labelled: Any = ndimage.label(skipped)  # (labels, count); the stubs type it loosely
    labels, regions = np.asarray(labelled[0], np.int64), int(labelled[1])
    # One node per region (the first node of its first block), evaluated to find its side.
    _, first = np.unique(labels.ravel(), return_index=True)
    first = first[labels.ravel()[first] > 0]
    where = np.stack(np.unravel_index(first, grid.grid), -1)
    side = np.full(regions + 1, np.nan)
    if len(where):
        node = [np.asarray(axes[k])[grid.first[k][where[:, k]]] for k in range(grid.ndim)]
        side[labels[tuple(where.T)]] = evaluator.values_and_gradients(np.stack(node, -1))[0]
    # Each node takes its block's region (a node shared by two blocks: the later one's;
    # shared with an evaluated block, overwritten below).
    owner = [np.minimum(np.arange(n) // grid.block, g - 1) for n, g in zip(grid.counts, grid.grid)]
    values = side[labels[np.ix_(*owner)]]
    evaluated = np.zeros(tuple(grid.counts), bool)
    for batch, block_values, real in grid.batch_values(evaluator, plan.blocks):
        for b, at in enumerate(batch):
            start = [grid.first[k][at[k]] for k in range(grid.ndim)]
            target = tuple(slice(f, f + n) for f, n in zip(start, real[b]))
            values[target] = block_values[(b,) + tuple(slice(0, n) for n in real[b])]
            evaluated[target] = True
    return values, evaluated, plan


def band_regions(
    evaluator: FinestSpline,
    axes,
    level: float,
    block: int = BLOCK_CELLS,
    plan: BandPlan | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lattice edges ``axes`` where g crosses ``level``, and the sign regions at
    their ends, evaluating only the band's blocks: ``(low, high, at)``, for each such
    edge the regions of its end nodes below and above the level (ids, one a region of the
    whole lattice) and its midpoint ``(k, d)`` in lattice index units. The regions are
    the full lattice's: nodes above the level joined across lattice edges, nodes at or
    below it across edges and the diagonals of cells, so that the two never cross.

    Each evaluated block (``plan``, default ``plan_band`` without nudge) is labelled on
    its own; every lattice edge and cell lies in one block, and blocks share their
    boundary nodes, so joining the labels a shared node gets in each of its blocks gives
    the lattice's regions. A connected group of skipped blocks (touching at a side, an
    edge or a corner: blocks that touch share nodes) lies on one side and is one region.
    The memory and work grow with the band's blocks, not the lattice: the fit's verdict
    sees one-cell shells on a hierarchy whose full lattice would not fit."""
    from scipy import ndimage
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    d = len(axes)
    if plan is None:
        plan = plan_band(evaluator, axes, level, 0.0, block)
    grid = BlockGrid(evaluator, axes, block)
    skipped = np.ones(grid.grid, bool)
    skipped[tuple(plan.blocks.T)] = False
    labelled: Any = ndimage.label(skipped, structure=np.ones((3,) * d, bool))
    block_region, next_id = np.asarray(labelled[0], np.int64) - 1, int(labelled[1])
    counts = np.asarray(grid.counts)
    faces_only = ndimage.generate_binary_structure(d, 1)
    every = np.ones((3,) * d, bool)
    shared_nodes, shared_ids, joins = [], [], []
    edge_keys, lows, highs, mids = [], [], [], []
    # A batch of blocks is labelled at once: no connection along the batch axis, so each
    # block's components are its own, numbered block by block in raster order.
    up_structure = np.zeros((3,) * (d + 1), bool)
    up_structure[1] = faces_only
    down_structure = np.zeros((3,) * (d + 1), bool)
    down_structure[1] = every
    for batch, values, real in grid.batch_values(evaluator, plan.blocks):
        count, side = len(batch), values.shape[1:]
        # A block cut by the lattice's end holds its own nodes below ``real``; the rest
        # repeat its last node and take part in nothing.
        valid = np.ones(values.shape, bool)
        border = np.zeros(values.shape, bool)
        for k in range(d):
            shape = [count] + [1] * d
            shape[1 + k] = side[k]
            index = np.arange(side[k])[None]
            valid &= (index < real[:, k : k + 1]).reshape(shape)
            border |= ((index == 0) | (index == real[:, k : k + 1] - 1)).reshape(shape)
        border &= valid
        positive = values > level
        # (labels, count); the stubs type it loosely.
        up: Any = ndimage.label(positive & valid, structure=up_structure)
        down: Any = ndimage.label(~positive & valid, structure=down_structure)
        up, down = up[0], down[0]
        # Region ids as if each block were labelled alone, in turn: its components above
        # the level, then those below.
        last_up = np.maximum.accumulate(up.reshape(count, -1).max(axis=1))
        last_down = np.maximum.accumulate(down.reshape(count, -1).max(axis=1))
        up_before = np.concatenate([[0], last_up[:-1]])
        down_before = np.concatenate([[0], last_down[:-1]])
        ups = last_up - up_before
        sizes = ups + last_down - down_before
        first = next_id + np.concatenate([[0], np.cumsum(sizes)[:-1]])
        each = (count,) + (1,) * d
        local = np.where(
            positive,
            (first - up_before - 1).reshape(each) + up,
            (first + ups - down_before - 1).reshape(each) + down,
        )
        next_id += int(sizes.sum())
        start = np.stack([grid.first[k][batch[:, k]] for k in range(d)], -1)
        for axis in range(d):
            head = (slice(None),) + tuple(
                slice(0, -1) if a == axis else slice(None) for a in range(d)
            )
            tail = (slice(None),) + tuple(
                slice(1, None) if a == axis else slice(None) for a in range(d)
            )
            crossed = (positive[head] != positive[tail]) & valid[head] & valid[tail]
            index = np.nonzero(crossed)
            if len(index[0]) == 0:
                continue
            node = np.stack(index[1:], axis=1) + start[index[0]]
            first_above = positive[head][index]
            a, c = local[head][index], local[tail][index]
            lows.append(np.where(first_above, c, a))
            highs.append(np.where(first_above, a, c))
            edge_keys.append(np.ravel_multi_index(tuple(node.T), counts) * d + axis)
            at = node.astype(float)
            at[:, axis] += 0.5
            mids.append(at)
        # The blocks' boundary nodes, shared with their neighbours.
        index = np.nonzero(border)
        node = np.stack(index[1:], axis=1) + start[index[0]]
        ids = local[index]
        shared_nodes.append(np.ravel_multi_index(tuple(node.T), counts))
        shared_ids.append(ids)
        # Skipped blocks holding these nodes: node i lies in block i // B and, at a
        # block's first node, in the block before too.
        for corner in cube_offsets(d, 2):
            holder = np.empty_like(node)
            ok = np.ones(len(node), bool)
            for k in range(d):
                primary = np.minimum(node[:, k] // grid.block, grid.grid[k] - 1)
                if corner[k]:
                    ok &= (node[:, k] % grid.block == 0) & (node[:, k] > 0)
                    holder[:, k] = node[:, k] // grid.block - 1
                else:
                    holder[:, k] = primary
            holder = np.clip(holder, 0, np.asarray(grid.grid) - 1)
            region = block_region[tuple(holder.T)]
            ok &= region >= 0
            joins.append(np.stack([ids[ok], region[ok]], 1))
    if not lows:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros((0, d))
    nodes, ids = np.concatenate(shared_nodes), np.concatenate(shared_ids)
    order = np.argsort(nodes, kind="stable")
    nodes, ids = nodes[order], ids[order]
    same = nodes[1:] == nodes[:-1]
    pairs = np.concatenate([np.stack([ids[:-1][same], ids[1:][same]], 1), *joins])
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(next_id, next_id))
    root = connected_components(graph, directed=False)[1]
    # An edge on two blocks' shared side was found in both.
    _, unique = np.unique(np.concatenate(edge_keys), return_index=True)
    low, high = np.concatenate(lows)[unique], np.concatenate(highs)[unique]
    return root[low].astype(np.int64), root[high].astype(np.int64), np.concatenate(mids)[unique]
