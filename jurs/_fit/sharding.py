"""Fits of clouds sharded over several devices: the Problem placed where the points are.

[`jurs.fit`][] given points (or normals) as a ``jax.Array`` sharded along the point axis
by a ``jax.sharding.NamedSharding`` over more than one device builds its
[`jurs.Problem`][] as for any concrete cloud, then places it on the same mesh: every
per-slot array (samples, targets, masks, local basis; the table form's per-bucket and
per-position arrays) sharded along its slot axis, the box and the scalars replicated. The
solve is then the same jitted function, and JAX's GSPMD partitioner splits it: the passes
over the samples (F, T, the moments of the normal equations) run on each device's own
slots, and their sums onto the grid become local sums and an all-reduce of grid-sized
arrays. Nothing here partitions by hand (docs/sharding.md).

In one process the sample layout ([`jurs.make_problem`][]: the offset samples, the sort
into buckets, the table form) is built from the whole cloud gathered on the host, and the
automatic settings and the orientation check read it there too: a sharded fit spreads the
solve's memory and work over the devices, not the host's.

Over several processes (``jax.distributed``: points and normals global arrays that are not
fully addressable, ``spans_processes``) [`jurs.fit`][] hands over to
``jurs._fit.fit.fit_across_processes``: each process builds the layout of its own rows only
(``process_problem``, the bucketed layout for curves, one sample a slot for
surfaces), the processes agree on the bucket size and on the slot count (two small
all-gathers), pad to it, and the per-slot arrays are assembled with
``jax.make_array_from_process_local_data``; ``sample_index`` counts in the global point
order. No process holds the whole cloud: the automatic settings are measured per
process and combined (``jurs._fit.process_settings``). What would read the whole cloud
on a host is not run there: the estimation of normals, the orientation and doubt checks,
the padding to stable sizes.

The slot count is padded to a whole number of buckets a device with masked-out copies of
the last bucket (the padding convention of [`jurs.internal.bucket_layout`][]), which the
solvers leave out of every sum; a sharded fit therefore equals the one-device fit up to
the order of the sums (rounding). Each device's cells stay sorted (its part of one
process's layout, sorted by cell), as the per-device sums onto the grid declare
(``indices_are_sorted``); over several processes the global slot order is not.
"""

from __future__ import annotations

import dataclasses
import gc
import math

import equinox as eqx
import jax
import numpy as np
from jax.core import Tracer
from jax.sharding import NamedSharding, PartitionSpec

from .._cloud.parts import local_rows
from .._model.basis import flat_cell, locate, num_cells
from .._model.local import LocalBasis
from .._problem.layout import choose_bucket_size
from .._problem.memory import check_memory, fit_memory
from .._problem.problem import Problem, make_problem, offset_samples, surface_bucket_size
from .._problem.validate import unit_normals, validate_inputs
from .._threads import release_freed_memory


def _point_sharding(x) -> NamedSharding | None:
    """``x``'s sharding where it is a concrete ``jax.Array`` split over more than one
    device (of one process or several), else None. ValueError for a split the fit cannot
    follow (not along the point axis, not a NamedSharding)."""
    if not isinstance(x, jax.Array) or isinstance(x, Tracer):
        return None
    sharding = x.sharding
    if len(sharding.device_set) <= 1:
        return None
    spec = getattr(sharding, "spec", None)
    if not isinstance(sharding, NamedSharding) or spec is None or not spec or spec[0] is None:
        raise ValueError(
            "sharded points must be split along the point axis by a NamedSharding, e.g. "
            "NamedSharding(Mesh(devices, ('points',)), PartitionSpec('points')); got "
            f"{sharding}"
        )
    if any(s is not None for s in tuple(spec)[1:]):
        raise ValueError(f"points must not be split along the coordinate axis, got {spec}")
    return sharding


