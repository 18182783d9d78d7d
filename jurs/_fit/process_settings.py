"""Automatic settings of a cloud held by several processes (``jax.distributed``): the
same choices as [`jurs.auto_settings`][], read off every process's own rows and combined
by small collectives (docs/sharding.md, "Automatic settings over processes").

* Clouds of at most ``PROBES`` points: the processes all-gather the whole cloud (at
  most ``PROBES`` rows, 0.5 MB in 3D float64) and every process chooses from it exactly
  as one process does: the same settings, bit for bit.
* Larger clouds: one process measures them at ``PROBES`` points evenly strided over the
  cloud's order (``jurs._cloud.measure.strided_probes``), against the whole cloud. Here
  each process measures the probes among its own rows against its own rows (a KD-tree
  of its part), and the per-probe values (nearest-neighbour distances, noise residuals,
  offset agreements, feature widths: at most ``PROBES`` numbers each) are all-gathered
  and reduced as one process reduces them (medians, fractions, the quantile). The
  domain and the data's diagonal come from an all-reduce (min/max) of every process's
  bounds, the sample count from the global shape: those are exact. A probe whose
  neighbours lie partly in another process's rows sees only those in its own, so near a
  boundary between parts the spacing reads longer and the noise slightly off; with parts
  that are contiguous pieces of the shape this touches a few probes a boundary, which the
  medians absorb (tests/test_distributed.py measures it). Points standing alone are not
  set aside (that needs every point's neighbours), and where a curve's lambda is chosen
  by held-out points the choice runs on the gathered probes, not the whole cloud.
"""

from __future__ import annotations

import jax
import numpy as np

from .._cloud.cloud import Cloud
from .._cloud.measure import (
    PROBES,
    feature_width,
    kd_tree,
    noise_residuals,
    offset_agreement,
    strided_probes,
)
from .._cloud.parts import agree, allgather, gather_ragged, local_rows
from .._problem.problem import offset_samples
from .._problem.sizes import DEFAULT_MARGIN
from .._problem.validate import unit_normals, validate_inputs
from .settings import (
    DEFAULT_MAX_GRID,
    DEFAULT_MAX_GRID_3D,
    FEATURE_CELLS,
    FEATURE_QUANTILE,
    Settings,
    choose_grid,
    choose_settings,
    choose_smoothing,
    data_cell,
    held_out_smoothing,
    scale_free_lam,
)


def check_global_arrays(points, normals) -> None:
    """ValueError unless ``points`` and ``normals`` are both global ``(m, d)``
    ``jax.Array`` s that no one process holds whole (split over the processes)."""
    for name, x in (("points", points), ("normals", normals)):
        if not isinstance(x, jax.Array) or x.is_fully_addressable or x.ndim != 2:
            raise ValueError(
                f"{name}: over several processes pass points and normals both as global "
                "(m, d) jax.Arrays split the same way along the point axis "
                "(jax.make_array_from_process_local_data)"
            )


