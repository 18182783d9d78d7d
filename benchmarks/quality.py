"""Quality of ``jurs.fit`` with its defaults against a thin-plate RBF, on the project's shapes.

One command measures everything, prints the tables and writes the dated results
``benchmarks/results/quality.{json,md}`` and the
figure ``benchmarks/results/quality/overview.png`` (``--quick``: a few cases in a few minutes,
written to the same files and marked as a quick subset):

* **Cases.** Closed outlines of [`jurs.shapes`][] (analytic curves, glyphs of DejaVu Sans,
  silhouettes traced from scikit-image images), uniformly sampled, non-uniformly sampled
  (``nonuniform=0.6``) or with a gap (``gap=0.08``); each at several noise levels.
* **jurs.** ``jurs.fit(points, normals)`` with nothing else: grid, offset, eps, lambda and
  solver all automatic (``sol.settings``). Zero set measured with
  ``jurs.levelset.analyze`` against dense samples of the clean outline.
* **Baseline.** ``_baselines.rbf_fit``: SciPy's thin-plate ``RBFInterpolator`` on the same
  offset samples (jurs's chosen d and eps), without smoothing and, on noisy cases, with a
  ladder of smoothing values; measured with the same level-set analysis on the same box
  and grid (see ``_baselines.rbf_grid_values`` for how the grid is evaluated).
* **Ratios.** jurs's Chamfer over the reference RBF's (the unsmoothed one on clean cases,
  the best smoothed one on noisy cases) and the RBF's fit time over jurs's, per run.

    python -m benchmarks.quality [--quick] [--markdown-only]

``--markdown-only`` rewrites the markdown from the JSON of the last run (no measurement).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import zlib

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import jurs  # noqa: E402
import jurs.datasets  # noqa: E402
import jurs.levelset  # noqa: E402
import jurs.shapes  # noqa: E402

from ._baselines import evaluate_rbf_grid, rbf_fit, rbf_grid_values  # noqa: E402
from ._common import RESULTS, machine, write_results  # noqa: E402
from ._quality_cases import (  # noqa: E402  (the cases, shared with smoothing.py)
    CASES,
    M_MAX,
    M_MIN,
    M_PER_LENGTH,
    REFERENCE_DIVISOR,
    RESOLUTION,
    choose_m,
    clean_outline,
)

# --------------------------------------------------------------------------- configuration

#: Noise levels, as fractions of the clean outline's bounding-box diagonal.
NOISE_LEVELS = (0.0, 0.002, 0.005, 0.01)
QUICK_CASES = ("example1", "annulus", "glyph_a")
QUICK_NOISE_LEVELS = (0.0, 0.005)

#: Warm fits timed after the first call (median reported).
WARM_REPEATS = 3
#: RBF smoothing ladder (noisy cases), searched from the top down; see ``smoothing_search``.
SMOOTHING_LADDER = (1e-3, 1e-2, 1e-1, 1.0, 10.0)
#: Tried above the ladder while its top value is still the best.
SMOOTHING_EXTENSION = (100.0, 1000.0)
#: Runs whose RBF grid evaluation is checked against a full ``rbf_report`` (case, noise).
CHECKS_FULL = (("glyph_a", 0.01),)
CHECKS_QUICK = (("example1", 0.005),)

FIGURE_DIR = os.path.join(RESULTS, "quality")


# --------------------------------------------------------------------------- data


def noise_seed(case: str, level: float) -> int:
    return zlib.crc32(f"{case}/{level}".encode())


# --------------------------------------------------------------------------- RBF


def rbf_measure(points, normals, *, offset, eps, smoothing, box, reference):
    rbf, fit_s = rbf_fit(points, normals, offset=offset, eps=eps, smoothing=smoothing)
    t0 = time.perf_counter()
    xs, ys, _ = jurs.levelset.sampling_grid(*box, RESOLUTION)
    values, count = rbf_grid_values(rbf, xs, ys)
    report = jurs.levelset.analyze_grid(xs, ys, values, points, offset=offset, reference=reference)
    return (
        rbf,
        report,
        {
            "smoothing": smoothing,
            "fit_s": fit_s,
            "measure_s": time.perf_counter() - t0,
            "evaluations": count,
            "grid_nodes": len(xs) * len(ys),
        },
        values,
    )


# --------------------------------------------------------------------------- one run


def summarise(report, diag, true_components):
    return {
        "chamfer": report.chamfer / diag,
        "hausdorff": report.hausdorff / diag,
        "num_components": report.num_components,
        "true_components": true_components,
        "num_supplementary": report.num_supplementary,
        "num_tiny_loops": report.num_tiny_loops,
        "supplementary_length": report.supplementary_length / diag,
        "total_length": report.total_length / diag,
        "zero_area_fraction": report.zero_area_fraction,
    }


def lines_of(report):
    return [(c.polyline, bool(c.supplementary)) for c in report.components]


def smoothing_search(measure):
    """Best-by-Chamfer RBF smoothing: the ladder is tried from its top value down while the
    Chamfer distance improves (stopping at the first value worse than the best so far);
    while the top value is the best, ``SMOOTHING_EXTENSION`` is tried above it the same way.
    Returns the results of every value tried."""
    tried = {}

    def go(order, best=None):
        for s in order:
            tried[s] = measure(s)
            if best is not None and tried[s][0] > tried[best][0]:
                break
            best = s
        return best

    ladder = sorted(SMOOTHING_LADDER, reverse=True)
    best = go(ladder)
    if best == ladder[0]:
        go(sorted(SMOOTHING_EXTENSION), best)
    return tried


def run_case(case, level, m, ref, diag, true_components, check):
    shape, kwargs, _ = CASES[case]
    points, normals = jurs.shapes.get(shape, m, **kwargs)
    if level > 0:
        points, normals = jurs.datasets.add_noise(
            points, normals, sigma=level * diag, seed=noise_seed(case, level)
        )
    out = {
        "case": case,
        "shape": shape,
        "sampling": kwargs,
        "m": m,
        "noise": level,
        "sigma": level * diag,
        "normal_sigma": level * diag,
        "seed": noise_seed(case, level) if level > 0 else None,
        "diag": diag,
    }

    # jurs, defaults only: first call (compiles: caches cleared) and warm median
    jax.clear_caches()
    t0 = time.perf_counter()
    sol = jurs.fit(points, normals)
    jax.block_until_ready(sol.spline.control)
    first = time.perf_counter() - t0
    warm = []
    for _ in range(WARM_REPEATS):
        t0 = time.perf_counter()
        sol = jurs.fit(points, normals)
        jax.block_until_ready(sol.spline.control)
        warm.append(time.perf_counter() - t0)
    st = sol.settings
    rep = jurs.levelset.analyze(
        sol.spline, points, offset=st.offset, reference=ref, resolution=RESOLUTION
    )
    box = (
        st.domain
        if st.domain is not None
        else (np.asarray(sol.spline.lower), np.asarray(sol.spline.upper))
    )
    out["settings"] = st.as_dict()
    out["jurs"] = {
        **summarise(rep, diag, true_components),
        "first_s": first,
        "warm_s": float(np.median(warm)),
        "warm_all_s": warm,
        "result": str(sol.message),
        "basis": "adaptive" if isinstance(sol.spline, jurs.AdaptiveSpline) else "uniform",
        "finest": list(sol.stats.get("finest") or ()),
    }
    figure = {"points": points, "jurs": lines_of(rep)}

    # RBF without smoothing (the time ratio's reference, the clean cases' Chamfer reference)
    common = dict(offset=st.offset, eps=st.eps, box=box, reference=ref)
    rbf, rrep, info, values = rbf_measure(points, normals, smoothing=0.0, **common)
    out["rbf"] = {**summarise(rrep, diag, true_components), **info}
    if check:  # what _baselines.rbf_report does: the full grid, then analyze_grid
        t0 = time.perf_counter()
        xs, ys, _ = jurs.levelset.sampling_grid(*box, RESOLUTION)
        full_values = evaluate_rbf_grid(rbf, xs, ys)
        full = jurs.levelset.analyze_grid(
            xs, ys, full_values, points, offset=st.offset, reference=ref
        )
        a, b = summarise(full, diag, true_components), out["rbf"]
        out["grid_check"] = {
            "rbf_report_s": time.perf_counter() - t0,
            "adaptive_s": info["measure_s"],
            "same_signs": bool(np.array_equal(np.sign(values), np.sign(full_values))),
            "same_counts": all(
                a[k] == b[k] for k in ("num_components", "num_supplementary", "num_tiny_loops")
            ),
            "chamfer_rel_diff": abs(a["chamfer"] - b["chamfer"]) / a["chamfer"],
            "hausdorff_rel_diff": abs(a["hausdorff"] - b["hausdorff"]) / a["hausdorff"],
            "full": a,
        }
    del rbf
    best = {"smoothing": 0.0, "chamfer": out["rbf"]["chamfer"]}
    figure["rbf_best"] = lines_of(rrep)

    # smoothed RBFs (noisy cases only)
    out["rbf_smoothed"] = []
    if level > 0:
        reports = {}

        def measure(s):
            _, r, i, _ = rbf_measure(points, normals, smoothing=s, **common)
            reports[s] = r
            row = {**summarise(r, diag, true_components), **i}
            out["rbf_smoothed"].append(row)
            return row["chamfer"], row

        tried = smoothing_search(measure)
        s_best = min(tried, key=lambda s: tried[s][0])
        out["rbf_smoothed"].sort(key=lambda r: r["smoothing"])
        if tried[s_best][0] < best["chamfer"]:
            best = {"smoothing": s_best, "chamfer": tried[s_best][0]}
            figure["rbf_best"] = lines_of(reports[s_best])
    out["rbf_best"] = best

    # ratios against the reference RBF of the same run
    j = out["jurs"]
    ref_chamfer = out["rbf"]["chamfer"] if level == 0 else best["chamfer"]
    out["chamfer_reference"] = ref_chamfer
    out["chamfer_ratio"] = j["chamfer"] / ref_chamfer
    out["time_ratio"] = out["rbf"]["fit_s"] / j["warm_s"]
    return out, figure


# --------------------------------------------------------------------------- report


def pct(x):
    return f"{100 * x:g} %"


def fmt_s(s):
    return "0" if s == 0 else f"{s:g}"


def label(r):
    return f"{r['case']} @ {pct(r['noise'])}"


def markdown(runs, meta):
    ok = [r for r in runs if "error" not in r]
    n = len(runs)
    lines = [
        "# Quality of `jurs.fit` defaults against a thin-plate RBF"
        + (" (quick subset)" if meta["quick"] else ""),
        "",
        f"Date: {meta.get('date', 'not recorded')}. Machine: {meta['machine']}. Float64. "
        f"Command: `{meta['command']}`; "
        f"{n} runs ({len(meta['cases'])} base cases x noise levels "
        f"{', '.join(pct(x) for x in meta['noise_levels'])}) in "
        f"{meta['total_s'] / 60:.1f} min." + (f" {meta['note']}" if meta.get("note") else ""),
        "",
    ]
    ratios = np.array([r["chamfer_ratio"] for r in ok])
    times = np.array([r["time_ratio"] for r in ok])
    first = np.array([r["jurs"]["first_s"] for r in ok])
    warm = np.array([r["jurs"]["warm_s"] for r in ok])
    lines += ["## How to read", ""]
    if len(ok):
        lines.append(
            f"Each run samples a clean outline of `jurs.shapes` with m points (m = "
            f"clip(round({M_PER_LENGTH} L / diag, -100), {M_MIN}, {M_MAX}), L the outline's "
            f"length, diag its bounding-box diagonal: here m = {min(r['m'] for r in ok)} to "
            f"{max(r['m'] for r in ok)}), adds noise, and fits `jurs.fit(points, normals)` with "
            "no other argument. Distances are relative to diag and printed in units of 1e-3 "
            "(so 1.0 means 0.1 % of the diagonal); they are measured from the zero set to "
            f"dense samples of the clean outline (spacing diag / {REFERENCE_DIVISOR}), on a "
            f"{RESOLUTION}-node grid over the fit's box, the same grid for the RBF. A "
            "*supplementary* component has more than half its length farther than 2 d from "
            "the data; a *tiny loop* is a closed component shorter than 4 grid cells. The "
            "RBF solves the same offset samples and targets (jurs's own d and eps) exactly "
            "(s = 0) or with SciPy's `smoothing` s; on noisy cases the best s is picked by "
            "Chamfer distance to the clean outline, which no user could do (an oracle), so the "
            "Chamfer ratio on noisy cases compares with the RBF at its best. "
            f"Over all runs the jurs/RBF Chamfer ratio (below 1: jurs closer to the true "
            f"curve) has median {np.median(ratios):.2f} (range {ratios.min():.2f} to "
            f"{ratios.max():.2f}). jurs's warm fit takes {np.median(warm) * 1e3:.0f} ms "
            f"(median; {warm.min() * 1e3:.0f} to {warm.max() * 1e3:.0f} ms) and its first "
            f"call {np.median(first):.1f} s (median, mostly compilation; caches are cleared "
            f"before every run); the unsmoothed RBF fit is {np.median(times):.1f}x (median; "
            f"{times.min():.1f}x to {times.max():.1f}x) the jurs warm time. The RBF's dense "
            "solve grows as m^3, jurs's time with the grid, so that ratio depends on m. "
            "Timings are medians of a few calls on a 2-core machine"
            + (
                f" (load average {meta['load_average']:.1f} when the run began)"
                if "load_average" in meta
                else ""
            )
            + ": expect tens of percent of noise. "
            f"The zero set has the true number of components in "
            f"{sum(r['jurs']['num_components'] == r['jurs']['true_components'] for r in ok)} "
            f"of {len(ok)} jurs runs and in "
            f"{sum(r['rbf']['num_components'] == r['rbf']['true_components'] for r in ok)} of "
            f"{len(ok)} unsmoothed-RBF runs. `jurs.fit` took the adaptive basis in "
            f"{sum(basis_of(r).startswith('adaptive') for r in ok)} of {len(ok)} runs "
            "(where the automatic uniform grid would be capped; column 'basis')."
        )
        whole = [
            r
            for r in ok
            if r["jurs"]["num_supplementary"]
            and r["jurs"]["supplementary_length"] >= 0.5 * r["jurs"]["total_length"]
            and r["jurs"]["num_components"] == r["jurs"]["true_components"]
        ]
        if whole:
            lines[-1] += (
                " Supplementary is a distance to the *data* (more than half of a component's "
                "length beyond 2 d): a zero set that bridges a gap in the sampling can still "
                "reach that. In "
                + ", ".join(label(r) for r in whole)
                + " the zero set has the true number of components and the supplementary "
                "one(s) make up "
                + ", ".join(
                    f"{100 * r['jurs']['supplementary_length'] / r['jurs']['total_length']:.0f} %"
                    for r in whole
                )
                + " of its length, i.e. the curve itself, bridging the gap, is flagged (see "
                "the figure)."
            )
    lines += ["", "## What ran", ""]
    lines.append(
        "Noise: `jurs.datasets.add_noise(points, normals, sigma=level * diag, seed=crc32("
        "'case/level'))`, i.e. Gaussian noise of standard deviation level x diag on each point "
        "coordinate and, with add_noise's default `normal_sigma = sigma`, the same number "
        "(level x diag, in absolute units) on each component of the unit normals, which are "
        "then re-normalised. With diag about "
        f"{min(r['diag'] for r in runs):.1f} to {max(r['diag'] for r in runs):.1f} (longest "
        f"side 8), the normals' per-component sigma is "
        + ", ".join(
            f"{min(r['diag'] for r in runs) * x:.3g}-{max(r['diag'] for r in runs) * x:.3g}"
            f" at {pct(x)}"
            for x in meta["noise_levels"]
            if x > 0
        )
        + "."
    )
    lines.append("")
    lines.append(
        f"jurs: `jurs.fit(points, normals)`; first call after `jax.clear_caches()`, then the "
        f"median of {WARM_REPEATS} warm calls (each includes the automatic settings). RBF: "
        "`_baselines.rbf_fit(points, normals, offset=d, eps=eps, smoothing=s)` (time: that one "
        "fit), s = 0 on every case; on noisy cases also the smoothing ladder "
        f"{', '.join(fmt_s(s) for s in SMOOTHING_LADDER)} searched from the top down while "
        "the Chamfer distance improves (stopping at the first value worse than the best so far; "
        f"while the top is the best, {', '.join(fmt_s(s) for s in SMOOTHING_EXTENSION)} above it); "
        "the values tried are in the JSON. 'best RBF' is the lowest Chamfer among s = 0 and the "
        "values tried."
    )
    lines.append("")
    checks = [r for r in ok if "grid_check" in r]
    evals = [x["evaluations"] / x["grid_nodes"] for r in ok for x in [r["rbf"]] + r["rbf_smoothed"]]
    evals = [float(np.median(evals))] if evals else []
    lines.append(
        "RBF zero sets are measured with `jurs.levelset.analyze_grid` (what "
        "`_baselines.rbf_report` calls) on the same grid, but the grid values come from an "
        "adaptive evaluation (`_baselines.rbf_grid_values`: exact wherever the zero set can "
        "pass, bilinear far from it), because the full grid costs half a minute or more per "
        "RBF. Checked against the full grid, evaluated and analysed as `rbf_report` does "
        "(`evaluate_rbf_grid`, then `analyze_grid`), on "
        + (
            "; ".join(
                f"{label(r)}: same sign at every grid node {r['grid_check']['same_signs']}, "
                f"same component counts {r['grid_check']['same_counts']}, "
                f"Chamfer rel. diff {r['grid_check']['chamfer_rel_diff']:.1e}, Hausdorff "
                f"rel. diff {r['grid_check']['hausdorff_rel_diff']:.1e} "
                f"({r['grid_check']['rbf_report_s']:.0f} s full vs "
                f"{r['grid_check']['adaptive_s']:.0f} s adaptive)"
                for r in checks
            )
            or "no run"
        )
        + ". Over all RBF fits the adaptive evaluation computed the "
        + (
            f"RBF at {100 * evals[0]:.0f} % (median) as many points as the full grid has nodes."
            if evals
            else ""
        )
    )
    lines += ["", "Cases:", ""]
    for key in meta["cases"]:
        shape, kwargs, text = CASES[key]
        extra = ", ".join(f"{k}={v}" for k, v in kwargs.items())
        lines.append(
            f"* `{key}`: {text}; `jurs.shapes.get({shape!r}, m"
            + (f", {extra}" if extra else "")
            + ")`, "
            f"{meta['true_components'][key]} true component(s), "
            f"m = {meta['m'][key]}."
        )
    lines += ["", "![overview](quality/" + meta["figure"] + ")", "", meta["caption"], ""]
    lines += [
        "## Per case",
        "",
        "Distances in 1e-3 of diag. d: jurs's offset, in 1e-3 of diag. comps: zero-set "
        "components / true ones. jurs time: warm median (first call). C ratio: jurs "
        "Chamfer / the reference RBF's Chamfer (s = 0 clean, best noisy). T ratio: RBF (s = 0) "
        "fit time / jurs warm time.",
        "",
        "| case | m | noise | basis | d | smoothing | jurs Chamfer | jurs Hausdorff | "
        "supp | tiny | comps | jurs time | RBF Chamfer | RBF supp | RBF tiny | RBF time | "
        "best RBF Chamfer (s) | C ratio | T ratio |",
        "|" + "---|" * 19,
    ]
    for r in runs:
        if "error" in r:
            lines.append(
                f"| {r['case']} | {r['m']} | {pct(r['noise'])} | error: {r['error']} |" + " |" * 15
            )
            continue
        st, j, b = r["settings"], r["jurs"], r["rbf"]
        lines.append(
            f"| {r['case']} | {r['m']} | {pct(r['noise'])} | {basis_of(r)} | "
            f"{st['offset'] / r['diag'] * 1e3:.2f} | {st['smoothing']:.2g} | "
            f"{j['chamfer'] * 1e3:.3f} | {j['hausdorff'] * 1e3:.2f} | {j['num_supplementary']} | "
            f"{j['num_tiny_loops']} | {j['num_components']}/{j['true_components']} | "
            f"{j['warm_s'] * 1e3:.0f} ms ({j['first_s']:.1f} s) | {b['chamfer'] * 1e3:.3f} | "
            f"{b['num_supplementary']} | {b['num_tiny_loops']} | {b['fit_s'] * 1e3:.0f} ms | "
            + (
                f"{r['rbf_best']['chamfer'] * 1e3:.3f} ({fmt_s(r['rbf_best']['smoothing'])})"
                if r["noise"] > 0
                else "-"
            )
            + f" | {r['chamfer_ratio']:.2f} | {r['time_ratio']:.1f} |"
        )
    smoothed = [r for r in ok if r["rbf_smoothed"]]
    if smoothed:
        lines += [
            "",
            "## Smoothed RBFs (noisy cases)",
            "",
            "Chamfer (1e-3 of diag) / supplementary / tiny loops for each smoothing s tried.",
            "",
            "| case | noise | s: Chamfer / supp / tiny |",
            "|---|---|---|",
        ]
        for r in smoothed:
            lines.append(
                f"| {r['case']} | {pct(r['noise'])} | "
                + "; ".join(
                    f"{fmt_s(x['smoothing'])}: {x['chamfer'] * 1e3:.3f} / "
                    f"{x['num_supplementary']} / "
                    f"{x['num_tiny_loops']}"
                    for x in r["rbf_smoothed"]
                )
                + " |"
            )
    return "\n".join(lines) + "\n"


def figure(figs, runs, path):
    """Small multiples: for every base case, its lowest and highest noise level side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {(r["case"], r["noise"]): (r, f) for r, f in zip(runs, figs) if f is not None}
    cases = list(dict.fromkeys(r["case"] for r in runs))
    levels = sorted({r["noise"] for r in runs})
    shown = [levels[0], levels[-1]] if len(levels) > 1 else levels
    panels = [(c, lv) for c in cases for lv in shown if (c, lv) in by]
    if not panels:
        return shown
    ncols = 3 * len(shown) if len(panels) > 6 else 2 * len(shown)
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(2.4 * ncols, 2.5 * nrows + 0.6), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, key in zip(axes.ravel(), panels):
        r, f = by[key]
        ax.scatter(*f["points"].T, s=0.8, c="0.55", linewidths=0, zorder=1)
        for poly, _ in f["rbf_best"]:
            ax.plot(*poly.T, color="tab:orange", lw=1.0, ls="--", zorder=2)
        for poly, supp in f["jurs"]:
            ax.plot(*poly.T, color="tab:red" if supp else "tab:blue", lw=0.9, zorder=3)
        p = f["points"]
        pad = 0.06 * np.ptp(p, axis=0).max()
        ax.set_xlim(p[:, 0].min() - pad, p[:, 0].max() + pad)
        ax.set_ylim(p[:, 1].min() - pad, p[:, 1].max() + pad)
        ax.set_aspect("equal")
        b = r["rbf_best"]
        ax.set_title(
            f"{r['case']} @ {pct(r['noise'])}\njurs {r['jurs']['chamfer'] * 1e3:.2f}, "
            f"RBF(s={fmt_s(b['smoothing'])}) {b['chamfer'] * 1e3:.2f}",
            fontsize=7.5,
        )
    handles = [
        plt.Line2D([], [], color="0.55", marker=".", ls="", label="data points"),
        plt.Line2D([], [], color="tab:blue", label="jurs defaults: zero set"),
        plt.Line2D([], [], color="tab:red", label="jurs: supplementary component"),
        plt.Line2D(
            [], [], color="tab:orange", ls="--", label="best RBF (Chamfer oracle): zero set"
        ),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return shown


# --------------------------------------------------------------------------- main


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x


def basis_of(run: dict) -> str:
    """The basis ``jurs.fit`` took, in words: ``grid NxM``, or ``adaptive`` with its
    finest level. Runs recorded before the basis was are the uniform grid's."""
    st, j = run["settings"], run["jurs"]
    if j.get("basis", "uniform") == "uniform":
        return "grid " + "x".join(map(str, st["grid"]))
    return "adaptive " + "x".join(map(str, j["finest"]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"cases {', '.join(QUICK_CASES)} at noise "
        f"{', '.join(map(str, QUICK_NOISE_LEVELS))} only",
    )
    parser.add_argument(
        "--note", default="", help="a sentence for the results' header (what the run measured)"
    )
    parser.add_argument(
        "--markdown-only",
        action="store_true",
        help="rewrite quality.md from the existing quality.json (no measurement)",
    )
    args = parser.parse_args(argv)
    if args.markdown_only:
        import json

        with open(os.path.join(RESULTS, "quality.json")) as fh:
            payload = json.load(fh)
        # An older run's per-run target verdicts and their threshold: not reported.
        payload["config"].pop("time_fraction", None)
        for r in payload["runs"]:
            r.pop("targets", None)
        if args.note:
            payload["meta"]["note"] = args.note
        text = markdown(payload["runs"], payload["meta"])
        write_results("quality", payload, text)
        print(text)
        return
    cases = QUICK_CASES if args.quick else tuple(CASES)
    levels = QUICK_NOISE_LEVELS if args.quick else NOISE_LEVELS
    checks = CHECKS_QUICK if args.quick else CHECKS_FULL
    start = time.perf_counter()
    runs, figs = [], []
    meta = {
        "date": time.strftime("%Y-%m-%d"),
        "quick": args.quick,
        "machine": machine(),
        "python": platform.python_version(),
        "load_average": os.getloadavg()[0],
        "command": "python -m benchmarks.quality" + (" --quick" if args.quick else ""),
        "note": args.note,
        "cases": list(cases),
        "noise_levels": list(levels),
        "m": {},
        "true_components": {},
    }
    for case in cases:
        shape = CASES[case][0]
        comps, ref, diag, length = clean_outline(shape)
        m = choose_m(length, diag)
        meta["m"][case], meta["true_components"][case] = m, len(comps)
        for level in levels:
            t0 = time.perf_counter()
            try:
                out, fig = run_case(
                    case, level, m, ref, diag, len(comps), check=(case, level) in checks
                )
            except Exception as exc:  # keep the other runs of a long benchmark
                out = {
                    "case": case,
                    "m": m,
                    "noise": level,
                    "diag": diag,
                    "error": f"{type(exc).__name__}: {exc}",
                }
                fig = None
            out["run_s"] = time.perf_counter() - t0
            runs.append(out)
            figs.append(fig)
            if "error" in out:
                print(f"{case:18s} {pct(level):>7s}  ERROR {out['error']}", flush=True)
            else:
                j = out["jurs"]
                print(
                    f"{case:18s} {pct(level):>7s} m={m} grid={out['settings']['grid']} "
                    f"jurs C={j['chamfer'] * 1e3:.3f} supp={j['num_supplementary']} "
                    f"tiny={j['num_tiny_loops']} comps={j['num_components']}/{len(comps)} "
                    f"warm={j['warm_s'] * 1e3:.0f}ms first={j['first_s']:.1f}s | RBF C="
                    f"{out['rbf']['chamfer'] * 1e3:.3f} t={out['rbf']['fit_s']:.2f}s best="
                    f"{out['rbf_best']['chamfer'] * 1e3:.3f}(s={out['rbf_best']['smoothing']:g})"
                    f" | {out['run_s']:.0f}s",
                    flush=True,
                )
    name, fig_name = "quality", "overview.png"
    shown = figure(figs, runs, os.path.join(FIGURE_DIR, fig_name))
    meta["figure"] = fig_name
    meta["caption"] = (
        "Figure: every base case at noise "
        + " and ".join(pct(x) for x in shown)
        + " (panel title: case @ noise, then the Chamfer distances in 1e-3 of diag of jurs "
        "and of the best RBF with its smoothing s). Grey dots: the data points; blue: the "
        "zero set of `jurs.fit` with defaults (red where a component is supplementary); "
        "dashed orange: the zero set of the best RBF (s = 0 on clean data, the "
        "Chamfer-best s on noisy data). At this scale the two zero sets mostly lie on top of "
        "each other; the distances in the titles and the tables say how far apart they are."
    )
    meta["total_s"] = time.perf_counter() - start
    payload = {
        "meta": meta,
        "config": {
            "noise_levels": list(levels),
            "smoothing_ladder": list(SMOOTHING_LADDER),
            "smoothing_extension": list(SMOOTHING_EXTENSION),
            "warm_repeats": WARM_REPEATS,
            "resolution": RESOLUTION,
            "reference_divisor": REFERENCE_DIVISOR,
            "m_rule": [M_PER_LENGTH, M_MIN, M_MAX],
        },
        "runs": runs,
    }
    text = markdown(runs, meta)
    write_results(name, jsonable(payload), text)
    print(text)


if __name__ == "__main__":
    main()
