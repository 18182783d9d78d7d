"""jurs.fit keeps small clouds by content: a fit that repeats its arrays checks, measures
and lays them out once, and any change to the arrays builds a new cloud."""

import jax.numpy as jnp
import numpy as np
from conftest import PAPER

import jurs
from jurs._cloud import cloud as cloud_module
from jurs._fit import fit as fit_module


def _count_clouds(monkeypatch) -> list:
    built = []
    original = cloud_module.Cloud.__init__

    def counting(self, *args, **kwargs):
        built.append(1)
        original(self, *args, **kwargs)

    monkeypatch.setattr(cloud_module.Cloud, "__init__", counting)
    monkeypatch.setattr(fit_module, "_kept_clouds", type(fit_module._kept_clouds)())
    return built


def test_repeated_fit_builds_its_cloud_once(monkeypatch):
    built = _count_clouds(monkeypatch)
    points, normals = jurs.datasets.example1(120)
    solver = jurs.LeastSquares(lam=1e-4)
    first = jurs.fit(points, normals, solver=solver, **PAPER)
    again = jurs.fit(np.array(points), jnp.asarray(normals), solver=solver, **PAPER)
    assert len(built) == 2  # a JAX array is not the same input as a NumPy one
    third = jurs.fit(np.array(points), jnp.asarray(normals), solver=solver, **PAPER)
    assert len(built) == 2
    np.testing.assert_array_equal(first.spline.control, again.spline.control)
    np.testing.assert_array_equal(first.spline.control, third.spline.control)
    moved = np.array(points)
    moved[0, 0] += 1e-3
    changed = jurs.fit(moved, normals, solver=solver, **PAPER)
    assert len(built) == 3
    assert not np.array_equal(changed.spline.control, first.spline.control)


def test_large_clouds_are_not_kept(monkeypatch):
    built = _count_clouds(monkeypatch)
    monkeypatch.setattr(fit_module, "KEPT_CLOUD_POINTS", 100)
    points, normals = jurs.datasets.example1(120)
    for _ in range(2):
        jurs.fit(points, normals, solver=jurs.LeastSquares(lam=1e-4), **PAPER)
    assert len(built) == 2
    assert len(fit_module._kept_clouds) == 0
