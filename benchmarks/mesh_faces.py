"""Face budgets of ``jurs.levelset.mesh``: faces, time and distances at several budgets.

One case of ``benchmarks/_surface_cases.py`` (default the bunny of pymeshlab's sample
meshes) is sampled (``--points``, exact samples), fitted with jurs's defaults once, and
its zero set meshed whole and with ``faces=`` each budget. Per mesh: its faces, the
meshing time (decimation and the Newton steps after it included), the point-to-surface
Chamfer and Hausdorff distances to the true surface (``surface_distances``, 200 000 mesh
samples, 20 000 exact reference samples), and the Hausdorff distance from the decimated
mesh's samples to the whole mesh's vertices, in cells of the fit's finest grid.

Run ``python -m benchmarks.mesh_faces --points 100000 --faces 400000 100000 20000``;
writes ``benchmarks/results/mesh_faces.{md,json}`` (``--name`` another name; docs/surfaces.md,
"Face budgets", quotes one); ``--save FILE``
keeps the fit (``jurs.save_spline``) and ``--load FILE`` meshes it again without fitting,
``--faces`` alone (no budgets) only fits. Needs the
``bench`` extra (Open3D for the distances, pymeshlab for the bunny) and
fast-simplification.
"""

from __future__ import annotations

import argparse
import datetime
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

import jurs  # noqa: E402
from jurs import levelset  # noqa: E402

from ._common import machine, md_table, write_results  # noqa: E402
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
    parser.add_argument("--name", default="mesh_faces", help="results file names")
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
    load_before = os.getloadavg()[0]
    whole = None
    rows = []
    for budget in [None, *args.faces]:
        start = time.perf_counter()
        vertices, faces = levelset.mesh(spline, faces=budget)
        seconds = time.perf_counter() - start
        d = surface_distances(vertices, faces, truth, reference, diag, 200_000)
        if whole is None:
            whole = cKDTree(vertices)
            to_whole = None
        else:
            samples = jurs.datasets.sample_mesh(vertices, faces, 200_000, seed=SEEDS["mesh"])[0]
            to_whole = float(whole.query(samples)[0].max() / cell)
        rows.append(
            dict(asked=budget, faces=len(faces), mesh_s=seconds, chamfer_rel=d["chamfer_rel"],
                 hausdorff_rel=d["hausdorff_rel"], to_whole_cells=to_whole)
        )  # fmt: skip
        print(rows[-1], flush=True)
    table = md_table(
        ["faces asked", "faces", "mesh s", "Chamfer / diag", "Hausdorff / diag",
         "to whole / cell"],
        [
            ["-" if r["asked"] is None else r["asked"], r["faces"], f"{r['mesh_s']:.1f}",
             f"{r['chamfer_rel']:.3g}", f"{r['hausdorff_rel']:.3g}",
             "-" if r["to_whole_cells"] is None else f"{r['to_whole_cells']:.2f}"]
            for r in rows
        ],
    )  # fmt: skip
    lines = [
        "# Face budgets of `jurs.levelset.mesh`",
        "",
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {machine()}, "
        f"load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after. "
        f"`python -m benchmarks.mesh_faces --points {args.points} --faces "
        f"{' '.join(map(str, args.faces))}`. {args.case}, {args.points} exact samples, "
        f"{fitted}, finest cell {cell:.4g}. Chamfer and Hausdorff to the true surface "
        "(200 000 mesh samples, 20 000 exact ones); *to whole*: the farthest of 200 000 "
        "samples of the decimated mesh from the whole mesh's vertices, in finest cells. "
        "*mesh s*: extraction, decimation and the Newton steps after it.",
        "",
        *table,
        "",
    ]
    payload = dict(case=args.case, points=args.points, finest_cell=cell, rows=rows)
    write_results(args.name, payload, "\n".join(lines))


if __name__ == "__main__":
    main()
