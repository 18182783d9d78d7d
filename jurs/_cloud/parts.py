"""A cloud held by several processes (``jax.distributed``): each process's own rows of the
global arrays, small all-gathers of per-process values (the normals of such a cloud:
``normals.normals_across_processes``, docs/sharding.md, "Normals over processes")."""

from __future__ import annotations

import jax
import numpy as np
from jax.core import Tracer

from .measure import strided_probes


def spans_processes(x) -> bool:
    """Whether ``x`` is a concrete ``jax.Array`` on the devices of several processes (not
    fully addressable: no process can read it whole)."""
    return isinstance(x, jax.Array) and not isinstance(x, Tracer) and not x.is_fully_addressable


def local_rows(x) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, data)``: this process's rows of the global array ``x``, each once (its
    shards with replica id 0, in global order), and their indices in ``x``."""
    parts = sorted(
        (
            (s.index[0].start or 0, np.asarray(s.data))
            for s in x.addressable_shards
            if s.replica_id == 0
        ),
        key=lambda part: part[0],
    )
    rows = np.concatenate([start + np.arange(len(data)) for start, data in parts])
    return rows, np.concatenate([data for _, data in parts])


def allgather(x: np.ndarray) -> np.ndarray:
    """``(processes, *x.shape)``: ``x`` of every process (the same shape in all)."""
    from jax.experimental.multihost_utils import process_allgather

    return np.asarray(process_allgather(np.asarray(x)))


def gather_ragged(x: np.ndarray) -> np.ndarray:
    """Every process's ``x`` (rows may differ in number), concatenated in process order:
    one all-gather of the counts, one of the rows padded to the longest."""
    counts = allgather(np.array([len(x)], np.int64))[:, 0]
    longest = max(int(counts.max()), 1)
    padded = np.zeros((longest,) + x.shape[1:], x.dtype)
    padded[: len(x)] = x
    table = allgather(padded)
    return np.concatenate([table[i, : int(c)] for i, c in enumerate(counts)])


def gathered_probes(rows: np.ndarray, x: np.ndarray, total: int, most: int):
    """``(probes, values)``: the global indices of at most ``most`` of the ``total`` rows,
    evenly strided (all where ``total <= most``: ``strided_probes``), and the rows ``x``
    of them held by every process, gathered in global order."""
    probes = strided_probes(total, most)
    probes = np.arange(total) if probes is None else probes
    mine = np.flatnonzero(np.isin(rows, probes))
    held = gather_ragged(rows[mine])
    order = np.argsort(held, kind="stable")
    return held[order], gather_ragged(np.ascontiguousarray(x[mine]))[order]


def agree(failure: Exception | None, what: str) -> None:
    """Raise in every process where one failed (one all-gather of a flag): the failed
    process its own ``failure``, the others a RuntimeError naming it, instead of waiting
    for it in the next collective."""
    failed = np.flatnonzero(allgather(np.array([failure is not None], np.int32))[:, 0])
    if failure is not None:
        raise failure
    if failed.size:
        raise RuntimeError(f"process {failed.tolist()} failed {what} (see its error)")
