"""A surface's slots gathered by cell (``jurs.internal.with_groups``), the warm start of the
robust fit's later solves, and the host measurements' shared KD-trees: each a faster path
to the same numbers as the one it replaces."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

import jurs
from jurs._cloud.measure import query_all
from jurs._problem.layout import MIN_GROUP_SIZE, cell_groups

jax.config.update("jax_enable_x64", True)

NO_GROUPS = dict(group_slot=None, group_filled=None, group_position=None)


def _without_groups(problem):
    return dataclasses.replace(problem, local=dataclasses.replace(problem.local, **NO_GROUPS))


@pytest.fixture(scope="module")
def surface():
    """A noisy sphere laid out as jurs.fit lays it out (stable shapes: grouped)."""
    points, normals = jurs.datasets.sphere3d(6000, seed=3)
    rng = np.random.default_rng(0)
    points = points + 0.01 * rng.standard_normal(points.shape)
    problem = jurs.make_problem(points, normals, grid=14, offset=0.04, eps=0.04, stable_shapes=True)
    return problem


def test_a_surface_problem_is_grouped_by_cell(surface):
    local = surface.local
    assert local.group_slot is not None and local.group_filled is not None
    slot, filled = np.asarray(local.group_slot), np.asarray(local.group_filled) > 0
    assert slot.shape[1] >= MIN_GROUP_SIZE
    # Every slot exactly once among the real entries, each group within one cell.
    assert np.array_equal(np.sort(slot[filled]), np.arange(local.cell.shape[0]))
    cells = np.asarray(local.cell)[slot]
    assert (cells == cells[:, :1]).all()
    assert np.all(np.diff(cells[:, 0]) >= 0)  # groups in cell order: a sorted scatter
    position = np.asarray(local.group_position)
    assert np.array_equal(slot.reshape(-1)[position], np.arange(local.cell.shape[0]))


def test_plain_make_problem_keeps_one_sample_a_slot():
    points, normals = jurs.datasets.sphere3d(500, seed=1)
    problem = jurs.make_problem(points, normals, grid=8, offset=0.05, eps=0.05)
    assert problem.local.group_slot is None


def test_sparse_clouds_are_not_grouped():
    cells = np.arange(100)  # one sample a cell
    assert cell_groups(cells, 200) is None


@pytest.mark.parametrize("reweighed", [False, True])
def test_grouped_assembly_equals_the_scatter(surface, reweighed):
    """The normal equations from the groups equal those of one sample a slot, with the
    mask as built or changed afterwards (the robust fit's weights)."""
    problem = surface
    if reweighed:
        weights = np.random.default_rng(1).random(problem.mask.shape[0])
        problem = dataclasses.replace(problem, mask=problem.mask * jnp.asarray(weights))
    grouped = jurs.internal.normal_equations(problem)
    plain = jurs.internal.normal_equations(_without_groups(problem))
    scale = float(jnp.max(jnp.abs(plain.stencil)))
    assert float(jnp.max(jnp.abs(grouped.stencil - plain.stencil))) < 1e-13 * scale
    np.testing.assert_allclose(
        grouped.rhs, plain.rhs, rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(plain.rhs)))
    )


def test_grouped_values_equal_the_gather(surface):
    rng = np.random.default_rng(2)
    grids = jnp.asarray(rng.standard_normal((2,) + surface.shape))
    grouped = jurs.internal.bspline_values(surface.local, grids)
    plain = jurs.internal.bspline_values(_without_groups(surface).local, grids)
    np.testing.assert_allclose(grouped, plain, rtol=0, atol=1e-13)
    # ... and their derivatives (F is linear: its transpose through the groups).
    loss = lambda local, g: jnp.sum(jnp.sin(jurs.internal.bspline_values(local, g)))  # noqa: E731
    d_grouped = jax.grad(loss, argnums=1)(surface.local, grids[0])
    d_plain = jax.grad(loss, argnums=1)(_without_groups(surface).local, grids[0])
    np.testing.assert_allclose(d_grouped, d_plain, rtol=0, atol=1e-12)


def test_warm_solve_skips_the_cascade_and_reaches_the_same_fit(surface, monkeypatch):
    """A solve started from a fit of the same problem (warm) runs no cascade and lands
    on the cold solve's fit, to the final CG's tolerance."""
    from jurs.solvers import _least_squares

    solver = jurs.LeastSquares(lam=1e-3)
    ones = jnp.ones(surface.shape)
    cold, _ = jax.jit(lambda p: solver.minimise(p, ones, jnp.zeros(surface.shape)))(surface)
    traced, _ = jax.jit(lambda p, c: solver.minimise(p, ones, c, jnp.array(True)))(surface, cold)

    def no_cascade(*args):
        raise AssertionError("a warm solve ran the cascade")

    monkeypatch.setattr(_least_squares, "cascadic_start", no_cascade)
    warm, _ = jax.jit(lambda p, c: solver.minimise(p, ones, c, True))(surface, cold)
    scale = float(jnp.max(jnp.abs(cold)))
    for fit in (warm, traced):
        assert float(jnp.max(jnp.abs(fit - cold))) < 0.02 * scale


def test_query_all_equals_the_tree_query():
    rng = np.random.default_rng(4)
    points = rng.random((3000, 3))
    tree = cKDTree(points)
    dist, index = query_all(tree, points, 5)
    want_dist, want_index = tree.query(points, k=5)
    np.testing.assert_array_equal(index, want_index)
    np.testing.assert_array_equal(dist, want_dist)
    other = rng.random((3000, 3))  # not the tree's points: still the same answers
    np.testing.assert_array_equal(query_all(tree, other, 3)[1], tree.query(other, k=3)[1])


def test_cloud_keeps_one_tree_without_the_points_set_aside():
    points, normals = jurs.datasets.sphere3d(400, seed=5)
    cloud = jurs.Cloud(points, normals)
    assert cloud.tree_without(()) is cloud.tree
    tree = cloud.tree_without((3, 7))
    assert cloud.tree_without((3, 7)) is tree  # built once
    assert tree.n == 398
    np.testing.assert_array_equal(tree.data, np.delete(cloud.points, [3, 7], axis=0))
