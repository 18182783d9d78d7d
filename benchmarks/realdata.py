"""Real data: ``jurs.fit`` with its defaults on traced outlines, against a thin-plate RBF.

Issue 23 asks whether the defaults, built on clean analytic curves and fonts, hold on the
outlines a new user brings: traced from images with plain marching squares (pixel
staircases), with noise, uneven density or outliers, many rings, thin parts. One command
measures it and writes the dated results ``benchmarks/results/realdata_default.{json,md}``
and the figure ``benchmarks/results/realdata/worst_default.png``:

* **Cases** (``_realdata_cases``): 14 outlines from data that ship with scikit-image and
  matplotlib (photos, a medical slice, a terrain model, binary blobs, text) or set in
  DejaVu Serif / Sans Mono; none is in the project's suite. Sampled finer than a pixel.
* **Variants** of each: ``clean``; ``noisy`` (positions + N(0, (0.5 % diag)^2) per
  coordinate, normals turned by N(0, 0.1 rad)); ``uneven`` (density varying 5x along the
  outline); ``outlier`` (1.5 % of the points moved uniformly into the enlarged box, at
  least 5 % of diag from the outline, with random normals). Fixed seeds per run.
* **jurs**: ``jurs.fit(points, normals, throw=False)``, nothing else (the uniform grid or
  the adaptive basis, as ``basis="auto"`` chooses): warm time
  (``_common.time_repeated``); status, settings and scalar stats recorded; results
  ``realdata_default.{json,md}``, with the other two fits' counts beside them where their
  results are present. ``--fit uniform`` adds ``basis="uniform"`` (``realdata.{json,md}``,
  the defaults before the automatic choice of basis); ``--fit adaptive`` fits
  ``jurs.fit_adaptive(points, normals, throw=False)`` (``realdata_adaptive.{json,md}``);
  each its own ``realdata/worst_<fit>.png`` (the uniform grid's ``worst.png``).
* **RBF**: ``_baselines.rbf_fit`` (SciPy's thin-plate ``RBFInterpolator``) on the same offset
  samples with jurs's d and eps, smoothing 0, no outlier handling (what a user has today);
  on at most ``RBF_MAX_POINTS`` evenly strided points (its dense solve is O((3m)^3)).
* **Measures**, both methods on the same box and grid (``jurs.levelset.analyze`` /
  ``analyze_grid``): Chamfer and Hausdorff distances of the zero set to the clean outline
  (fractions of its bounding-box diagonal), and a ring-by-ring topology match
  (``match_rings``): a count of components can be right while one ring splits and two
  others merge, so every true ring is checked for the one component that follows it.

    python -m benchmarks.realdata [--quick] [--cases a,b] [--variants clean,noisy]
                                  [--fit uniform|default|adaptive]
    python -m benchmarks.realdata --markdown-only [--fit ...]

``--markdown-only`` re-renders the markdown from the JSON (no measurement, no figure).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import zlib
from typing import Any

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402  # pyright: ignore[reportAttributeAccessIssue]

import jurs  # noqa: E402
import jurs.levelset  # noqa: E402
import jurs.shapes  # noqa: E402

from . import _realdata_cases as cases  # noqa: E402
from ._baselines import rbf_fit, rbf_grid_values  # noqa: E402
from ._common import RESULTS, machine, rerender_beside, time_repeated, write_results  # noqa: E402

# --------------------------------------------------------------------------- configuration

#: The fits compared with the RBF, each with nothing but the cloud: ``jurs.fit`` on the
#: uniform grid always (its defaults before the automatic choice of basis), ``jurs.fit``'s
#: defaults (``basis="auto"``: the capped grid, or the adaptive basis where the grid misses
#: the data) and ``jurs.fit_adaptive``.
FITS = {
    "uniform": lambda points, normals: jurs.fit(points, normals, throw=False, basis="uniform"),
    "default": lambda points, normals: jurs.fit(points, normals, throw=False),
    "adaptive": lambda points, normals: jurs.fit_adaptive(points, normals, throw=False),
}
#: The call each fit makes, and its name in the results pages' titles and tables.
CALLS = {
    "uniform": 'jurs.fit(points, normals, throw=False, basis="uniform")',
    "default": "jurs.fit(points, normals, throw=False)",
    "adaptive": "jurs.fit_adaptive(points, normals, throw=False)",
}
TITLES = {
    "uniform": "`jurs.fit` on the uniform grid",
    "default": "`jurs.fit` defaults",
    "adaptive": "`jurs.fit_adaptive` defaults",
}
#: Results file of each fit.
RESULTS_NAME = {
    "uniform": "realdata",
    "default": "realdata_default",
    "adaptive": "realdata_adaptive",
}

VARIANTS = ("clean", "noisy", "uneven", "outlier")
QUICK_CASES = ("rocket", "coffee", "blobs_small", "mono")
QUICK_VARIANTS = ("clean", "outlier")
#: Noise: position sigma (fraction of diag) and normal rotation sigma (radians).
NOISE, NORMAL_NOISE = 0.005, 0.1
#: ``nonuniform`` of the uneven variant: density 1/3 .. 5/3 of the mean (5x).
UNEVEN = 2.0 / 3.0
#: Outliers: fraction of points replaced; box enlargement per side (fraction of the box's
#: size); least distance to the outline (fraction of diag).
OUTLIERS, OUTLIER_PAD, OUTLIER_MIN_DIST = 0.015, 0.05, 0.05
#: The RBF is fitted on at most this many (evenly strided) points.
RBF_MAX_POINTS = 4000
#: Warm-timing budget of ``time_repeated`` (at least 3 warm calls).
WARM_BUDGET_S = 1.0
#: Reference samples of the clean outline: spacing diag / REFERENCE_DIVISOR.
REFERENCE_DIVISOR = 2000
#: Analysis grid: nodes per image pixel along the box's longer side, within a range.
NODES_PER_PIXEL, RESOLUTION_MIN, RESOLUTION_MAX = 3, 512, 1024
#: Ring matching tolerance, a fraction of diag (the noisy Hausdorff target).
MATCH_TOL = 0.01
#: Issue 23's targets: Hausdorff (fraction of diag) clean / other variants; warm time at
#: m <= TIME_MAX_M.
HAUSDORFF_CLEAN, HAUSDORFF_OTHER, TIME_TARGET_S, TIME_MAX_M = 0.005, 0.01, 0.150, 5000
#: Runs shown in the figure (see ``worst_runs``).
WORST = 8

FIGURE_DIR = os.path.join(RESULTS, "realdata")


# --------------------------------------------------------------------------- ring matching


def _line_samples(lines, spacing):
    """Samples of polylines at arc-length ``spacing``: points, line index, the arc length
    each sample stands for, and the lines' lengths."""
    pts, lab, wts, lengths = [], [], [], []
    for k, line in enumerate(lines):
        line = np.asarray(line, float).reshape(-1, 2)
        p = jurs.levelset.resample(line, spacing)
        length = jurs.levelset.polyline_length(line)
        pts.append(p)
        lab.append(np.full(len(p), k))
        wts.append(np.full(len(p), length / len(p)))
        lengths.append(length)
    if not pts:
        return np.empty((0, 2)), np.empty(0, int), np.empty(0), np.empty(0)
    return np.concatenate(pts), np.concatenate(lab), np.concatenate(wts), np.array(lengths)


