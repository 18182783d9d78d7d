"""Surfaces from oriented clouds: ``jurs.fit`` + ``jurs.levelset.mesh`` beside screened
Poisson reconstruction (Open3D's ``TriangleMesh.create_from_point_cloud_poisson``), on the
same samples.

One command measures everything, prints the ratio table and writes the dated results
``benchmarks/results/surfaces.{json,md,png}`` (the figure drawn by the run):

* **Cases.** A unit sphere, a torus (R 1, r 0.35), the smooth double torus of
  [`jurs.datasets.genus2`][], and the bunny and the airplane of pymeshlab's sample meshes
  (``pip install -e '.[bench]'``); area-uniform samples with exact normals (face normals on
  the meshes); 1e5 points (1e6 with ``--million``); clean, and with Gaussian noise of 0.5 %
  of the bounding-box diagonal on each coordinate of the positions (normals kept exact).
* **Methods.** jurs as a user runs it: ``jurs.fit(points, normals)`` with its defaults (in
  float64), then ``jurs.levelset.mesh(sol.spline)`` at its default resolution. Poisson:
  ``create_from_point_cloud_poisson(cloud, depth)`` with the same points and normals,
  ``depth = round(log4 m)`` (8 at 1e5 points, the issue's setting: about one octree leaf
  per point on a surface), its mesh taken as Open3D returns it (no trimming by density);
  ``--depths 8 9 10`` runs each and keeps the one of least Chamfer. ``--fit uniform``
  (the default, into ``surfaces.{json,md,png}``) adds ``basis="uniform"``: the uniform
  grid, as the defaults were before they chose the basis; ``--fit default`` runs
  ``jurs.fit``'s own choice (``surfaces_default``); ``--fit adaptive`` fits
  ``jurs.fit_adaptive`` (fine cells only near the data, its finest level uncapped;
  ``surfaces_adaptive``).
* **Accuracy.** Against the true surface, not against points: ``Z`` area-uniform samples of
  the reconstructed mesh and ``Y`` exact samples of the true surface, both dense, with
  point-to-surface distances (analytic shapes: Newton projection onto their implicit
  function, exact for the sphere and the torus; meshes and the reconstructions: Open3D's
  ``RaycastingScene``). Chamfer ``(mean_Z d(z, truth) + mean_Y d(y, mesh)) / 2``,
  Hausdorff ``max(max_Z, max_Y)``, normal consistency (mean ``|cos|`` between each ``z``'s
  face normal and the true normal at its closest point), the definitions of
  ``jurs.levelset.mesh_distances`` without its point-set floor (about half the sample
  spacing, which would be larger than the errors compared here). Components, supplementary
  components (bubbles) and genus by ``jurs.levelset.analyze_mesh`` against the input cloud.
* **Cost.** Each method runs in a fresh child process per case, so that its peak resident
  set (``VmHWM``) is its own; jurs's fit runs twice, the second call is the warm time and
  the first includes compilation (its result dropped before the second, as a script that
  fits once holds one); wall and CPU seconds.

    python -m benchmarks.surfaces [--quick] [--million] [--cases a,b] [--points m]
                                  [--max-grid N] [--depths D ...] [--fit F]
                                  [--out DIR] [--name NAME]
    python -m benchmarks.surfaces --from-json benchmarks/results/surfaces.json  # re-render

``--quick``: 2e4 points, torus and bunny, a smaller grid cap, fewer evaluation samples (a
development run, not the issue's sizes).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import sys
import time

import numpy as np

# Nothing heavier at module level: each method runs in a spawned child that re-imports this
# file, and importing JAX there would put JAX's resident set into Poisson's peak.
from ._common import (
    RESULTS,
    current_rss_bytes,
    elapsed_log,
    import_open3d,
    in_child,
    peak_rss_bytes,
    rerender_beside,
    write_results,
)
from ._surface_cases import (  # the cases, their truth and the distances
    EVAL_SAMPLES,
    NOISE,
    SEEDS,
    diagonal,
    make_truth,
    surface_distances,
    topology,
)

CASES = ("sphere", "torus", "genus2", "bunny", "airplane")
SIZES = (100_000,)
MILLION = 1_000_000
VARIANTS = ("clean", "noise")
QUICK = {"cases": ("torus", "bunny"), "sizes": (20_000,), "max_grid": 32, "eval_samples": 100_000}
#: Cases drawn side by side in the figure (those present at the smallest size run).
FIGURE_CASES = ("torus/clean", "bunny/clean", "bunny/noise")
GB = 1e9


# --------------------------------------------------------------------------- the methods


def timed(fn, *args, **kwargs):
    """``(result, wall seconds, CPU seconds of all threads of this process)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def run_jurs(points, normals, max_grid, fit="uniform"):
    """In a child: ``jurs.fit`` (``fit="uniform"``: with ``basis="uniform"``; ``"default"``:
    its own choice of basis; ``"adaptive"``: ``jurs.fit_adaptive``) twice (the first call
    compiles), then ``jurs.levelset.mesh``."""
    import jax

    jax.config.update("jax_enable_x64", True)  # as the README's examples run it
    import jurs
    import jurs.levelset

    base = current_rss_bytes()
    # A cap only changes the grid; fit then chooses everything else as by default.
    grid = None if max_grid is None else jurs.auto_settings(points, normals, max_grid=max_grid).grid

    def fit_once():
        if fit == "adaptive":
            sol = jurs.fit_adaptive(points, normals, throw=False)
        elif fit == "uniform":
            sol = jurs.fit(points, normals, grid=grid, basis="uniform")
        else:
            sol = jurs.fit(points, normals, grid=grid)
        jax.block_until_ready(sol.spline.control)
        return sol

    # The first call's Solution is not kept: a script that fits once holds one, and a
    # hierarchy's (its index tables) would add to the warm fit's peak.
    first_s, first_cpu = timed(fit_once)[1:]
    sol, fit_s, fit_cpu = timed(fit_once)
    (vertices, faces), mesh_s, mesh_cpu = timed(jurs.levelset.mesh, sol.spline)
    return {
        "vertices": vertices,
        "faces": faces,
        "first_s": first_s,
        "fit_s": fit_s,
        "mesh_s": mesh_s,
        "total_s": fit_s + mesh_s,
        "first_cpu_s": first_cpu,
        "cpu_s": fit_cpu + mesh_cpu,
        "base_rss": base,
        "peak_rss": peak_rss_bytes(),
        "settings": {
            k: np.asarray(v).tolist() for k, v in dataclasses.asdict(sol.settings).items()
        },
        "message": sol.message,
        "converged": bool(sol.result == jurs.RESULTS.successful),
        "method": (
            f"finest {'x'.join(map(str, sol.stats['finest']))}, "
            f"{sum(sol.stats['active'])} functions, {sol.stats['num_steps']} CG steps "
            f"({sol.stats['method']})"
            + (
                f", one point in {sol.stats['hierarchy_stride']} ({sol.stats['hierarchy_points']})"
                if "hierarchy_points" in sol.stats
                else ""
            )
            if isinstance(sol.spline, jurs.AdaptiveSpline)
            else f"grid {'x'.join(map(str, sol.settings.grid))}"
        )
        + (
            f"; uniform residual {sol.stats['uniform_residual']:.3f}"
            if "uniform_residual" in sol.stats
            else f"; noise {sol.stats['noise_spacings']:.2f} spacings, no grid trial"
            if "noise_spacings" in sol.stats
            else ""
        ),
    }


