"""The uniform cubic basis, the local-term maps and the spline evaluation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import dense_basis, without_table
from jax.test_util import check_grads

import jurs
from jurs._model import basis as jurs_basis
from jurs._model.basis import (
    CENTRED_POWER,
    grid_to_patches,
    patch_to_power,
    patches_to_grid,
    power_values,
)


def random_points(rng, n, lower=(-1.0, 2.0), upper=(3.0, 5.0)):
    lower, upper = np.asarray(lower), np.asarray(upper)
    return lower + (upper - lower) * rng.random((n, 2)), lower, upper


@pytest.mark.parametrize("shape", [(4, 4), (9, 9), (7, 12)])
def test_partition_of_unity(rng, shape):
    xy, lower, upper = random_points(rng, 500)
    local = jurs.internal.local_basis(
        jnp.asarray(xy), jnp.asarray(lower), jnp.asarray(upper), shape
    )
    sums = np.asarray(local.products.sum(axis=1))
    np.testing.assert_allclose(sums, 1.0, atol=1e-14)
    assert np.all(np.asarray(local.products) >= 0)
    # On the box corners too (the last cell is closed on the right).
    corners = jnp.asarray([lower, upper, [lower[0], upper[1]]])
    corner_sums = jurs.internal.local_basis(
        corners, jnp.asarray(lower), jnp.asarray(upper), shape
    ).products.sum(1)
    np.testing.assert_allclose(np.asarray(corner_sums), 1.0, atol=1e-14)


@pytest.mark.parametrize("shape", [(4, 5), (9, 9), (13, 8)])
def test_basis_matches_scipy(rng, shape):
    xy, lower, upper = random_points(rng, 200)
    local = jurs.internal.local_basis(
        jnp.asarray(xy), jnp.asarray(lower), jnp.asarray(upper), shape
    )
    # Scatter the 16 local terms into a dense row per point.
    ours = np.zeros((len(xy), shape[0] * shape[1]))
    patch_index = np.asarray(grid_to_patches(jnp.arange(shape[0] * shape[1]).reshape(shape)))
    cols = patch_index[np.asarray(local.cell)]
    np.put_along_axis(ours, cols, np.asarray(local.products), axis=1)
    np.testing.assert_allclose(ours, dense_basis(xy, lower, upper, shape), atol=1e-14)


def test_cubic_derivatives_match_autodiff():
    t = jnp.linspace(-0.2, 1.2, 31)
    auto = jax.vmap(jax.jacfwd(jurs.internal.cubic_weights))(t)
    np.testing.assert_allclose(
        np.asarray(jurs.internal.cubic_derivatives(t)), np.asarray(auto), atol=1e-14
    )


def test_patch_maps_are_adjoint(rng):
    shape = (8, 6)
    grid = jnp.asarray(rng.standard_normal(shape))
    patches = jnp.asarray(rng.standard_normal(((shape[0] - 3) * (shape[1] - 3), 16)))
    lhs = jnp.vdot(grid_to_patches(grid), patches)
    rhs = jnp.vdot(grid, patches_to_grid(patches, shape))
    np.testing.assert_allclose(float(lhs), float(rhs), rtol=1e-13)


def test_windowed_patch_gather_matches_the_cell_patches(rng):
    """The table form's one-window-a-bucket gather reads the same 16 coefficients, in the
    same order, as grid_to_patches gives each cell, for every grid of a stack."""
    from jurs._model.spline import gather_patches

    shape = (9, 7)
    grids = jnp.asarray(rng.standard_normal((3,) + shape))
    cells = rng.integers(0, (shape[0] - 3) * (shape[1] - 3), size=40)
    corner = jnp.asarray(np.stack([cells // (shape[1] - 3), cells % (shape[1] - 3)], 1), jnp.int32)
    got = np.asarray(gather_patches(grids, corner))  # (buckets, grids, 16)
    want = np.stack([np.asarray(grid_to_patches(g))[cells] for g in grids], axis=1)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("bucket_size", [1, 4])
@pytest.mark.slow
def test_transpose_is_adjoint_of_values(rng, bucket_size):
    points, normals = jurs.datasets.example1(400)
    problem = jurs.make_problem(points, normals, grid=(8, 7), bucket_size=bucket_size)
    grid = jnp.asarray(rng.standard_normal((8, 7)))
    values = jnp.asarray(rng.standard_normal(problem.samples.shape[0]))
    lhs = jnp.vdot(jurs.internal.bspline_values(problem.local, grid), values)
    rhs = jnp.vdot(grid, jurs.internal.bspline_transpose(problem.local, values, problem.shape))
    np.testing.assert_allclose(float(lhs), float(rhs), rtol=1e-12)


def test_rational_evaluation_against_definition(rng):
    shape = (7, 9)
    xy, lower, upper = random_points(rng, 100)
    control = rng.standard_normal(shape)
    weights = 0.5 + rng.random(shape)
    spline = jurs.ImplicitSpline(
        jnp.asarray(control), jnp.asarray(weights), jnp.asarray(lower), jnp.asarray(upper)
    )
    basis = dense_basis(xy, lower, upper, shape)
    expected = basis @ (weights * control).ravel() / (basis @ weights.ravel())  # eq. 14
    np.testing.assert_allclose(
        np.asarray(spline(jnp.asarray(xy))), expected, rtol=1e-12, atol=1e-14
    )
    # One point in, one value out.
    np.testing.assert_allclose(float(spline(jnp.asarray(xy[0]))), expected[0], rtol=1e-12)
    # All weights 1: the B-spline f of eq. 2.
    bspline = jurs.ImplicitSpline.bspline(jnp.asarray(control), lower, upper)
    np.testing.assert_allclose(
        np.asarray(bspline(jnp.asarray(xy))), basis @ control.ravel(), atol=1e-12
    )


@pytest.mark.slow
def test_check_grads_spline_evaluation(rng):
    shape = (6, 6)
    xy, lower, upper = random_points(rng, 20)
    lower, upper = jnp.asarray(lower), jnp.asarray(upper)

    def evaluate(control, weights, xy):
        return jurs.ImplicitSpline(control, weights, lower, upper)(xy)

    args = (
        jnp.asarray(rng.standard_normal(shape)),
        jnp.asarray(0.5 + rng.random(shape)),
        jnp.asarray(xy),
    )
    check_grads(evaluate, args, order=2, modes=("fwd", "rev"), eps=1e-6)


@pytest.mark.slow
def test_spatial_gradient(rng):
    shape = (8, 8)
    xy, lower, upper = random_points(rng, 10)
    spline = jurs.ImplicitSpline(
        jnp.asarray(rng.standard_normal(shape)),
        jnp.asarray(0.5 + rng.random(shape)),
        jnp.asarray(lower),
        jnp.asarray(upper),
    )
    grad = np.asarray(spline.grad(jnp.asarray(xy)))
    h = 1e-6
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = h
        fd = (
            np.asarray(spline(jnp.asarray(xy + step))) - np.asarray(spline(jnp.asarray(xy - step)))
        ) / (2 * h)
        np.testing.assert_allclose(grad[:, axis], fd, rtol=1e-6, atol=1e-8)


def test_spline_rejects_bad_grids():
    with pytest.raises(ValueError, match="at least 4"):
        jurs.ImplicitSpline(jnp.zeros((3, 5)), jnp.ones((3, 5)), jnp.zeros(2), jnp.ones(2))
    with pytest.raises(ValueError, match="matching"):
        jurs.ImplicitSpline(jnp.zeros((5, 5)), jnp.ones((5, 6)), jnp.zeros(2), jnp.ones(2))


def test_bucket_layout_groups_samples_by_cell():
    points, normals = jurs.datasets.example1(300)
    flat = jurs.make_problem(points, normals, grid=(10, 10), bucket_size=1)
    bucketed = jurs.make_problem(points, normals, grid=(10, 10), bucket_size=8)
    k = bucketed.local.bucket_size
    cells = np.asarray(bucketed.local.cell).reshape(-1, k)
    assert (cells == cells[:, :1]).all(), "a bucket spans one cell"
    index = np.asarray(bucketed.sample_index)[np.asarray(bucketed.mask) > 0]
    assert sorted(index.tolist()) == list(range(900)), "every sample in exactly one real slot"
    np.testing.assert_allclose(
        np.asarray(bucketed.samples)[np.asarray(bucketed.mask) > 0], np.asarray(flat.samples)[index]
    )
    assert float(bucketed.is_data.sum()) == 300


def test_centred_power_basis_is_the_cubic_basis(rng):
    s = jnp.asarray(rng.random(50) - 0.5)
    powers = jnp.stack([s**p for p in range(4)], axis=-1)
    np.testing.assert_allclose(
        np.asarray(powers @ jnp.asarray(CENTRED_POWER.T)),
        np.asarray(jurs.internal.cubic_weights(s + 0.5)),
        atol=1e-15,
    )
    # A cell's patch in powers of (sx, sy) evaluates to the same bicubic as in B-splines.
    patch = rng.standard_normal(16)
    sx, sy = (jnp.asarray(rng.random(30) - 0.5) for _ in range(2))
    coeffs = patch @ patch_to_power()
    by_basis = (
        jurs_basis.tensor_basis(
            jurs.internal.cubic_weights(sx + 0.5), jurs.internal.cubic_weights(sy + 0.5)
        )
        @ patch
    )
    np.testing.assert_allclose(
        np.asarray(power_values(list(coeffs), sx, sy)), np.asarray(by_basis), rtol=1e-13, atol=1e-15
    )


@pytest.mark.slow
def test_table_and_power_forms_agree(rng):
    """Small concrete problems keep the paper's order with a table of their own buckets;
    F and T match the power form (one sample a bucket, and bucketed) on the same samples."""
    points, normals = jurs.datasets.example1(700)
    table = jurs.make_problem(points, normals, grid=(11, 9))
    assert table.local.terms is not None and table.local.bucket_size == 1
    np.testing.assert_array_equal(np.asarray(table.sample_index), np.arange(2100))
    local = table.local
    assert np.all(
        np.asarray(local.to_layout(jnp.arange(2100.0)))[np.asarray(local.position)]
        == np.arange(2100)
    ), "to_layout and position are inverse"
    cells = np.asarray(local.cell)[np.asarray(local.order)].reshape(local.index.shape[0], -1)
    assert (cells == cells[:, :1]).all(), "a table bucket spans one cell"
    power = without_table(table)
    bucketed = jurs.make_problem(points, normals, grid=(11, 9), bucket_size=8)
    real = np.asarray(bucketed.mask) > 0
    index = np.asarray(bucketed.sample_index)[real]
    grids = jnp.asarray(rng.standard_normal((2, 11, 9)))
    values = jnp.asarray(rng.standard_normal((2, 2100)))
    expected = np.asarray(jurs.internal.bspline_values(power.local, grids))
    np.testing.assert_allclose(
        np.asarray(jurs.internal.bspline_values(local, grids)), expected, rtol=1e-13, atol=1e-14
    )
    np.testing.assert_allclose(
        np.asarray(jurs.internal.bspline_values(bucketed.local, grids))[:, real],
        expected[:, index],
        rtol=1e-13,
        atol=1e-14,
    )
    expected = np.asarray(jurs.internal.bspline_transpose(power.local, values, (11, 9)))
    np.testing.assert_allclose(
        np.asarray(jurs.internal.bspline_transpose(local, values, (11, 9))),
        expected,
        rtol=1e-12,
        atol=1e-13,
    )
    spread = (
        jnp.zeros((2, bucketed.samples.shape[0])).at[:, np.nonzero(real)[0]].set(values[:, index])
    )
    np.testing.assert_allclose(
        np.asarray(jurs.internal.bspline_transpose(bucketed.local, spread, (11, 9))),
        expected,
        rtol=1e-12,
        atol=1e-13,
    )


def test_bucket_layout_pads_to_a_rounded_count():
    cells = np.array([3, 0, 3, 3, 1, 3, 0])
    slot_sample, valid = jurs.internal.bucket_layout(cells, 2, 5, num_buckets=6)
    assert slot_sample.shape == (12,) and valid.sum() == 7
    slots = slot_sample.reshape(-1, 2)
    assert (cells[slots] == cells[slots[:, :1]]).all()
    assert sorted(slot_sample[valid].tolist()) == list(range(7))
    assert not valid[8:].any(), "appended buckets are empty"
    assert np.all(np.diff(cells[slots[:, 0]]) >= 0), "buckets in cell order"


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_host_and_traced_problems_agree(dtype):
    """make_problem lays small concrete problems out on the host in NumPy and traced ones
    out in XLA: the same arithmetic, so the same samples, box, cells and coordinates, in
    the requested dtype (NumPy would promote float32 - int32 to float64)."""
    points, normals = jurs.datasets.example1(50)
    mask = np.arange(50) < 45  # exercises the masked bounding box too
    kw = dict(grid=(7, 9), offset=0.1, eps=0.01, dtype=dtype, mask=mask)
    host = jurs.make_problem(points, normals, **kw)
    traced = jax.jit(lambda p, n: jurs.make_problem(p, n, **kw))(points, normals)
    assert host.local.terms is not None and traced.local.terms is None  # the two paths
    for leaf in jax.tree_util.tree_leaves(host):
        assert leaf.dtype in (dtype, jnp.int32), leaf.dtype
    rtol = 1e-6 if dtype == jnp.float32 else 1e-14
    for name in (
        "points",
        "normals",
        "samples",
        "targets",
        "mask",
        "is_data",
        "lower",
        "upper",
        "offset",
        "eps",
    ):
        np.testing.assert_allclose(
            np.asarray(getattr(host, name)),
            np.asarray(getattr(traced, name)),
            rtol=rtol,
            atol=rtol,
            err_msg=name,
        )
    np.testing.assert_array_equal(np.asarray(host.local.cell), np.asarray(traced.local.cell))
    np.testing.assert_allclose(
        np.asarray(host.local.s), np.asarray(traced.local.s), rtol=rtol, atol=10 * rtol
    )