def match_rings(
    rings,
    components,
    tol: float,
    *,
    link: float = 0.1,
    cover: float = 0.5,
    elsewhere: float = 0.25,
    spacing: float | None = None,
) -> dict:
    """Match true rings to zero-set components one by one.

    ``rings`` and ``components`` are polylines drawn as given (close a ring by repeating
    its first vertex). Both are sampled by arc length (``spacing``, default ``tol / 4``);
    every ring sample is assigned to its nearest component and every component sample to
    its nearest ring, when within ``tol``. With ``cover[r, c]`` the length of ring r
    assigned to component c and ``along[c, r]`` the length of c assigned to r, r and c are
    *linked* when both are at least ``link`` x the ring's length (c follows a good part of
    r), or when at least half of c lies along r, at least ``tol`` of r is assigned to c
    and c is no shorter than ``tol`` (a piece pinched off a ring, not a tiny loop).
    Nearest assignment on both sides keeps a component that follows one ring from being
    linked to a close neighbour it is not along. Then, per ring:

    * ``lost``: no component linked;
    * ``split``: several components linked;
    * ``merged``: a linked component is linked to another ring too (a ring can be split
      and merged: both counts include it);
    * ``partial``: one component, linked to it alone, but following less than ``cover``
      of the ring's length, or lying farther than ``tol`` from every ring along more than
      ``elsewhere`` of its own length;
    * ``matched``: otherwise.

    Components linked to no ring (tiny loops included) are ``extra``. Exact topology: every
    ring matched and no extra. Returns the counts, ``rings``, ``components``, ``exact``,
    the per-ring ``ring_status`` (one word; "merged" before "split") and per-component
    ``component_rings`` (the rings each component is linked to).
    """
    tol = float(tol)
    spacing = tol / 4 if spacing is None else float(spacing)
    rp, rl, rw, rlen = _line_samples(rings, spacing)
    cp, cl, cw, clen = _line_samples(components, spacing)
    nr, nc = len(rlen), len(clen)
    covered = np.zeros((nr, nc))
    along = np.zeros((nc, nr))
    away = clen.copy()
    if nr and nc:
        dist, idx = cKDTree(cp).query(rp)
        ok = dist <= tol
        np.add.at(covered, (rl[ok], cl[idx[ok]]), rw[ok])
        dist, idx = cKDTree(rp).query(cp)
        ok = dist <= tol
        np.add.at(along, (cl[ok], rl[idx[ok]]), cw[ok])
        away = np.bincount(cl[~ok], weights=cw[~ok], minlength=nc)
    overlap = np.minimum(covered, along.T)
    pinched = (along.T >= 0.5 * clen[None, :]) & (covered >= tol) & (clen[None, :] >= tol)
    linked = (overlap >= link * rlen[:, None]) | pinched
    per_component = linked.sum(axis=0)
    split = linked.sum(axis=1) > 1
    merged = np.array([(per_component[linked[r]] > 1).any() for r in range(nr)], bool)
    status = []
    for r in range(nr):
        (comps,) = np.nonzero(linked[r])
        if len(comps) == 0:
            status.append("lost")
        elif merged[r]:
            status.append("merged")
        elif split[r]:
            status.append("split")
        elif covered[r, comps[0]] < cover * rlen[r] or away[comps[0]] > elsewhere * clen[comps[0]]:
            status.append("partial")
        else:
            status.append("matched")
    counts = {
        "matched": status.count("matched"),
        "split": int(split.sum()),
        "merged": int(merged.sum()),
        "lost": status.count("lost"),
        "partial": status.count("partial"),
    }
    extra = int(np.sum(per_component == 0))
    return {
        **counts,
        "extra": extra,
        "rings": nr,
        "components": nc,
        "exact": counts["matched"] == nr and extra == 0,
        "ring_status": status,
        "component_rings": [np.nonzero(linked[:, c])[0].tolist() for c in range(nc)],
    }


def compact(t: dict) -> dict:
    """``match_rings``'s result for the JSON: the counts, and the indices of the rings
    not matched by status (not the per-ring and per-component lists)."""
    out = {k: v for k, v in t.items() if k not in ("ring_status", "component_rings")}
    out["not_matched"] = {}
    for r, s in enumerate(t["ring_status"]):
        if s != "matched":
            out["not_matched"].setdefault(s, []).append(r)
    return out