def bounds_across_processes(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner of every process's rows ``x`` together (an all-reduce)."""
    d = x.shape[1]
    local = np.stack([x.min(axis=0), x.max(axis=0)]) if len(x) else np.full((2, d), np.nan)
    table = allgather(local)
    return np.nanmin(table[:, 0], axis=0), np.nanmax(table[:, 1], axis=0)


def local_cloud(points, normals) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``(rows, p, n, total)``: this process's rows of the global arrays, their indices in
    the global order, and the global point count (normals as given: ``jurs.Cloud``
    makes them unit length, once)."""
    rows, p = local_rows(points)
    normal_rows, n = local_rows(normals)
    if not np.array_equal(rows, normal_rows) or tuple(normals.shape) != tuple(points.shape):
        raise ValueError("normals must be shaped and split like the points")
    return rows, np.asarray(p, float), np.asarray(n, float), int(points.shape[0])


def settings_across_processes(
    points,
    normals,
    shape: tuple[int, ...] | None = None,
    offset=None,
    eps=None,
    domain=None,
    margin: float = DEFAULT_MARGIN,
    smoothing: float | None = None,
    solver=None,
    gather_limit: int = PROBES,
) -> Settings:
    """The automatic [`Settings`][jurs.Settings] of the cloud whose rows the global
    arrays ``points`` and ``normals`` spread over several processes; every process calls
    this with the same arguments and gets the same settings. Any of ``shape``,
    ``offset``, ``eps``, ``domain`` and ``smoothing`` given is kept. Clouds of at most
    ``gather_limit`` points are gathered and chosen from as one process chooses; larger
    ones are measured per process and combined (module docstring)."""
    rows, p, n, total = local_cloud(points, normals)
    failure = None
    try:  # this process's rows, checked as one process checks its cloud
        validate_inputs(p, n, offset=offset, eps=eps, domain=domain, margin=margin)
    except (TypeError, ValueError) as error:
        failure = type(error)(f"process {jax.process_index()}, its own part: {error}")
    agree(failure, "checking its points")
    if total <= gather_limit:  # the whole cloud is no more than the probes: gather it
        order = np.argsort(gather_ragged(rows), kind="stable")
        whole_p, whole_n = gather_ragged(p)[order], gather_ragged(n)[order]
        return choose_settings(
            Cloud(whole_p, whole_n), shape, offset, eps, domain, margin, smoothing, solver=solver
        )
    return _combined_settings(
        rows, p, n, total, shape, offset, eps, domain, margin, smoothing, gather_limit
    )


def _combined_settings(rows, p, n, total, shape, offset, eps, domain, margin, smoothing, most):
    """``settings_across_processes`` of a cloud over ``most`` points: measured at the
    probes each process holds, against its own rows, and combined (module docstring)."""
    ndim = p.shape[1]
    n = unit_normals(n)
    probes = strided_probes(total, most)
    assert probes is not None
    mine = np.flatnonzero(np.isin(rows, probes))  # positions in this process's rows
    sample = np.argsort(gather_ragged(rows[mine]), kind="stable")
    sample_p, sample_n = gather_ragged(p[mine])[sample], gather_ragged(n[mine])[sample]
    tree = kd_tree(p) if len(p) > 1 else None
    # Spacing: nearest other point of each probe in this process's rows (duplicates skipped).
    nearest = np.empty(0)
    if tree is not None and len(mine):
        dist = tree.query(p[mine], k=min(len(p), 4))[0][:, 1:]
        nearest = np.where(dist > 0, dist, np.inf).min(axis=1)
    nearest = gather_ragged(nearest)
    nearest = nearest[np.isfinite(nearest)]
    if nearest.size == 0:
        raise ValueError("all points coincide; the cloud has no extent")
    spacing = float(np.median(nearest))
    # Noise: each probe's residual RMS, from estimate_noise's per-probe form.
    residual = noise_residuals(p, n, tree, at=mine) if len(mine) else np.empty(0)
    residual = gather_ragged(np.asarray(residual, float))
    noise = float(np.median(residual)) if residual.size else 0.0
    if offset is None:
        d0 = max(0.5 * spacing, 2.0 * noise)
        ladder = d0 * 0.7 ** np.arange(6)
        # Agreement of every offset of the ladder: the probes' mean over all processes.
        local = offset_agreement(p, n, ladder, tree, mine) if len(mine) else np.zeros(6)
        table = allgather(np.concatenate([[len(mine)], len(mine) * np.asarray(local)]))
        agreement = table[:, 1:].sum(axis=0) / table[:, 0].sum()
        best = ladder[np.argmax(agreement >= agreement.max() - 0.01)]  # as choose_offset
        d = float(d0) if agreement[0] >= 0.99 else float(best)
    else:
        d = float(offset)
    e = d if eps is None else float(eps)
    if domain is None:  # make_problem's box: the offset samples' bounds and the margin
        samples = offset_samples(p, n, d, e, np)[0]  # pyright: ignore[reportArgumentType]
        lo, hi = bounds_across_processes(np.asarray(samples))
        pad = margin * float(np.max(hi - lo))
        lower, upper = lo - pad, hi + pad
    else:
        lower, upper = (np.asarray(c, float) for c in domain)
    max_grid = DEFAULT_MAX_GRID if ndim == 2 else DEFAULT_MAX_GRID_3D
    width = None
    if ndim == 2:
        radius = 2.0 * float(np.max(upper - lower)) / (max_grid - 3)
        local_width = feature_width(p, n, radius, spacing, mine)[0] if len(mine) else np.empty(0)
        width = gather_ragged(np.asarray(local_width, float))
    feature = np.inf if width is None else float(np.sort(width)[int(FEATURE_QUANTILE * width.size)])
    chosen = shape is None
    if chosen:
        shape = choose_grid(lower, upper, spacing, noise, max_grid, feature)
    lo, hi = bounds_across_processes(p)
    diagonal = float(np.linalg.norm(hi - lo))
    cell = float(np.max((upper - lower) / (np.asarray(shape) - 3)))
    thin = 0.0 if width is None else float(np.mean(width < FEATURE_CELLS * cell))
    unit = scale_free_lam(1.0, 3 * total, diagonal, lower, upper, cell)
    beta = choose_smoothing(d, noise, ndim) if smoothing is None else float(smoothing)
    held_out = None
    if beta is None:  # chosen by held-out points of the gathered probes
        sample_unit = scale_free_lam(1.0, 3 * len(sample_p), diagonal, lower, upper, cell)
        cloud = Cloud(sample_p, sample_n)
        beta, held_out = held_out_smoothing(cloud, None, shape, d, e, (lower, upper), sample_unit)
    return Settings(
        grid=tuple(shape),
        offset=d,
        eps=e,
        lam=beta * unit,
        smoothing=beta,
        domain=(tuple(map(float, lower)), tuple(map(float, upper))),
        spacing=spacing,
        noise=noise,
        held_out=held_out,
        thin_fraction=thin,
        data_cell=data_cell(ndim, spacing, noise, feature) if chosen else None,
    )
