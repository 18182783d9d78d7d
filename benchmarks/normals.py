"""Normals for clouds without them: ``jurs.estimate_normals`` beside the spanning-tree
baseline (Hoppe et al. 1992) and Open3D, on 2D outlines and 3D surfaces with known normals.

One command measures everything, prints the tables and writes the dated results
``benchmarks/results/normals.{json,md}``:

* **2D cases.** Outlines traced from scikit-image images with
  ``skimage.measure.find_contours`` (``horse``, ``coins``, ``text``, ``binary_blobs``,
  through [`jurs.shapes.mask_outline`][]), DejaVu glyphs, and planted hard cases (nested
  rings, a thin band, two close discs); sampled by arc length (true normals from
  [`jurs.shapes.sample_outline`][]), clean, with 0.5 % noise, with uneven density
  (``nonuniform=0.6``) and with 2 % outliers (scored on the inliers).
* **3D cases.** Area-uniform samples of the bunny and the cow from pymeshlab's sample meshes
  (``pip install pymeshlab trimesh``; face normals as truth), a sphere, a torus and a thick
  spherical shell (both surfaces); clean and with 0.5 % noise; 1e4 and 1e5 points.
* **Methods.** ``jurs.estimate_normals(points)``; the baseline ``_baselines.orient_mst``
  (PCA normals of the same ``k``, minimum spanning tree over 15 neighbours, topmost point
  up); Open3D (``pip install open3d-cpu``, 3D only) with PCA over 30 neighbours and
  ``orient_normals_consistent_tangent_plane(15)``, as the issue's anchors.
* **Scores.** Correct sign: strictly outward (``outward``) and up to one global flip
  (``consistent``, what propagation alone can give); median angle to the truth (unsigned);
  wall time. A fit with estimated normals against true ones on a few 2D cases
  (``jurs.fit(points, normals)`` with defaults; Chamfer and Hausdorff to the clean outline)
  and on two surfaces of 1e5 points (the clouds of benchmarks/surfaces.py, meshed).

    python -m benchmarks.normals [--quick] [--markdown-only]
    python -m benchmarks.normals --cases text,horse/noise --only-2d   # a subset, not saved

Noise: Gaussian, standard deviation level x bounding-box diagonal on each coordinate.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time

import numpy as np

import jurs
import jurs.shapes

from . import _surface_cases as surface_cases
from ._baselines import orient_mst
from ._common import RESULTS, optional, write_results

NOISE = 0.005
OUTLIERS = 0.02
M_2D = 2000
#: 2D cases sampled with more points. scikit-image's ``text`` traced at 2000 points has
#: strokes about one point spacing wide: their two sides are not separable at that
#: density, and the case stays as the hard one; ten times the points makes the strokes
#: several spacings wide (docs/normals.md gives the widths).
M_CASE = {"text_dense": 20_000}
M_3D = (10_000, 100_000)
#: 3D cases run at the larger size (the rest at the smaller only, to keep the run short).
LARGE_3D = ("sphere", "torus", "bunny")
FIT_CASES = ("annulus", "glyph_a", "horse", "coins")
#: Surfaces fitted with true and with estimated normals, on the clouds of
#: benchmarks/surfaces.py (same samples, noise and evaluation; its Poisson figures apply).
FIT_SURFACES = ("sphere", "bunny")
FIT_SURFACE_POINTS = 100_000
MESHES = surface_cases.MESHES


# --------------------------------------------------------------------------- 2D cases


def image_outline(name):
    from skimage import data, filters

    if name == "text":
        image = data.text()
        return jurs.shapes.mask_outline(
            image < filters.threshold_otsu(image), blur=1.0, min_area=30.0
        )
    if name == "binary_blobs":
        return jurs.shapes.mask_outline(
            data.binary_blobs(256, blob_size_fraction=0.12, volume_fraction=0.4, rng=3),
            blur=1.0,
            min_area=30.0,
        )
    raise ValueError(name)


def circles(radii, centres):
    t = np.linspace(0.0, 2 * np.pi, 4096, endpoint=False)
    return [np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)] for r, c in zip(radii, centres)]


def band():
    return [np.array([[-2.0, -0.06], [2.0, -0.06], [2.0, 0.06], [-2.0, 0.06]])]


OUTLINES_2D = {
    "horse": lambda: jurs.shapes.outline("horse"),
    "coins": lambda: jurs.shapes.outline("coins"),
    "text": lambda: jurs.shapes.normalise(jurs.shapes.orient(image_outline("text"))),
    "text_dense": lambda: jurs.shapes.normalise(jurs.shapes.orient(image_outline("text"))),
    "binary_blobs": lambda: jurs.shapes.normalise(
        jurs.shapes.orient(image_outline("binary_blobs"))
    ),
    "glyph_a": lambda: jurs.shapes.outline("glyph_a"),
    "glyph_B": lambda: jurs.shapes.outline("glyph_B"),
    "annulus": lambda: jurs.shapes.outline("annulus"),
    "nested_rings": lambda: jurs.shapes.normalise(
        jurs.shapes.orient(circles((1.0, 0.9, 0.6, 0.5), [(0, 0)] * 4))
    ),
    "thin_band": lambda: jurs.shapes.normalise(jurs.shapes.orient(band())),
    "close_discs": lambda: jurs.shapes.normalise(
        jurs.shapes.orient(circles((1.0, 1.0), ((-1.03, 0), (1.03, 0))))
    ),
}
VARIANTS_2D = ("clean", "noise", "uneven", "outliers")


def cloud_2d(name, variant, m=None, seed=0):
    """``(points, truth, inlier mask, clean outline)`` of a 2D case (``m`` points: by
    default ``M_CASE``'s or ``M_2D``)."""
    m = M_CASE.get(name, M_2D) if m is None else m
    comps = OUTLINES_2D[name]()
    points, truth = jurs.shapes.sample_outline(
        comps, m, nonuniform=0.6 if variant == "uneven" else 0.0
    )
    rng = np.random.default_rng(seed)
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    inlier = np.ones(m, bool)
    if variant == "noise":
        points = points + NOISE * diag * rng.standard_normal(points.shape)
    if variant == "outliers":
        lo, hi = points.min(axis=0), points.max(axis=0)
        extra = rng.uniform(lo, hi, (int(OUTLIERS * m), 2))
        points = np.concatenate([points, extra])
        truth = np.concatenate([truth, np.zeros_like(extra)])
        inlier = np.concatenate([inlier, np.zeros(len(extra), bool)])
    return points, truth, inlier, comps


# --------------------------------------------------------------------------- 3D cases


def sphere(m, rng):
    v = rng.standard_normal((m, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v, v.copy()


def torus(m, rng, big=1.0, small=0.35):
    u, v = rng.uniform(0, 2 * np.pi, (2, 4 * m))
    keep = rng.uniform(0, 1, 4 * m) < (big + small * np.cos(v)) / (big + small)
    u, v = u[keep][:m], v[keep][:m]
    normal = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    return big * np.stack([np.cos(u), np.sin(u), 0 * u], axis=1) + small * normal, normal


def shell(m, rng, outer=1.0, inner=0.8):
    """Thick spherical shell: both surfaces, sampled with the same density."""
    m_in = int(round(m * inner**2 / (1 + inner**2)))
    a, na = sphere(m - m_in, rng)
    b, nb = sphere(m_in, rng)
    return np.concatenate([outer * a, inner * b]), np.concatenate([na, -nb])


def mesh_sampler(name):
    trimesh = optional("trimesh")
    pymeshlab = optional("pymeshlab")
    if trimesh is None or pymeshlab is None:
        return None
    folder = MESHES or os.path.join(os.path.dirname(pymeshlab.__file__), "tests", "sample_meshes")
    path = os.path.join(folder, f"{name}.obj")
    if not os.path.exists(path):
        return None
    mesh = trimesh.load(path, force="mesh", process=True)

    def sample(m, rng):
        points, faces = trimesh.sample.sample_surface(mesh, m, seed=int(rng.integers(1 << 31)))
        return np.asarray(points, float), np.asarray(mesh.face_normals[faces], float)

    sample.origin = (
        f"{os.path.basename(path)} ({len(mesh.faces)} faces, watertight {mesh.is_watertight})"
    )
    return sample


SURFACES = {"sphere": sphere, "torus": torus, "thick_shell": shell}


# --------------------------------------------------------------------------- methods


def score(normals, truth, mask, seconds):
    dot = np.sum(normals[mask] * truth[mask], axis=1)
    outward = float(np.mean(dot > 0))
    return {
        "outward": outward,
        "consistent": max(outward, 1 - outward),
        "angle_deg": float(np.degrees(np.median(np.arccos(np.clip(np.abs(dot), 0, 1))))),
        "seconds": seconds,
    }


def run_methods(points, truth, mask, o3d):
    out = {}
    t0 = time.perf_counter()
    normals, info = jurs.estimate_normals(points, return_info=True)
    out["jurs"] = {
        **score(normals, truth, mask, time.perf_counter() - t0),
        "k": info.k,
        "components": info.components,
        "patches": info.patches,
        "flipped": info.flipped,
        "corrected": info.corrected,
        "residual": info.residual,
    }
    t0 = time.perf_counter()
    unsigned = jurs.estimate_normals(points, k=info.k, orient=False)
    baseline = orient_mst(points, unsigned, k=15)
    out["mst"] = score(baseline, truth, mask, time.perf_counter() - t0)
    if o3d is not None and points.shape[1] == 3:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        t0 = time.perf_counter()
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
        cloud.orient_normals_consistent_tangent_plane(15)
        out["open3d"] = score(np.asarray(cloud.normals), truth, mask, time.perf_counter() - t0)
    return out


def fit_quality(name, variant):
    """jurs.fit with true and with estimated normals; distances in 1e-3 of the diagonal."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jurs
    import jurs.levelset

    points, truth, _, comps = cloud_2d(name, variant, m=1200)
    reference = jurs.shapes.sample_outline(comps, 20000)[0]
    diag = float(np.linalg.norm(np.ptp(reference, axis=0)))
    out = {}
    for label, normals in (("true", truth), ("estimated", jurs.estimate_normals(points))):
        sol = jurs.fit(points, normals)
        rep = jurs.levelset.analyze(
            sol.spline, points, offset=sol.settings.offset, reference=reference
        )
        out[label] = {
            "chamfer": 1e3 * rep.chamfer / diag,
            "hausdorff": 1e3 * rep.hausdorff / diag,
            "components": rep.num_components,
            "supplementary": rep.num_supplementary,
        }
    out["true_components"] = len(comps)
    return out


def fit_quality_3d(name, variant, m=FIT_SURFACE_POINTS):
    """``jurs.fit`` + ``jurs.levelset.mesh`` with true and with estimated normals on the
    cloud benchmarks/surfaces.py fits at ``m`` points (the same seeds, noise and
    distances); Chamfer / Hausdorff to the true surface in 1e-3 of the diagonal, mesh
    components (supplementary), wall seconds of the fit and mesh (warm) and of the
    estimation. None when the case's mesh is not available."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jurs.levelset

    truth = surface_cases.make_truth(name)
    if truth is None:
        return None
    reference, _ = truth.sample(surface_cases.EVAL_SAMPLES, surface_cases.SEEDS["truth"])
    diag = surface_cases.diagonal(reference)
    points, true_normals = truth.sample(m, surface_cases.SEEDS["cloud"])
    if variant == "noise":
        rng = np.random.default_rng(surface_cases.SEEDS["noise"])
        points = points + surface_cases.NOISE * diag * rng.standard_normal(points.shape)
    start = time.perf_counter()
    estimated = jurs.estimate_normals(points)
    out = {"estimate_s": time.perf_counter() - start, "true_components": truth.components}
    for label, normals in (("true", true_normals), ("estimated", estimated)):
        jurs.fit(points, normals, throw=False)  # compiles
        start = time.perf_counter()
        sol = jurs.fit(points, normals, throw=False)
        vertices, faces = jurs.levelset.mesh(sol.spline)
        seconds = time.perf_counter() - start
        dist = surface_cases.surface_distances(
            vertices, faces, truth, reference, diag, surface_cases.EVAL_SAMPLES
        )
        shape, _ = surface_cases.topology(vertices, faces, points)
        out[label] = {
            "chamfer": 1e3 * dist["chamfer_rel"],
            "hausdorff": 1e3 * dist["hausdorff_rel"],
            "components": shape["num_components"],
            "supplementary": shape["num_supplementary"],
            "status": sol.status,
            "seconds": seconds,
        }
    return out


# --------------------------------------------------------------------------- report


def fmt(entry):
    return (
        f"{100 * entry['outward']:.2f} / {100 * entry['consistent']:.2f} | "
        f"{entry['angle_deg']:.2f} | {entry['seconds']:.2f}"
    )


def fit_rows(fits: dict, timed: bool = False) -> list:
    """The table of fits with true and with estimated normals: Chamfer / Hausdorff,
    components (supplementary) and, where ``timed``, the seconds of each fit and of the
    estimation."""
    rows = ["| case | true normals | estimated normals |", "|---|---|---|"]
    for key, f in fits.items():
        cell = [
            f"{f[s]['chamfer']:.3f} / {f[s]['hausdorff']:.2f}, {f[s]['components']} "
            f"({f[s]['supplementary']})" + (f", {f[s]['seconds']:.1f} s" if timed else "")
            for s in ("true", "estimated")
        ]
        if timed:
            cell[1] += f" ({f['estimate_s']:.1f} s)"
        rows.append(f"| {key} ({f['true_components']} true) | {cell[0]} | {cell[1]} |")
    return rows


def markdown(payload):
    lines = [
        "# Normals without normals: `jurs.estimate_normals` beside the spanning tree and Open3D",
        "",
        f"Run {payload['date']} on {payload['machine']}. Command: `{payload['command']}` "
        f"({payload['total_s']:.0f} s). Open3D: {payload['open3d']}. Meshes: "
        f"{payload['meshes']}.",
        "",
        "Per method: correct sign in % (strictly outward / up to one global flip), "
        "median angle to the truth in degrees (unsigned), wall seconds. 'mst' is "
        "Hoppe's spanning tree (topmost point up) on the same PCA normals; Open3D: PCA "
        "over 30 neighbours + `orient_normals_consistent_tangent_plane(15)`. Noise: "
        f"Gaussian, {100 * NOISE:g} % of the bounding-box diagonal per coordinate; "
        f"outliers: {100 * OUTLIERS:g} % extra points uniform in the box, scored on "
        "the inliers; uneven: density 0.4x-1.6x along the outline. Times are wall "
        "clock on a machine shared with other jobs (1-minute load average "
        f"{payload.get('load_start', float('nan')):.1f} at the start of the run, "
        f"{payload.get('load_end', float('nan')):.1f} at the end, on 2 cores): expect "
        "tens of percent of noise, more on short runs.",
        "",
    ]
    for dim in ("2D", "3D"):
        rows = [r for r in payload["runs"] if r["dim"] == dim]
        has_o3d = any("open3d" in r for r in rows)
        head = "| case | m | jurs sign % | angle | s | k | mst sign % | angle | s |" + (
            " Open3D sign % | angle | s |" if has_o3d else ""
        )
        lines += [f"## {dim}", "", head, "|---" * (9 + 3 * has_o3d) + "|"]
        for r in rows:
            row = (
                f"| {r['case']} | {r['m']} | {fmt(r['jurs'])} | {r['jurs']['k']} | "
                f"{fmt(r['mst'])} |"
            )
            if has_o3d:
                row += f" {fmt(r['open3d'])} |" if "open3d" in r else " - | - | - |"
            lines.append(row)
        lines.append("")
    lines += [
        "## Fit with estimated normals",
        "",
        "`jurs.fit(points, normals)` with defaults, 1200 points; Chamfer / Hausdorff "
        "to the clean outline in 1e-3 of the diagonal; zero-set components "
        "(supplementary).",
        "",
        *fit_rows(payload["fits"]),
    ]
    if payload.get("surface_fits"):
        lines += [
            "",
            f"Surfaces: `jurs.fit` then `jurs.levelset.mesh`, defaults, "
            f"{payload['surface_points']} points, on the clouds of "
            "`benchmarks/surfaces.py` (same samples, noise and distances: its Poisson "
            "figures apply); Chamfer / Hausdorff to the true surface in 1e-3 of the "
            "diagonal; mesh components (supplementary); warm fit + mesh seconds "
            "(estimation seconds).",
            "",
            *fit_rows(payload["surface_fits"], timed=True),
        ]
    lines += [
        "",
        "## What limits the misses",
        "",
        'Measured in `docs/normals.md` ("Why the noisy 2D cases fail", "Limits"): with '
        "0.5 % noise an oracle that gives each noisy 2D point the normal of the nearest "
        "clean point scores 96.65 % on the horse, 99.45 % on binary_blobs and 74.6 % on "
        "`text` (the noise is as wide as their legs, necks and strokes): even it stays under "
        "99.5 % there. Not bounded that way: the close discs (oracle 99.75 %) and the thin "
        "band (single points at its ends, whose PCA normal lies along it). `text` at 2000 "
        "points has strokes 1.2 spacings wide, not separable clean either (99.97 % at "
        "20000 points); the glyphs' clean misses are 2-3 points at cusps whose sides are "
        "closer than two spacings; the cow mesh self-intersects, so its face normals are "
        "no clean truth. Fits with estimated normals inherit the orientation's misses "
        "(noisy horse and coins).",
    ]
    lines += ["", "Cases: " + "; ".join(f"`{k}`: {v}" for k, v in payload["origins"].items()), ""]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--cases",
        default="",
        help="comma-separated substrings: run only the cases whose 'name/variant' contains "
        "one (e.g. 'text,horse/noise'); results are printed, not written",
    )
    parser.add_argument("--only-2d", action="store_true", help="skip the 3D cases and fits")
    parser.add_argument(
        "--max-3d", type=int, default=M_3D[-1], help="largest 3D size to run (e.g. 10000)"
    )
    parser.add_argument(
        "--markdown-only",
        action="store_true",
        help="re-render the markdown from the last run's JSON",
    )
    args = parser.parse_args()
    if args.markdown_only:
        import json

        with open(os.path.join(RESULTS, "normals.json")) as fh:
            payload = json.load(fh)
        payload.pop("verdicts", None)  # an older run's target verdicts: not reported
        write_results("normals", payload, markdown(payload))
        return
    start = time.perf_counter()
    load_start = os.getloadavg()[0]
    o3d = optional("open3d")
    rng = np.random.default_rng(0)
    runs, origins = [], {}
    wanted = [c for c in args.cases.split(",") if c]

    def selected(case):
        return not wanted or any(w in case for w in wanted)

    names_2d = list(OUTLINES_2D)[:4] if args.quick else list(OUTLINES_2D)
    for name in names_2d:
        for variant in VARIANTS_2D:
            if not selected(f"{name}/{variant}"):
                continue
            points, truth, inlier, _ = cloud_2d(name, variant)
            res = run_methods(points, truth, inlier, None)
            runs.append(
                {
                    "dim": "2D",
                    "case": f"{name}/{variant}",
                    "variant": variant,
                    "m": len(points),
                    **res,
                }
            )
            print(runs[-1]["case"], fmt(res["jurs"]), "| mst", fmt(res["mst"]), flush=True)
    surfaces = dict(SURFACES)
    for mesh in ("bunny", "cow"):
        sampler = mesh_sampler(mesh)
        if sampler is not None:
            surfaces[mesh] = sampler
            origins[mesh] = sampler.origin
    sizes = M_3D[:1] if args.quick else tuple(m for m in M_3D if m <= args.max_3d)
    if args.only_2d:
        surfaces = {}
    for name, sampler in surfaces.items():
        for m in sizes:
            if m > sizes[0] and name not in LARGE_3D:
                continue
            for variant in ("clean", "noise"):
                points, truth = sampler(m, rng)
                if not selected(f"{name}/{variant}"):
                    continue
                if variant == "noise":
                    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
                    points = points + NOISE * diag * rng.standard_normal(points.shape)
                res = run_methods(points, truth, np.ones(m, bool), o3d)
                runs.append(
                    {"dim": "3D", "case": f"{name}/{variant}", "variant": variant, "m": m, **res}
                )
                print(
                    runs[-1]["case"],
                    m,
                    fmt(res["jurs"]),
                    "| mst",
                    fmt(res["mst"]),
                    "| o3d",
                    fmt(res["open3d"]) if "open3d" in res else "-",
                    flush=True,
                )
    fits = {}
    if wanted or args.only_2d or args.max_3d < M_3D[-1]:
        return  # a subset: printed above, the stored results are left alone
    for name in FIT_CASES[:2] if args.quick else FIT_CASES:
        for variant in ("clean", "noise"):
            fits[f"{name}/{variant}"] = fit_quality(name, variant)
            print("fit", name, variant, fits[f"{name}/{variant}"], flush=True)
    surface_fits = {}
    for name in FIT_SURFACES[:1] if args.quick else FIT_SURFACES:
        for variant in ("clean", "noise"):
            result = fit_quality_3d(name, variant)
            if result is not None:
                surface_fits[f"{name}/{variant}"] = result
                print("fit", name, variant, result, flush=True)
    origins.update(
        {
            "2D": "jurs.shapes outlines (horse, coins: scikit-image images; glyphs: "
            "DejaVu Sans); text, binary_blobs: skimage.data images traced "
            "with find_contours (text_dense: the same outline at 20000 "
            "points); nested_rings: 4 concentric circles (2 annuli); "
            "thin_band: 4 x 0.12 rectangle; close_discs: two unit "
            "discs 0.06 apart (2D sizes before scaling to a longest side of "
            "8)",
            "3D": "sphere, torus (R 1, r 0.35), thick_shell (radii 1 and 0.8): "
            "area-uniform random samples",
        }
    )
    payload = {
        "date": datetime.date.today().isoformat(),
        "load_start": load_start,
        "load_end": os.getloadavg()[0],
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
        f"{platform.processor() or 'cpu'}, Python {platform.python_version()}",
        "command": "python -m benchmarks.normals" + (" --quick" if args.quick else ""),
        "open3d": getattr(o3d, "__version__", "not installed"),
        "meshes": ", ".join(v for k, v in origins.items() if k in ("bunny", "cow"))
        or "pymeshlab/trimesh not installed",
        "runs": runs,
        "fits": fits,
        "surface_fits": surface_fits,
        "surface_points": FIT_SURFACE_POINTS,
        "origins": origins,
    }
    payload["total_s"] = time.perf_counter() - start
    text = markdown(payload)
    write_results("normals", payload, text)
    print(text)


if __name__ == "__main__":
    main()
