"""``jurs demo``: its table's quantities, recomputed from the fits, and the note under it."""

import jax

jax.config.update("jax_enable_x64", True)

import re  # noqa: E402

import numpy as np  # noqa: E402

import jurs  # noqa: E402
from jurs import demo  # noqa: E402


def _eq35(spline, points, normals, offset, eps):
    """Eq. 35 with lambda 0, summed here from the spline's values: g at the data points
    (target 0) and at the offset samples P + d n (target eps) and P - d n (target -eps)."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    on = np.asarray(spline(points))
    outer = np.asarray(spline(points + offset * n)) - eps
    inner = np.asarray(spline(points - offset * n)) + eps
    return float(np.sum(on**2) + np.sum(outer**2) + np.sum(inner**2)), on


def test_demo_table_says_what_it_compares(tmp_path, capsys):
    """The demo printed E 14x the paper's with no word of why. Its E, E_max and E_ave are
    recomputed here from the fits (eq. 35-37 from the spline's values), and the note under
    the table names the samples E sums and the ratios it states."""
    rows = demo.run(str(tmp_path), steps=200)
    text = capsys.readouterr().out
    printed = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 6 and cells[0] in rows:
            printed[cells[0]] = [float(c) for c in cells[1:4]]
    assert set(printed) == set(rows) == {*demo.PAPER, demo.REFERENCE}

    points, normals = jurs.datasets.example1(120)
    solvers = {
        "B-spline (IPIA)": jurs.IPIA(max_steps=200, tol=0.0),
        "uniform rational (IURS)": jurs.IURS(tau=1e-2, max_steps=200, tol=0.0),
        demo.REFERENCE: jurs.LeastSquares(lam=demo.REFERENCE_LAM),
    }
    energies = {}
    for name, solver in solvers.items():
        sol = jurs.fit(points, normals, solver=solver, grid=(9, 9), offset=0.1, eps=0.01)
        e, on = _eq35(sol.spline, points, normals, 0.1, 0.01)
        energies[name] = e
        expected = [e, np.max(np.abs(on)), np.mean(on**2)]
        # Printed to 5 significant digits.
        np.testing.assert_allclose(printed[name], expected, rtol=1e-4)

    note = " ".join(text.split())  # the notes are wrapped
    assert f"the {len(points)} data points" in note
    assert f"the {2 * len(points)} offset samples" in note
    ipia = energies["B-spline (IPIA)"]
    # The ratios the note states, to their 3 printed digits.
    ratio = re.search(r"E: ours is ([0-9.]+)x the paper's", note)
    assert ratio and ratio.group(1) == f"{ipia / demo.PAPER['B-spline (IPIA)'][0]:.3g}"
    far = re.search(r"row: ours is ([0-9.]+)x it", note)
    assert far and far.group(1) == f"{ipia / energies[demo.REFERENCE]:.3g}"
    assert (tmp_path / "example1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