def input_sharding(points, normals) -> NamedSharding | None:
    """The NamedSharding that [`jurs.fit`][] places its problem by: that of ``points``
    (else of ``normals``) where it splits the point axis over more than one device, else
    None (a one-device fit, unchanged). ValueError where points and normals are split over
    different meshes or axes."""
    found = [s for s in (_point_sharding(points), _point_sharding(normals)) if s is not None]
    if not found:
        return None
    first = found[0]
    for other in found[1:]:
        if other.mesh != first.mesh or other.spec[0] != first.spec[0]:
            raise ValueError(
                f"points and normals are sharded differently ({first} and {other}); "
                "split both the same way along the point axis"
            )
    return first


def point_axis_size(sharding: NamedSharding) -> int:
    """The number of shards along the point axis."""
    names = sharding.spec[0]
    names = names if isinstance(names, tuple) else (names,)
    return math.prod(sharding.mesh.shape[n] for n in names)


def _padded(x, axis: int, extra: int, zero: bool):
    """``x`` (host copy) with ``extra`` copies of its last entry along ``axis`` appended,
    those zeroed where ``zero``."""
    x = np.asarray(x)
    if extra == 0:
        return x
    tail = np.take(x, [-1], axis=axis)
    tail = np.zeros_like(tail) if zero else tail
    return np.concatenate([x, np.repeat(tail, extra, axis=axis)], axis=axis)


def _extra(count: int, multiple: int) -> int:
    return -count % multiple


def _padded_problem(problem: Problem, shards: int) -> tuple[Problem, dict]:
    """``(problem, axes)``: the problem's slots (and the table form's buckets) padded to a
    multiple of ``shards`` whole buckets with masked copies of the last one, on the host;
    ``axes`` maps each padded field's name to its slot (or bucket) axis."""
    local = problem.local
    k = local.bucket_size
    slot_extra = _extra(local.cell.shape[0], shards * k)
    slot_fields = {"samples": 0, "targets": 0, "mask": 0, "is_data": 0, "sample_index": 0}
    zeroed = {"mask", "is_data", "filled"}  # the padding takes no part in any sum
    values = {
        n: _padded(getattr(problem, n), a, slot_extra, n in zeroed) for n, a in slot_fields.items()
    }
    local_fields = {"cell": 0, "s": 1, "position": 0}
    if local.terms is not None:
        assert local.order is not None  # the table fields are set together
        table_k = local.order.shape[0] // local.index.shape[0]  # pyright: ignore[reportOptionalMemberAccess]
        bucket_extra = _extra(local.index.shape[0], shards)  # pyright: ignore[reportOptionalMemberAccess]
        table = {"terms": 1, "terms_t": 0, "index": 0, "corner": 0}
        positions = {"order": 0, "filled": 0}
        local_values = {
            n: _padded(getattr(local, n), a, bucket_extra, False) for n, a in table.items()
        }
        local_values.update(
            {
                n: _padded(getattr(local, n), a, bucket_extra * table_k, n in zeroed)
                for n, a in positions.items()
            }
        )
        local_fields.update(table)
        local_fields.update(positions)
    else:
        local_values = {}
    for n in ("cell", "s", "position"):
        if getattr(local, n) is not None:
            local_values[n] = _padded(getattr(local, n), local_fields[n], slot_extra, False)
    local = eqx.tree_at(
        lambda x: [getattr(x, n) for n in local_values],
        local,
        list(local_values.values()),
        is_leaf=lambda x: x is None,
    )
    problem = eqx.tree_at(
        lambda p: [getattr(p, n) for n in values] + [p.local],
        problem,
        list(values.values()) + [local],
    )
    axes = {**slot_fields, **{"local." + n: a for n, a in local_fields.items()}}
    return problem, axes


def _spec(axis: int, names) -> PartitionSpec:
    return PartitionSpec(*([None] * axis + [names]))


