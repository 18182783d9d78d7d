"""The two hierarchical bases the adaptive fit could use, measured on the same structure.

* **THB** (what ``jurs.fit_adaptive`` fits): truncated hierarchical B-splines, linearly
  independent, a partition of unity; one joint least-squares solve (QDLDL).
* **Sum of levels, coarse to fine** (Poisson reconstruction's scheme): at every level
  ``l`` the full uniform B-splines of that level whose support meets ``Omega_l`` (the
  same band of cells THB refines), not truncated, so a point sees every level's functions
  and ``g = sum_l g_l``. Solved as a cascade: level 0 fits the targets, each finer level
  fits what the coarser ones left, each by its own exact solve with the same regulariser
  (eq. 31 on the level's functions, ``lam`` as THB's); then ``--sweeps`` more passes
  coarse to fine over the remaining residual (block Gauss-Seidel over the levels).

Both on the same traced outlines (``benchmarks/_realdata_cases.py``, clean, exact
normals), with the same settings, offset samples, levels, band and ``lam``; distances and
ring matches as ``benchmarks/adaptive.py`` measures them (the zero set on the case's
analysis lattice). Curves only: the point of the comparison is the basis, and the 2D
solves are exact.

    python -m benchmarks.thb_vs_levels [--cases camera text ...] [--sweeps N]

writes ``benchmarks/results/thb_vs_levels.{md,json}``.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy import sparse  # noqa: E402

import jurs  # noqa: E402
import jurs.levelset  # noqa: E402
from jurs._fit.adaptive import finest_cell_width, hierarchy_layout, solve_normal  # noqa: E402
from jurs._fit.settings import scale_free_lam  # noqa: E402
from jurs.internal import cubic_weights, offset_samples, refine_near  # noqa: E402

from . import _realdata_cases as cases  # noqa: E402
from . import realdata  # noqa: E402
from ._common import machine, md_table, write_results  # noqa: E402
from .adaptive import _rings as rings  # noqa: E402

DEFAULT_CASES = ("camera", "coffee", "text", "terrain", "logo", "hubble")


def _axis_weights(x, lower, width, cells):
    """Per axis: each coordinate's cell (clipped to the box) and its four cubic weights."""
    cell = np.clip(np.floor((x - lower) / width), 0, cells - 1).astype(np.int64)
    return cell, cubic_weights((x - lower) / width - cell, xp=np)


def level_functions(cells, omega):
    """Row-major keys (in the ``(cells + 3)`` function grid) of the level's functions whose
    support meets a cell of ``omega`` (``(k, 2)`` cell indices)."""
    a = np.arange(4)
    keys = (omega[:, 0, None, None] + a[:, None]) * (cells[1] + 3) + (omega[:, 1, None, None] + a)
    return np.unique(keys.ravel())


def level_matrices(samples, lower, width, cells, keys):
    """``(B_l, 2 G_l^T G_l)``: the level's active functions at the samples, and eq. 31's
    differences between active neighbours (weight 1 in 2D: the scale-free sum)."""
    fy = cells[1] + 3
    cx, wx = _axis_weights(samples[:, 0], lower[0], width[0], cells[0])
    cy, wy = _axis_weights(samples[:, 1], lower[1], width[1], cells[1])
    a = np.arange(4)
    rows = np.repeat(np.arange(len(samples)), 16)
    funcs = (cx[:, None, None] + a[None, :, None]) * fy + (cy[:, None, None] + a[None, None, :])
    values = wx[:, :, None] * wy[:, None, :]
    funcs, values = funcs.reshape(-1), values.reshape(-1)
    pos = np.searchsorted(keys, funcs)
    hit = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == funcs)
    basis = sparse.csr_matrix((values[hit], (rows[hit], pos[hit])), shape=(len(samples), len(keys)))
    pairs = []
    for step in (fy, 1):  # neighbours along x, then along y
        nxt = keys + step
        same_row = (step == fy) | ((keys % fy) < fy - 1)
        j = np.searchsorted(keys, nxt)
        ok = same_row & (j < len(keys)) & (keys[np.minimum(j, len(keys) - 1)] == nxt)
        pairs.append(np.stack([np.nonzero(ok)[0], j[ok]], 1))
    pairs = np.concatenate(pairs)
    e = len(pairs)
    difference = sparse.csr_matrix(
        (np.tile([1.0, -1.0], e), (np.repeat(np.arange(e), 2), pairs.ravel())),
        shape=(e, len(keys)),
    )
    return basis, sparse.csr_matrix(2.0 * difference.T @ difference)


