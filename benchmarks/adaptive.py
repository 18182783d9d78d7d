"""The adaptive (THB) fit beside the uniform grid on real 2D outlines, and its scaling.

Three tables:

* **Accuracy.** For each case of ``benchmarks/_realdata_cases.py`` asked for (clean
  variant, exact normals, as ``benchmarks/realdata.py`` samples it): Chamfer and
  Hausdorff distances (fractions of the diagonal) against the dense clean outline, the
  ring match, and the warm fit time of ``jurs.fit(basis="uniform")`` (the uniform grid,
  defaults otherwise; ``basis="auto"`` takes the adaptive basis where that grid is
  capped), ``jurs.fit_adaptive`` (defaults) and SciPy's thin-plate RBF on the same offset samples.
* **Scaling (2D).** ``jurs.fit_adaptive(finest=...)`` on one case from 256 to 4096 cells
  along the longer side: active functions, CG steps, first and warm time, peak memory; the
  ratios between successive rows show whether the cost follows the boundary (about 2x a
  doubling) or the box (4x).
* **Scaling (3D).** The same on a surface: the bunny (pymeshlab's sample mesh; the largest
  analytic shape of ``benchmarks/_surface_cases.py``, the double torus, where the mesh is
  missing) at 2e4 area-uniform samples with exact normals, from 64 cells up (about 4x a
  doubling where the cost follows the boundary, 8x where it follows the box).

Each scaling row runs in a fresh spawned process, so that its peak resident set is its own
(its first call compiles); a ladder stops at the first row that passes ``--timeout`` seconds
or ``--max-gb`` of resident memory, recorded with the bound it passed, and lists the rows
above it as not run.

Run ``python -m benchmarks.adaptive`` (``--cases camera text --finest 256 512
--surface-finest 64 128``); writes ``benchmarks/results/adaptive.{md,json}``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jurs  # noqa: E402
import jurs.levelset  # noqa: E402

from . import _realdata_cases as cases  # noqa: E402
from . import realdata  # noqa: E402
from ._baselines import rbf_fit, rbf_grid_values  # noqa: E402
from ._common import (  # noqa: E402
    RESULTS,
    current_rss_bytes,
    in_child,
    machine,
    peak_rss_bytes,
    time_repeated,
    write_results,
)
from ._surface_cases import SEEDS, make_truth  # noqa: E402

DEFAULT_CASES = ("camera", "coffee", "text", "serif")
DEFAULT_FINEST = (256, 512, 1024, 2048, 4096)
SCALING_CASE = "camera"
#: The surface of the 3D ladder, its fallback (no pymeshlab) and its number of samples.
SURFACE_CASES = ("bunny", "genus2")
SURFACE_POINTS = 20_000
DEFAULT_SURFACE_FINEST = (64, 128, 256, 512, 1024)
#: Bounds of one scaling row (its whole child process): wall seconds, resident GB.
TIMEOUT_S = 360.0
MAX_GB = 12.0
#: The issue's targets: active functions and warm time per doubling of the finest level.
TARGETS = {2: 2.2, 3: 4.5}
GB = 1e9


def _measure(spline, points, offset, reference, rings, diag, res, box):
    report = jurs.levelset.analyze(
        spline, points, offset=offset, reference=reference, resolution=res, box=box
    )
    return realdata.measure(report, rings, diag, reference)[0]


def accuracy_row(name: str) -> dict:
    case = cases.build(name)
    reference = realdata.reference_samples(case)
    rings = [np.vstack([c, c[:1]]) for c in case.components]
    points, normals, _ = realdata.cloud(case, "clean", reference)
    diag, res = case.diag, realdata.resolution_of(case)
    row: dict = {"case": name, "m": case.m, "pixel": case.pixel / diag, "resolution": res}

    timing = time_repeated(
        lambda: jurs.fit(points, normals, basis="uniform", throw=False), budget_s=3.0, max_repeats=5
    )
    sol = timing.pop("output")
    box = tuple(np.asarray(v, float) for v in sol.settings.domain)
    row["uniform"] = {
        **_measure(sol.spline, points, sol.settings.offset, reference, rings, diag, res, box),
        **timing,
        "status": sol.status,
        "grid": list(sol.settings.grid),
    }
    settings = sol.settings
    timing = time_repeated(
        lambda: jurs.fit_adaptive(points, normals, settings=settings), budget_s=3.0, max_repeats=5
    )
    adaptive = timing.pop("output")
    row["adaptive"] = {
        **_measure(adaptive.spline, points, settings.offset, reference, rings, diag, res, box),
        **timing,
        "status": adaptive.status,
        "finest": list(adaptive.stats["finest"]),
        "active": int(sum(adaptive.stats["active"])),
        "cg_steps": adaptive.stats["num_steps"],
    }
    rbf, fit_s = rbf_fit(points, normals, offset=settings.offset, eps=settings.eps, smoothing=0.0)
    xs, ys, _ = jurs.levelset.sampling_grid(box[0], box[1], res)
    values, _ = rbf_grid_values(rbf, xs, ys)
    report = jurs.levelset.analyze_grid(
        xs, ys, values, points, offset=settings.offset, reference=reference
    )
    row["rbf"] = {**realdata.measure(report, rings, diag, reference)[0], "fit_s": fit_s}
    return row


def scaling_row(points, normals, finest: int) -> dict:
    """In a child: ``jurs.fit_adaptive(finest=finest)`` on a curve, timed (first call, then
    warm repeats)."""
    base = current_rss_bytes()
    settings = jurs.auto_settings(points, normals)
    timing = time_repeated(
        lambda: jurs.fit_adaptive(points, normals, finest=finest, settings=settings),
        budget_s=3.0,
        max_repeats=3,
    )
    sol = timing.pop("output")
    # The same fit without the verdicts' checks on the host (checks=False): the part of
    # the time that is the fit itself.
    unchecked = time_repeated(
        lambda: jurs.fit_adaptive(points, normals, finest=finest, settings=settings, checks=False),
        budget_s=3.0,
        max_repeats=3,
    )
    return {
        **_hierarchy(sol, finest),
        **timing,
        "unchecked_s": unchecked["warm_s"],
        "base_rss": base,
        "peak_rss": peak_rss_bytes(),
    }


def surface_row(points, normals, finest: int, timeout_s: float) -> dict:
    """In a child: ``jurs.fit_adaptive(finest=finest)`` on a surface, a first call and a
    warm one; the warm call is left out (``warm_s`` None) when the first took more of
    ``timeout_s`` than is left, so that the row still reports what it measured."""
    start = time.perf_counter()
    base = current_rss_bytes()
    settings = jurs.auto_settings(points, normals)

    def fit():
        sol = jurs.fit_adaptive(points, normals, finest=finest, settings=settings, throw=False)
        jax.block_until_ready(sol.spline.control)
        return sol

    times, cpu = [], []
    for _ in range(2):
        if times and time.perf_counter() - start + times[0] > timeout_s:
            break
        wall, used = time.perf_counter(), time.process_time()
        sol = fit()
        times.append(time.perf_counter() - wall)
        cpu.append(time.process_time() - used)
        print(f"  surface finest {finest}: call {len(times)} {times[-1]:.1f} s", flush=True)
    return {
        **_hierarchy(sol, finest),
        "first_s": times[0],
        "warm_s": times[1] if len(times) > 1 else None,
        "cpu_s": cpu[-1],
        "base_rss": base,
        "peak_rss": peak_rss_bytes(),
    }


def _hierarchy(sol, finest: int) -> dict:
    cells = [int(c) for c in sol.stats["finest"]]
    return {
        "finest": finest,
        "cells": cells,
        "levels": sol.stats["levels"],
        "active": int(sum(sol.stats["active"])),
        "uniform_functions": int(np.prod([c + 3 for c in cells])),
        "cg_steps": sol.stats["num_steps"],
        "status": sol.status,
    }


def ladder(row_fn, points, normals, finest, timeout_s, max_gb, *extra) -> list[dict]:
    """``row_fn(points, normals, f, *extra)`` for each ``f`` of ``finest``, each in a fresh
    child; after the first row that fails (a bound passed, an error), the rest are recorded
    as not run."""
    rows: list[dict] = []
    for f in finest:
        if rows and "error" in rows[-1]:
            rows.append({"finest": f, "skipped": f"not run: the {rows[-1]['finest']} row failed"})
            continue
        row = in_child(
            row_fn, points, normals, f, *extra, timeout_s=timeout_s, max_rss_bytes=max_gb * GB
        )
        if "error" in row:
            row = {"finest": f, **row}
        rows.append(row)
        print(f, {k: row.get(k) for k in ("active", "cg_steps", "warm_s", "peak_rss", "error")})
    return rows


def scaling_rows(name: str, finest, timeout_s: float, max_gb: float) -> list[dict]:
    case = cases.build(name)
    reference = realdata.reference_samples(case)
    points, normals, _ = realdata.cloud(case, "clean", reference)
    return ladder(scaling_row, points, normals, finest, timeout_s, max_gb)


def surface_cloud(m: int):
    """``(name, origin, points, normals)`` of the first of ``SURFACE_CASES`` available."""
    for name in SURFACE_CASES:
        truth = make_truth(name)
        if truth is not None:
            points, normals = truth.sample(m, SEEDS["cloud"])
            return name, truth.origin, np.asarray(points), np.asarray(normals)
    raise RuntimeError(f"none of {SURFACE_CASES} is available")


def _rings(fit: dict) -> str:
    topology = fit["topology"]
    mark = "" if topology["exact"] else "*"
    return f"{topology['matched']}/{topology['rings']}{mark}"


def markdown(payload: dict) -> str:
    load = payload.get("load_average", [float("nan")] * 2)
    lines = [
        f"# Adaptive (THB) fits beside the uniform grid ({payload['date']})",
        "",
        f"Machine: {payload['machine']}; float64. 1-minute load average "
        f"{load[0]:.1f} at the start, {load[1]:.1f} at the end. {payload['note']}",
        "",
        "## Accuracy on real outlines (clean, exact normals)",
        "",
        "Uniform: `jurs.fit(points, normals, basis='uniform')` (the uniform grid, "
        "defaults otherwise); adaptive: `jurs.fit_adaptive(points, normals)` with the same "
        "settings. Distances are fractions of the diagonal against the dense clean outline; rings: "
        "matched / expected (`*` where the match is not exact); times are warm medians (s), "
        "'adaptive first s' the first call on the case's cloud, new to the process (its "
        "compilations included).",
        "",
        "| case | m | uniform grid | uniform chamfer | adaptive finest | adaptive chamfer | "
        "RBF chamfer | adaptive / RBF | uniform hausdorff | adaptive hausdorff | "
        "uniform rings | adaptive rings | uniform s | adaptive s | adaptive first s | active |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in payload["accuracy"]:
        u, a, b = r["uniform"], r["adaptive"], r["rbf"]
        lines.append(
            f"| {r['case']} | {r['m']} | {u['grid'][0]}x{u['grid'][1]} | {u['chamfer']:.2e} | "
            f"{a['finest'][0]}x{a['finest'][1]} | {a['chamfer']:.2e} | {b['chamfer']:.2e} | "
            f"{a['chamfer'] / b['chamfer']:.2f} | {u['hausdorff']:.2e} | {a['hausdorff']:.2e} | "
            f"{_rings(u)} | {_rings(a)} | {u['warm_s']:.3f} | {a['warm_s']:.3f} | "
            f"{a['first_s']:.3f} | {a['active']} |"
        )
    rows = payload["accuracy"]
    better = sum(r["adaptive"]["chamfer"] < r["uniform"]["chamfer"] for r in rows)
    no_worse = sum(r["adaptive"]["chamfer"] <= r["rbf"]["chamfer"] for r in rows)
    exact = sum(bool(r["adaptive"]["topology"]["exact"]) for r in rows)
    ratios = [r["adaptive"]["chamfer"] / r["rbf"]["chamfer"] for r in rows]
    gains = [r["uniform"]["chamfer"] / r["adaptive"]["chamfer"] for r in rows]
    lines += [
        "",
        f"Adaptive Chamfer below the uniform grid's in {better}/{len(rows)} cases "
        f"({min(gains):.2f}-{max(gains):.2f}x smaller); no worse than the RBF's in "
        f"{no_worse}/{len(rows)} (ratio {min(ratios):.2f}-{max(ratios):.2f}); every ring "
        f"matched exactly in {exact}/{len(rows)}.",
    ]
    lines += ["", f"## Scaling in 2D ({payload['scaling_case']}, clean)", ""]
    lines += scaling_table(payload["scaling"], 2, payload)
    if payload.get("surface_scaling"):
        lines += ["", f"## Scaling in 3D ({payload['surface_case']})", ""]
        run = payload.get("surface_run")
        if run:  # measured apart from the 2D tables (--surface-only)
            lines += [
                f"Measured {run['date']}, 1-minute load average {run['load_average'][0]:.1f} "
                f"at the start, {run['load_average'][1]:.1f} at the end. {run['note']}",
                "",
            ]
        lines += scaling_table(payload["surface_scaling"], 3, payload)
    return "\n".join(lines) + "\n"


def _seconds(row) -> tuple[float, str]:
    """The row's warm time, or its first call (marked) where no warm call ran."""
    if row.get("warm_s") is not None:
        return row["warm_s"], f"{row['warm_s']:.3f}"
    return row["first_s"], f"{row['first_s']:.3f} (first call)"