def shard_problem(problem: Problem, sharding: NamedSharding) -> Problem:
    """``problem`` placed over ``sharding``'s mesh: its slot, table-bucket and
    table-position axes padded (with masked entries) to whole buckets a shard and split
    along the point axis's mesh axes, the data points too where their count divides, every
    other array (box, offset, eps) replicated. The fit of the result equals that of
    ``problem`` up to the order of its sums."""
    shards = point_axis_size(sharding)
    problem, axes = _padded_problem(problem, shards)
    # Chunked sums over the slots run per device (jurs._linalg.normal.chunked_segment_sum);
    # the slots gathered by cell would read across devices: the assembly runs without them.
    groups = dict(group_slot=None, group_filled=None, group_position=None)
    local = dataclasses.replace(problem.local, parts=shards, **groups)
    problem = eqx.tree_at(lambda p: p.local, problem, local)
    mesh, names = sharding.mesh, sharding.spec[0]
    replicated = NamedSharding(mesh, PartitionSpec())

    def place(path, leaf):
        name = ".".join(getattr(k, "name", str(k)) for k in path)
        if name in axes:
            return NamedSharding(mesh, _spec(axes[name], names))
        if name in ("points", "normals") and leaf.shape[0] % shards == 0:
            return NamedSharding(mesh, _spec(0, names))
        return replicated

    shardings = jax.tree_util.tree_map_with_path(place, problem)
    return jax.device_put(problem, shardings)


def replicate(tree, sharding: NamedSharding):
    """Every array of ``tree`` (a solver's hyperparameters, a start spline) replicated over
    ``sharding``'s mesh, so that one jit takes them with the sharded problem (committed
    arrays on other devices would be refused)."""
    replicated = NamedSharding(sharding.mesh, PartitionSpec())
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.device_put(arrays, replicated), rest)


def is_sharded(problem) -> bool:
    """Whether ``problem``'s samples are split over more than one device."""
    samples = problem.samples
    return isinstance(samples, jax.Array) and len(samples.sharding.device_set) > 1


def place_fit(points, normals, problem: Problem, solver, init):
    """``(problem, solver, init)`` for [`jurs.fit`][]: unchanged for a one-device cloud;
    for points (or normals) sharded along the point axis over several devices
    (``input_sharding``), the problem split over their mesh (``shard_problem``)
    and the solver's arrays and ``init`` replicated on it."""
    sharding = input_sharding(points, normals)
    if sharding is None or not isinstance(problem.samples, jax.Array):
        return problem, solver, init
    return shard_problem(problem, sharding), replicate(solver, sharding), replicate(init, sharding)


# Several processes (jax.distributed): each lays out its own points.

#: The settings of a fit over several processes: where any is not given, all not given
#: are chosen over every process's points (``jurs._fit.process_settings``).
PROCESS_SETTINGS = ("grid", "offset", "eps", "domain", "solver")


def spans_processes(points, normals) -> bool:
    """Whether ``points`` or ``normals`` is a concrete ``jax.Array`` on the devices of
    several processes (not fully addressable): ``jurs._fit.fit.fit_across_processes``
    fits those."""
    return any(
        isinstance(x, jax.Array) and not isinstance(x, Tracer) and not x.is_fully_addressable
        for x in (points, normals)
    )


def process_positions(sharding: NamedSharding, shards: int) -> list[int]:
    """The positions along the point axis (``0 .. shards - 1``) held by this process's
    devices, in order. ValueError where devices of two processes hold one position (the
    points replicated across processes: both would count them)."""
    owners: dict[int, set[int]] = {}
    for device, index in sharding.devices_indices_map((shards,)).items():
        owners.setdefault(index[0].start or 0, set()).add(device.process_index)
    if any(len(o) > 1 for o in owners.values()):
        raise ValueError(
            "points over several processes must give each process its own rows: split the "
            f"point axis over mesh axes that separate the processes, got {sharding}"
        )
    me = jax.process_index()
    return sorted(p for p, o in owners.items() if me in o)


def _agreed(values: list[int], failure: Exception | None, what: str) -> np.ndarray:
    """``(processes, len(values))``: ``values`` of every process (one small all-gather).
    Where a process failed (``failure``) it raises its own error and every other process
    a RuntimeError naming it, instead of waiting for it in the next collective."""
    from jax.experimental.multihost_utils import process_allgather

    row = np.array([failure is not None, *values], np.int32)
    table = np.asarray(process_allgather(row))
    if failure is not None:
        raise failure
    failed = np.flatnonzero(table[:, 0])
    if failed.size:
        raise RuntimeError(f"process {failed.tolist()} failed {what} (see its error)")
    return table[:, 1:]