def run_poisson(points, normals, depth):
    """In a child: Open3D's screened Poisson reconstruction, its mesh as returned."""
    o3d = import_open3d()

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    base = current_rss_bytes()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    (mesh, _densities), wall, cpu = timed(
        o3d.geometry.TriangleMesh.create_from_point_cloud_poisson, cloud, depth=depth
    )
    return {
        "vertices": np.asarray(mesh.vertices),
        "faces": np.asarray(mesh.triangles),
        # One call fits and meshes: no separate mesh time.
        "first_s": wall,
        "fit_s": wall,
        "mesh_s": None,
        "total_s": wall,
        "first_cpu_s": cpu,
        "cpu_s": cpu,
        "base_rss": base,
        "peak_rss": peak_rss_bytes(),
        "method": f"depth {depth}",
        "open3d": o3d.__version__,
    }


def poisson_depth(m: int) -> int:
    """``round(log4 m)``: a surface crosses about ``4^depth`` leaves of a depth-``depth``
    octree, so one leaf per point; 8 at 1e5 points (the issue's setting), 10 at 1e6."""
    return int(round(np.log(m) / np.log(4.0)))


# --------------------------------------------------------------------------- measuring


def measure(result, truth, points, reference, diag, samples):
    """Drop the mesh from a method's result and add its accuracy and topology;
    returns ``(record, (vertices, faces, bubble faces))``."""
    if "error" in result:
        return result, None
    vertices, faces = result.pop("vertices"), result.pop("faces")
    shape, bubbles = topology(vertices, faces, points)
    result.update(surface_distances(vertices, faces, truth, reference, diag, samples))
    result.update(shape, vertices=len(vertices), faces=len(faces))
    return result, (vertices, faces, bubbles)


