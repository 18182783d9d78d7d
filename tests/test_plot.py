"""Figures: each returns a Figure with labelled axes, a colour bar where g is shown, equal
aspect for maps, and saves as PNG and SVG."""

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import PAPER  # noqa: E402

import jurs  # noqa: E402
import jurs.plot as jplot  # noqa: E402
from jurs import levelset as ls  # noqa: E402

# Every test here takes several seconds (fits and figures): make test-fast skips them.
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(example1_cloud):
    p, n = example1_cloud
    return jurs.fit_in_chunks(
        p, n, solver=jurs.IURS(max_steps=40, tol=0.0), checkpoints=(0, 10, 40), **PAPER
    )


def _map_axes(fig):
    return [ax for ax in fig.axes if ax.get_label() != "<colorbar>" and ax.get_visible()]


def _colorbars(fig):
    return [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]


def _saves(fig, tmp_path, name):
    for ext in ("png", "svg"):
        path = tmp_path / f"{name}.{ext}"
        fig.savefig(path)
        assert path.stat().st_size > 1000
    plt.close(fig)


def test_plot_fit(run, example1_cloud, tmp_path):
    sol, _ = run
    p, n = example1_cloud
    fig = jplot.plot_fit(sol.spline, p, n, 0.1, title="fit")
    assert isinstance(fig, plt.Figure)
    (ax,) = _map_axes(fig)
    assert ax.get_xlabel() == "x" and ax.get_ylabel() == "y"
    assert ax.get_aspect() == 1.0
    (cbar,) = _colorbars(fig)
    assert cbar.get_ylabel() == "g(x, y)"
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"data points", "g = 0", "outer offsets (+eps)", "inner offsets (-eps)"} <= set(labels)
    _saves(fig, tmp_path, "fit")


def test_plot_fit_highlights_supplementary(run, example1_cloud, tmp_path):
    sol, _ = run
    p, n = example1_cloud
    s = sol.spline
    bumped = jurs.ImplicitSpline(s.control.at[0:2, 0:2].set(-0.2), s.weights, s.lower, s.upper)
    report = ls.analyze(bumped, p, offset=0.1, resolution=256)
    assert report.num_supplementary == 1
    fig = jplot.plot_fit(bumped, p, n, 0.1, levelset=report)
    (ax,) = _map_axes(fig)
    magenta = [
        ln
        for ln in ax.get_lines()
        if ln.get_color() == jplot.SUPPLEMENTARY_COLOUR and len(ln.get_xdata())
    ]
    assert len(magenta) == report.num_supplementary
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "supplementary g = 0 (1)" in labels
    _saves(fig, tmp_path, "fit_supplementary")


def test_evaluate_on_grid_signature(run):
    sol, _ = run
    xs, ys, v = jplot.evaluate_on_grid(sol.spline, 50)
    assert v.shape == (len(ys), len(xs)) and max(len(xs), len(ys)) == 50
    np.testing.assert_allclose(v[3, 7], float(sol.spline(np.array([[xs[7], ys[3]]]))[0]))


def test_plot_iterations(run, example1_cloud, tmp_path):
    _, snaps = run
    p, n = example1_cloud
    fig = jplot.plot_iterations(snaps, p, n, 0.1, resolution=80)
    axes = _map_axes(fig)
    assert [ax.get_title() for ax in axes] == ["step 0", "step 10", "step 40"]
    assert all(ax.get_aspect() == 1.0 and ax.get_xlabel() == "x" for ax in axes)
    assert len(_colorbars(fig)) == 1  # one shared scale
    _saves(fig, tmp_path, "iterations")
    with pytest.raises(ValueError):
        jplot.plot_iterations({})


def test_plot_energy_history(run, example1_cloud, tmp_path):
    sol, _ = run
    p, n = example1_cloud
    ipia = jurs.fit(p, n, solver=jurs.IPIA(max_steps=40, tol=0.0), **PAPER)
    fig = jplot.plot_energy_history({"IURS": sol, "IPIA": ipia, "array": [1.0, 0.5, np.nan]})
    (ax,) = fig.axes
    assert ax.get_yscale() == "log" and ax.get_xlabel() == "step" and ax.get_ylabel()
    lines = ax.get_lines()
    assert [ln.get_label() for ln in lines] == ["IURS", "IPIA", "array"]
    assert len(lines[0].get_xdata()) == 41 and len(lines[2].get_xdata()) == 2
    _saves(fig, tmp_path, "energy")


def test_plot_lambda_sensitivity(tmp_path):
    lams = [0.0, 1e-3, 1e-2, 3e-2]
    records = [
        {
            "E_ave": 1e-7 * (1 + 10 * lam),
            "E_max": 1e-3,
            "R": 1.0 / (1 + 100 * lam),
            "num_supplementary": 3 if lam == 0 else 0,
        }
        for lam in lams
    ]
    fig = jplot.plot_lambda_sensitivity(lams, records, lam_label="lambda (eq. 33)")
    axes = _map_axes(fig)
    assert len(axes) == 4
    assert all(ax.get_xscale() == "symlog" and ax.get_xlabel() == "lambda (eq. 33)" for ax in axes)
    assert axes[0].get_yscale() == "log" and axes[3].get_yscale() == "linear"
    np.testing.assert_array_equal(axes[3].get_lines()[0].get_ydata(), [3, 0, 0, 0])
    _saves(fig, tmp_path, "lambda")
    with pytest.raises(ValueError):
        jplot.plot_lambda_sensitivity([0.1], [])


def test_import_jurs_does_not_import_matplotlib():
    import subprocess
    import sys

    code = (
        "import sys, jurs; assert 'matplotlib' not in sys.modules; import jurs.levelset; "
        "assert 'matplotlib' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