def topology_text(t: dict) -> str:
    """``'exact'`` or the non-zero failure counts, e.g. ``'2 lost, 1 extra'``."""
    if t["exact"]:
        return "exact"
    parts = [f"{t[k]} {k}" for k in ("split", "merged", "lost", "partial", "extra") if t[k]]
    return ", ".join(parts) or "exact"


# --------------------------------------------------------------------------- data


def seed_of(case: str, variant: str) -> int:
    return zlib.crc32(f"{case}/{variant}".encode())


def reference_samples(case) -> np.ndarray:
    """Dense samples of the clean outline (spacing diag / ``REFERENCE_DIVISOR``)."""
    spacing = case.diag / REFERENCE_DIVISOR
    return np.concatenate(
        [jurs.levelset.resample(np.vstack([c, c[:1]]), spacing) for c in case.components]
    )


def resolution_of(case) -> int:
    """Analysis grid nodes along the longer side: ``NODES_PER_PIXEL`` per pixel of the
    longest side (size 8), within ``RESOLUTION_MIN .. RESOLUTION_MAX``."""
    pixels = cases.SIZE / case.pixel
    return int(np.clip(round(NODES_PER_PIXEL * pixels, -2), RESOLUTION_MIN, RESOLUTION_MAX))


def cloud(case, variant: str, reference: np.ndarray):
    """``(points, normals, outlier indices)`` of ``case`` in ``variant`` (seeded by
    ``seed_of``)."""
    rng = np.random.default_rng(seed_of(case.name, variant))
    comps, m, diag = list(case.components), case.m, case.diag
    nonuniform = UNEVEN if variant == "uneven" else 0.0
    points, normals = jurs.shapes.sample_outline(comps, m, nonuniform=nonuniform)
    moved = np.empty(0, int)
    if variant == "noisy":
        points = points + rng.normal(0.0, NOISE * diag, points.shape)
        angle = rng.normal(0.0, NORMAL_NOISE, m)
        c, s = np.cos(angle), np.sin(angle)
        normals = np.stack(
            [c * normals[:, 0] - s * normals[:, 1], s * normals[:, 0] + c * normals[:, 1]], 1
        )
    elif variant == "outlier":
        count = int(round(OUTLIERS * m))
        lo, hi = reference.min(axis=0), reference.max(axis=0)
        pad = OUTLIER_PAD * (hi - lo)
        tree, found = cKDTree(reference), []
        for _ in range(1000):
            cand = rng.uniform(lo - pad, hi + pad, (4 * count, 2))
            found.append(cand[tree.query(cand)[0] > OUTLIER_MIN_DIST * diag])
            if sum(len(f) for f in found) >= count:
                break
        else:
            raise RuntimeError(f"{case.name}: no room for outliers")
        moved = np.sort(rng.choice(m, count, replace=False))
        points, normals = points.copy(), normals.copy()
        points[moved] = np.concatenate(found)[:count]
        angle = rng.uniform(0.0, 2 * np.pi, count)
        normals[moved] = np.stack([np.cos(angle), np.sin(angle)], 1)
    elif variant not in ("clean", "uneven"):
        raise ValueError(f"unknown variant {variant!r}")
    return points, normals, moved


# --------------------------------------------------------------------------- one run


def stat_summary(stats) -> dict:
    """JSON-ready scalars of ``sol.stats`` / ``sol.metrics``: scalars as numbers, arrays as
    shape and NaN-aware min / median / max, other values as text."""
    out = {}
    for key, value in dict(stats).items():
        if isinstance(value, (str, bool, int, float)) or value is None:
            out[key] = value
            continue
        try:
            a = np.asarray(value)
        except Exception:  # noqa: BLE001 (anything else: its text)
            out[key] = str(value)
            continue
        if a.dtype.kind not in "biuf":
            out[key] = str(value)
        elif a.size == 1:
            out[key] = a.item()
        elif a.size and np.isfinite(a).any():
            f = a[np.isfinite(a)].astype(float)
            out[key] = {
                "shape": list(a.shape),
                "min": float(f.min()),
                "median": float(np.median(f)),
                "max": float(f.max()),
            }
        else:
            out[key] = {"shape": list(a.shape)}
    return out


def focus(report, topo, rings, reference):
    """Where the figure's zoom looks. On the shortest true ring not matched: for a split
    ring, the shortest component following it; otherwise the ring's point farthest from
    the zero set (where a bridge or loss shows). Where all rings are matched: where the
    Hausdorff distance between the reference and the components along true rings is
    attained (extra components show in the full view). None: no zero set."""
    h = report.cell_size / 2
    lines = [c.polyline for c in report.components]
    bad = [r for r, s in enumerate(topo["ring_status"]) if s != "matched"]
    if not bad:
        lines = [p for p, r in zip(lines, topo["component_rings"]) if r]
    if not lines:
        return None

    def middle(line):
        return line[np.argmin(np.linalg.norm(line - line.mean(axis=0), axis=1))]

    zero = np.concatenate([jurs.levelset.resample(p, h) for p in lines])
    if bad:
        r = min(bad, key=lambda r: jurs.levelset.polyline_length(rings[r]))
        followers = [p for p, rs in zip(lines, topo["component_rings"]) if r in rs]
        if topo["ring_status"][r] == "split":
            return middle(min(followers, key=jurs.levelset.polyline_length))
        ring = jurs.levelset.resample(rings[r], h)
        return ring[np.argmax(cKDTree(zero).query(ring)[0])]
    d_zr = cKDTree(reference).query(zero)[0]
    d_rz = cKDTree(zero).query(reference)[0]
    return zero[np.argmax(d_zr)] if d_zr.max() >= d_rz.max() else reference[np.argmax(d_rz)]


def measure(report, rings, diag, reference) -> tuple[dict, dict]:
    """Distances (fractions of diag) and the ring match of one zero set; and what the
    figure needs."""
    lines = [c.polyline for c in report.components]
    topo = match_rings(rings, lines, MATCH_TOL * diag)
    out = {
        "chamfer": report.chamfer / diag,
        "hausdorff": report.hausdorff / diag,
        "num_components": report.num_components,
        "num_supplementary": report.num_supplementary,
        "num_tiny_loops": report.num_tiny_loops,
        "topology": compact(topo),
    }
    return out, {"lines": lines, "topology": topo, "focus": focus(report, topo, rings, reference)}