def level_values(coeffs, keys, cells, lower, width, xs, ys):
    """The level's spline on the lattice ``xs x ys`` (``(len(ys), len(xs))``)."""
    fx, fy = cells[0] + 3, cells[1] + 3
    dense = np.zeros(fx * fy)
    dense[keys] = coeffs
    dense = dense.reshape(fx, fy)

    def weights(x, lo, w, n, f):
        cell, wt = _axis_weights(x, lo, w, n)
        rows = np.repeat(np.arange(len(x)), 4)
        cols = (cell[:, None] + np.arange(4)[None]).ravel()
        return sparse.csr_matrix((wt.ravel(), (rows, cols)), shape=(len(x), f))

    wx = weights(xs, lower[0], width[0], cells[0], fx)
    wy = weights(ys, lower[1], width[1], cells[1], fy)
    return (wy @ (wx @ dense).T).reshape(len(ys), len(xs))


def sum_of_levels(points, normals, settings, sweeps):
    """The cascadic sum-of-levels fit on THB's own layout; its per-level keys, coefficients
    and statistics."""
    layout = hierarchy_layout(settings, 2, None, None, None, None, None)
    lower, upper, base, levels = (layout[k] for k in ("lower", "upper", "base", "levels"))
    offset, eps, band = layout["offset"], layout["eps"], layout["band"]
    samples, targets = offset_samples(points, normals, offset, eps, xp=np)  # pyright: ignore[reportArgumentType]
    refine = refine_near(lower, upper, base, levels, samples, band)
    finest = finest_cell_width(settings, 2, None)
    diag = float(np.linalg.norm(points.max(0) - points.min(0)))
    lam = scale_free_lam(settings.smoothing, len(samples), diag, lower, upper, finest)
    start = time.perf_counter()
    structure = []
    for level in range(levels + 1):
        cells = np.asarray([n << level for n in base])
        width = (upper - lower) / cells
        if level == 0:
            omega = np.stack(np.meshgrid(*(np.arange(c) for c in cells), indexing="ij"), -1)
            omega = omega.reshape(-1, 2)
        else:  # the children of the refined cells of the level above
            parent_cells = cells // 2
            parents = np.stack(np.unravel_index(refine[level - 1], tuple(parent_cells)), 1)
            kids = np.stack(np.meshgrid([0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 2)
            omega = (2 * parents[:, None, :] + kids[None]).reshape(-1, 2)
        keys = level_functions(cells, omega)
        basis, regulariser = level_matrices(samples, lower, width, cells, keys)
        # The level's normal matrix, the same in every pass: formed once.
        matrix = (basis.T @ basis + lam * regulariser).tocsc()
        structure.append((cells, width, keys, basis, matrix))
    assembled = time.perf_counter() - start
    residual = np.asarray(targets, float).copy()
    coeffs = [np.zeros(len(s[2])) for s in structure]
    passes = []  # after the cascade, and after the sweeps
    start = time.perf_counter()
    for sweep in range(1 + sweeps):
        for level, (_, _, _, basis, matrix) in enumerate(structure):
            residual += basis @ coeffs[level]  # this level's part back in
            coeffs[level], _ = solve_normal(matrix, basis.T @ residual)
            residual -= basis @ coeffs[level]
        if sweep in (0, sweeps):
            passes.append(
                {
                    "coeffs": [c.copy() for c in coeffs],
                    "solve_s": time.perf_counter() - start,
                    "rms_residual": float(np.sqrt(np.mean(residual**2))),
                }
            )
    return {
        "structure": structure,
        "lower": lower,
        "functions": int(sum(len(s[2]) for s in structure)),
        "levels": levels + 1,
        "assemble_s": assembled,
        "passes": passes,
    }


def compare(name: str, sweeps: int) -> dict:
    case = cases.build(name)
    reference = realdata.reference_samples(case)
    rings = [np.vstack([c, c[:1]]) for c in case.components]
    points, normals, _ = realdata.cloud(case, "clean", reference)
    diag, res = case.diag, realdata.resolution_of(case)
    settings = jurs.auto_settings(points, normals)
    box = tuple(np.asarray(v, float) for v in settings.domain)
    xs, ys, _ = jurs.levelset.sampling_grid(box[0], box[1], res)
    row: dict = {"case": name, "m": case.m}

    # Warm, and without the verdicts' checks: the sum of levels runs none.
    jurs.fit_adaptive(points, normals, settings=settings, checks=False)
    start = time.perf_counter()
    thb = jurs.fit_adaptive(points, normals, settings=settings, checks=False)
    thb_s = time.perf_counter() - start
    report = jurs.levelset.analyze(
        thb.spline, points, offset=settings.offset, reference=reference, resolution=res, box=box
    )
    row["thb"] = {
        **realdata.measure(report, rings, diag, reference)[0],
        "functions": int(sum(thb.stats["active"])),
        "levels": thb.stats["levels"],
        "fit_s": thb_s,
    }
    fit = sum_of_levels(points, normals, settings, sweeps)
    for label, done in zip(("cascade", "levels"), fit["passes"]):
        values = sum(
            level_values(c, keys, cells, fit["lower"], width, xs, ys)
            for (cells, width, keys, _, _), c in zip(fit["structure"], done["coeffs"])
        )
        report = jurs.levelset.analyze_grid(
            xs, ys, np.asarray(values), points, offset=settings.offset, reference=reference
        )
        row[label] = {
            **realdata.measure(report, rings, diag, reference)[0],
            **{k: fit[k] for k in ("functions", "levels", "assemble_s")},
            "solve_s": done["solve_s"],
            "rms_residual": done["rms_residual"],
        }
    return row


def markdown(payload: dict) -> str:
    lines = [
        f"# THB against a sum of levels solved coarse to fine ({payload['date']})",
        "",
        f"Machine: {payload['machine']}; float64. Command: `{payload['command']}`. "
        f"{payload['note']}",
        "",
        "Both bases on the same hierarchy (levels, band of cells around the offset samples, "
        "finest cell one spacing), the same samples, settings and lambda. THB: "
        "`jurs.fit_adaptive` (one exact joint solve; warm, `checks=False`: the hierarchy, "
        "assembly, factorisation and metrics). Sum of "
        f"levels: every level's untruncated functions meeting its band, {payload['sweeps']} "
        "extra coarse-to-fine sweep(s) after the cascade, each level's solve exact (QDLDL); "
        "'cascade': one pass coarse to fine, as Poisson reconstruction solves; 'levels': "
        "after the sweeps. Times are assembly plus solves, the lattice evaluation left out. "
        "Distances are "
        "fractions of the diagonal against the dense clean outline; rings matched / "
        "expected (`*`: not one to one).",
        "",
    ]
    header = (
        "case", "m", "THB functions", "levels functions", "THB chamfer", "cascade chamfer",
        "levels chamfer", "levels / THB", "THB hausdorff", "cascade hausdorff",
        "levels hausdorff", "THB rings", "cascade rings", "levels rings", "THB s",
        "cascade s", "levels s", "cascade / levels rms residual",
    )  # fmt: skip
    cells = []
    for r in payload["rows"]:
        t, c, s = r["thb"], r["cascade"], r["levels"]
        cells.append(
            (
                r["case"],
                r["m"],
                t["functions"],
                s["functions"],
                f"{t['chamfer']:.2e}",
                f"{c['chamfer']:.2e}",
                f"{s['chamfer']:.2e}",
                f"{s['chamfer'] / t['chamfer']:.2f}",
                f"{t['hausdorff']:.2e}",
                f"{c['hausdorff']:.2e}",
                f"{s['hausdorff']:.2e}",
                rings(t),
                rings(c),
                rings(s),
                f"{t['fit_s']:.2f}",
                f"{c['assemble_s'] + c['solve_s']:.2f}",
                f"{s['assemble_s'] + s['solve_s']:.2f}",
                f"{c['rms_residual']:.2e} / {s['rms_residual']:.2e}",
            )  # fmt: skip
        )
    lines += md_table(header, cells)
    rows = payload["rows"]

    def spread(key, variant):
        values = [r[variant][key] / r["thb"][key] for r in rows]
        return f"{min(values):.2f}-{max(values):.2f}x"

    lines += [
        "",
        f"Over THB on {len(rows)} outlines: the cascade alone {spread('chamfer', 'cascade')} "
        f"Chamfer and {spread('hausdorff', 'cascade')} Hausdorff; after the sweeps "
        f"{spread('chamfer', 'levels')} and {spread('hausdorff', 'levels')}, on "
        f"{spread('functions', 'levels')} the functions.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(DEFAULT_CASES))
    parser.add_argument("--sweeps", type=int, default=2)
    parser.add_argument("--note", default="")
    args = parser.parse_args(argv)
    rows = []
    for name in args.cases:
        row = compare(name, args.sweeps)
        print(name, row["thb"]["chamfer"], row["levels"]["chamfer"], flush=True)
        rows.append(row)
    payload = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": "python -m benchmarks.thb_vs_levels " + " ".join(sys.argv[1:]),
        "note": args.note,
        "sweeps": args.sweeps,
        "rows": rows,
    }
    write_results("thb_vs_levels", payload, markdown(payload))


if __name__ == "__main__":
    main()
