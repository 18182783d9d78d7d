"""Meshing an adaptive sphere (or contouring an adaptive curve) over the band against the
full lattice: nodes and time.

For each spline and resolution: the lattice's nodes, the nodes the band path evaluates
(``jurs._model.band.plan_band``), the band mesh's time (``jurs.levelset.mesh``, Newton
steps included) and, where asked, the full lattice's marching (the slab path on every
node) at the same resolution. Splines: a ``jurs.fit_adaptive`` sphere at a finest level
(``--fit FINEST``), or a THB quasi-interpolant of the unit sphere's distance on the same
kind of hierarchy (``--synthetic FINEST``: no fit, for finest levels whose fit takes too
long here).

Run ``python -m benchmarks.band_mesh --fit 128 --synthetic 256 --resolution 257 513``
(``--load FILE`` takes a fit saved by ``jurs.save_spline`` instead of fitting);
prints a Markdown table (docs/design.md section 8 quotes one).

Curves: ``--curve camera --resolution 1025 2049 4097`` fits ``jurs.fit_adaptive`` (default
settings) to a traced outline of ``benchmarks/_realdata_cases.py`` and contours it over
the band (``jurs.levelset._contour_values``) and over the full lattice (``evaluate_grid``),
checking that the lines are the same; each time is the best of three.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jurs  # noqa: E402
from jurs import AdaptiveSpline  # noqa: E402
from jurs._fit.adaptive import adaptive_layout  # noqa: E402
from jurs._model.band import plan_band  # noqa: E402
from jurs._model.lattice import FinestSpline  # noqa: E402
from jurs.internal import build_hierarchy, refine_near  # noqa: E402
from jurs.levelset import _meshing  # noqa: E402


def synthetic_sphere(finest: int, samples: int = 200_000) -> AdaptiveSpline:
    """Each active function's coefficient is the sphere's signed distance at its Greville
    point, on the hierarchy ``fit_adaptive`` would build around samples of the sphere."""
    v = np.random.default_rng(0).normal(size=(samples, 3))
    points = v / np.linalg.norm(v, axis=1, keepdims=True)
    lower, upper, base, levels = adaptive_layout(np.full(3, -1.3), np.full(3, 1.3), 2.6 / finest)
    hierarchy = build_hierarchy(
        lower, upper, base, refine_near(lower, upper, base, levels, points, 2)
    )
    coeffs = []
    for lev in range(hierarchy.num_levels):
        keys = np.asarray(hierarchy.function_keys[lev])[np.asarray(hierarchy.active[lev])]
        multi = np.stack(np.unravel_index(keys, hierarchy.functions(lev)), -1)
        width = (upper - lower) / np.asarray(hierarchy.cells(lev))
        coeffs.append(np.linalg.norm(lower + (multi - 1) * width, axis=1) - 1.0)
    control = jnp.asarray(np.concatenate(coeffs))
    return AdaptiveSpline(hierarchy, control, jnp.ones_like(control))


def fitted_sphere(finest: int) -> AdaptiveSpline:
    points, normals = jurs.datasets.sphere3d(20_000)
    spline = jurs.fit_adaptive(points, normals, finest=finest).spline
    assert isinstance(spline, AdaptiveSpline)
    return spline


def loaded_sphere(path: str) -> AdaptiveSpline:
    spline = jurs.load_spline(path)
    assert isinstance(spline, AdaptiveSpline), f"{path} holds no adaptive spline"
    return spline


def measure(name: str, spline: AdaptiveSpline, resolution: int, full: bool) -> str:
    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    axes = _meshing.lattice_axes(lower, upper, resolution)
    evaluator = FinestSpline(spline)
    t0 = time.perf_counter()
    plan = plan_band(evaluator, axes, 0.0, 0.0)
    planned = time.perf_counter() - t0
    t0 = time.perf_counter()
    vertices, faces = jurs.levelset.mesh(spline, resolution, max_nodes=None)
    band_s = time.perf_counter() - t0
    report = jurs.levelset.analyze_mesh(vertices, faces)
    full_s = "not run"
    if full:
        spacing = _meshing._spacing(axes)
        nudge = _meshing.NUDGE * float(np.max(spacing * spline.slope_bound()))
        t0 = time.perf_counter()
        _meshing._march_in_slabs(spline, axes, 0.0, nudge, _meshing.SLAB_NODES)
        full_s = f"{time.perf_counter() - t0:.1f}"
    return (
        f"| {name} | {spline.finest_cells[0]} | {resolution} | {plan.lattice_nodes:.3g} | "
        f"{plan.nodes:.3g} | {plan.nodes / plan.lattice_nodes:.3f} | {planned:.1f} | "
        f"{band_s:.1f} | {full_s} | {len(vertices)} | {report.num_components} / "
        f"{report.components[0].genus if report.components else '-'} |"
    )


def fitted_curve(name: str) -> AdaptiveSpline:
    from ._realdata_cases import build

    case = build(name)
    points, normals = jurs.shapes.sample_outline(list(case.components), case.m)
    spline = jurs.fit_adaptive(points, normals).spline
    assert isinstance(spline, AdaptiveSpline)
    return spline


def _best(fn, repeats: int):
    """``(result, seconds)``: the fastest of ``repeats`` calls (the machine is shared)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def measure_curve(name: str, spline: AdaptiveSpline, resolution: int, repeats: int = 3) -> str:
    from jurs.levelset import _curves

    xs, ys, _ = _curves.sampling_grid(spline.lower, spline.upper, resolution)
    (band, _, plan), band_s = _best(lambda: _curves._band_values(spline, xs, ys, 0.0), repeats)
    band_lines, band_contour_s = _best(lambda: _curves.contour_lines(xs, ys, band), repeats)
    full, full_s = _best(lambda: _curves.evaluate_grid(spline, xs, ys), repeats)
    full_lines, full_contour_s = _best(lambda: _curves.contour_lines(xs, ys, full), repeats)
    same = len(band_lines) == len(full_lines) and all(
        a[1] == b[1] and np.array_equal(a[0], b[0]) for a, b in zip(band_lines, full_lines)
    )
    return (
        f"| {name} | {max(spline.finest_cells)} | {resolution} | {plan.lattice_nodes:.3g} | "
        f"{plan.nodes:.3g} | {plan.nodes / plan.lattice_nodes:.3f} | {band_s:.2f} | "
        f"{band_contour_s:.2f} | {full_s:.2f} | {full_contour_s:.2f} | {len(band_lines)} | "
        f"{'yes' if same else 'NO'} |"
    )


