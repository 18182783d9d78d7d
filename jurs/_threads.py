"""The host's threads: how many the host's NumPy and SciPy work uses, kept pools of them,
a SciPy CSR matrix's rows in blocks, independent pieces of work shared out over the
threads, and a sequence of items worked by the threads ahead of the caller.

SciPy's sparse products and NumPy's element-wise work on large arrays release the GIL,
so threads share the cores without another process. Every helper here gives the same
bits as the plain sequential loop: each piece of work is made alone, and the results
come back in their order. The pages a worker thread frees stay in its allocator arena,
where the main thread never reuses them: each helper hands them back when its threaded
work ends (``release_freed_memory``)."""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import functools
import os
import threading
from collections.abc import Callable, Iterable, Iterator, Sized
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np

#: At most this many threads for the host's sparse products: each thread's transposed
#: product in ``jurs._linalg.sparse.normal_product`` writes a whole coefficient-length
#: vector, so more threads cost memory and a longer sum for products that shrink;
#: measured on two cores only.
MAX_HOST_THREADS = 8


def host_threads() -> int:
    """The threads the host's threaded work uses: the CPUs this process may run on, at
    most ``MAX_HOST_THREADS``."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, MAX_HOST_THREADS))


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or None on a C library without it."""
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None


def release_freed_memory() -> None:
    """Give the heap's freed pages back to the system (glibc's ``malloc_trim``; nothing
    elsewhere). The allocator keeps the pages of freed buffers below its mmap threshold,
    so a step that frees many (a compiled fit's working arrays) leaves the process that
    much larger, and the next step's large arrays, mapped afresh, are added on top (a
    capped grid's trial fit before the hierarchy's assembly: docs/performance.md, "A
    hierarchy fit's host work and peak"). Pages freed by a worker thread sit in its
    arena, where the main thread's arrays never reuse them: the helpers below call this
    when their threaded work ends (docs/performance.md, "The host's threads")."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


#: The process's thread pools, by role and size, made on first use and kept: each thread
#: keeps the allocator's arena it took, so the freed pages of one call's work serve the
#: next call's, where pools made afresh each call took new threads, and each new thread
#: left its arena's freed pages held (hundreds of MB over a fit and its mesh).
_POOLS: dict[tuple[str, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()
_IN_POOL = threading.local()


def _forget_pools() -> None:
    """A forked child has none of its parent's threads: it makes pools of its own."""
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


def _mark_worker() -> None:
    _IN_POOL.inside = True


def in_worker() -> bool:
    """Whether this thread is one of this module's pool threads: work there runs
    sequentially (a pool thread waiting on its own pool could wait for ever)."""
    return getattr(_IN_POOL, "inside", False)


def pool(role: str, workers: int) -> ThreadPoolExecutor:
    """The kept pool of ``workers`` threads for ``role``."""
    key = (role, int(workers))
    with _POOLS_LOCK:
        found = _POOLS.get(key)
        if found is None:
            found = ThreadPoolExecutor(
                int(workers), thread_name_prefix=f"jurs-{role}", initializer=_mark_worker
            )
            _POOLS[key] = found
        return found


def row_blocks(matrix, count: int) -> list:
    """A SciPy CSR ``matrix``'s rows in ``count`` contiguous blocks of about equal entries,
    ``[(first row, block)]``, each block a CSR view of the matrix's own arrays: nothing
    is copied."""
    from scipy.sparse import csr_matrix

    bounds = np.searchsorted(matrix.indptr, np.linspace(0, matrix.nnz, count + 1))
    bounds[0], bounds[-1] = 0, matrix.shape[0]
    blocks = []
    for first, last in zip(bounds[:-1], bounds[1:]):
        if last <= first:
            continue
        start, stop = matrix.indptr[first], matrix.indptr[last]
        # Built empty, then given the views: SciPy's constructor copies a view of a much
        # larger array (its prune step), which would copy the whole matrix block by block.
        block = csr_matrix((int(last - first), matrix.shape[1]), dtype=matrix.dtype)
        block.data = matrix.data[start:stop]
        block.indices = matrix.indices[start:stop]
        block.indptr = (matrix.indptr[first : last + 1] - start).astype(matrix.indptr.dtype)
        blocks.append((int(first), block))
    return blocks


