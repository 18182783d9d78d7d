"""The adaptive (THB) fit beside the uniform default on real 2D outlines, and its scaling.

Two tables, measured in one process:

* **Accuracy.** For each case of ``benchmarks/_realdata_cases.py`` asked for (clean
  variant, exact normals, as ``benchmarks/realdata.py`` samples it): Chamfer and
  Hausdorff distances (fractions of the diagonal) against the dense clean outline, the
  ring match, and the warm fit time of ``jurs.fit`` (defaults), ``jurs.fit_adaptive``
  (defaults) and SciPy's thin-plate RBF on the same offset samples.
* **Scaling.** ``jurs.fit_adaptive(finest=...)`` on one case from 256 to 4096 cells along
  the longer side: active functions, CG steps, warm time; the ratios between successive
  rows show whether the cost follows the boundary (about 2x a doubling) or the box (4x).

Run ``python benchmarks/adaptive.py`` (``--cases camera text --finest 256 512``); writes
``benchmarks/results/adaptive.{md,json}``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jurs  # noqa: E402
import jurs.levelset  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _realdata_cases as cases  # noqa: E402
import realdata  # noqa: E402
from _baselines import rbf_fit, rbf_grid_values  # noqa: E402
from _common import RESULTS, machine, time_repeated, write_results  # noqa: E402

DEFAULT_CASES = ("camera", "coffee", "text", "serif")
DEFAULT_FINEST = (256, 512, 1024, 2048, 4096)
SCALING_CASE = "camera"


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
        lambda: jurs.fit(points, normals, throw=False), budget_s=3.0, max_repeats=5
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


def scaling_rows(name: str, finest: tuple[int, ...]) -> list[dict]:
    case = cases.build(name)
    reference = realdata.reference_samples(case)
    points, normals, _ = realdata.cloud(case, "clean", reference)
    settings = jurs.auto_settings(points, normals)
    rows = []
    for f in finest:
        timing = time_repeated(
            lambda f=f: jurs.fit_adaptive(points, normals, finest=f, settings=settings),
            budget_s=3.0,
            max_repeats=3,
        )
        sol = timing.pop("output")
        rows.append(
            {
                "finest": f,
                "levels": sol.stats["levels"],
                "active": int(sum(sol.stats["active"])),
                "uniform_functions": int((f + 3) ** 2),
                "cg_steps": sol.stats["num_steps"],
                "status": sol.status,
                **timing,
            }
        )
    return rows


def _rings(fit: dict) -> str:
    topology = fit["topology"]
    mark = "" if topology["exact"] else "*"
    return f"{topology['matched']}/{topology['rings']}{mark}"


def markdown(payload: dict) -> str:
    lines = [
        f"# Adaptive (THB) fits beside the uniform default ({payload['date']})",
        "",
        f"Machine: {payload['machine']}; float64. {payload['note']}",
        "",
        "## Accuracy on real outlines (clean, exact normals)",
        "",
        "Distances are fractions of the diagonal against the dense clean outline; rings: "
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
        f"Adaptive Chamfer below the uniform default's in {better}/{len(rows)} cases "
        f"({min(gains):.2f}-{max(gains):.2f}x smaller); no worse than the RBF's in "
        f"{no_worse}/{len(rows)} (ratio {min(ratios):.2f}-{max(ratios):.2f}); every ring "
        f"matched exactly in {exact}/{len(rows)}.",
    ]
    lines += [
        "",
        f"## Scaling ({payload['scaling_case']}, clean)",
        "",
        "| finest | levels | active | uniform grid's functions | CG steps (0: direct) | warm s | "
        "active x | time x |",
        "|---|---|---|---|---|---|---|---|",
    ]
    previous = None
    for r in payload["scaling"]:
        ratio_a = "" if previous is None else f"{r['active'] / previous['active']:.2f}"
        ratio_t = "" if previous is None else f"{r['warm_s'] / previous['warm_s']:.2f}"
        lines.append(
            f"| {r['finest']} | {r['levels']} | {r['active']} | {r['uniform_functions']} | "
            f"{r['cg_steps']} | {r['warm_s']:.3f} | {ratio_a} | {ratio_t} |"
        )
        previous = r
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(DEFAULT_CASES))
    parser.add_argument("--finest", nargs="*", type=int, default=list(DEFAULT_FINEST))
    parser.add_argument("--note", default="")
    parser.add_argument(
        "--render", action="store_true", help="rewrite the .md from the committed .json only"
    )
    args = parser.parse_args(argv)
    if args.render:
        with open(os.path.join(RESULTS, "adaptive.json")) as fh:
            payload = json.load(fh)
        write_results("adaptive", payload, markdown(payload))
        return
    accuracy = []
    for name in args.cases:
        row = accuracy_row(name)
        print(name, {k: row[k]["chamfer"] for k in ("uniform", "adaptive", "rbf")}, flush=True)
        accuracy.append(row)
    scaling = scaling_rows(SCALING_CASE, tuple(args.finest))
    for r in scaling:
        print(r["finest"], r["active"], r["cg_steps"], f"{r['warm_s']:.3f}", flush=True)
    payload = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "note": args.note,
        "accuracy": accuracy,
        "scaling_case": SCALING_CASE,
        "scaling": scaling,
    }
    write_results("adaptive", payload, markdown(payload))


if __name__ == "__main__":
    main()
