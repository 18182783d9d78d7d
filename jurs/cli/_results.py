"""What a curve fit and a surface fit write: records, figures and summaries.

``curve_outputs`` analyses a 2D fit's zero-level curves, ``surface_outputs`` meshes and
measures a 3D fit's zero set; each returns the function that writes the outputs and the
summary line. ``fit_record`` is the part of metrics.json they share.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TYPE_CHECKING

from ._inputs import printable
from ._outputs import (
    MAX_ADAPTIVE_RESOLUTION,
    json_safe,
    save_figure,
    write_record_and_spline,
)
from ._progress import StageClock

if TYPE_CHECKING:
    from ._job import FitJob


def fit_record(job: FitJob, args, sol, seconds: float) -> dict:
    """The part of metrics.json that curves and surfaces share: input, settings and the
    fit's own metrics (the level-set or mesh measures are added to ``metrics``), with the
    reasons to doubt the zero set (``doubts``, in words, as ``sol.stats["doubts"]``) and
    the closed components away from the data (``extra_components``: centre, bounding box,
    share of the zero set and distance to the points, as lists and numbers); both empty
    lists where the fit gave no doubt."""
    metrics = {k: v for k, v in sol.metrics.items()}
    metrics.update(
        num_steps=int(sol.stats["num_steps"]),
        status=sol.status,
        result=sol.message,
        converged=bool(sol.succeeded),
        time_s=seconds,
        doubts=[str(d) for d in sol.stats.get("doubts") or ()],
        extra_components=json_safe(list(sol.stats.get("extra_components") or ())),
    )
    settings = {
        "solver": args.solver,
        "grid": None if job.adaptive else list(job.grid),
        "lam": _lam(job, sol),
        "tau": args.tau if args.solver == "iurs" else None,
        "offset": job.chosen.offset,
        "eps": job.chosen.eps,
        "steps": args.steps,
        "tol": args.tol,
        "chosen_from_data": job.chosen.as_dict(),
    }
    if job.adaptive:
        settings.update(
            basis="adaptive",
            finest=list(sol.stats["finest"]),
            levels=int(sol.stats["levels"]),
            active=list(sol.stats["active"]),
        )
    return {
        "input": printable(os.path.abspath(job.path)),
        "num_points": int(len(job.points)),
        "normals": "estimated" if job.estimated else "given",
        "settings": settings,
        "metrics": metrics,
    }


def _lam(job: FitJob, sol) -> float:
    """The fit's lambda: an adaptive fit's own (made for its finest cell), else the job's."""
    return float(sol.metrics["lam"]) if job.adaptive else job.lam


def basis_shown(job: FitJob, sol) -> str:
    """The basis of a finished fit in words: ``grid 96x96``, or ``adaptive, finest
    2048x1536`` (the finest level's cells over the box)."""
    if not job.adaptive:
        return job.basis
    return f"adaptive, finest {'x'.join(map(str, sol.stats['finest']))}"


def _fit_title(job: FitJob, args, sol) -> str:
    """First lines of the figures' titles: file, solver, grid, lambda, E_ave."""
    return (
        f"{printable(os.path.basename(job.path))}: {args.solver}, {basis_shown(job, sol)}, "
        f"lam = {_lam(job, sol):.3g}\nE_ave = "
        f"{float(sol.metrics['E_ave']):.3e}, "
    )


