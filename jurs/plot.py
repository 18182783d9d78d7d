"""Figures with matplotlib. Each function returns the Figure; save it with ``fig.savefig``
(``.png`` or ``.svg``).

* :func:`plot_fit` - the paper's view: heatmap of g, its zero curve, data and offset points;
  given a :class:`jurs.levelset.LevelSetReport`, supplementary components are highlighted.
* :func:`plot_iterations` - several iteration states of one run (like the paper's Fig. 15).
* :func:`plot_energy_history` - energy per step, log scale, for several solvers.
* :func:`plot_lambda_sensitivity` - metrics against the regularisation weight (Fig. 16).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import matplotlib.pyplot as plt
import numpy as np

from ._spline import ImplicitSpline
from .levelset import evaluate_grid, sampling_grid

#: Colour of the zero curve, and of supplementary components when they are highlighted.
ZERO_COLOUR = "k"
SUPPLEMENTARY_COLOUR = "magenta"


def evaluate_on_grid(spline: ImplicitSpline, resolution: int = 400, box=None):
    """g sampled on a regular grid over ``box`` (default the spline's box).

    ``resolution`` points along the longer side. Returns ``(xs, ys, values)`` with
    ``values[j, i] = g(xs[i], ys[j])``.
    """
    lower, upper = (spline.lower, spline.upper) if box is None else box
    xs, ys, _ = sampling_grid(lower, upper, resolution)
    return xs, ys, evaluate_grid(spline, xs, ys)


def _new_axes(ax, figsize=(6, 6)):
    if ax is None:
        fig, ax = plt.subplots(figsize=figsize, constrained_layout=True)
        return fig, ax
    return ax.figure, ax


def _heatmap(ax, xs, ys, values, limit=None):
    """Diverging heatmap of g, symmetric about 0 (blue inside, red outside)."""
    limit = float(np.nanmax(np.abs(values))) if limit is None else float(limit)
    limit = limit if limit > 0 else 1.0
    return ax.pcolormesh(xs, ys, values, cmap="RdBu_r", vmin=-limit, vmax=limit,
                         shading="auto", rasterized=True)


def _draw_data(ax, points, normals, offset, markersize=3):
    points = np.asarray(points)
    if normals is not None and offset is not None:
        normals = np.asarray(normals)
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        out, inn = points + offset * normals, points - offset * normals
        ax.plot(out[:, 0], out[:, 1], ".", color="tab:red", ms=markersize * 2 / 3,
                label="outer offsets (+eps)")
        ax.plot(inn[:, 0], inn[:, 1], ".", color="tab:blue", ms=markersize * 2 / 3,
                label="inner offsets (-eps)")
    ax.plot(points[:, 0], points[:, 1], "o", color="gold", mec="k", mew=0.4, ms=markersize,
            label="data points")


def _finish(ax, title=None):
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if title:
        ax.set_title(title, fontsize=10)


def plot_fit(spline: ImplicitSpline, points=None, normals=None, offset=None, *, ax=None,
             title=None, resolution: int = 400, levelset=None, colorbar: bool = True):
    """The paper's view: a heatmap of g over the box with a colour bar, its zero curve, the
    data points and, given ``normals`` and ``offset``, the inner and outer offset samples.

    ``levelset``: a :class:`jurs.levelset.LevelSetReport` of this spline; its components
    are drawn instead of matplotlib's own zero contour, supplementary ones in magenta and
    counted in the legend. Returns the Figure.
    """
    fig, ax = _new_axes(ax)
    xs, ys, values = evaluate_on_grid(spline, resolution)
    mesh = _heatmap(ax, xs, ys, values)
    if colorbar:
        fig.colorbar(mesh, ax=ax, label="g(x, y)", shrink=0.8)
    if levelset is None:
        ax.contour(xs, ys, values, levels=[0.0], colors=ZERO_COLOUR, linewidths=1.5)
    else:
        for c in levelset.components:
            ax.plot(c.polyline[:, 0], c.polyline[:, 1], "-", lw=1.5,
                    color=SUPPLEMENTARY_COLOUR if c.supplementary else ZERO_COLOUR)
    if points is not None:
        _draw_data(ax, points, normals, offset)
    ax.plot([], [], "-", color=ZERO_COLOUR, label="g = 0")  # contour lines carry no legend entry
    if levelset is not None and levelset.num_supplementary:
        ax.plot([], [], "-", color=SUPPLEMENTARY_COLOUR,
                label=f"supplementary g = 0 ({levelset.num_supplementary})")
    # Below the x-axis label, not on it.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8, frameon=False)
    _finish(ax, title)
    return fig


def plot_iterations(states, points=None, normals=None, offset=None, *, resolution: int = 200,
                    ncols: int | None = None, panel_size: float = 3.6, title=None):
    """Several states of one run side by side on one colour scale (like the paper's Fig. 15).

    Args:
        states: ``{step: spline}`` (e.g. the snapshots of
            :func:`jurs.fit_in_chunks`) or a sequence of ``(label, spline)``.
        points, normals, offset: data (and offset samples) drawn on every panel.
        resolution: heatmap nodes along the longer side.
        ncols: panels per row (default all in one row, at most 4).

    Returns the Figure (one colour bar for all panels).
    """
    items = ([(f"step {k}", s) for k, s in sorted(states.items())]
             if isinstance(states, Mapping) else list(states))
    if not items:
        raise ValueError("no states to plot")
    ncols = ncols or min(len(items), 4)
    nrows = -(-len(items) // ncols)
    figsize = (panel_size * ncols + 1.0, panel_size * nrows + 0.6)
    fig, axes = plt.subplots(nrows, ncols, figsize=figsize, constrained_layout=True,
                             squeeze=False)
    grids = [evaluate_on_grid(s, resolution) for _, s in items]
    limit = max(float(np.nanmax(np.abs(v))) for _, _, v in grids)
    for ax, (label, _), (xs, ys, values) in zip(axes.flat, items, grids):
        mesh = _heatmap(ax, xs, ys, values, limit)
        if np.nanmin(values) < 0 < np.nanmax(values):
            ax.contour(xs, ys, values, levels=[0.0], colors=ZERO_COLOUR, linewidths=1.2)
        if points is not None:
            _draw_data(ax, points, normals, offset, markersize=2)
        _finish(ax, label)
    for ax in list(axes.flat)[len(items):]:
        ax.set_visible(False)
    fig.colorbar(mesh, ax=axes, label="g(x, y)", shrink=0.8)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    handles.append(plt.Line2D([], [], color=ZERO_COLOUR))
    labels.append("g = 0")
    fig.legend(handles, labels, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    return fig


def plot_energy_history(histories, *, ax=None, title=None):
    """Energy against step on a log scale, one line per run.

    ``histories``: ``{label: Solution or 1-D array}``; a Solution contributes
    ``stats["energy_history"]`` up to its ``num_steps``. The energy is eq. 35's
    ``E = E_d + lam R`` with each run's own lambda. Returns the Figure.
    """
    fig, ax = _new_axes(ax, figsize=(6.5, 4.2))
    styles = ("-", "--", ":", "-.")  # runs that coincide stay visible
    for i, (label, h) in enumerate(histories.items()):
        if hasattr(h, "stats"):
            k = int(h.stats["num_steps"])
            h = np.asarray(h.stats["energy_history"])[: k + 1]
        h = np.asarray(h, float)
        keep = np.isfinite(h) & (h > 0)
        ax.plot(np.arange(len(h))[keep], h[keep], styles[i % len(styles)],
                lw=1.5 + (i % len(styles) > 0) * 0.5, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("energy E = E_d + lambda R (eq. 35)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return fig


_SENSITIVITY_LABELS = {
    "E": "E (eq. 35)", "E_d": "E_d (eq. 16)", "E_ave": "E_ave (eq. 36)", "E_max": "E_max (eq. 37)",
    "R": "R(C) (eq. 31)", "num_supplementary": "supplementary components",
    "num_components": "zero-set components", "chamfer": "Chamfer distance",
    "hausdorff": "Hausdorff distance",
}


def plot_lambda_sensitivity(lams: Sequence[float], records: Sequence[Mapping],
                            keys=("E_ave", "E_max", "R", "num_supplementary"), *, title=None,
                            lam_label: str = "lambda"):
    """Metrics against the regularisation weight, one panel each (like the paper's Fig. 16).

    Args:
        lams: the lambda of each run.
        records: one mapping of metric name to number per run (``sol.metrics``, merged with
            ``LevelSetReport.as_dict()`` for the level-set counts).
        keys: which metrics to plot. Energies use a log y axis, counts a linear one.
        lam_label: x-axis label (say which lambda: eq. 33's or the objective's).

    Returns the Figure.
    """
    lams = np.asarray(lams, float)
    if len(lams) != len(records) or len(lams) == 0:
        raise ValueError("need one record per lambda, and at least one")
    order = np.argsort(lams)
    lams = lams[order]
    records = [records[i] for i in order]
    ncols = min(len(keys), 2)
    nrows = -(-len(keys) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.4 * ncols, 3.2 * nrows),
                             constrained_layout=True, squeeze=False)
    positive = lams[lams > 0]
    for ax, key in zip(axes.flat, keys):
        y = np.array([float(r[key]) for r in records])
        count = key.startswith("num_")
        ax.plot(lams, y, "o-", lw=1.5, ms=4, drawstyle="default")
        if positive.size and lams.min() == 0:
            ax.set_xscale("symlog", linthresh=positive.min())
        elif positive.size == lams.size and lams.max() / lams.min() > 20:
            ax.set_xscale("log")
        if not count and (y > 0).all():
            ax.set_yscale("log")
        if count:
            ax.yaxis.get_major_locator().set_params(integer=True)
            ax.set_ylim(bottom=-0.5 if y.min() >= 0 else None)
        ax.set_xlabel(lam_label)
        ax.set_ylabel(_SENSITIVITY_LABELS.get(key, key))
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig
