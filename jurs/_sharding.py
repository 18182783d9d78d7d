"""Fits of clouds sharded over several devices: the Problem placed where the points are.

:func:`jurs.fit` given points (or normals) as a ``jax.Array`` sharded along the point axis
by a :class:`jax.sharding.NamedSharding` over more than one device builds its
:class:`jurs.Problem` as for any concrete cloud, then places it on the same mesh: every
per-slot array (samples, targets, masks, local basis; the table form's per-bucket and
per-position arrays) sharded along its slot axis, the box and the scalars replicated. The
solve is then the same jitted function, and JAX's GSPMD partitioner splits it: the passes
over the samples (F, T, the moments of the normal equations) run on each device's own
slots, and their sums onto the grid become local sums and an all-reduce of grid-sized
arrays. Nothing here partitions by hand (docs/sharding.md).

What stays on one machine: the sample layout (:func:`jurs.make_problem`: the offset
samples, the sort into buckets, the table form) is built from the whole cloud gathered on
the host, and the automatic settings and the orientation check read it there too. So a
sharded fit spreads the solve's memory and work over the devices, not the host's; clouds
split over several processes (``jax.distributed``, arrays that are not fully addressable)
are refused.

The slot count is padded to a whole number of buckets a device with masked-out copies of
the last bucket (the padding convention of :func:`jurs._problem.bucket_layout`), which the
solvers leave out of every sum; a sharded fit therefore equals the one-device fit up to
the order of the sums (rounding).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import numpy as np
from jax.core import Tracer
from jax.sharding import NamedSharding, PartitionSpec

from ._problem import Problem


def _point_sharding(x) -> NamedSharding | None:
    """``x``'s sharding where it is a concrete ``jax.Array`` split over more than one
    device, else None. ValueError for a split the fit cannot follow (not along the point
    axis, not a NamedSharding); NotImplementedError for arrays spread over processes."""
    if not isinstance(x, jax.Array) or isinstance(x, Tracer):
        return None
    sharding = x.sharding
    if len(sharding.device_set) <= 1:
        return None
    if not x.is_fully_addressable:
        raise NotImplementedError(
            "points sharded over several processes: jurs builds the sample layout from "
            "the whole cloud on one host (docs/sharding.md); gather it in one process"
        )
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
    """The NamedSharding that :func:`jurs.fit` places its problem by: that of ``points``
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


def _axis_size(sharding: NamedSharding) -> int:
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
    shards = _axis_size(sharding)
    problem, axes = _padded_problem(problem, shards)
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
    """``(problem, solver, init)`` for :func:`jurs.fit`: unchanged for a one-device cloud;
    for points (or normals) sharded along the point axis over several devices
    (:func:`input_sharding`), the problem split over their mesh (:func:`shard_problem`)
    and the solver's arrays and ``init`` replicated on it."""
    sharding = input_sharding(points, normals)
    if sharding is None or not isinstance(problem.samples, jax.Array):
        return problem, solver, init
    return shard_problem(problem, sharding), replicate(solver, sharding), replicate(init, sharding)