def run_one(name: str, variant: str, fit: str = "default") -> tuple[dict, dict]:
    """Fit (``FITS[fit]``), time and measure one (case, variant); returns the JSON row and
    figure data."""
    case = cases.build(name)
    ref = reference_samples(case)
    diag, res = case.diag, resolution_of(case)
    rings = [np.vstack([c, c[:1]]) for c in case.components]
    points, normals, moved = cloud(case, variant, ref)
    out = {
        "case": name,
        "variant": variant,
        "m": case.m,
        "rings": len(rings),
        "diag": diag,
        "pixel": case.pixel / diag,
        "resolution": res,
        "seed": seed_of(name, variant),
        "outliers": len(moved),
    }

    # jurs, defaults only
    timing = time_repeated(
        lambda: FITS[fit](points, normals), budget_s=WARM_BUDGET_S, max_repeats=5
    )
    sol = timing.pop("output")
    st = sol.settings
    lower, upper = (sol.spline.lower, sol.spline.upper) if st.domain is None else st.domain
    box = (np.asarray(lower, float), np.asarray(upper, float))
    rep = jurs.levelset.analyze(
        sol.spline, points, offset=st.offset, reference=ref, resolution=res, box=box
    )
    jm, jfig = measure(rep, rings, diag, ref)
    out["settings"] = st.as_dict() if hasattr(st, "as_dict") else dict(vars(st))
    out["jurs"] = {
        **jm,
        **timing,
        "status": sol.status,
        "message": str(sol.message),
        "stats": stat_summary(sol.stats),
        "metrics": stat_summary(sol.metrics),
    }
    if "finest" in sol.stats:  # the adaptive basis, chosen or asked for
        out["jurs"]["finest"] = list(sol.stats["finest"])
        out["jurs"]["active"] = int(sum(sol.stats["active"]))

    # RBF on the same offset samples (an evenly strided subset above RBF_MAX_POINTS)
    keep = np.arange(case.m)
    if case.m > RBF_MAX_POINTS:
        keep = np.unique(np.round(np.linspace(0, case.m - 1, RBF_MAX_POINTS)).astype(int))
    rbf, fit_s = rbf_fit(points[keep], normals[keep], offset=st.offset, eps=st.eps, smoothing=0.0)
    t0 = time.perf_counter()
    xs, ys, _ = jurs.levelset.sampling_grid(*box, res)
    values, evaluations = rbf_grid_values(rbf, xs, ys)
    rrep = jurs.levelset.analyze_grid(xs, ys, values, points, offset=st.offset, reference=ref)
    rm, rfig = measure(rrep, rings, diag, ref)
    out["rbf"] = {
        **rm,
        "points": len(keep),
        "fit_s": fit_s,
        "measure_s": time.perf_counter() - t0,
        "evaluations": evaluations,
    }
    out["chamfer_ratio"] = jm["chamfer"] / rm["chamfer"]
    fig = {"points": points, "moved": moved, "rings": rings, "jurs": jfig, "rbf": rfig}
    return out, fig


# --------------------------------------------------------------------------- targets


def hausdorff_target(variant: str) -> float:
    return HAUSDORFF_CLEAN if variant == "clean" else HAUSDORFF_OTHER


def targets(r: dict) -> dict:
    """Which of issue 23's targets the jurs fit of run ``r`` meets (None: not applicable)."""
    j = r["jurs"]
    out = {
        "topology": bool(j["topology"]["exact"]),
        "hausdorff": j["hausdorff"] <= hausdorff_target(r["variant"]),
        "chamfer": j["chamfer"] <= r["rbf"]["chamfer"],
        "time": j["warm_s"] <= TIME_TARGET_S if r["m"] <= TIME_MAX_M else None,
    }
    out["all"] = all(v for v in out.values() if v is not None)
    return out


# --------------------------------------------------------------------------- report


def pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def cell(text: str) -> str:
    """``text`` for a markdown table cell (pipes escaped)."""
    return text.replace("|", "\\|")


def label(r: dict) -> str:
    return f"{r['case']}/{r['variant']}"


def summary_table(runs: list) -> list:
    """Counts of runs meeting each target, per variant and over all runs."""
    names = ("topology", "hausdorff", "chamfer", "time", "all")
    lines = [
        "| variant | runs | exact topology: jurs (RBF) | Hausdorff target: jurs (RBF) | "
        "Chamfer <= RBF's | warm fit <= 150 ms (m <= 5000) | all four |",
        "|---|---|---|---|---|---|---|",
    ]
    groups = [(v, [r for r in runs if r["variant"] == v]) for v in VARIANTS]
    for variant, group in groups + [("all", runs)]:
        if not group:
            continue
        t = [targets(r) for r in group]
        n = {k: sum(bool(x[k]) for x in t) for k in names}
        timed = sum(x["time"] is not None for x in t)
        rbf_topo = sum(r["rbf"]["topology"]["exact"] for r in group)
        rbf_h = sum(r["rbf"]["hausdorff"] <= hausdorff_target(r["variant"]) for r in group)
        lines.append(
            f"| {variant} | {len(group)} | {n['topology']} ({rbf_topo}) | "
            f"{n['hausdorff']} ({rbf_h}) | {n['chamfer']} | {n['time']} of {timed} | "
            f"{n['all']} |"
        )
    return lines


