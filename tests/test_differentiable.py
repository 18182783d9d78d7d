"""Fits inside JAX programs: jax.grad through a fit (checked against central finite
differences in float64) and jax.vmap over a padded batch of point clouds."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

import jurs

# Every test here takes several seconds (compiles and long iterations): make test-fast skips them.
pytestmark = pytest.mark.slow

jax.config.update("jax_enable_x64", True)

HELD_OUT = jnp.asarray(jurs.datasets.example1(37)[0]) * 1.02  # near, not on, the data

SOLVERS = {
    "LeastSquares": lambda lam: jurs.LeastSquares(lam=lam),
    "LeastSquares(CG)": lambda lam: jurs.LeastSquares(
        lam=lam, linear_solver=lx.CG(rtol=1e-13, atol=1e-16, max_steps=2000)
    ),
    # B-spline Gauss-Newton; gradients by optimistix's implicit adjoint.
    "optx.GaussNewton": lambda lam: jurs.OptimistixLeastSquares(
        optx.GaussNewton(rtol=1e-12, atol=1e-14), lam=lam, max_steps=20
    ),
}


def validation_loss(points, normals, lam, make_solver):
    """Mean g^2 of the fitted spline at held-out points."""
    sol = jurs.fit(points, normals, grid=8, solver=make_solver(lam), offset=0.1, eps=0.01)
    return jnp.mean(sol.spline(HELD_OUT) ** 2)


@pytest.mark.parametrize("name", list(SOLVERS))
def test_grad_matches_central_differences(name):
    make_solver = SOLVERS[name]
    points, normals = jurs.datasets.example1(60)
    # Jittered: on the symmetric curve two offset samples tie for the box's largest y
    # (jurs.fit takes its domain from the samples' min and max). At a tie the box has a
    # kink: JAX's max splits the gradient between the two, which central differences
    # match, but where the device's rounding breaks the tie (a GPU's does) the gradient is
    # one side's, 1.4 % off the differences here. Away from ties both are exact.
    points = points + 1e-3 * np.random.default_rng(0).standard_normal(points.shape)
    points, normals = jnp.asarray(points), jnp.asarray(normals)
    lam = jnp.asarray(1e-3)
    # One compiled program gives the gradient and, for the differences, the loss: a jit of
    # the loss alone would compile the fit a second time (seconds; the value is the same
    # forward computation).
    value_and_grad = jax.jit(
        jax.value_and_grad(
            lambda p, n, lam: validation_loss(p, n, lam, make_solver), argnums=(0, 1, 2)
        )
    )
    _, grads = value_and_grad(points, normals, lam)
    key_p, key_n = jax.random.split(jax.random.PRNGKey(0))
    directions = (
        jax.random.normal(key_p, points.shape),
        jax.random.normal(key_n, normals.shape),
        jnp.asarray(1e-3),
    )
    for k, (arg, grad, direction) in enumerate(zip((points, normals, lam), grads, directions)):
        h = 1e-5 if k < 2 else 1e-7

        def moved(t):
            args = [points, normals, lam]
            args[k] = arg + t * direction
            return value_and_grad(*args)[0]

        fd = (moved(h) - moved(-h)) / (2 * h)
        ad = jnp.vdot(grad, direction)
        assert abs(float(fd)) > 1e-12, (name, k)  # a real dependence, not 0 == 0
        assert abs(float(ad - fd)) <= 1e-5 * abs(float(fd)), (name, k, float(ad), float(fd))


def _pad(points, normals, size):
    extra = size - len(points)
    mask = np.arange(size) < len(points)
    # Padding: copies of the first point (finite, inside the box), masked out.
    return (
        np.concatenate([points, np.repeat(points[:1], extra, 0)]),
        np.concatenate([normals, np.repeat(normals[:1], extra, 0)]),
        mask,
    )


def test_vmap_over_padded_batch_matches_single_fits():
    # Three sizes in one band of the size ladder (padded to 96 each): the single fits
    # share one compilation, and the batch still pads two clouds (to 90 points).
    clouds = [
        jurs.datasets.example1(90),
        jurs.datasets.example1(82),
        jurs.datasets.ellipse(86, a=3.0, b=2.0),
    ]
    size = max(len(p) for p, _ in clouds)
    batch = [_pad(p, n, size) for p, n in clouds]
    points, normals, masks = (np.stack(x) for x in zip(*batch))
    solver = jurs.LeastSquares(lam=1e-4)

    def fit_one(p, n, mask):
        sol = jurs.fit(p, n, grid=8, offset=0.1, eps=0.01, solver=solver, mask=mask)
        return sol.spline.control, sol.spline.lower, sol.metrics["E"], sol.metrics["E_ave"]

    batched = jax.vmap(fit_one)(points, normals, masks)
    for k, (p, n) in enumerate(clouds):
        single = jurs.fit(p, n, grid=8, offset=0.1, eps=0.01, solver=solver)
        np.testing.assert_allclose(batched[0][k], single.spline.control, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batched[1][k], single.spline.lower, rtol=1e-12)
        np.testing.assert_allclose(batched[2][k], single.metrics["E"], rtol=1e-9)
        np.testing.assert_allclose(batched[3][k], single.metrics["E_ave"], rtol=1e-9)
