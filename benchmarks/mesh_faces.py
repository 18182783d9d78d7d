"""Face budgets of ``jurs.levelset.mesh``: faces, time and distances at several budgets.

One case of ``benchmarks/_surface_cases.py`` (default the bunny of pymeshlab's sample
meshes) is sampled (``--points``, exact samples), fitted with jurs's defaults once, and
its zero set meshed whole and with ``faces=`` each budget. Per mesh: its faces, the
meshing time (decimation and the Newton steps after it included), the point-to-surface
Chamfer and Hausdorff distances to the true surface (``surface_distances``, 200 000 mesh
samples, 20 000 exact reference samples), and the Hausdorff distance from the decimated
mesh's samples to the whole mesh's vertices, in cells of the fit's finest grid.

Run ``python -m benchmarks.mesh_faces --points 100000 --faces 400000 100000 20000``;
prints a Markdown table (docs/surfaces.md, "Face budgets", quotes one); ``--save FILE``
keeps the fit (``jurs.save_spline``) and ``--load FILE`` meshes it again without fitting,
``--faces`` alone (no budgets) only fits. Needs the
``bench`` extra (Open3D for the distances, pymeshlab for the bunny) and
fast-simplification.
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

import jurs  # noqa: E402
from jurs import levelset  # noqa: E402

from ._surface_cases import SEEDS, diagonal, make_truth, surface_distances  # noqa: E402


def finest_cell(spline) -> float:
    """The width of the fit's finest cell (its finest level's, for an adaptive fit)."""
    extent = np.asarray(spline.upper) - np.asarray(spline.lower)
    cells = getattr(spline, "finest_cells", None)
    if cells is None:
        cells = np.asarray(spline.control).shape
        cells = [n - 3 for n in cells]
    return float(np.min(extent / np.asarray(cells)))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="bunny", help="a case of benchmarks/_surface_cases")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--faces", type=int, nargs="*", default=[400_000, 100_000, 20_000])
    parser.add_argument("--save", metavar="FILE", help="save the fit (jurs.save_spline)")
    parser.add_argument("--load", metavar="FILE", help="a fit saved by --save: no fit")
    args = parser.parse_args(argv)
    truth = make_truth(args.case)
    if truth is None:
        raise SystemExit(f"{args.case}: its mesh is not available (pymeshlab)")
    points, normals = truth.sample(args.points, SEEDS["cloud"])
    reference = truth.sample(20_000, SEEDS["truth"])[0]
    diag = diagonal(points)
    start = time.perf_counter()
    spline = jurs.load_spline(args.load) if args.load else jurs.fit(points, normals).spline
    fit_s = time.perf_counter() - start
    if args.save:
        jurs.save_spline(args.save, spline)
    cell = finest_cell(spline)
    fitted = "loaded" if args.load else f"fit {fit_s:.1f} s"
    print(f"{args.case}, {args.points} points: {fitted}, finest cell {cell:.4g}\n")
    if not args.faces:
        return
    print("| faces asked | faces | mesh s | Chamfer / diag | Hausdorff / diag | to whole / cell |")
    print("|---|---|---|---|---|---|")
    whole = None
    for budget in [None, *args.faces]:
        start = time.perf_counter()
        vertices, faces = levelset.mesh(spline, faces=budget)
        seconds = time.perf_counter() - start
        d = surface_distances(vertices, faces, truth, reference, diag, 200_000)
        if whole is None:
            whole = cKDTree(vertices)
            to_whole = "-"
        else:
            samples = jurs.datasets.sample_mesh(vertices, faces, 200_000, seed=SEEDS["mesh"])[0]
            to_whole = f"{whole.query(samples)[0].max() / cell:.2f}"
        print(
            f"| {'-' if budget is None else budget} | {len(faces)} | {seconds:.1f} | "
            f"{d['chamfer_rel']:.3g} | {d['hausdorff_rel']:.3g} | {to_whole} |"
        )


if __name__ == "__main__":
    main()
