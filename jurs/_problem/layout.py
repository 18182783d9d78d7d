"""Sample layouts: the 3m samples grouped into buckets that share a cell, so that the
per-sample sums of the solvers run as per-bucket sums (docs/design.md section 5)."""

from __future__ import annotations

import numpy as np

from .sizes import round_octave

#: Largest automatic bucket size.
MAX_BUCKET_SIZE = 64


#: Largest automatic bucket size of the table form of small problems (their per-bucket
#: sums are unrolled in one kernel).
SMALL_MAX_BUCKET_SIZE = 16


def choose_bucket_size(cells: np.ndarray, count: int, small: bool = False) -> int:
    """Automatic bucket size, a power of two: the largest not above the median number of
    samples per occupied cell (at most ``MAX_BUCKET_SIZE``), so that most buckets are full
    and padding stays below about half the slots. ``small`` (the table form of small
    problems): the largest not above half that median (at most ``SMALL_MAX_BUCKET_SIZE``),
    where padding costs as much as extra buckets (docs/design.md section 5, "Sample
    layouts"; docs/performance.md, "Measurements behind the defaults")."""
    counts = np.bincount(cells, minlength=count)
    median = float(np.median(counts[counts > 0]))
    if not small:
        cap = MAX_BUCKET_SIZE
    else:
        cap, median = SMALL_MAX_BUCKET_SIZE, median / 2.0
    return int(min(cap, 2 ** int(np.floor(np.log2(max(median, 1.0))))))


def round_buckets(count: int) -> int:
    """``count`` buckets rounded up to one of eight sizes an octave (at most 1/8 more),
    so that clouds of similar size share one compiled fit."""
    if count <= 32:
        return count
    step = 1 << (int(count).bit_length() - 4)
    return -(-count // step) * step


def bucket_layout(cells: np.ndarray, bucket_size: int, count: int, num_buckets: int | None = None):
    """Group sample indices into buckets of ``bucket_size`` samples sharing a cell.

    ``cells`` (S,) is each sample's flat cell, ``count`` the number of cells. Returns
    ``(slot_sample, valid)``, both ``(num_buckets * bucket_size,)``: the sample in each slot
    and whether it is real. Padding slots repeat their bucket's first sample (so the basis
    stays well defined) and have ``valid`` False. A cell with more samples than a bucket
    holds gets several buckets. Buckets are in cell order; ``num_buckets`` (at least the
    number needed) appends empty buckets in the last cell.
    """
    k = bucket_size
    # A stable sort by cell; 16-bit keys sort by radix, several times faster.
    keys = cells.astype(np.uint16) if count <= 1 << 16 else cells
    order = np.argsort(keys, kind="stable").astype(np.int32)
    sorted_cells = cells[order]
    counts = np.bincount(cells, minlength=count)
    buckets_per_cell = -(-counts // k)
    first_slot = (np.cumsum(buckets_per_cell) - buckets_per_cell) * k
    cell_start = np.cumsum(counts) - counts
    # Position within its cell (rank) plus the cell's first slot: consecutive buckets of a
    # cell are consecutive slots.
    slot = (first_slot - cell_start)[sorted_cells] + np.arange(cells.shape[0])
    needed = int(buckets_per_cell.sum())
    slot_sample = np.full(max(needed, num_buckets or 0) * k, -1, dtype=np.int32)
    slot_sample[slot] = order
    slot_sample[needed * k :] = order[-1]
    slot_sample = slot_sample.reshape(-1, k)
    valid = slot_sample >= 0
    valid[needed:] = False
    slot_sample = np.where(valid, slot_sample, slot_sample[:, :1])
    return slot_sample.reshape(-1), valid.reshape(-1)


def stable_layout(
    cells: np.ndarray,
    sample_mask: np.ndarray,
    count: int,
    bucket_size: int | None = None,
    small: bool = False,
):
    """[`bucket_layout`][jurs.internal.bucket_layout] of the real samples (``sample_mask`` > 0),
    sized from the number of slots (padding included) and the occupied cells rounded up by
    ``jurs._problem.sizes.round_octave``, not from the exact counts: clouds padded to one size
    ([`jurs.fit`][]) whose samples occupy about as many cells get the same shapes, so one
    compiled fit. Padding samples take no bucket.

    The bucket size (None chooses) is the power of two ``choose_bucket_size`` would take
    with the mean count per rounded occupied cell in place of the median. The number of
    buckets, ``ceil(S / K) + occupied``, bounds ``sum_cells ceil(count / K)`` for any
    placement of the real samples. Returns ``(slot_sample, valid, bucket_size)``.
    """
    real = np.flatnonzero(np.asarray(sample_mask) > 0)
    cells = np.asarray(cells)
    num_slots = cells.shape[0]
    occupied = min(
        count, round_octave(int(np.count_nonzero(np.bincount(cells[real], minlength=count))))
    )
    if bucket_size is None:
        cap, per_cell = (
            (SMALL_MAX_BUCKET_SIZE, num_slots / occupied / 2.0)
            if small
            else (MAX_BUCKET_SIZE, num_slots / occupied)
        )
        bucket_size = int(min(cap, 2 ** int(np.floor(np.log2(max(per_cell, 1.0))))))
    num_buckets = -(-num_slots // bucket_size) + occupied
    slot, valid = bucket_layout(cells[real], bucket_size, count, num_buckets)
    return real[slot].astype(np.int32), valid, bucket_size


#: Smallest group of ``cell_groups``: with fewer samples an occupied cell, grouping them
#: saves the assembly little and pads it much.
MIN_GROUP_SIZE = 4


def cell_groups(cells: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A problem's slots (``cells (S,)``: the flat cell of each) gathered by cell into
    groups of one size, for the assembly of a surface's normal equations
    ([`jurs.internal.with_groups`][]): ``(slot, valid)``, both ``(G, K)``; None where
    the samples are under ``MIN_GROUP_SIZE`` an occupied cell. Every slot takes part,
    masked ones too: a solver may weigh them in later (the robust fit's weights are its
    mask). Sized as ``stable_layout``, so that clouds padded to one size share one
    compiled fit."""
    slot, valid, k = stable_layout(cells, np.ones(cells.shape[0]), count)
    if k < MIN_GROUP_SIZE:
        return None
    return slot.reshape(-1, k), valid.reshape(-1, k)