def verdict_table(runs: list) -> list:
    """How many of the runs missing a quality target the fit's own verdict flagged (any
    status but ``successful``: the user is told), and how many that met both were flagged
    anyway."""
    met = [(targets(r), r["jurs"]["status"] != "successful") for r in runs]
    rows = [
        ("topology not exact", lambda t: not t["topology"]),
        ("Hausdorff over its target", lambda t: not t["hausdorff"]),
        ("both met", lambda t: t["topology"] and t["hausdorff"]),
    ]
    lines = [
        "| runs | count | flagged by the fit (status not successful) |",
        "|---|---|---|",
    ]
    for name, keep in rows:
        group = [flagged for t, flagged in met if keep(t)]
        lines.append(f"| {name} | {len(group)} | {sum(group)} |")
    return lines


def solve_count(r: dict) -> int:
    """Linear solves of the default fit: the held-out candidates tried, then the fit."""
    return len(r["settings"].get("held_out") or ()) + 1


def basis_of(r: dict) -> str:
    """The basis a run's fit ended on: ``"adaptive"`` or ``"grid"``."""
    return "adaptive" if "active" in r["jurs"] else "grid"


def basis_size(r: dict) -> int:
    """Active functions of an adaptive fit, coefficients of a grid's."""
    return r["jurs"]["active"] if "active" in r["jurs"] else int(np.prod(r["settings"]["grid"]))


def time_table(runs: list) -> list:
    """Warm times of the runs the time target applies to, by basis and number of solves."""
    timed = [r for r in runs if r["m"] <= TIME_MAX_M]
    lines = [
        "| basis | solves on the grid | runs | median functions | median warm fit | <= 150 ms |",
        "|---|---|---|---|---|---|",
    ]
    for key in sorted({(basis_of(r), solve_count(r)) for r in timed}):
        group = [r for r in timed if (basis_of(r), solve_count(r)) == key]
        size = np.median([basis_size(r) for r in group])
        warm = np.median([r["jurs"]["warm_s"] for r in group])
        fast = sum(r["jurs"]["warm_s"] <= TIME_TARGET_S for r in group)
        lines.append(
            f"| {key[0]} | {key[1]} | {len(group)} | {size:.0f} | {1e3 * warm:.0f} ms | {fast} |"
        )
    return lines