def scaling_table(rows: list[dict], ndim: int, payload: dict) -> list[str]:
    target = TARGETS[ndim]
    box = 2**ndim
    if ndim == 2:
        intro = (
            f"`jurs.fit_adaptive(points, normals, finest=F, settings=...)` on the "
            f"{payload['scaling_case']} cloud (settings measured once, outside the timing; "
            "the direct solve, so no CG steps)."
        )
    else:
        intro = (
            f"`jurs.fit_adaptive(points, normals, finest=F, settings=...)` on "
            f"{payload['surface_origin']}, {payload['surface_points']} area-uniform samples "
            "with exact normals (settings measured once, outside the timing; conjugate "
            "gradients, the surface default). Warm s: the second call; where the first "
            "call took more of the row's time bound than was left, it alone is reported."
        )
    unchecked = any("unchecked_s" in r for r in rows)
    if unchecked:
        intro += (
            " 'no checks s': the warm time of the same fit with `checks=False` (without the "
            "verdicts' checks of the zero set on the host)."
        )
    lines = [
        intro + f" Each row in a fresh process: 'first s' includes its compilations; peak "
        "RSS is the process's VmHWM, in brackets its resident set before the fit (Python, "
        f"JAX and the benchmark's imports). A row stops at {payload['timeout_s']:.0f} s or "
        f"{payload['max_gb']:.0f} GB resident. 'x' columns: ratio to the row above (one "
        "doubling of F; memory: of the peak above the base); the target is at most about "
        f"{target}x (a box-bound cost would be {box}x).",
        "",
    ]
    header = [
        "finest F",
        "finest cells",
        "levels",
        "active",
        "uniform grid's functions",
        "CG steps",
        "first s",
        "warm s",
        *(["no checks s"] if unchecked else []),
        "peak RSS GB (base)",
        "active x",
        "time x",
        *(["no checks x"] if unchecked else []),
        "memory x",
    ]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    previous = None
    checked = []
    for r in rows:
        if "skipped" in r or "error" in r:
            reason = r.get("skipped") or r["error"]
            lines.append(f"| {r['finest']} | {reason} |" + "  |" * (len(header) - 2))
            previous = None
            continue
        seconds, text = _seconds(r)
        ratios = [""] * (4 if unchecked else 3)
        if previous is not None:
            ratios = [
                r["active"] / previous["active"],
                seconds / _seconds(previous)[0],
                *([r["unchecked_s"] / previous["unchecked_s"]] if unchecked else []),
                (r["peak_rss"] - r["base_rss"]) / (previous["peak_rss"] - previous["base_rss"]),
            ]
            checked.append((ratios[0], ratios[1], ratios[2] if unchecked else None))
            ratios = [f"{x:.2f}" for x in ratios]
        cells = [
            r["finest"],
            "x".join(map(str, r["cells"])),
            r["levels"],
            r["active"],
            r["uniform_functions"],
            r["cg_steps"],
            f"{r['first_s']:.3f}",
            text,
            *([f"{r['unchecked_s']:.3f}"] if unchecked else []),
            f"{r['peak_rss'] / GB:.2f} ({r['base_rss'] / GB:.2f})",
            *ratios,
        ]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
        previous = r
    if checked:

        def spread(k: int) -> str:
            values = [c[k] for c in checked]
            ok = sum(v <= target for v in values)
            return f"{min(values):.2f}-{max(values):.2f}x ({ok}/{len(values)} at most {target}x)"

        def mean(k: int) -> str:  # geometric mean per doubling over the whole ladder
            values = np.array([c[k] for c in checked], float)
            return f"{float(np.exp(np.log(values).mean())):.2f}x"

        text = f"Per doubling, active functions grew by {spread(0)}, warm time by {spread(1)}"
        text += f", time without checks by {spread(2)}." if unchecked else "."
        text += (
            f" Over the {len(checked)} doublings of the ladder: {mean(0)} a doubling in active "
            f"functions, {mean(1)} in warm time"
            + (f", {mean(2)} without checks." if unchecked else ".")
        )
        lines += ["", text]
    return lines