T = TypeVar("T")


def in_threads(work: Callable[[Any], T], items: Iterable[Any]) -> list[T]:
    """``[work(item) for item in items]``, the items shared out over ``host_threads``
    threads: for independent pieces of host work (chunks of points) whose NumPy
    operations release the GIL. The results come back in the items' order."""
    items = list(items)
    if host_threads() == 1 or len(items) <= 1 or in_worker():
        return [work(item) for item in items]
    out = list(pool("map", host_threads()).map(work, items))
    release_freed_memory()
    return out


#: ``by_rows`` splits an array only from this many rows on.
MIN_SPLIT_ROWS = 1 << 15


def by_rows(work: Callable[[np.ndarray], np.ndarray], array: np.ndarray) -> np.ndarray:
    """``work(array)`` for a ``work`` that maps each row of ``array`` on its own (the
    result's row ``i`` made from the array's row ``i`` alone): the rows cut in
    ``host_threads`` parts worked side by side, the results stacked in order."""
    threads = host_threads()
    if threads == 1 or len(array) < MIN_SPLIT_ROWS:
        return work(array)
    return np.concatenate(in_threads(work, np.array_split(array, threads)))


def product_by_rows(left, right):
    """``left @ right`` for SciPy CSR ``left`` and a SciPy sparse ``right``, as SciPy CSR
    with the same bits: ``left``'s rows in ``host_threads`` blocks of about equal entries
    (``row_blocks``), each block's product made in a thread (a product's row is made
    from that row of ``left`` alone, its entries in the same order), then copied into
    one matrix block by block, each block dropped once copied, so that the blocks and
    the result are not held whole at once."""
    from scipy.sparse import csr_matrix

    threads = host_threads()
    blocks = row_blocks(left, threads) if threads > 1 and not in_worker() else []
    if len(blocks) <= 1:
        return csr_matrix(left @ right)
    parts: list[Any] = in_threads(lambda block: csr_matrix(block[1] @ right), blocks)
    del blocks
    total = sum(part.nnz for part in parts)
    index = np.result_type(*(part.indices.dtype for part in parts))
    if total >= np.iinfo(np.int32).max:
        index = np.int64
    # Allocated, not written: a page costs memory once a block is copied onto it.
    data = np.empty(total, parts[0].dtype)
    indices = np.empty(total, index)
    indptr = np.zeros(left.shape[0] + 1, index)
    at = row = 0
    for k in range(len(parts)):
        part, parts[k] = parts[k], None
        count, rows = part.nnz, part.shape[0]
        data[at : at + count] = part.data
        indices[at : at + count] = part.indices
        indptr[row + 1 : row + rows + 1] = part.indptr[1:] + at
        at, row = at + count, row + rows
        del part
    out = csr_matrix((left.shape[0], right.shape[1]), dtype=data.dtype)
    out.data, out.indices, out.indptr = data, indices, indptr
    return out


def ahead(work: Callable[[Any], T], items: Iterable[Any]) -> Iterator[T]:
    """``work(item)`` for each item, in order, the next items' made in ``host_threads``
    worker threads while the caller handles this one's: host work in batches (a spline's
    values on blocks of a lattice) overlaps itself and what the caller does with each
    batch. At most ``host_threads() + 1`` results exist at once. With one thread
    (``host_threads``), or one item, a plain loop."""
    threads = host_threads()
    if threads == 1 or (isinstance(items, Sized) and len(items) <= 1) or in_worker():
        yield from map(work, items)
        return
    iterator = iter(items)
    workers = pool("ahead", threads)
    pending: collections.deque = collections.deque()

    def submit() -> None:
        for item in iterator:
            pending.append(workers.submit(work, item))
            return

    try:
        for _ in range(threads):
            submit()
        while pending:
            done = pending.popleft().result()
            submit()
            yield done
    finally:
        # The caller stopped early: the items made ahead are dropped, once they are done.
        for future in pending:
            if not future.cancel():
                future.exception()
        release_freed_memory()
