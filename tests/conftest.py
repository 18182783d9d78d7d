"""Shared test setup: the maths runs in float64 (E_ave sits at 1e-6..1e-8)."""

import os

import equinox as eqx
import jax
import matplotlib
import numpy as np
import pytest
from scipy.interpolate import BSpline

jax.config.update("jax_enable_x64", True)
# jurs.cli.main turns JAX's persistent compilation cache on (in the user's cache folder) for
# the rest of its process: in-process CLI calls in tests would then write there and change
# what later tests in the same worker compile. Tests of the cache itself run subprocesses
# with their own environment (tests/test_startup.py).
os.environ["JURS_NO_COMPILATION_CACHE"] = "1"
matplotlib.use("Agg")


#: The paper's Example 1 settings (fit's defaults are chosen from the data instead).
PAPER = dict(grid=(9, 9), offset=0.1, eps=0.01)


def dense_basis(xy, lower, upper, shape):
    """All N*M tensor-product B-spline values at ``xy`` as a dense (n, N*M) matrix, built
    independently of jurs with scipy (knots: uniform, extended 3 cells past the box)."""
    columns = []
    for axis in range(2):
        n = shape[axis]
        h = (upper[axis] - lower[axis]) / (n - 3)
        knots = lower[axis] + (np.arange(n + 4) - 3.0) * h
        columns.append(BSpline.design_matrix(np.asarray(xy)[:, axis], knots, 3).toarray())
    bx, by = columns
    return (bx[:, :, None] * by[:, None, :]).reshape(len(xy), -1)


def dense_collocation(problem, weights):
    """D of eq. 23 (rows w_ij B_ij / W), dense, in the problem's slot order (test sizes only)."""
    basis = dense_basis(
        np.asarray(problem.samples),
        np.asarray(problem.lower),
        np.asarray(problem.upper),
        problem.shape,
    )
    wb = basis * np.asarray(weights).ravel()[None, :]
    return wb / wb.sum(axis=1, keepdims=True)


TABLE_FIELDS = ("terms", "terms_t", "index", "corner", "order", "position", "filled")


def without_table(problem):
    """The same problem with its basis in the power form only (as a traced build has it)."""
    return eqx.tree_at(
        lambda p: tuple(getattr(p.local, f) for f in TABLE_FIELDS),
        problem,
        (None,) * len(TABLE_FIELDS),
        is_leaf=lambda x: x is None,
    )


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def example1_cloud():
    """The paper's Example 1 at 120 points: ``(points, normals)``."""
    import jurs

    return jurs.datasets.example1(120)
