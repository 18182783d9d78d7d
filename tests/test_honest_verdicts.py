"""Verdicts that mean what they say (issue 54): a closed shape fitted inside out is not
``successful``; ``E_ave`` and ``E_max`` are the same measurement on every basis; small
closed parts the data do not carry are supplementary and make a fit ``doubtful``."""

import equinox as eqx
import numpy as np
import pytest

import jurs

BASES = ("uniform", "adaptive")


def _data_metrics(sol, points):
    """``(mean g^2, max |g|)`` at ``points``, from the fitted spline itself."""
    g = np.asarray(sol.spline(np.asarray(points)))
    return float(np.mean(g * g)), float(np.max(np.abs(g)))


@pytest.fixture(scope="module")
def curve():
    return jurs.datasets.example1(120)


@pytest.fixture(scope="module")
def sphere():
    return jurs.datasets.sphere3d(400, seed=1)


@pytest.mark.parametrize("basis", BASES)
@pytest.mark.parametrize("shape", ["curve", "sphere"])
def test_inward_normals_are_refused(shape, basis, request):
    """Every normal pointing inward: the fit followed its offsets into a g positive
    inside, passed every orientation check (the normals agree with each other) and was
    ``successful``. The same cloud with outward normals keeps its verdict."""
    points, normals = request.getfixturevalue(shape)
    good = jurs.fit(points, normals, basis=basis, throw=False)
    assert good.status == "successful", good.stats.get("doubts")
    assert float(good.metrics["border_negative_fraction"]) == 0.0
    bad = jurs.fit(points, -normals, basis=basis, throw=False)
    assert bad.status == "inconsistent_normals"
    assert float(bad.metrics["border_negative_fraction"]) == 1.0
    (doubt,) = bad.stats["doubts"]
    assert "inward" in doubt and "-normals" in doubt
    # Indeed inside out: positive at the centre, where the data enclose.
    assert float(bad.spline(np.mean(points, axis=0)[None])[0]) > 0
    with pytest.raises(eqx.EquinoxRuntimeError, match="inward"):
        jurs.fit(points, -normals, basis=basis)


def test_an_open_profile_is_not_judged_inside_out():
    """An open curve has no inside: its zero set crosses the box's border, which reads
    both signs, whichever side the normals face."""
    x = np.linspace(-1.0, 1.0, 150)
    points = np.stack([x, 0.3 * np.sin(3.0 * x)], axis=1)
    normals = np.stack([-0.9 * np.cos(3.0 * x), np.ones_like(x)], axis=1)
    for sign in (1.0, -1.0):
        sol = jurs.fit(points, sign * normals, throw=False)
        assert sol.status != "inconsistent_normals", sol.stats.get("doubts")
        assert 0.0 < float(sol.metrics["border_negative_fraction"]) < 1.0


@pytest.mark.parametrize("shape", ["curve", "sphere"])
def test_e_ave_and_e_max_mean_the_same_on_both_bases(shape, request):
    """``E_ave`` is the mean of g^2 and ``E_max`` the largest |g| at the data points on
    either basis: the hierarchy's ``E_ave`` was ``E_d / 3m``, the offset samples
    included (about eps^2 / 1.5 on a good fit, whatever the fit did at the points)."""
    points, normals = request.getfixturevalue(shape)
    for basis in BASES:
        sol = jurs.fit(points, normals, basis=basis, throw=False)
        e_ave, e_max = _data_metrics(sol, points)
        np.testing.assert_allclose(float(sol.metrics["E_ave"]), e_ave, rtol=1e-9, err_msg=basis)
        np.testing.assert_allclose(float(sol.metrics["E_max"]), e_max, rtol=1e-9, err_msg=basis)
