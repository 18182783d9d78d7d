"""jaxopt wrappers (optional extra): skipped cleanly when jaxopt is absent."""

import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jurs

jax.config.update("jax_enable_x64", True)

LAM = 1e-4


@pytest.mark.slow
def test_jurs_works_without_jaxopt():
    """Hide jaxopt from the import system: jurs imports, other solvers fit, and a jaxopt
    solver fails with an ImportError naming the extra."""
    script = textwrap.dedent("""
        import sys
        sys.modules["jaxopt"] = None  # makes `import jaxopt` raise ImportError
        import jurs
        points, normals = jurs.datasets.example1(40)
        jurs.fit(points, normals, grid=6, offset=0.1, eps=0.01, solver=jurs.LeastSquares(lam=1e-4))
        try:
            jurs.fit(points, normals, grid=6, offset=0.1, eps=0.01, solver=jurs.JaxoptLBFGS())
        except ImportError as exc:
            assert "pip install -e '.[jaxopt]'" in str(exc), exc
            print("ok")
    """)
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert out.stdout.strip() == "ok", out.stderr[-2000:]


def test_missing_jaxopt_says_to_install_from_the_checkout(monkeypatch):
    """jurs is not published: the hint installs the extra from the checkout."""
    from jurs.solvers._jaxopt import _import_jaxopt

    monkeypatch.setitem(sys.modules, "jaxopt", None)  # `import jaxopt` raises ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[jaxopt\]'"):
        _import_jaxopt()


jaxopt = pytest.importorskip("jaxopt")


@pytest.fixture(scope="module")
def example1():
    points, normals = jurs.datasets.example1(120)
    reference = jurs.fit(
        points, normals, grid=9, offset=0.1, eps=0.01, solver=jurs.LeastSquares(lam=LAM)
    )
    return points, normals, float(reference.metrics["E"])


@pytest.mark.parametrize(
    "solver",
    [
        jurs.JaxoptLBFGS(lam=LAM, max_steps=3000, tol=1e-9),
        jurs.JaxoptGaussNewton(lam=LAM, max_steps=20, tol=1e-10),
        jurs.JaxoptLevenbergMarquardt(lam=LAM, max_steps=50, tol=1e-10),
    ],
    ids=["LBFGS", "GaussNewton", "LevenbergMarquardt"],
)
@pytest.mark.slow
def test_fixed_weight_jaxopt_solvers_agree_with_least_squares(example1, solver):
    points, normals, reference = example1
    sol = jurs.fit(points, normals, grid=9, offset=0.1, eps=0.01, solver=solver)
    energy = float(sol.metrics["E"])
    assert abs(energy - reference) <= 1e-6 * reference
    history = np.asarray(sol.stats["energy_history"])
    assert history[1] < history[0]


@pytest.mark.slow
def test_joint_jaxopt_levenberg_marquardt_improves_on_the_bspline(example1):
    points, normals, reference = example1
    solver = jurs.JaxoptLevenbergMarquardt(
        lam=LAM,
        joint=True,
        max_steps=30,
        options=(("solver", "cholesky"), ("materialize_jac", True)),
    )
    sol = jurs.fit(points, normals, grid=9, offset=0.1, eps=0.01, solver=solver)
    assert float(sol.metrics["E"]) < reference
    assert float(sol.spline.weights.min()) > 0


def test_bad_arguments():
    with pytest.raises(ValueError, match="lam"):
        jurs.JaxoptLBFGS(lam=-1.0)
    with pytest.raises(ValueError, match="tol"):
        jurs.JaxoptGaussNewton(tol=-1.0)