def run_case(truth, m, variant, args, reference, diag, log):
    """Both methods on one cloud; the record and the meshes (for the figure)."""
    points, normals = truth.sample(m, SEEDS["cloud"])
    if variant == "noise":
        rng = np.random.default_rng(SEEDS["noise"])
        points = points + NOISE * diag * rng.standard_normal(points.shape)
    depths = args.depths or (poisson_depth(m),)
    record = {
        "case": truth.name,
        "m": m,
        "variant": variant,
        "diag": diag,
        "true_components": truth.components,
        "true_genus": truth.genus,
    }
    meshes = {}
    log(f"{truth.name}/{variant} m {m}: jurs")
    record["jurs"], meshes["jurs"] = measure(
        in_child(run_jurs, points, normals, args.max_grid, args.fit),
        truth,
        points,
        reference,
        diag,
        args.eval_samples,
    )
    # Poisson at each depth asked for; the record keeps the one of least Chamfer.
    tried = []
    for depth in depths:
        log(f"{truth.name}/{variant} m {m}: Poisson depth {depth}")
        result = measure(
            in_child(run_poisson, points, normals, depth),
            truth,
            points,
            reference,
            diag,
            args.eval_samples,
        )
        tried.append(result)
    scored = [t for t in tried if "error" not in t[0]]
    record["poisson"], meshes["poisson"] = min(scored or tried, key=lambda t: _chamfer(t[0]))
    if len(depths) > 1:
        record["poisson_depths"] = [
            {k: t[0].get(k) for k in ("method", "chamfer", "hausdorff", "total_s", "error")}
            for t in tried
        ]
    return record, meshes


def _chamfer(entry) -> float:
    return float(entry.get("chamfer", np.inf))


# --------------------------------------------------------------------------- report


def ratio(record, key):
    """jurs / Poisson of ``key``, NaN when either is missing."""
    try:
        return record["jurs"][key] / record["poisson"][key]
    except (KeyError, ZeroDivisionError):
        return float("nan")


def ok(record, method):
    return "error" not in record[method]


def notes(runs):
    """Runs that failed and jurs fits whose result is not ``successful``, one line each."""

    def name(r):
        return f"{r['case']}/{r['variant']} m {r['m']}"

    failed = [name(r) for r in runs if not (ok(r, "jurs") and ok(r, "poisson"))]
    out = [f"- runs that failed: {'; '.join(failed)}"] if failed else []
    unconverged = [
        f"{name(r)}: {r['jurs']['message'].split(':')[0]}"
        for r in runs
        if ok(r, "jurs") and not r["jurs"]["converged"]
    ]
    if unconverged:
        out.append(f"- jurs fits whose result is not 'successful': {'; '.join(unconverged)}")
    return out