def beside_table(meta: dict, runs: list) -> list:
    """The target counts of this page's ``runs`` beside the other fits' results files
    (where present and over the same runs): each fit measured in its own run of this
    script."""
    rows = []
    for fit in ("uniform", "default", "adaptive"):
        if fit == meta.get("fit"):
            these, date = runs, meta["date"]
        else:
            path = os.path.join(RESULTS, f"{RESULTS_NAME[fit]}.json")
            if not os.path.exists(path):
                continue
            with open(path) as f:
                other = json.load(f)
            if other["meta"].get("quick") != meta["quick"]:
                continue
            these, date = other["runs"], other["meta"]["date"]
        these = [r for r in these if "error" not in r]
        t = [targets(r) for r in these]
        n = {k: sum(bool(x[k]) for x in t) for k in ("topology", "hausdorff", "chamfer", "time")}
        timed = sum(x["time"] is not None for x in t)
        adaptive = sum(basis_of(r) == "adaptive" for r in these)
        rows.append(
            f"| {TITLES[fit]} | {date} | {len(these)} | {adaptive} | "
            f"{n['topology']} | {n['hausdorff']} | {n['chamfer']} | {n['time']} of {timed} |"
        )
    if not rows:
        return []
    return [
        "| fit | run | runs | on the adaptive basis | exact topology | Hausdorff target | "
        "Chamfer <= RBF's | warm fit <= 150 ms |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ]


def markdown(payload: dict) -> str:
    """The results page from the JSON payload."""
    meta, runs = payload["meta"], payload["runs"]
    fit = meta.get("fit", "uniform")
    adaptive = fit == "adaptive"
    call = CALLS[fit]
    ok = [r for r in runs if "error" not in r]
    lines = [
        f"# Real data: {TITLES[fit]} on traced outlines against a thin-plate RBF"
        + (" (quick subset)" if meta["quick"] else ""),
        "",
        f"Date: {meta['date']}. Machine: {meta['machine']} (load average "
        f"{meta['load_average']:.1f} at the start"
        + (f", {meta['load_average_end']:.1f} at the end" if "load_average_end" in meta else "")
        + f"). Float64. Command: `{meta['command']}`; "
        f"{len(runs)} runs ({len(meta['cases'])} cases x variants "
        f"{', '.join(meta['variants'])}) in {meta['total_s'] / 60:.1f} min."
        + (f" {meta['note']}" if meta.get("note") else ""),
        "",
        "## Targets of issue 23",
        "",
        "Runs meeting each target (jurs's defaults; the RBF's own counts in brackets where "
        f"they apply). Hausdorff target: <= {pct(HAUSDORFF_CLEAN)} of diag on clean data, <= "
        f"{pct(HAUSDORFF_OTHER)} on the other variants. 'all four': every target that applies.",
        "",
        *summary_table(ok),
        "",
    ]
    beside = beside_table(meta, ok) if fit == "default" else []
    if beside:
        lines += [
            "## Beside the uniform grid and the adaptive basis",
            "",
            "The same runs fitted on the uniform grid always and on the adaptive basis "
            "always, each from its own results file and run of this script (dates in the "
            "table; machine load differs between runs, so the time column compares loosely):",
            "",
            *beside,
            "",
            "The default fits the capped grid first wherever the data ask for finer cells "
            "than it affords, and moves to the adaptive basis where fewer than 90 % of the "
            "points lie within `jurs._fit.adaptive.UNIFORM_RESIDUAL_SPACINGS` spacings of "
            "the grid's zero set (`sol.stats['uniform_residual']`); such a fit pays for both.",
            "",
        ]
    lines += [
        "## Misses, verdicts and limits",
        "",
        "Whether the fit said so where it missed (`sol.status`: `doubtful` with the reasons "
        "in `sol.stats['doubts']`, or a failure verdict):",
        "",
        *verdict_table(ok),
        "",
        "Warm time against the number of exact solves (a traced outline's smoothing is chosen "
        "by held-out points: one solve per candidate tried on the kept points, then the fit "
        "on all of them):",
        "",
        *time_table(ok),
        "",
    ]
    if adaptive:
        lines += [
            "The adaptive fit is one direct solve on the THB basis (no held-out choice of "
            "its own; the settings' measurements are those of `jurs.auto_settings`), with "
            "its finest cell one point spacing or 4 noise levels wide (`jurs._fit.adaptive"
            ".CELL_SPACINGS`); the per-run table gives its finest level (cells along each "
            "axis over the box) and its active functions.",
            "",
        ]
    elif fit == "uniform":
        lines += [
            "What limits the misses (measurements in `docs/performance.md` and "
            "`docs/design.md`): the topology misses are features of 1-3 pixels (handles, tripod "
            "legs, fins, letter gaps) narrower than a cell; cells finer than the data's spacing "
            "or 4 noise levels are not chosen, and the grid stays within its coefficient "
            "budget, because the exact solve (a block Cholesky of the stencil, about N M^3) "
            "grows as the cube of the shorter side. The same solve bounds the time: one "
            "costs 35-60 ms at 96 x 96 on this CPU, and a held-out choice needs two or more "
            "before the fit. Chamfer on clean and uneven data: the RBF interpolates the pixel "
            "staircase, while jurs's cells are several spacings wide.",
            "",
        ]
    errors = [r for r in runs if "error" in r]
    if errors:
        lines += ["Errors: " + "; ".join(f"{label(r)}: {r['error']}" for r in errors), ""]
    lines += [
        "## How to read",
        "",
        "Each run samples a real outline (below) with m points, applies its variant and calls "
        f"`{call}` with nothing else; the warm time is the "
        f"median of warm calls after a first one (`_common.time_repeated`, budget "
        f"{WARM_BUDGET_S:g} s). The RBF is `_baselines.rbf_fit` (SciPy's thin-plate "
        "`RBFInterpolator`) on the same offset samples with jurs's d and eps, smoothing 0, "
        "no outlier handling; above "
        f"{RBF_MAX_POINTS} points it gets an evenly strided subset of {RBF_MAX_POINTS} "
        "('RBF pts'), its dense solve being O((3m)^3). Both zero sets are extracted on the "
        "same grid over jurs's box (`jurs.levelset.analyze` / `analyze_grid`, the RBF's grid "
        "values by `_baselines.rbf_grid_values`, exact wherever the zero set can pass) with "
        f"{NODES_PER_PIXEL} nodes per image pixel along the longer side "
        f"({RESOLUTION_MIN}..{RESOLUTION_MAX}). Chamfer and Hausdorff: zero set to dense "
        f"samples of the clean outline, in % of its bounding-box diagonal. "
        "**Topology** (`match_rings`): the clean outline's rings against the zero set's "
        f"components, with tolerance {pct(MATCH_TOL)} of diag (each ring sample assigned to "
        "its nearest component, each component sample to its nearest ring, within the "
        "tolerance). A component follows a ring when both assignments give it at least 10 % "
        "of the ring's length, or when half of it lies along the ring and it is no shorter "
        "than the tolerance (a piece pinched off). A ring is *matched* when exactly one component "
        "follows it, along most of it, and that component follows no other ring and lies "
        "mostly near the rings; otherwise it is *lost* (no component), *split* (several "
        "components), *merged* (its component also follows another ring; a ring can be split "
        "and merged) or *partial* (one component, along less than half of it or wandering "
        "off). Components following no ring (tiny loops included) are *extra*. Exact: every "
        "ring matched, no extra.",
        "",
        "## Cases",
        "",
        "Traced outlines: plain marching squares on the 0/1 mask (no blur), so their "
        "vertices lie on half-pixel positions and carry the pixel staircase. m = "
        f"clip(round({cases.POINTS_PER_PIXEL:g} L, -2), {cases.M_MIN}, {cases.M_MAX}), L the "
        f"outline's length in pixels (fonts: as if set {cases.FONT_PIXELS} px wide); page: m "
        f"= {cases.MULTI_RING_M}. Outlines scaled to a longest side of {cases.SIZE:g}.",
        "",
        "| case | rings | L (px) | m | pixel (% diag) | source |",
        "|---|---|---|---|---|---|",
    ]
    for name, c in meta["case_info"].items():
        lines.append(
            f"| {name} | {c['rings']} | {c['length_px']:.0f} | {c['m']} | "
            f"{100 * c['pixel'] / c['diag']:.2f} | {cell(c['source'])} |"
        )
    lines += [
        "",
        "Variants (seed crc32('case/variant')): "
        f"*clean*; *noisy*: positions + N(0, ({pct(NOISE)} diag)^2) per coordinate, normals "
        f"turned by N(0, {NORMAL_NOISE:g} rad); *uneven*: `sample_outline(..., "
        f"nonuniform={UNEVEN:.3f})`, density {1 - UNEVEN:.2f}..{1 + UNEVEN:.2f} of the mean "
        f"(5x); *outlier*: {pct(OUTLIERS)} of the points replaced by points uniform in the "
        f"outline's box enlarged by {100 * OUTLIER_PAD:g} % per side, at least "
        f"{pct(OUTLIER_MIN_DIST)} of diag from the outline, with random unit normals.",
        "",
    ]
    if meta.get("figure"):
        lines += [f"![worst runs](realdata/{meta['figure']})", "", meta["caption"], ""]
    basis = "grid, or finest (active)"
    lines += [
        "## Per run",
        "",
        "d, noise: jurs's offset and noise estimate (`sol.settings`), in % of diag. "
        "Topology: 'exact' or the failure counts (rings split / merged / lost / partial, "
        "extra components). C, H: Chamfer, Hausdorff in % of diag. C ratio: jurs / RBF "
        "Chamfer. jurs time: warm median / fastest (first call; it compiles where the "
        "grid is new to the process).",
        "",
        f"| case | variant | m | RBF pts | {basis} | smoothing | d | noise | status | "
        "jurs topology | jurs C | jurs H | RBF topology | RBF C | RBF H | C ratio | "
        "jurs time | RBF fit |",
        "|" + "---|" * 18,
    ]
    for r in runs:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['variant']} | {r['m']} | error: {r['error']} |")
            continue
        st, j, b = r["settings"], r["jurs"], r["rbf"]
        grid = "x".join(str(g) for g in (j["finest"] if "finest" in j else st["grid"]))
        if "finest" in j:
            grid = f"finest {grid} ({j['active']})"
        lines.append(
            f"| {r['case']} | {r['variant']} | {r['m']} | {b['points']} | {grid} | "
            f"{st['smoothing']:.2g} | {100 * st['offset'] / r['diag']:.3f} | "
            f"{100 * st['noise'] / r['diag']:.3f} | {j['status']} | "
            f"{topology_text(j['topology'])} | {100 * j['chamfer']:.3f} | "
            f"{100 * j['hausdorff']:.2f} | {topology_text(b['topology'])} | "
            f"{100 * b['chamfer']:.3f} | {100 * b['hausdorff']:.2f} | "
            f"{r['chamfer_ratio']:.2f} | {1e3 * j['warm_s']:.0f} / "
            f"{1e3 * j.get('min_s', j['warm_s']):.0f} ms ({j['first_s']:.1f} s) | "
            f"{b['fit_s']:.1f} s |"
        )
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- figure