def _in_process(error: Exception) -> Exception:
    """``error`` (a ValueError or TypeError of this process's inputs) with its process
    named: rows it names count in that process's part."""
    named = type(error)(f"process {jax.process_index()}, its own part: {error}")
    named.__cause__ = error
    return named


def _local_bucket_size(points, normals, offset, shape, domain) -> int:
    """The automatic bucket size (``jurs._problem.problem.choose_bucket_size``) of this
    process's samples."""
    n = unit_normals(np.asarray(normals, float))
    p = np.asarray(points, float)
    samples, _ = offset_samples(p, n, float(offset), 1.0, np)  # pyright: ignore[reportArgumentType]
    box = np.asarray(domain, float)
    cells = flat_cell(locate(samples, box[0], box[1], shape, np)[0], shape)
    return choose_bucket_size(np.asarray(cells), num_cells(shape))


def process_problem(
    points, normals, shape, offset, eps, domain, margin, bucket_size, dtype, solver=None
) -> Problem:
    """The [`Problem`][jurs.Problem] of a cloud held by several processes, each building
    the sample layout of its own points only (their addressable rows):
    [`jurs.make_problem`][] of those, in the bucketed layout (one sample a slot for
    surfaces), with every process's slot count padded to the largest (masked copies of its
    last bucket) and the per-slot arrays assembled into global ones split along the
    points' mesh axis (``jax.make_array_from_process_local_data``); ``sample_index``
    counts in the global point order, so per-point sums see one cloud. Box, offset and eps
    replicated. Every process calls this (it runs two small all-gathers: the bucket size,
    the slot count); an input error in one process is raised in all. ``solver``: checks
    the memory of this process's share of the fit
    (``jurs._problem.problem.fit_memory``). Memory: each per-slot array is freed in this
    process as soon as its global array exists, and the heap's freed memory is returned
    to the system before and after the layout (``release_freed``)."""
    release_freed()  # a previous fit's freed buffers, before this layout's
    sharding = input_sharding(points, normals)
    assert sharding is not None
    shards = point_axis_size(sharding)
    positions = process_positions(sharding, shards)
    rows, p = local_rows(points)
    normal_rows, n = local_rows(normals)
    total = int(points.shape[0])
    if not np.array_equal(rows, normal_rows) or tuple(normals.shape) != tuple(points.shape):
        raise ValueError("normals must be shaped and split like the points")
    if 3 * total > np.iinfo(np.int32).max:  # sample_index is int32
        raise ValueError(f"{total} points: their sample indices exceed int32")
    surface = len(shape) == 3
    failure, k = None, 0
    try:  # this process's inputs, checked as make_problem checks a cloud
        validate_inputs(p, n, offset=offset, eps=eps, domain=domain, margin=margin)
        if solver is not None:
            grid = "grid=" + "x".join(map(str, shape))
            check_memory(grid, fit_memory(shape, 3 * len(rows), solver))
        if surface:
            k = surface_bucket_size(bucket_size)
        elif bucket_size is not None:
            if int(bucket_size) != bucket_size or bucket_size < 2:
                raise ValueError(
                    "bucket_size must be an int >= 2 for a curve fitted over several "
                    f"processes (the bucketed layout), got {bucket_size!r}"
                )
            k = int(bucket_size)
        else:
            k = _local_bucket_size(p, n, offset, shape, domain)
    except (TypeError, ValueError) as error:
        failure = _in_process(error)
    # One bucket size for all (a static field of the basis): the smallest chosen; a
    # curve's at least 2, so that small parts too take the bucketed layout, not the table.
    k = int(_agreed([k], failure, "checking its points")[:, 0].min())
    k = k if surface else max(k, 2)
    failure, per_device, local = None, 0, None
    try:
        local = make_problem(
            p, n, grid=shape, offset=offset, eps=eps, domain=domain, margin=margin,
            bucket_size=k, dtype=dtype,
        )  # fmt: skip
        per_device = -(-local.samples.shape[0] // (len(positions) * k)) * k
    except (TypeError, ValueError) as error:
        failure = _in_process(error)
    del p, n, normal_rows  # this process's rows: the layout holds what it needs
    per_device = int(_agreed([per_device], failure, "laying out its samples").max())
    assert local is not None and local.local.terms is None  # no table form
    extra = per_device * len(positions) - local.samples.shape[0]
    index = np.asarray(local.sample_index).astype(np.int64)
    kind, point = np.divmod(index, len(rows))
    del index
    global_index = (kind * total + rows[point]).astype(np.int32)  # in the global point order
    del kind, point
    # (array, slot axis, zeroed in the padding): the per-slot arrays, taken out of ``local``
    # so that each is freed as soon as its global array exists (one at a time, not the
    # whole layout held twice).
    slotted = dict(
        samples=(local.samples, 0, False),
        targets=(local.targets, 0, False),
        mask=(local.mask, 0, True),
        is_data=(local.is_data, 0, True),
        sample_index=(global_index, 0, False),
        cell=(local.local.cell, 0, False),
        s=(local.local.s, 1, False),
    )
    local_points, local_normals = local.points, local.normals
    box = (local.lower, local.upper, local.offset, local.eps)
    k = local.local.bucket_size
    del local, global_index
    mesh, names = sharding.mesh, sharding.spec[0]
    replicated = NamedSharding(mesh, PartitionSpec())

    def spread(x, axis: int):  # this process's slots of the global per-slot array
        size = list(x.shape)
        size[axis] = per_device * shards
        return jax.make_array_from_process_local_data(
            NamedSharding(mesh, _spec(axis, names)), x, tuple(size)
        )

    def same(x):  # one value on every device (the same in every process)
        x = np.asarray(x)
        return jax.make_array_from_process_local_data(replicated, x, x.shape)

    by_point_sharding = NamedSharding(mesh, _spec(0, names))

    def by_point(x, given=None):  # ``given``: a global array that may hold ``x`` already
        if (
            isinstance(given, jax.Array)
            and given.dtype == x.dtype
            and given.sharding.is_equivalent_to(by_point_sharding, given.ndim)
        ):
            return given  # the points, not cast: not copied again
        return jax.make_array_from_process_local_data(
            by_point_sharding, np.asarray(x), tuple(points.shape)
        )

    arrays = {}
    for name in list(slotted):
        x, axis, zero = slotted.pop(name)
        arrays[name] = spread(_padded(x, axis, extra, zero), axis)
        del x  # this process's copy: the global array holds its own
    basis = LocalBasis(cell=arrays.pop("cell"), s=arrays.pop("s"), bucket_size=k, parts=shards)
    problem = Problem(
        points=by_point(local_points, points),
        normals=by_point(local_normals),  # made unit length: its own
        lower=same(box[0]),
        upper=same(box[1]),
        offset=same(box[2]),
        eps=same(box[3]),
        local=basis,
        shape=tuple(shape),
        **arrays,
    )
    del local_points, local_normals
    release_freed()
    return problem


def release_freed() -> None:
    """Collect Python's garbage cycles and hand the memory freed on the host back to the
    system (glibc's ``malloc_trim``; elsewhere the collection only). A fit over several
    processes calls it before and after laying out its samples: the previous fit's
    buffers and the layout's host temporaries, freed but kept by the C heap, would
    otherwise stay in the resident set beneath the solve's buffers (which are mapped
    anew), and raise each process's peak (benchmarks/results/sharding.md)."""
    gc.collect()
    release_freed_memory()


def replicate_across_processes(tree, sharding: NamedSharding):
    """Every array of ``tree`` (host values, the same in every process) replicated on every
    device of ``sharding``'s mesh, in all processes."""
    replicated = NamedSharding(sharding.mesh, PartitionSpec())
    arrays, rest = eqx.partition(tree, eqx.is_array)
    arrays = jax.tree_util.tree_map(
        lambda x: jax.make_array_from_process_local_data(
            replicated, np.asarray(x), tuple(np.shape(x))
        ),
        arrays,
    )
    return eqx.combine(arrays, rest)