def cell(record, method, fmt):
    """``fmt(record[method])`` or the error's first words."""
    entry = record[method]
    return f"error ({entry['error'][:40]})" if "error" in entry else fmt(entry)


def genera(entry):
    """Genus per component, largest first ("open" for an open one), at most four."""
    g = ["open" if x is None else str(x) for x in entry["genera"]]
    return ", ".join(g[:4]) + (", ..." if len(g) > 4 else "")


def tables(runs):
    """Markdown: accuracy and cost per case and method, and the jurs / Poisson ratios."""
    methods = (("jurs", "jurs"), ("poisson", "Poisson"))
    acc = [
        "| case | m | method | Chamfer | / diag (1e-4) | Hausdorff | / diag (1e-3) | "
        "normal cons. | components (bubbles) | genus |",
        "|---" * 10 + "|",
    ]
    cost = [
        "| case | m | method | setting | first call s | warm fit s | mesh s | total s | "
        "CPU s | peak RSS GB (base) |",
        "|---" * 10 + "|",
    ]
    ratios = [
        "| case | m | Chamfer | Hausdorff | warm fit time | total time | peak RSS |",
        "|---" * 7 + "|",
    ]
    for r in runs:
        key = f"{r['case']}/{r['variant']}"
        truth = f"{r['true_components']} (0)"
        for method, label in methods:
            acc.append(
                f"| {key} | {r['m']} | {label} | "
                + cell(
                    r,
                    method,
                    lambda e: (
                        f"{e['chamfer']:.2e} | {1e4 * e['chamfer_rel']:.2f} | "
                        f"{e['hausdorff']:.2e} | "
                        f"{1e3 * e['hausdorff_rel']:.2f} | {e['normal_consistency']:.4f} | "
                        f"{e['num_components']} ({e['num_supplementary']}) | {genera(e)} |"
                    ),
                )
            )
            cost.append(
                f"| {key} | {r['m']} | {label} | "
                + cell(
                    r,
                    method,
                    lambda e: (
                        f"{e['method']} | {e['first_s']:.2f} | {e['fit_s']:.2f} | "
                        f"{'-' if e['mesh_s'] is None else format(e['mesh_s'], '.2f')} | "
                        f"{e['total_s']:.2f} | {e['cpu_s']:.1f} | {e['peak_rss'] / GB:.2f} "
                        f"({e['base_rss'] / GB:.2f}) |"
                    ),
                )
            )
        acc.append(
            f"| {key} | {r['m']} | truth | - | - | - | - | - | {truth} | {r['true_genus']} |"
        )
        ratios.append(
            f"| {key} | {r['m']} | "
            + " | ".join(
                f"{ratio(r, k):.2f}"
                for k in ("chamfer", "hausdorff", "fit_s", "total_s", "peak_rss")
            )
            + " |"
        )
    return acc, cost, ratios


#: The bounds measured behind the ratios above 1 (docs/surfaces.md, "Accuracy, speed and
#: limits", where each is measured and dated).
LIMITS = (
    'Measured in `docs/surfaces.md` ("Accuracy, speed and limits"). Accuracy on the bunny '
    "and the airplane: detail finer than the default cap of 48 functions a side (ears, "
    "wings), which Poisson's octree resolves; a cap of 64 brought the clean bunny to 1.31x "
    "and the airplane to 0.98x Poisson's Chamfer (noisy: 0.75x, 0.92x), for warm fits of "
    "35 s and 9 s and 5.2 GB. At 1e6 points Poisson's depth 10 is finer still. Time: at "
    "48^3 about 2 s of assembly, 1.4 s of the cascade and 200-300 CG steps of the "
    "343-point stencil at about 20 ms each; two stencil layouts and a scattered assembly "
    "measured slower, `Multigrid()` 14 % faster on the sphere with several times the "
    "memory. Noisy fits whose thin parts are cut (noise about half their thickness or more) are "
    "reported `doubtful`."
)