def curve_outputs(job: FitJob, args, sol, seconds: float):
    """A curve's outputs (``OUTPUTS``): ``(write, summary line)``, ``write(folder)``
    writing them all. The level set is analysed here, before anything is written."""
    import numpy as np

    from .. import levelset as ls
    from .. import plot

    resolution = job.resolution or adaptive_resolution(sol.spline)
    report = ls.analyze(
        sol.spline,
        job.points,
        offset=job.chosen.offset,
        threshold=args.threshold,
        resolution=resolution,
        trim=_trim(args),
        rim=_rim(args),
    )
    record = fit_record(job, args, sol, seconds)
    record["metrics"].update(report.as_dict())
    title = (
        _fit_title(job, args, sol) + f"{report.num_components} component(s), "
        f"{report.num_supplementary} supplementary"
    )

    def write(folder):
        write_record_and_spline(folder, record, sol.spline)
        np.savetxt(
            os.path.join(folder, "zero_level.csv"),
            ls.polylines_table(report.components),
            delimiter=",",
            header="component,closed,supplementary,x,y",
            comments="",
            fmt=["%d", "%d", "%d", "%.10g", "%.10g"],
        )
        fig, ax = plot._new_axes(None, pyplot=False)
        plot.plot_fit(
            sol.spline,
            job.points,
            job.normals,
            job.chosen.offset,
            ax=ax,
            levelset=report,
            title=title,
        )
        save_figure(fig, os.path.join(folder, "fit.png"), dpi=130)

    summary = (
        f"  E_ave = {float(sol.metrics['E_ave']):.4e}, E_max = "
        f"{float(sol.metrics['E_max']):.4e}, zero set: {report.num_components} "
        f"component(s), {report.num_supplementary} supplementary, chamfer = "
        f"{report.chamfer:.3g}"
    )
    return write, summary


def adaptive_resolution(spline) -> int:
    """An adaptive curve's level-set grid (``--resolution`` not given): one node per finest
    cell along the longer side, at least ``DEFAULT_RESOLUTION`` (512) and at most
    ``MAX_ADAPTIVE_RESOLUTION``. An adaptive spline is evaluated point by point (a leaf
    search, then its 16 terms), its time grows with the nodes, and a finer default grid
    would cost more than the fit (docs/performance.md, "Measurements behind the level-set
    and plotting defaults")."""
    from .. import levelset as ls

    finest = max(spline.finest_cells)
    return int(min(max(ls.DEFAULT_RESOLUTION, finest + 1), MAX_ADAPTIVE_RESOLUTION))


def _trim(args) -> float | None:
    """``--trim`` in spacings (given alone: the default), None without it."""
    from ..levelset._trimming import check_trim

    # The points only stand in for "given": the CLI always has them.
    return check_trim(getattr(args, "trim", None), ())


def _rim(args) -> float:
    """``--rim`` in spacings (``DEFAULT_RIM`` when not given)."""
    from ..levelset._trimming import DEFAULT_RIM

    rim = getattr(args, "rim", None)
    return DEFAULT_RIM if rim is None else float(rim)


def mesh_record(vertices, faces, report, distances, resolution: int | None) -> dict:
    """metrics.json's ``mesh`` entry: size, lattice resolution (None: chosen by the band
    mesh of an adaptive fit) and every component."""
    components = [
        {
            "num_faces": c.num_faces,
            "area": c.area,
            "closed": c.closed,
            "genus": c.genus,
            "median_distance": c.median_distance,
            "supplementary": c.supplementary,
        }
        for c in report.components
    ]
    return {
        "num_vertices": int(len(vertices)),
        "num_faces": int(len(faces)),
        "resolution": None if resolution is None else int(resolution),
        "samples": distances["samples"],
        "components": components,
    }


def _mesh_counts(report) -> str:
    """The mesh's components in words, e.g. "1 component(s), 1 closed, genus 0, 0
    supplementary" (an open component's genus reads "open")."""
    closed = sum(c.closed for c in report.components)
    genera = ", ".join("open" if c.genus is None else str(c.genus) for c in report.components)
    return (
        f"{report.num_components} component(s), {closed} closed, genus {genera or '-'}, "
        f"{len(report.supplementary)} supplementary"
    )


def _vertex_colours(job: FitJob, sol, vertices):
    """The mesh's vertex colours in [0, 1], fitted from the input PLY's per-vertex red,
    green and blue (``jurs.fit_attributes``), or None where the input has none. A fit
    whose box leaves points out (a --domain given) writes the mesh without them, with a
    note."""
    import numpy as np

    import jurs

    from ..datasets._meshes import ply_vertex_colors

    rgb = ply_vertex_colors(job.path)
    if rgb is None or len(rgb) != len(job.points):
        return None
    try:
        field = jurs.fit_attributes(sol, job.points, rgb / 255.0)
    except ValueError as exc:
        print(f"jurs: note: {job.shown}: colours not carried ({exc})", file=sys.stderr)
        return None
    return np.asarray(field(vertices))


