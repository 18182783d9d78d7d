"""A cloud read in parts, one per process (``jax.distributed``): each process reads only
its own rows of a large ``.npy`` (memory-mapped) or its own files of a list, and the parts
become global ``jax.Array`` s split along the point axis (docs/sharding.md, "Reading and
writing in parts"). Public through [`jurs.datasets`][].
"""

from __future__ import annotations

import glob
import os
from collections.abc import Sequence

import numpy as np
from jaxtyping import Float

from ._files import checked_cloud, cloud_from_table, load_points

#: Columns of a ``.npy`` read by rows, and what they hold: ``(dimension, with normals)``.
NPY_COLUMNS = {2: (2, False), 3: (3, False), 4: (2, True), 6: (3, True)}


def part_rows(total: int, process_index: int, process_count: int) -> slice:
    """The rows of ``total`` that process ``process_index`` of ``process_count`` reads:
    contiguous, in process order, the counts differing by at most one
    (``total * i // count`` to ``total * (i + 1) // count``). Where ``total`` is a
    multiple of the device count these are exactly the rows the process's devices hold
    of an ``(total, d)`` array split over a 1-D mesh of ``jax.devices()`` (process by
    process, the same number of devices each): ``jurs._cloud.parts.local_rows``."""
    _check_process(process_index, process_count)
    if total < process_count:
        raise ValueError(
            f"{total} rows for {process_count} processes: every process needs rows of its own"
        )
    i, count = process_index, process_count
    return slice(total * i // count, total * (i + 1) // count)


def part_files(paths: Sequence[str], process_index: int, process_count: int) -> list[str]:
    """The files of ``paths`` (in their order) that process ``process_index`` of
    ``process_count`` reads: a contiguous run, the counts differing by at most one. Fewer
    files than processes is refused (ValueError): a file is read whole by one process,
    and a process without rows cannot hold a part of the cloud."""
    _check_process(process_index, process_count)
    if len(paths) < process_count:
        raise ValueError(
            f"{len(paths)} file(s) for {process_count} processes: each file is read whole by "
            "one process, so every process needs at least one; split the cloud into more "
            "files, or write it as one .npy (read by rows)"
        )
    share = slice(
        len(paths) * process_index // process_count,
        len(paths) * (process_index + 1) // process_count,
    )
    return list(paths[share])


def _check_process(process_index, process_count) -> None:
    for name, value in (("process_index", process_index), ("process_count", process_count)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ValueError(f"{name} must be an int, got {value!r}")
    if process_count < 1 or not 0 <= process_index < process_count:
        raise ValueError(
            f"process_index must lie in 0 .. process_count - 1, got {process_index} of "
            f"{process_count}"
        )


def _paths(path_or_paths) -> list[str]:
    """Files named: one path, a glob pattern (sorted matches; FileNotFoundError where none)
    or a sequence of paths (in its order)."""
    if isinstance(path_or_paths, (str, os.PathLike)):
        name = os.fspath(path_or_paths)
        if glob.has_magic(name) and not os.path.exists(name):
            paths = sorted(glob.glob(name))
            if not paths:
                raise FileNotFoundError(f"{name}: no file matches")
            return paths
        paths = [name]
    else:
        paths = [os.fspath(p) for p in path_or_paths]
        if not paths:
            raise ValueError("path_or_paths: no files given")
    return paths


def _check_exist(paths: list[str]) -> None:
    """FileNotFoundError naming every one of ``paths`` that is missing."""
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        shown = ", ".join(missing[:5]) + more
        raise FileNotFoundError(f"{shown}: no such file")


def load_rows(
    path_or_paths,
    process_index: int | None = None,
    process_count: int | None = None,
    *,
    mesh_samples: int | None = None,
) -> tuple[Float[np.ndarray, "mi d"], Float[np.ndarray, "mi d"] | None]:
    """This process's part of a cloud that no one process reads whole: ``(points,
    normals)`` of its own rows (normals None where the data has none), float64.

    * **One ``.npy``**: an ``(m, c)`` numeric array, memory-mapped; only this process's
      rows are read ([`part_rows`][jurs.datasets.part_rows]: contiguous, in process
      order, the counts differing by at most one). The columns say what it holds:
      ``x y`` (2), ``x y z`` (3), ``x y nx ny`` (4) or ``x y z nx ny nz`` (6). Points and
      normals in one array, so that one row is one point (save them with
      ``np.save(path, np.hstack([points, normals]))``, or
      [`save_points`][jurs.datasets.save_points] in 2D).
    * **Several files** (a sequence of paths, in its order, or a glob pattern such as
      ``"scan_*.ply"``, its matches sorted): whole files are split over the processes
      ([`part_files`][jurs.datasets.part_files]: a contiguous run each, the counts
      differing by at most one), and each process reads its own with
      [`load_points`][jurs.datasets.load_points] (``mesh_samples`` is passed on) and
      concatenates them in order. Every file must hold the same columns: the same
      dimension, all with normals or all without. One path that is not a ``.npy`` is a
      list of one file. Every process must be given the same list (a glob sees the same
      files where the folder is shared; on machines with their own disks pass the list),
      and checks that its own files exist.

    The parts together are the whole cloud, in the order of the rows and the files,
    process 0's first: [`global_arrays`][jurs.datasets.global_arrays] makes them the global
    arrays [`jurs.fit`][] takes.

    ``process_index`` and ``process_count`` default to ``jax.process_index()`` and
    ``jax.process_count()`` (after ``jax.distributed.initialize``, or
    [`jurs.distributed.initialize`][]); pass both to read a part without JAX's runtime.

    Raises FileNotFoundError naming this process's missing files (or a pattern without
    matches), ValueError for fewer rows or files than processes (every process must hold
    a part), for a ``.npy`` that is not a 2-D numeric array of 2, 3, 4 or 6 columns, for files of
    different columns (naming the first that differs from the part's first), and for the
    checks of [`load_points`][jurs.datasets.load_points] on this process's rows
    (NaN/Inf, zero normals; a ``.npy`` row is named by its row in the whole file).
    """
    if process_index is None or process_count is None:
        import jax

        process_index = jax.process_index() if process_index is None else process_index
        process_count = jax.process_count() if process_count is None else process_count
    paths = _paths(path_or_paths)
    if len(paths) == 1 and paths[0].lower().endswith(".npy"):
        _check_exist(paths)
        return _npy_rows(paths[0], process_index, process_count)
    mine = part_files(paths, process_index, process_count)
    _check_exist(mine)  # its own only: machines may hold only their own files
    parts = [(path, *load_points(path, mesh_samples=mesh_samples)) for path in mine]
    first, p0, n0 = parts[0]
    for path, p, n in parts[1:]:
        if p.shape[1] != p0.shape[1] or (n is None) != (n0 is None):
            raise ValueError(
                f"{path}: {_columns(p, n)}, but {first} holds {_columns(p0, n0)}: every file "
                "of a cloud read in parts must hold the same columns"
            )
    points = np.concatenate([p for _, p, _ in parts])
    normals = None if n0 is None else np.concatenate([n for _, _, n in parts])  # pyright: ignore[reportCallIssue, reportArgumentType]
    return points, normals


def _columns(points, normals) -> str:
    return f"{points.shape[1]}D points {'with' if normals is not None else 'without'} normals"


def _npy_rows(path: str, process_index: int, process_count: int):
    """This process's rows of a memory-mapped ``.npy``, checked as
    [`load_points`][jurs.datasets.load_points] checks a table (rows named as in the file)."""
    try:
        table = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:  # corrupt header, pickled objects, ...
        raise ValueError(f"{path}: not a readable .npy array ({exc})") from None
    if not np.issubdtype(table.dtype, np.number):
        raise ValueError(f"{path}: array dtype {table.dtype} is not numeric")
    if table.ndim != 2 or table.shape[1] not in NPY_COLUMNS:
        raise ValueError(
            f"{path}: expected an (m, c) array of c = 2 (x y), 3 (x y z), 4 (x y nx ny) or 6 "
            f"(x y z nx ny nz) columns, got shape {table.shape}"
        )
    rows = part_rows(table.shape[0], process_index, process_count)
    mine = np.asarray(table[rows], dtype=float)  # reads these rows only
    numbers = np.arange(rows.start, rows.stop) + 1  # 1-based rows of the whole file
    d, with_normals = NPY_COLUMNS[table.shape[1]]
    if d == 2:
        return cloud_from_table(mine, path, numbers)
    normals = mine[:, 3:] if with_normals else None
    points, normals = checked_cloud(mine[:, :3], normals, path, numbers)
    return points, normals


# --- the parts as global arrays -----------------------------------------------------------


def _outgoing(own: np.ndarray, start: int, target: tuple[int, int]):
    """``(indices, rows)``: the rows of ``own`` (global rows ``start, start + 1, ...``) that
    lie outside this process's ``target`` range of global rows, which other processes
    hold."""
    index = start + np.arange(len(own))
    away = (index < target[0]) | (index >= target[1])
    return index[away], own[away]


def _assemble(own, start: int, target: tuple[int, int], index, rows) -> np.ndarray:
    """The global rows ``target[0] .. target[1] - 1``: those of ``own`` (global rows from
    ``start``) in range, and those among the rows other processes sent (global ``index``);
    AssertionError unless every row is found once."""
    lo, hi = target
    out = np.empty((hi - lo,) + own.shape[1:], own.dtype)
    filled = np.zeros(hi - lo, bool)
    a, b = max(lo, start), min(hi, start + len(own))
    if a < b:
        out[a - lo : b - lo] = own[a - start : b - start]
        filled[a - lo : b - lo] = True
    take = (index >= lo) & (index < hi)
    out[index[take] - lo] = rows[take]
    filled[index[take] - lo] = True
    assert filled.all(), "rows lost between processes"
    return out


def _target(sharding, shape) -> tuple[int, int]:
    """The global rows this process's devices hold under ``sharding`` (one contiguous
    range; ValueError for a split that gives a process rows apart)."""
    ranges = sorted(
        (index[0].start or 0, index[0].stop if index[0].stop is not None else shape[0])
        for index in sharding.addressable_devices_indices_map(shape).values()
    )
    lo, hi = ranges[0][0], ranges[0][1]
    for a, b in ranges[1:]:
        if a > hi:
            raise ValueError(
                "sharding: this process's devices hold rows apart; order the mesh's devices "
                "process by process (Mesh(np.array(jax.devices()), ('points',)))"
            )
        hi = max(hi, b)
    return lo, hi


def global_arrays(
    points: Float[np.ndarray, "mi d"],
    normals: Float[np.ndarray, "mi d"] | None = None,
    *,
    sharding=None,
    drop_remainder: bool = False,
):
    """Global ``jax.Array`` s of the whole cloud from every process's part (its rows from
    [`load_rows`][jurs.datasets.load_rows]): ``(points, normals)``, both ``(m, d)`` split
    along the point axis over ``sharding``'s devices (normals None where ``normals`` is
    None). Every process calls it, with its own part; the row order is process 0's part
    first, then process 1's, and so on.

    ``sharding``: a ``NamedSharding`` that splits the rows over a mesh axis; default every
    device of every process, ``NamedSharding(Mesh(np.array(jax.devices()), ("points",)),
    PartitionSpec("points"))``. The devices hold equal numbers of rows (JAX splits an
    axis evenly), so a process's devices may need rows another process read: where the
    parts are not the split's rows (files of different sizes, an ``.npy`` whose rows do
    not divide by the device count), the rows that belong elsewhere are exchanged. Those
    rows only travel: an all-gather of every process's outgoing rows, each process
    keeping its own. With parts of equal size nothing moves; parts far from equal (one
    process read most of the cloud) send most of it to every process, so keep the files
    of similar sizes.

    The point count m must be a multiple of the number of devices along the split (JAX's
    even split): ValueError otherwise, naming the count of rows left over;
    ``drop_remainder=True`` drops those last rows (fewer than the devices) instead.
    Processes whose parts differ in dimension, or with normals in some and not others,
    raise ValueError in every process. Built with
    ``jax.make_array_from_process_local_data``; in one process the same call makes the
    arrays of its devices.
    """
    import jax
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from .._cloud.parts import allgather, gather_ragged

    points = np.ascontiguousarray(points)
    if points.ndim != 2 or normals is not None and np.shape(normals) != points.shape:
        raise ValueError(
            f"points must be (m, d) and normals None or the same shape, got {points.shape} and "
            f"{None if normals is None else np.shape(normals)}"
        )
    if sharding is None:
        mesh = Mesh(np.array(jax.devices()), ("points",))
        sharding = NamedSharding(mesh, PartitionSpec("points"))
    if not isinstance(sharding, NamedSharding) or not sharding.spec or sharding.spec[0] is None:
        raise ValueError(
            "sharding: pass a NamedSharding that splits the rows (PartitionSpec('points'))"
        )
    axes = sharding.spec[0] if isinstance(sharding.spec[0], tuple) else (sharding.spec[0],)
    parts = int(np.prod([sharding.mesh.shape[a] for a in axes]))
    table = allgather(np.array([len(points), points.shape[1], normals is not None], np.int64))
    if len(set(map(tuple, table[:, 1:].tolist()))) > 1:
        said = ", ".join(
            f"process {i}: {d}D {'with' if n else 'without'} normals"
            for i, (_, d, n) in enumerate(table.tolist())
        )
        raise ValueError(f"the parts hold different columns ({said})")
    counts = table[:, 0]
    total = int(counts.sum())
    left = total % parts
    if left and not drop_remainder:
        raise ValueError(
            f"{total} points over {parts} devices: JAX splits the rows evenly, and {left} "
            f"are left over; pass drop_remainder=True to drop the last {left} rows, or read "
            "a multiple of the device count"
        )
    total -= left
    d = points.shape[1]
    start = int(counts[: jax.process_index()].sum())
    keep = max(0, min(len(points), total - start))  # rows past ``total`` dropped
    target = _target(sharding, (total, d))
    dtype = jax.dtypes.canonicalize_dtype(float)  # float32 where JAX's x64 is off
    if (start, start + keep) == target:  # this part is its devices' rows: no copy
        empty = np.empty((0, 2 * d if normals is not None else d), dtype)
        gather_ragged(np.empty(0, np.int64)), gather_ragged(empty)  # the others' exchange
        mine_p = np.asarray(points[:keep], dtype)
        mine_n = None if normals is None else np.asarray(np.asarray(normals)[:keep], dtype)
    else:
        own = points if normals is None else np.concatenate([points, np.asarray(normals)], 1)
        own = own[:keep].astype(dtype)
        index, rows = _outgoing(own, start, target)
        mine = _assemble(own, start, target, gather_ragged(index), gather_ragged(rows))
        mine_p, mine_n = mine[:, :d], (None if normals is None else mine[:, d:])

    def make(x):
        return jax.make_array_from_process_local_data(sharding, np.ascontiguousarray(x), (total, d))

    return make(mine_p), (None if mine_n is None else make(mine_n))