def badness(r: dict) -> tuple:
    """Sort key, worst first: topology failures, then Hausdorff over its target."""
    j = r["jurs"]
    return (j["topology"]["exact"], -j["hausdorff"] / hausdorff_target(r["variant"]))


def worst_runs(runs: list, count: int = WORST) -> list:
    """Indices of the runs the figure shows, worst first, one per case: the worst run of
    each variant among cases not shown yet, then the worst run of each further case,
    ``count`` in all."""
    ok = sorted((i for i, r in enumerate(runs) if "error" not in r), key=lambda i: badness(runs[i]))
    shown = []
    for per_variant in (True, False):
        for i in ok:
            taken = [runs[k] for k in shown]
            if len(shown) == count or runs[i]["case"] in {t["case"] for t in taken}:
                continue
            if per_variant and runs[i]["variant"] in {t["variant"] for t in taken}:
                continue
            shown.append(i)
    return sorted(shown, key=lambda i: badness(runs[i]))


def _draw(ax, fig, window=None):
    """One panel: data, RBF and jurs zero sets (jurs components along no ring in red), the
    true outline on top (rings not matched underlaid in magenta), the worst jurs deviation
    circled; ``window``: half-width of a zoom on it."""
    p = fig["points"]
    ax.scatter(*p.T, s=0.6 if window is None else 5, c="0.6", linewidths=0, zorder=1)
    if len(fig["moved"]):
        ax.scatter(*p[fig["moved"]].T, s=3, c="0.3", marker="x", linewidths=0.5, zorder=1)
    for ring, s in zip(fig["rings"], fig["jurs"]["topology"]["ring_status"]):
        if s != "matched":
            ax.plot(*ring.T, color="m", lw=2.5, alpha=0.6, zorder=2)
        ax.plot(*ring.T, color="k", lw=0.5, zorder=5)
    for line in fig["rbf"]["lines"]:
        ax.plot(*line.T, color="tab:orange", lw=0.9, ls="--", zorder=3)
    for line, linked in zip(fig["jurs"]["lines"], fig["jurs"]["topology"]["component_rings"]):
        ax.plot(*line.T, color="tab:blue" if linked else "tab:red", lw=1.0, zorder=4)
    where = fig["jurs"]["focus"]
    span = np.ptp(np.concatenate(fig["rings"]), axis=0).max()
    if where is not None:
        ax.add_patch(_circle(where, 0.03 * span if window is None else 0.15 * window))
    if window is None:
        lo, hi = p.min(axis=0), p.max(axis=0)
        pad = 0.04 * (hi - lo).max()
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    elif where is not None:
        ax.set_xlim(where[0] - window, where[0] + window)
        ax.set_ylim(where[1] - window, where[1] + window)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def _circle(center, radius):
    from matplotlib.patches import Circle

    return Circle(tuple(center), radius, fill=False, color="tab:green", lw=1.2, zorder=6)