def surface_outputs(job: FitJob, args, sol, seconds: float):
    """A surface's outputs (``OUTPUTS_3D``): ``(write, summary line)``. The zero set is
    meshed and measured here (components, genus, supplementary ones; Chamfer and Hausdorff
    distances against the data points, normal consistency against their normals), before
    anything is written."""
    import numpy as np

    from .. import datasets, plot
    from .. import levelset as ls
    from ..levelset._meshing import default_resolution

    spline = sol.spline
    trim, rim = _trim(args), _rim(args)
    budget = getattr(args, "faces", None)  # --faces: decimated to it, None keeps every face
    t0 = time.perf_counter()
    if job.adaptive and job.resolution is None:
        # The band mesh chooses its resolution (2.5 nodes a finest cell, 5 trimmed, lowered until
        # the marched nodes fit in its node limit); metrics.json records it as None.
        resolution = None
        with StageClock(f"{job.shown}: meshing", enabled=not args.quiet):
            vertices, faces = ls.mesh(spline, points=job.points, trim=trim, rim=rim, faces=budget)
    else:
        resolution = job.resolution or default_resolution(
            spline, np.asarray(spline.lower, np.float64), np.asarray(spline.upper, np.float64)
        )
        # The user chose --resolution, its memory checked before the fit: no node limit.
        label = f"{job.shown}: meshing ({resolution} nodes along the longest side)"
        with StageClock(label, enabled=not args.quiet):
            vertices, faces = ls.mesh(
                spline,
                resolution,
                max_nodes=None,
                points=job.points,
                trim=trim,
                rim=rim,
                faces=budget,
            )
    t1 = time.perf_counter()
    with StageClock(f"{job.shown}: measuring the mesh", enabled=not args.quiet):
        report = ls.analyze_mesh(vertices, faces, job.points, threshold=args.threshold)
        colours = _vertex_colours(job, sol, vertices)
        distances = ls.mesh_distances(vertices, faces, job.points, job.normals)
    if report.mostly_unsupported and trim is None:
        fraction = report.unsupported_fraction or 0.0
        print(
            f"jurs: warning: {job.shown}: most of the surface is unsupported "
            f"({100 * fraction:.0f} % of its area lies farther than "
            f"{ls.DEFAULT_TRIM:g} point spacings from the data), as where an open scan "
            "is fitted; --trim keeps the part the data support",
            file=sys.stderr,
        )
    t2 = time.perf_counter()
    record = fit_record(job, args, sol, seconds)
    record["metrics"].update(
        report.as_dict(),
        chamfer=distances["chamfer"],
        hausdorff=distances["hausdorff"],
        normal_consistency=distances["normal_consistency"],
        trim=trim,
        rim=None if trim is None else rim,
    )
    record["mesh"] = mesh_record(vertices, faces, report, distances, resolution)
    record["mesh"]["face_budget"] = budget
    record["mesh"]["vertex_colors"] = colours is not None
    record["timings"] = {"fit_s": seconds, "mesh_s": t1 - t0, "analysis_s": t2 - t1}
    counts = _mesh_counts(report)
    highlight = (
        np.concatenate([c.faces for c in report.supplementary]) if report.supplementary else None
    )

    def write(folder):
        with StageClock(f"{job.shown}: writing", enabled=not args.quiet):
            write_record_and_spline(folder, record, spline)
            path = os.path.join(folder, "mesh.ply")
            datasets.save_mesh(path, vertices, faces, colors=colours)
            fig, axes = plot._mesh_axes(None, pyplot=False)
            plot.plot_mesh(
                vertices,
                faces,
                ax=axes,
                highlight=highlight,
                highlight_label="supplementary",
                title=_fit_title(job, args, sol) + counts,
            )
            save_figure(fig, os.path.join(folder, "preview.png"), dpi=110)

    summary = (
        f"  E_ave = {float(sol.metrics['E_ave']):.4e}, E_max = "
        f"{float(sol.metrics['E_max']):.4e}, surface: {len(faces)} faces, {counts}, "
        f"chamfer = {distances['chamfer']:.3g}"
    )
    if trim is not None:
        summary += (
            f"\n  trimmed to {trim:g} point spacings amid the data, {rim:g} past "
            f"its rim: {report.num_boundary_loops} boundary "
            f"loop(s), {report.boundary_length:.3g} long"
        )
    return write, summary