def depth_table(runs) -> list:
    """Poisson's Chamfer and Hausdorff at each depth tried (runs with several depths)."""
    tried = [r for r in runs if r.get("poisson_depths")]
    if not tried:
        return []
    lines = [
        "## Poisson at each depth",
        "",
        "The tables above keep the depth of least Chamfer.",
        "",
        "| case | m | depth | Chamfer | Hausdorff | total s |",
        "|---|---|---|---|---|---|",
    ]
    for r in tried:
        for t in r["poisson_depths"]:
            measured = t.get("error") is None and t.get("chamfer") is not None
            lines.append(
                f"| {r['case']}/{r['variant']} | {r['m']} | {t.get('method') or '-'} | "
                + (
                    f"{t['chamfer']:.2e} | {t['hausdorff']:.2e} | {t['total_s']:.2f} |"
                    if measured
                    else f"error ({str(t.get('error'))[:40]}) | | |"
                )
            )
    return lines + [""]


#: What bounds the adaptive fit's ratios (docs/design.md section 8).
ADAPTIVE_LIMITS = (
    "The adaptive fit (`jurs.fit_adaptive`): finest cells three point spacings wide "
    "(`jurs._fit.adaptive.CELL_SPACINGS`) in a band of two cells around the samples, "
    "coarser levels elsewhere; conjugate gradients with the exact diagonal as "
    "preconditioner, in JAX or (the CPU default, `host_cg` in the cost table) by SciPy on "
    "the host (docs/design.md section 8). Its time and memory follow the active functions "
    "(the cost table)."
)


def default_limits() -> str:
    """What decides the default fit's basis (docs/design.md section 8), from the library's
    own constants (imported here: the parent process does not import jurs up front)."""
    from jurs._fit.adaptive import (
        AUTO_MAX_SURFACE_POINTS,
        NOISY_SPACINGS,
        UNIFORM_RESIDUAL_SPACINGS,
    )
    from jurs._fit.settings import DEFAULT_MAX_GRID_3D

    return (
        f"`jurs.fit` fits the uniform grid (cap {DEFAULT_MAX_GRID_3D} a side) and keeps it "
        f"where 90 % of the points lie within {UNIFORM_RESIDUAL_SPACINGS} spacings of its zero "
        "set; otherwise it fits the adaptive basis (the cost table gives the uniform residual "
        "of each escalated fit, and its time includes the grid's fit). Where the grid is "
        f"capped and the cloud's noise is at least {NOISY_SPACINGS} spacings, it fits the "
        "adaptive basis without the grid's trial (the cost table gives the noise). Above "
        f"{AUTO_MAX_SURFACE_POINTS} points the adaptive fit takes an evenly strided "
        "subsample of at most that many, with settings chosen for it (the cost table says "
        "which); the grid's trial fits every point. " + ADAPTIVE_LIMITS
    )


def per_function(runs) -> str:
    """The hierarchy fits' warm time and peak memory (above the runtime's base) per active
    function, measured in this run (the functions read from the cost table's setting,
    which older results files hold alone): the bound on time and memory."""
    import re

    rates = []
    for r in runs:
        jurs_run = r.get("jurs", {})
        found = re.match(r"finest \S+, (\d+) functions", str(jurs_run.get("method", "")))
        if found is None or "error" in jurs_run:
            continue
        functions = int(found.group(1))
        rates.append(
            (
                1e6 * jurs_run["fit_s"] / functions,
                (jurs_run["peak_rss"] - jurs_run["base_rss"]) / functions / 1e3,
                functions,
            )
        )
    if not rates:
        return ""
    us, kb, n = zip(*rates)
    return (
        f" Measured here over the {len(rates)} fits on the hierarchy ({min(n)}-{max(n)} "
        f"functions): {min(us):.0f}-{max(us):.0f} us of warm fit and {min(kb):.1f}-"
        f"{max(kb):.1f} KB of peak memory per active function (the grid's fit included where "
        "`jurs.fit` fitted it first). At the functions the detail asks for, that is "
        "several times Poisson's time and memory: the ratios above."
    )