def main_curves(names, resolutions):
    print(
        "| outline | finest | resolution | lattice nodes | band nodes | fraction | band "
        "values s | band contour s | full values s | full contour s | lines | identical |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        spline = fitted_curve(name)
        for resolution in resolutions:
            print(measure_curve(name, spline, resolution), flush=True)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--curve", nargs="*", default=[], help="outlines to contour instead")
    parser.add_argument("--fit", type=int, nargs="*", default=[128])
    parser.add_argument("--load", nargs="*", default=[], help="saved adaptive sphere fits")
    parser.add_argument("--synthetic", type=int, nargs="*", default=[256])
    parser.add_argument("--resolution", type=int, nargs="+", default=[257, 513])
    parser.add_argument("--full-up-to", type=int, default=257, help="largest full lattice")
    args = parser.parse_args()
    if args.curve:
        main_curves(args.curve, args.resolution)
        return
    print(
        "| spline | finest | resolution | lattice nodes | band nodes | fraction | plan s | "
        "band mesh s | full lattice s | vertices | components / genus |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    splines = [("fit_adaptive (loaded)", loaded_sphere(path)) for path in args.load]
    splines += [(f"fit_adaptive, {f}", fitted_sphere(f)) for f in args.fit]
    splines += [(f"quasi-interpolant, {f}", synthetic_sphere(f)) for f in args.synthetic]
    for name, spline in splines:
        jurs.levelset.mesh(spline, 33, max_nodes=None)  # compile the cascade once
        for resolution in args.resolution:
            row = measure(name, spline, resolution, resolution <= args.full_up_to)
            print(row, flush=True)


if __name__ == "__main__":
    main()
