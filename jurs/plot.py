"""Figures with matplotlib. Each function returns the Figure; save it with ``fig.savefig``
(``.png`` or ``.svg``). New figures are pyplot's (``plt.show()`` and notebooks show them);
matplotlib itself loads at the first figure, not at ``import jurs.plot``.

* [`plot_fit`][jurs.plot.plot_fit] - the paper's view: heatmap of g, its zero curve, data
  and offset points; given a [`jurs.levelset.LevelSetReport`][], supplementary components
  are highlighted.
* [`plot_iterations`][jurs.plot.plot_iterations] - several iteration states of one run (like
  the paper's Fig. 15).
* [`plot_energy_history`][jurs.plot.plot_energy_history] - energy per step, log scale, for
  several solvers.
* [`plot_lambda_sensitivity`][jurs.plot.plot_lambda_sensitivity] - metrics against the
  regularisation weight (Fig. 16).
* [`plot_mesh`][jurs.plot.plot_mesh] - a triangle mesh (a surface's zero set,
  [`jurs.levelset.mesh`][]) from two or three directions side by side, shaded.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

from ._model.spline import ImplicitSpline
from .levelset import evaluate_grid, sampling_grid
from .levelset._faces import check_mesh

if TYPE_CHECKING:  # matplotlib loads at the first figure
    from matplotlib.figure import Figure

#: Colour of the zero curve, and of supplementary components when they are highlighted.
ZERO_COLOUR = "k"
SUPPLEMENTARY_COLOUR = "magenta"


def evaluate_on_grid(
    spline: ImplicitSpline, resolution: int = 400, box=None
) -> tuple[Float[np.ndarray, " nx"], Float[np.ndarray, " ny"], Float[np.ndarray, "ny nx"]]:
    """g sampled on a regular grid over ``box`` (default the spline's box).

    ``resolution`` points along the longer side. Returns ``(xs, ys, values)`` with
    ``values[j, i] = g(xs[i], ys[j])``.
    """
    lower, upper = (spline.lower, spline.upper) if box is None else box
    xs, ys, _ = sampling_grid(lower, upper, resolution)
    return xs, ys, evaluate_grid(spline, xs, ys)


def _new_figure(*, pyplot: bool = True, **kwargs):
    """A new Figure (``kwargs`` as ``plt.figure`` takes them): pyplot's own, or with
    ``pyplot=False`` a standalone one with an Agg canvas, which writes files without
    loading pyplot or a GUI backend (the command line's figures)."""
    if pyplot:
        import matplotlib.pyplot as plt

        return plt.figure(**kwargs)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _new_axes(ax, figsize=(6, 6), *, pyplot: bool = True):
    """``(figure, axes)``: ``ax`` and its figure, or a new figure with one axes."""
    if ax is None:
        fig = _new_figure(pyplot=pyplot, figsize=figsize, layout="constrained")
        return fig, fig.subplots()
    return ax.figure, ax


def _heatmap(ax, xs, ys, values, limit=None):
    """Diverging heatmap of g, symmetric about 0 (blue inside, red outside)."""
    limit = float(np.nanmax(np.abs(values))) if limit is None else float(limit)
    limit = limit if limit > 0 else 1.0
    return ax.pcolormesh(
        xs, ys, values, cmap="RdBu_r", vmin=-limit, vmax=limit, shading="auto", rasterized=True
    )


def _draw_data(ax, points, normals, offset, markersize=3):
    points = np.asarray(points)
    if normals is not None and offset is not None:
        normals = np.asarray(normals)
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        for side, color, label in (
            (1, "tab:red", "outer offsets (+eps)"),
            (-1, "tab:blue", "inner offsets (-eps)"),
        ):
            shifted = points + side * offset * normals
            ax.plot(
                shifted[:, 0], shifted[:, 1], ".", color=color, ms=markersize * 2 / 3, label=label
            )
    ax.plot(
        points[:, 0],
        points[:, 1],
        "o",
        color="gold",
        mec="k",
        mew=0.4,
        ms=markersize,
        label="data points",
    )


def _finish(ax, title=None):
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if title:
        ax.set_title(title, fontsize=10)


def plot_fit(
    spline: ImplicitSpline,
    points: Float[npt.ArrayLike, "m 2"] | None = None,
    normals: Float[npt.ArrayLike, "m 2"] | None = None,
    offset: float | None = None,
    *,
    ax=None,
    title=None,
    resolution: int = 400,
    levelset=None,
    colorbar: bool = True,
) -> Figure:
    """The paper's view: a heatmap of g over the box with a colour bar, its zero curve, the
    data points and, given ``normals`` and ``offset``, the inner and outer offset samples.

    ``levelset``: a [`jurs.levelset.LevelSetReport`][] of this spline; its components
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
            ax.plot(
                c.polyline[:, 0],
                c.polyline[:, 1],
                "-",
                lw=1.5,
                color=SUPPLEMENTARY_COLOUR if c.supplementary else ZERO_COLOUR,
            )
    if points is not None:
        _draw_data(ax, points, normals, offset)
    ax.plot([], [], "-", color=ZERO_COLOUR, label="g = 0")  # contour lines carry no legend entry
    if levelset is not None and levelset.num_supplementary:
        ax.plot(
            [],
            [],
            "-",
            color=SUPPLEMENTARY_COLOUR,
            label=f"supplementary g = 0 ({levelset.num_supplementary})",
        )
    # Below the x-axis label, not on it.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8, frameon=False)
    _finish(ax, title)
    return fig


def plot_iterations(
    states,
    points: Float[npt.ArrayLike, "m 2"] | None = None,
    normals: Float[npt.ArrayLike, "m 2"] | None = None,
    offset: float | None = None,
    *,
    resolution: int = 200,
    ncols: int | None = None,
    panel_size: float = 3.6,
    title=None,
) -> Figure:
    """Several states of one run side by side on one colour scale (like the paper's Fig. 15).

    Args:
        states: ``{step: spline}`` (e.g. the snapshots of
            [`jurs.fit_in_chunks`][]) or a sequence of ``(label, spline)``.
        points, normals, offset: data (and offset samples) drawn on every panel.
        resolution: heatmap nodes along the longer side.
        ncols: panels per row (default all in one row, at most 4).

    Returns the Figure (one colour bar for all panels).
    """
    items = (
        [(f"step {k}", s) for k, s in sorted(states.items())]
        if isinstance(states, Mapping)
        else list(states)
    )
    if not items:
        raise ValueError("no states to plot")
    ncols = ncols or min(len(items), 4)
    nrows = -(-len(items) // ncols)
    figsize = (panel_size * ncols + 1.0, panel_size * nrows + 0.6)
    fig = _new_figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    grids = [evaluate_on_grid(s, resolution) for _, s in items]
    limit = max(float(np.nanmax(np.abs(v))) for _, _, v in grids)
    for ax, (label, _), (xs, ys, values) in zip(axes.flat, items, grids):
        mesh = _heatmap(ax, xs, ys, values, limit)
        if np.nanmin(values) < 0 < np.nanmax(values):
            ax.contour(xs, ys, values, levels=[0.0], colors=ZERO_COLOUR, linewidths=1.2)
        if points is not None:
            _draw_data(ax, points, normals, offset, markersize=2)
        _finish(ax, label)
    for ax in list(axes.flat)[len(items) :]:
        ax.set_visible(False)
    fig.colorbar(mesh, ax=axes, label="g(x, y)", shrink=0.8)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    from matplotlib.lines import Line2D

    handles.append(Line2D([], [], color=ZERO_COLOUR))
    labels.append("g = 0")
    fig.legend(handles, labels, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    return fig


def plot_energy_history(histories, *, ax=None, title=None) -> Figure:
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
        ax.plot(
            np.arange(len(h))[keep],
            h[keep],
            styles[i % len(styles)],
            lw=1.5 + (i % len(styles) > 0) * 0.5,
            label=label,
        )
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("energy E = E_d + lambda R (eq. 35)")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return fig


_SENSITIVITY_LABELS = {
    "E": "E (eq. 35)",
    "E_d": "E_d (eq. 16)",
    "E_ave": "E_ave (eq. 36)",
    "E_max": "E_max (eq. 37)",
    "R": "R(C) (eq. 31)",
    "num_supplementary": "supplementary components",
    "num_components": "zero-set components",
    "chamfer": "Chamfer distance",
    "hausdorff": "Hausdorff distance",
}


def plot_lambda_sensitivity(
    lams: Sequence[float],
    records: Sequence[Mapping],
    keys=("E_ave", "E_max", "R", "num_supplementary"),
    *,
    title=None,
    lam_label: str = "lambda",
) -> Figure:
    """Metrics against the regularisation weight, one panel each (like the paper's Fig. 16).

    Args:
        lams: the lambda of each run.
        records: one mapping of metric name to number per run (``sol.metrics``, merged with
            ``LevelSetReport.as_dict()`` for the level-set counts).
        keys: which metrics to plot. Energies use a log y axis, counts a linear one.
        lam_label: x-axis label (say which lambda: eq. 33's or the objective's).

    Returns the Figure.
    """
    lam = np.asarray(lams, float)
    if len(lam) != len(records) or len(lam) == 0:
        raise ValueError("need one record per lambda, and at least one")
    order = np.argsort(lam)
    lam = lam[order]
    records = [records[i] for i in order]
    ncols = min(len(keys), 2)
    nrows = -(-len(keys) // ncols)
    fig = _new_figure(figsize=(4.4 * ncols, 3.2 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    positive = lam[lam > 0]
    for ax, key in zip(axes.flat, keys):
        y = np.array([float(r[key]) for r in records])
        count = key.startswith("num_")
        ax.plot(lam, y, "o-", lw=1.5, ms=4, drawstyle="default")
        if positive.size and lam.min() == 0:
            ax.set_xscale("symlog", linthresh=positive.min())
        elif positive.size == lam.size and lam.max() / lam.min() > 20:
            ax.set_xscale("log")
        if not count and (y > 0).all():
            ax.set_yscale("log")
        if count:
            ax.yaxis.get_major_locator().set_params(integer=True)
            ax.set_ylim(bottom=-0.5 if y.min() >= 0 else None)
        ax.set_xlabel(lam_label)
        ax.set_ylabel(_SENSITIVITY_LABELS.get(key, key))
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(keys) :]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    return fig


#: Directions of [`plot_mesh`][jurs.plot.plot_mesh]'s panels,
#: ``(elevation, azimuth)`` in degrees as matplotlib's ``view_init`` takes them: from
#: the front and above, from the side and above, and from the top (down the z axis).
MESH_VIEWS = ((25.0, -60.0), (25.0, 30.0), (90.0, -90.0))
#: Faces drawn per panel at most: matplotlib draws and depth-sorts every polygon on the CPU,
#: so a figure's time grows with its faces; larger meshes are decimated first
#: ([`decimate_mesh`][jurs.plot.decimate_mesh]), which keeps a figure to about a second or
#: two whatever the mesh (docs/performance.md, "Measurements behind the level-set and
#: plotting defaults").
MAX_DRAWN_FACES = 20_000
MESH_COLOUR = (0.60, 0.72, 0.88)
#: Share of the light every face gets whatever its direction, so faces turned away from the
#: light stay distinguishable from the background.
AMBIENT = 0.25
#: Opacity of the faces that are not highlighted, in a mesh where some are.
SEE_THROUGH_ALPHA = 0.35


def _face_normals(vertices, faces) -> np.ndarray:
    """``cross(b - a, c - a)`` of each face: its normal (right-hand rule) times twice its
    area."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def decimate_mesh(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    max_faces: int,
    flags: npt.ArrayLike | None = None,
) -> tuple[
    Float[np.ndarray, "V2 3"], Int[np.ndarray, "F2 3"], np.ndarray, Float[np.ndarray, "F2 3"]
]:
    """A coarser copy of a triangle mesh with at most ``max_faces`` faces, for drawing.

    Vertex clustering: vertices are binned into cubes and each cube's vertices merged into
    their mean; faces that collapse (two corners in one cube) or repeat another are
    dropped. The cube starts at the size that leaves about ``max_faces`` faces on a smooth
    surface and grows by 25 % until few enough are left. Fine detail and thin parts can
    lose faces (holes), which a preview can afford; the outline stays.

    Args:
        vertices, faces: the mesh.
        max_faces: the most faces to keep (>= 1).
        flags: optional per-face values, returned for the faces kept.

    Returns:
        ``(vertices, faces, flags, normals)``: ``normals (F', 3)`` are unit shading
        normals per face kept: the mean, weighted by area, of the original faces' normals
        around its three corners. The clustered faces' own normals are unreliable (slivers
        point anywhere); these keep the original surface's shading. A mesh with no more
        than ``max_faces`` faces comes back as it is, with its own face normals.
    """
    vertices, faces = check_mesh(vertices, faces)
    flags = np.zeros(len(faces), bool) if flags is None else np.asarray(flags)
    if int(max_faces) < 1:
        raise ValueError(f"max_faces must be >= 1, got {max_faces}")
    normals = _face_normals(vertices, faces)
    if len(faces) <= max_faces:
        return vertices, faces, flags, _unit(normals)
    # A surface of area A crosses about A / h^2 cubes of side h, a merged vertex each with
    # about two faces: start there and grow.
    area = 0.5 * np.linalg.norm(normals, axis=1).sum()
    cube = max(np.sqrt(2.0 * area / max_faces), 1e-9 * np.ptp(vertices, axis=0).max())
    while True:
        keys = np.floor((vertices - vertices.min(axis=0)) / cube).astype(np.int64)
        cluster = np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)
        merged = cluster[faces]
        keep = (
            (merged[:, 0] != merged[:, 1])
            & (merged[:, 1] != merged[:, 2])
            & (merged[:, 2] != merged[:, 0])
        )
        first = np.unique(np.sort(merged[keep], axis=1), axis=0, return_index=True)[1]
        if len(first) <= max_faces:
            break
        cube *= 1.25
    kept = np.flatnonzero(keep)[np.sort(first)]
    count = int(cluster.max()) + 1
    centres = _cluster_sums(cluster, vertices, count) / np.bincount(cluster)[:, None]
    # Each original face's normal goes to its corners' clusters, then to the faces kept.
    corner_normals = np.repeat(normals, 3, axis=0)
    cluster_normals = _cluster_sums(merged.reshape(-1), corner_normals, count)
    shading = cluster_normals[merged[kept]].sum(axis=1)
    return centres, merged[kept], flags[kept], _unit(shading)


def _cluster_sums(labels, values, count: int) -> np.ndarray:
    """Per label in ``0 .. count - 1``, the sum of the rows of ``values (n, 3)``."""
    return np.stack([np.bincount(labels, values[:, k], count) for k in range(3)], axis=1)


def _unit(vectors) -> np.ndarray:
    """Rows scaled to length 1; zero rows stay zero."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return vectors / np.where(length > 0, length, 1.0)


def _light(elevation: float, azimuth: float) -> np.ndarray:
    """Unit direction towards a light above and left of a viewer looking from
    ``(elevation, azimuth)`` (a light fixed to the camera, so every panel reads alike)."""
    e, a = np.radians(elevation), np.radians(azimuth)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])  # screen right
    up = np.cross(eye, right)
    light = eye + 0.5 * up - 0.4 * right
    return light / np.linalg.norm(light)


def _shaded_colours(normals, flags, light) -> np.ndarray:
    """RGBA per face by Lambert's law: the face's colour (magenta where flagged) times
    ``AMBIENT + (1 - AMBIENT) |cos|`` of the angle between its unit normal and the light.
    The absolute value lights both sides: an open mesh shows its inner side through its
    boundary. Where some faces are flagged, the others are translucent
    (``SEE_THROUGH_ALPHA``), so that flagged faces inside a closed surface, such as a
    bubble within it, show."""
    from matplotlib.colors import to_rgb

    flags = np.asarray(flags, bool)
    cos = np.abs(normals @ light)[:, None]
    base = np.where(flags[:, None], to_rgb(SUPPLEMENTARY_COLOUR), MESH_COLOUR)
    rgb = np.clip(base * (AMBIENT + (1.0 - AMBIENT) * cos), 0.0, 1.0)
    alpha = np.where(flags | ~flags.any(), 1.0, SEE_THROUGH_ALPHA)
    return np.column_stack([rgb, alpha])


def _mesh_axes(ax, views=MESH_VIEWS, panel_size=4.0, *, pyplot: bool = True):
    """``(figure, [3D axes])``: new panels side by side, one per view, or the given ones."""
    if ax is None:
        fig = _new_figure(
            pyplot=pyplot,
            figsize=(panel_size * len(views), panel_size + 0.5),
            layout="constrained",
        )
        return fig, [
            fig.add_subplot(1, len(views), k + 1, projection="3d") for k in range(len(views))
        ]
    axes = list(ax) if np.iterable(ax) else [ax]
    if not all(hasattr(a, "view_init") for a in axes):
        raise ValueError("ax must be a 3D Axes (projection='3d') or a sequence of them")
    if len(axes) > len(views):
        raise ValueError(f"{len(axes)} axes for {len(views)} views")
    return axes[0].figure, axes


def _draw_mesh_panel(ax, vertices, faces, colours, view):
    """One view of the mesh in ``ax``: coloured faces, orthographic, equal scales, no axes."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax.view_init(elev=view[0], azim=view[1])
    ax.set_proj_type("ortho")
    ax.set_axis_off()
    # Below the drawing, out of the way of the figure's title.
    ax.text2D(
        0.5,
        0.04,
        f"elevation {view[0]:g}\N{DEGREE SIGN}, azimuth {view[1]:g}\N{DEGREE SIGN}",
        ha="center",
        fontsize=8,
        color="0.35",
        transform=ax.transAxes,
    )
    if len(faces) == 0:
        ax.text2D(0.5, 0.5, "empty mesh", ha="center", va="center", transform=ax.transAxes)
        return
    # Edges in the face colour: without them antialiasing leaves hairline gaps between
    # opaque faces. Translucent faces get none (an edge over its face would show darker).
    ax.add_collection3d(
        Poly3DCollection(
            vertices[faces],
            facecolors=colours,
            edgecolors=colours,
            linewidths=np.where(colours[:, 3] < 1, 0.0, 0.3),
        )
    )
    lower, upper = vertices.min(axis=0), vertices.max(axis=0)
    centre, half = (lower + upper) / 2, (upper - lower) / 2
    half = np.maximum(half, 1e-3 * half.max() if half.max() > 0 else 1.0)  # flat meshes
    ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
    ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
    ax.set_zlim(centre[2] - half[2], centre[2] + half[2])
    ax.set_box_aspect(half)  # equal scales on the three axes: a sphere looks round


def plot_mesh(
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    *,
    ax=None,
    views=MESH_VIEWS,
    highlight=None,
    highlight_label: str = "highlighted faces",
    max_faces: int = MAX_DRAWN_FACES,
    title=None,
    panel_size: float = 4.0,
) -> Figure:
    """A triangle mesh from several directions side by side, with matplotlib's mplot3d.

    Faces are drawn (``Poly3DCollection``, orthographic projection, equal scales) in one
    colour shaded by Lambert's law from their normals, with a light fixed above and left of
    the viewer, so the shape reads from its shading. mplot3d sorts whole faces by depth
    (the painter's algorithm): right for the smooth surfaces of a fit, wrong in places
    where surfaces interpenetrate.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` and ``(F, 3)`` (as from
            [`jurs.levelset.mesh`][]). An empty mesh gives panels saying so.
        ax: a 3D Axes (``projection="3d"``), or a sequence of them, to draw the first
            views into; None makes a figure with one panel per view.
        views: ``(elevation, azimuth)`` pairs in degrees, one per panel (default
            ``MESH_VIEWS``: front, side, top).
        highlight: indices (or a boolean mask) of faces drawn in magenta, e.g. the faces
            of supplementary components ([`jurs.levelset.analyze_mesh`][]), named
            ``highlight_label`` in the legend. The other faces are then drawn translucent,
            so that highlighted faces inside a closed surface show through it.
        max_faces: a mesh with more faces is drawn decimated to at most this many, by
            vertex clustering ([`decimate_mesh`][jurs.plot.decimate_mesh]), so that the
            figure takes no longer to draw and save than one of ``max_faces`` faces,
            however large the mesh (docs/performance.md). Pass ``len(faces)`` to draw
            every face.
        title: the figure's title.
        panel_size: inches per panel.

    Returns the Figure.
    """
    vertices, faces = check_mesh(vertices, faces)
    views = [tuple(map(float, v)) for v in views]
    if not views or any(len(v) != 2 for v in views):
        raise ValueError(f"views must be (elevation, azimuth) pairs, got {views}")
    flags = np.zeros(len(faces), bool)
    if highlight is not None:
        flags[np.asarray(highlight)] = True
    vertices, faces, flags, normals = decimate_mesh(vertices, faces, max_faces, flags)
    fig, axes = _mesh_axes(ax, views, panel_size)
    for a, view in zip(axes, views):
        colours = _shaded_colours(normals, flags, _light(*view))
        _draw_mesh_panel(a, vertices, faces, colours, view)
    if flags.any():
        from matplotlib.layout_engine import ConstrainedLayoutEngine
        from matplotlib.patches import Patch

        handles = [
            Patch(color=MESH_COLOUR, label="g = 0"),
            Patch(color=SUPPLEMENTARY_COLOUR, label=highlight_label),
        ]
        # "outside": below the panels, where the layout engine can make room for it.
        constrained = isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)
        fig.legend(
            handles=handles,
            loc="outside lower center" if constrained else "lower center",
            ncol=2,
            fontsize=8,
            frameon=False,
        )
    if title:
        fig.suptitle(title, fontsize=10)
    return fig