def surface_ladder(args) -> dict:
    """The 3D ladder's fields of the payload: the case, its origin, its points and rows."""
    surface_case, origin, points, normals = surface_cloud(args.surface_points)
    rows = ladder(
        surface_row, points, normals, args.surface_finest, args.timeout, args.max_gb,
        args.timeout,
    )  # fmt: skip
    return {
        "surface_case": surface_case,
        "surface_origin": origin,
        "surface_points": args.surface_points,
        "surface_scaling": rows,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(DEFAULT_CASES))
    parser.add_argument("--finest", nargs="*", type=int, default=list(DEFAULT_FINEST))
    parser.add_argument(
        "--surface-finest", nargs="*", type=int, default=list(DEFAULT_SURFACE_FINEST)
    )
    parser.add_argument("--surface-points", type=int, default=SURFACE_POINTS)
    parser.add_argument(
        "--timeout", type=float, default=TIMEOUT_S, help="seconds a scaling row may run"
    )
    parser.add_argument(
        "--max-gb", type=float, default=MAX_GB, help="resident GB a scaling row may take"
    )
    parser.add_argument("--note", default="")
    parser.add_argument(
        "--render", action="store_true", help="rewrite the .md from the committed .json only"
    )
    parser.add_argument(
        "--surface-only",
        action="store_true",
        help="measure the 3D ladder again, keeping the committed 2D tables (dated apart)",
    )
    args = parser.parse_args(argv)
    if args.render:
        with open(os.path.join(RESULTS, "adaptive.json")) as fh:
            payload = json.load(fh)
        write_results("adaptive", payload, markdown(payload))
        return
    if args.surface_only:
        with open(os.path.join(RESULTS, "adaptive.json")) as fh:
            payload = json.load(fh)
        load = os.getloadavg()[0]
        payload.update(
            surface_ladder(args),
            surface_run={
                "date": datetime.date.today().isoformat(),
                "note": args.note,
                "load_average": [load, os.getloadavg()[0]],
            },
        )
        write_results("adaptive", payload, markdown(payload))
        return
    load = [os.getloadavg()[0]]
    accuracy = []
    for name in args.cases:
        row = accuracy_row(name)
        print(name, {k: row[k]["chamfer"] for k in ("uniform", "adaptive", "rbf")}, flush=True)
        accuracy.append(row)
    scaling = scaling_rows(SCALING_CASE, args.finest, args.timeout, args.max_gb)
    surface = surface_ladder(args)
    load.append(os.getloadavg()[0])
    payload = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "note": args.note,
        "load_average": load,
        "timeout_s": args.timeout,
        "max_gb": args.max_gb,
        "accuracy": accuracy,
        "scaling_case": SCALING_CASE,
        "scaling": scaling,
        **surface,
    }
    write_results("adaptive", payload, markdown(payload))


if __name__ == "__main__":
    main()