def figure(runs: list, figs: list, path: str) -> str:
    """The worst runs, each as a full view and a zoom on where jurs's Hausdorff distance is
    attained; written with matplotlib's object API on Agg. Returns the caption."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    shown = [i for i in worst_runs(runs) if figs[i] is not None]
    if not shown:
        return ""
    ncols = 4
    nrows = -(-2 * len(shown) // ncols)
    fig = Figure(figsize=(3.2 * ncols, 3.2 * nrows + 0.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes:
        ax.set_axis_off()
    for k, i in enumerate(shown):
        r, f = runs[i], figs[i]
        j = r["jurs"]
        for ax, window in ((axes[2 * k], None), (axes[2 * k + 1], 0.05 * r["diag"])):
            ax.set_axis_on()
            _draw(ax, f, window)
        axes[2 * k].set_title(
            f"{label(r)}: {topology_text(j['topology'])}\n"
            f"H {100 * j['hausdorff']:.2f} % (RBF {100 * r['rbf']['hausdorff']:.2f} %)",
            fontsize=8,
        )
        axes[2 * k + 1].set_title("zoom: 10 % of diag wide", fontsize=8)
    handles = [
        Line2D([], [], color="0.6", marker=".", ls="", label="data points (x: outliers)"),
        Line2D([], [], color="k", lw=0.5, label="true outline"),
        Line2D([], [], color="m", lw=2.5, alpha=0.6, label="true ring not matched"),
        Line2D([], [], color="tab:blue", label="jurs zero set"),
        Line2D([], [], color="tab:red", label="jurs: component along no ring"),
        Line2D([], [], color="tab:orange", ls="--", label="RBF zero set"),
        Line2D([], [], color="tab:green", marker="o", mfc="none", ls="", label="zoom centre"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=7.5, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 0.99))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)
    return (
        f"Figure: {len(shown)} runs, worst first (ranked by topology failure, then Hausdorff "
        "distance over its target), one per case: the worst run of each variant, then the "
        "worst of further cases. Each: the whole outline, and beside it a window 10 % of "
        "diag wide around the green circle, placed on the shortest true ring not matched one "
        "to one (for a split ring: on the shortest component following it; otherwise at the "
        "ring's point farthest from the jurs zero set) or, where all rings are matched, "
        "where the Hausdorff distance of the jurs components along true rings is attained. "
        "Grey dots: data points (x: planted outliers); thin black: the true "
        "outline (underlaid in magenta: a ring not matched); blue: the jurs zero set (red: a "
        "component along no true ring); dashed orange: the RBF zero set. Titles: topology of "
        "the jurs fit, its Hausdorff distance and the RBF's."
    )


# --------------------------------------------------------------------------- main


def jsonable(x) -> Any:
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x


def main(argv=None):
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"cases {', '.join(QUICK_CASES)}, variants {', '.join(QUICK_VARIANTS)}",
    )
    parser.add_argument("--cases", help=f"comma-separated subset of {', '.join(cases.CASES)}")
    parser.add_argument("--variants", help=f"comma-separated subset of {', '.join(VARIANTS)}")
    parser.add_argument(
        "--markdown-only",
        action="store_true",
        help="re-render the results page of --fit from its JSON",
    )
    parser.add_argument(
        "--fit",
        choices=tuple(FITS),
        default="default",
        help="jurs.fit's defaults (the basis chosen; default), jurs.fit on the uniform grid "
        "or jurs.fit_adaptive",
    )
    args = parser.parse_args(argv)
    name_of_results = RESULTS_NAME[args.fit]
    if args.markdown_only:
        print(rerender_beside(os.path.join(RESULTS, f"{name_of_results}.json"), markdown))
        return
    names = args.cases.split(",") if args.cases else QUICK_CASES if args.quick else cases.CASES
    variants = (
        args.variants.split(",") if args.variants else QUICK_VARIANTS if args.quick else VARIANTS
    )
    for n in names:
        cases.build(n)  # unknown names fail here, before any fit
    bad = set(variants) - set(VARIANTS)
    if bad:
        parser.error(f"unknown variants {sorted(bad)}; known: {', '.join(VARIANTS)}")
    start = time.perf_counter()
    meta = {
        "date": time.strftime("%Y-%m-%d"),
        "quick": bool(args.quick or args.cases or args.variants),
        "machine": machine(),
        "python": platform.python_version(),
        "load_average": os.getloadavg()[0],
        "command": " ".join(
            ["python -m benchmarks.realdata", *(sys.argv[1:] if argv is None else argv)]
        ),
        "cases": list(names),
        "variants": list(variants),
        "fit": args.fit,
        "case_info": {},
    }
    runs, figs = [], []
    for name in names:
        case = cases.build(name)
        meta["case_info"][name] = {
            "rings": len(case.components),
            "length_px": case.length_px,
            "m": case.m,
            "pixel": case.pixel,
            "diag": case.diag,
            "source": case.source,
            "what": cases.CASES[name][1],
        }
        for variant in variants:
            t0 = time.perf_counter()
            try:
                out, fig = run_one(name, variant, args.fit)
            except Exception as exc:  # keep the other runs of a long benchmark
                out = {"case": name, "variant": variant, "m": case.m}
                out["error"] = f"{type(exc).__name__}: {exc}"
                fig = None
            out["run_s"] = time.perf_counter() - t0
            runs.append(out)
            figs.append(fig)
            if "error" in out:
                print(f"{name:12s} {variant:8s} ERROR {out['error']}", flush=True)
                continue
            j, b = out["jurs"], out["rbf"]
            basis = f"finest={j['finest']}" if "finest" in j else f"grid={out['settings']['grid']}"
            print(
                f"{name:12s} {variant:8s} m={out['m']} "
                f"{basis} "
                f"s={out['settings']['smoothing']:.2g} {j['status']} | jurs "
                f"{topology_text(j['topology'])} C={100 * j['chamfer']:.3f}% "
                f"H={100 * j['hausdorff']:.2f}% warm={1e3 * j['warm_s']:.0f}ms | RBF "
                f"{topology_text(b['topology'])} C={100 * b['chamfer']:.3f}% "
                f"H={100 * b['hausdorff']:.2f}% fit={b['fit_s']:.1f}s | {out['run_s']:.0f}s",
                flush=True,
            )
    meta["figure"] = "worst.png" if args.fit == "uniform" else f"worst_{args.fit}.png"
    meta["caption"] = figure(runs, figs, os.path.join(FIGURE_DIR, meta["figure"]))
    meta["total_s"] = time.perf_counter() - start
    meta["load_average_end"] = os.getloadavg()[0]
    payload = jsonable(
        {
            "meta": meta,
            "config": {
                "noise": NOISE,
                "normal_noise": NORMAL_NOISE,
                "uneven": UNEVEN,
                "outliers": [OUTLIERS, OUTLIER_PAD, OUTLIER_MIN_DIST],
                "rbf_max_points": RBF_MAX_POINTS,
                "match_tol": MATCH_TOL,
                "reference_divisor": REFERENCE_DIVISOR,
                "resolution_rule": [NODES_PER_PIXEL, RESOLUTION_MIN, RESOLUTION_MAX],
                "m_rule": [cases.POINTS_PER_PIXEL, cases.M_MIN, cases.M_MAX],
            },
            "runs": runs,
        }
    )
    text = markdown(payload)
    write_results(name_of_results, payload, text)
    print(text)


if __name__ == "__main__":
    main()
