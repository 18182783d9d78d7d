"""The sum-of-levels fit of benchmarks/thb_vs_levels.py: its level matrices and its lattice
evaluation agree, and the cascade fits a circle as THB does."""

import numpy as np

import jurs

from .. import thb_vs_levels as levels


def _circle(m=200):
    t = np.linspace(0, 2 * np.pi, m, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    return points, points.copy()


def test_level_matrices_and_lattice_values_agree():
    """A level's spline read through its basis matrix at lattice nodes equals its
    separable lattice evaluation; every row of the basis sums to 1 where all 16 functions
    are active (level 0: all of them)."""
    rng = np.random.default_rng(0)
    cells, lower, upper = np.array([6, 5]), np.array([-1.0, -1.0]), np.array([2.0, 1.5])
    width = (upper - lower) / cells
    omega = np.stack(np.meshgrid(np.arange(6), np.arange(5), indexing="ij"), -1).reshape(-1, 2)
    keys = levels.level_functions(cells, omega)
    assert len(keys) == (6 + 3) * (5 + 3)
    xs, ys = np.linspace(-1.0, 2.0, 13), np.linspace(-1.0, 1.5, 11)
    nodes = np.stack(np.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    basis, regulariser = levels.level_matrices(nodes, lower, width, cells, keys)
    np.testing.assert_allclose(np.asarray(basis.sum(1)).ravel(), 1.0, atol=1e-12)
    coeffs = rng.normal(size=len(keys))
    lattice = levels.level_values(coeffs, keys, cells, lower, width, xs, ys)
    np.testing.assert_allclose(lattice.ravel(), basis @ coeffs, atol=1e-12)
    # eq. 31 on the level: no penalty on a constant, a positive one on anything else.
    assert abs(np.ones(len(keys)) @ regulariser @ np.ones(len(keys))) < 1e-9
    assert coeffs @ regulariser @ coeffs > 0


def test_the_cascade_fits_a_circle_as_thb_does():
    points, normals = _circle()
    settings = jurs.auto_settings(points, normals)
    fit = levels.sum_of_levels(points, normals, settings, sweeps=1)
    assert fit["levels"] >= 2 and len(fit["passes"]) == 2
    thb = jurs.fit_adaptive(points, normals, settings=settings, checks=False)
    assert fit["functions"] > sum(thb.stats["active"])  # untruncated: more functions
    xs = np.linspace(-1.3, 1.3, 27)
    sum_values = sum(
        levels.level_values(c, keys, cells, fit["lower"], width, xs, xs)
        for (cells, width, keys, _, _), c in zip(fit["structure"], fit["passes"][-1]["coeffs"])
    )
    nodes = np.stack(np.meshgrid(xs, xs, indexing="xy"), -1).reshape(-1, 2)
    thb_values = np.asarray(thb.spline(nodes)).reshape(27, 27)
    # The same sign pattern away from the circle (the two slopes differ: each level has
    # its own regulariser), and the offset samples' targets met to a small fraction of eps.
    distance = np.abs(np.linalg.norm(nodes, axis=1) - 1.0).reshape(27, 27)
    far = distance > 0.15
    assert np.array_equal(np.sign(sum_values[far]), np.sign(thb_values[far]))
    for done in fit["passes"]:
        assert done["rms_residual"] < 0.01 * settings.eps