def markdown(payload):
    acc, cost, ratios = tables(payload["runs"])
    quick = " A `--quick` development run: not the issue's sizes." if payload["quick"] else ""
    fit = payload.get("fit", "uniform")
    adaptive = fit == "adaptive"
    call = "jurs.fit_adaptive" if adaptive else "jurs.fit"
    depths = payload.get("depths")
    lines = (
        [
            f"# Surfaces: `{call}` + `jurs.levelset.mesh` beside screened Poisson (Open3D)",
            "",
            f"Run {payload['date']} on {payload['machine']}, {payload['memory']}. Command: "
            f"`{payload['command']}` ({payload['total_s']:.0f} s). Open3D {payload['open3d']}. "
            f"1-minute load average {payload['load_start']:.1f} at the start, "
            f"{payload['load_end']:.1f} at the end (a shared machine: times carry tens of "
            f"percent of noise).{quick}" + (f" {payload['note']}" if payload.get("note") else ""),
            "",
            f"**Setup.** jurs: `{call}(points, normals)` with defaults (float64; "
            + (
                "its finest level chosen from the data"
                if adaptive
                else "the basis chosen by the fit: the cost table's setting says which"
                if fit == "default"
                else f"grid capped at {payload['max_grid']}"
                if payload["max_grid"]
                else "the default grid cap"
            )
            + ") and `jurs.levelset.mesh(sol.spline)` at its "
            "default resolution. Poisson: Open3D's `create_from_point_cloud_poisson(cloud, "
            "depth)` on the same points and (exact) normals, "
            + (
                f"at depths {', '.join(map(str, depths))}, the one of least Chamfer kept"
                if depths
                else "`depth = round(log4 m)` (8 at 1e5 points)"
            )
            + ", its mesh as Open3D returns it. Users often trim Poisson's vertices of low "
            "density (its second output) to cut the surface it extrapolates where data are "
            "sparse; not done here. Noise: Gaussian, "
            f"{100 * NOISE:g} % of the bounding-box diagonal per coordinate, on the positions "
            "only; accuracy is measured against the clean surface.",
            "",
            "**Accuracy.** Point-to-surface distances between "
            f"{payload['eval_samples']} area-uniform samples of each mesh and as many exact "
            "samples of the true surface (analytic shapes: Newton projection onto their "
            "implicit function; meshes: Open3D's RaycastingScene): Chamfer = mean of the two "
            "one-sided means, Hausdorff = the larger maximum, both absolute and over the "
            "bounding-box diagonal `diag` of the true surface; normal consistency = mean |cos| "
            "between a sample's face normal and the true normal at its closest point. These "
            "are `jurs.levelset.mesh_distances`'s definitions without its point-set floor. "
            "Components (bubbles = supplementary components, `jurs.levelset.analyze_mesh` "
            "against the input cloud) and genus per closed component.",
            "",
            "**Cost.** Each method and case in a fresh child process: peak resident set "
            "(VmHWM, with the runtime's own at the start in brackets: Python + JAX for jurs); "
            "jurs fits twice (first call: compilation included, its result dropped before the "
            "second; warm fit: the second); "
            "Poisson's one call is its fit and total; CPU s: all threads, warm fit + mesh.",
            "",
        ]
        + (["## Runs that did not succeed", ""] + notes(payload["runs"]) + [""])
        * bool(notes(payload["runs"]))
        + ["## jurs / Poisson", "", "Ratios (below 1: jurs smaller, i.e. better).", ""]
        + ratios
        + [
            "",
            "## What limits the misses",
            "",
            (ADAPTIVE_LIMITS if adaptive else default_limits() if fit == "default" else LIMITS)
            + per_function(payload["runs"]),
        ]
        + ["", "## Accuracy", ""]
        + acc
        + ["", "## Cost", ""]
        + cost
        + [""]
        + depth_table(payload["runs"])
    )
    if payload.get("figure"):
        lines += [
            "## Figure",
            "",
            f"![jurs and Poisson meshes side by side]({payload['figure']['file']})",
            "",
            payload["figure"]["caption"],
            "",
        ]
    lines += ["Cases: " + "; ".join(f"`{k}`: {v}" for k, v in payload["origins"].items()), ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------- figure

#: Per case: view (elevation, azimuth) and the axis that is "up" in the model's file.
VIEWS = {
    "torus": ((35.0, -60.0), 2),
    "bunny": ((15.0, 20.0), 1),
    "sphere": ((20.0, -60.0), 2),
    "genus2": ((40.0, -60.0), 2),
    "airplane": ((25.0, -30.0), 1),
}


def figure(meshes, records, path):
    """jurs's and Poisson's meshes side by side, one row per case; returns the caption."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jurs.plot import plot_mesh

    rows = list(meshes)
    fig = plt.figure(figsize=(8.0, 3.8 * len(rows) + 0.6), constrained_layout=True)
    for i, key in enumerate(rows):
        case = key.split("/")[0]
        view, up = VIEWS.get(case, ((25.0, -60.0), 2))
        # A cyclic permutation (a rotation, not a mirror) that draws the model's up axis up.
        order = [(up + 1) % 3, (up + 2) % 3, up]
        for j, (method, label) in enumerate((("jurs", "jurs"), ("poisson", "Poisson"))):
            ax = fig.add_subplot(len(rows), 2, 2 * i + j + 1, projection="3d")
            r = records[key][method]
            heading = f"{label}, {key}, m {records[key]['m']}"
            if meshes[key][method] is None:
                ax.set_axis_off()
                ax.set_title(f"{heading}\n{r.get('error', 'no mesh')[:60]}", fontsize=8)
                continue
            vertices, faces, bubbles = meshes[key][method]
            plot_mesh(
                vertices[:, order],
                faces,
                ax=ax,
                views=[view],
                highlight=bubbles,
                highlight_label="supplementary components",
            )
            ax.set_title(
                f"{heading}\n{chr(10).join(textwrap.wrap(r['method'], 60))}\n"
                f"Chamfer {1e4 * r['chamfer_rel']:.2f}e-4, "
                f"Hausdorff {1e3 * r['hausdorff_rel']:.2f}e-3 of the diagonal\n"
                f"components {r['num_components']} (supplementary "
                f"{r['num_supplementary']})",
                fontsize=8,
            )
    caption = (
        "jurs (left) and Open3D's screened Poisson (right) on the same clouds ("
        + ", ".join(rows)
        + "). Supplementary components (bubbles) are drawn in "
        "magenta, and the rest of that mesh translucent so that bubbles inside it "
        "show."
    )
    fig.suptitle("\n".join(textwrap.wrap(caption, 110)), fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return caption


# --------------------------------------------------------------------------- main


def parse():
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="2e4 points, torus and bunny, grid cap 32 (development)",
    )
    parser.add_argument("--million", action="store_true", help="also 1e6 points")
    parser.add_argument("--cases", help=f"comma-separated subset of {','.join(CASES)}")
    parser.add_argument("--points", type=int, nargs="+", help="point counts (replace the sizes)")
    parser.add_argument(
        "--max-grid",
        type=int,
        help="cap on jurs's automatic grid (jurs.auto_settings max_grid); default: the library's",
    )
    parser.add_argument(
        "--depths",
        type=int,
        nargs="+",
        help="Poisson depths, the best Chamfer kept (default one: round(log4 m))",
    )
    parser.add_argument(
        "--fit",
        choices=("uniform", "default", "adaptive"),
        default="uniform",
        help="jurs.fit with basis='uniform', jurs.fit's own defaults, or jurs.fit_adaptive",
    )
    parser.add_argument("--eval-samples", type=int, help="samples per side for distances")
    parser.add_argument("--out", default=RESULTS, help="folder of the results files")
    parser.add_argument("--note", default="", help="a sentence for the results page")
    parser.add_argument(
        "--name",
        help="results file names, <name>.{json,md,png} (default: surfaces, or "
        "surfaces_adaptive with --fit adaptive; the 1e6 run: --cases sphere,bunny --points "
        "1000000 --fit default --depths 8 9 10 --name surfaces_1e6_default)",
    )
    parser.add_argument(
        "--markdown-only",
        action="store_true",
        help="re-render the markdown from <out>/<name>.json (no measuring)",
    )
    parser.add_argument(
        "--from-json", metavar="PATH", help="re-render the markdown beside a results JSON"
    )
    args = parser.parse_args()
    preset = (
        QUICK
        if args.quick
        else {"cases": CASES, "sizes": SIZES, "max_grid": None, "eval_samples": EVAL_SAMPLES}
    )
    args.cases = tuple(args.cases.split(",")) if args.cases else preset["cases"]
    unknown = set(args.cases) - set(CASES)
    if unknown:
        parser.error(f"unknown cases {sorted(unknown)}; choose from {CASES}")
    args.sizes = tuple(args.points or preset["sizes"]) + ((MILLION,) if args.million else ())
    args.max_grid = args.max_grid or preset["max_grid"]
    args.eval_samples = args.eval_samples or preset["eval_samples"]
    args.name = args.name or ("surfaces" if args.fit == "uniform" else f"surfaces_{args.fit}")
    return args


def rerender(data):
    data.pop("verdicts", None)  # an older run's target verdicts: not reported
    return markdown(data)


def summary(payload) -> str:
    """What the run prints at the end: failures and the ratio table."""
    return "\n".join(notes(payload["runs"]) + [""] + tables(payload["runs"])[2])


def main():
    args = parse()
    if args.from_json or args.markdown_only:
        path = args.from_json or os.path.join(args.out, f"{args.name}.json")
        print(rerender_beside(path, rerender))
        return
    try:
        open3d = import_open3d()
    except ImportError:
        sys.exit("this benchmark compares with Open3D: pip install -e '.[bench]'")
    from ._common import machine

    log = elapsed_log()
    start, load_start = time.perf_counter(), os.getloadavg()[0]
    runs, origins, shown, records = [], {}, {}, {}
    for name in args.cases:
        truth = make_truth(name)
        if truth is None:
            log(f"{name}: mesh not available (pip install pymeshlab trimesh), skipped")
            continue
        origins[name] = truth.origin
        reference, _ = truth.sample(args.eval_samples, SEEDS["truth"])
        diag = diagonal(reference)
        for m in args.sizes:
            for variant in VARIANTS:
                record, meshes = run_case(truth, m, variant, args, reference, diag, log)
                runs.append(record)
                key = f"{name}/{variant}"
                if key in FIGURE_CASES and m == min(args.sizes):
                    shown[key], records[key] = meshes, record
                print(
                    f"{key} m {m}: jurs/Poisson Chamfer {ratio(record, 'chamfer'):.2f}, "
                    f"Hausdorff {ratio(record, 'hausdorff'):.2f}, warm fit "
                    f"{ratio(record, 'fit_s'):.2f}, total {ratio(record, 'total_s'):.2f}, "
                    f"peak RSS {ratio(record, 'peak_rss'):.2f}",
                    flush=True,
                )
    os.makedirs(args.out, exist_ok=True)
    caption = figure(shown, records, os.path.join(args.out, f"{args.name}.png")) if shown else None
    command = "python -m benchmarks.surfaces " + " ".join(sys.argv[1:])
    total_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    payload = {
        "date": datetime.date.today().isoformat(),
        "quick": args.quick,
        "machine": f"{machine()}, Python {platform.python_version()}",
        "memory": f"{total_bytes / GB:.0f} GB RAM",
        "command": command.strip(),
        "open3d": open3d.__version__,
        "max_grid": args.max_grid,
        "fit": args.fit,
        "note": args.note,
        "depths": args.depths,
        "eval_samples": args.eval_samples,
        "load_start": load_start,
        "load_end": os.getloadavg()[0],
        "runs": runs,
        "origins": origins,
        "total_s": time.perf_counter() - start,
        "figure": caption and {"file": f"{args.name}.png", "caption": caption},
    }
    write_results(args.name, payload, markdown(payload), args.out)
    print(summary(payload))


if __name__ == "__main__":
    main()
