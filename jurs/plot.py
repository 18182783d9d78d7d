"""Figures with matplotlib. Each function returns the Figure; save it with ``fig.savefig``."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from ._spline import ImplicitSpline


def evaluate_on_grid(spline: ImplicitSpline, resolution: int = 400, box=None):
    """g sampled on a regular grid over ``box`` (default the spline's box).

    ``resolution`` points along the longer side. Returns ``(xs, ys, values)`` with
    ``values[j, i] = g(xs[i], ys[j])``.
    """
    lower, upper = (np.asarray(spline.lower), np.asarray(spline.upper)) if box is None else map(np.asarray, box)
    extent = upper - lower
    counts = np.maximum(2, np.round(resolution * extent / extent.max()).astype(int))
    xs = np.linspace(lower[0], upper[0], counts[0])
    ys = np.linspace(lower[1], upper[1], counts[1])
    gx, gy = np.meshgrid(xs, ys)
    values = np.asarray(spline(np.stack([gx.ravel(), gy.ravel()], axis=1))).reshape(gx.shape)
    return xs, ys, values


def plot_fit(spline: ImplicitSpline, points=None, normals=None, offset=None, *, ax=None,
             title=None, resolution: int = 400):
    """The paper's view: a heatmap of g over the box, its zero curve, the data points and,
    given ``normals`` and ``offset``, the inner and outer offset samples."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(6, 6), constrained_layout=True)
    else:
        fig = ax.figure
    xs, ys, values = evaluate_on_grid(spline, resolution)
    limit = np.max(np.abs(values))
    mesh = ax.pcolormesh(xs, ys, values, cmap="RdBu_r", vmin=-limit, vmax=limit, shading="auto")
    fig.colorbar(mesh, ax=ax, label="g(x, y)", shrink=0.8)
    ax.contour(xs, ys, values, levels=[0.0], colors="k", linewidths=1.5)
    if points is not None:
        points = np.asarray(points)
        if normals is not None and offset is not None:
            normals = np.asarray(normals)
            out, inn = points + offset * normals, points - offset * normals
            ax.plot(out[:, 0], out[:, 1], ".", color="tab:red", ms=2, label="outer offsets (+eps)")
            ax.plot(inn[:, 0], inn[:, 1], ".", color="tab:blue", ms=2, label="inner offsets (-eps)")
        ax.plot(points[:, 0], points[:, 1], "o", color="gold", mec="k", mew=0.4, ms=3,
                label="data points")
    ax.plot([], [], "k-", label="g = 0")  # contour lines carry no legend entry of their own
    if points is not None:
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=4, fontsize=8,
                  frameon=False)
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if title:
        ax.set_title(title)
    return fig
