"""The adaptive (THB) basis: its defining properties, exactness against the uniform
basis, and fits on it (value, agreement with the uniform fit, derivatives)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs._fit.adaptive import adaptive_layout, solve_adaptive, solve_direct
from jurs._model.hierarchy import cube_offsets, ravel_keys, unravel_keys
from jurs._problem.adaptive import (
    adaptive_metrics,
    assemble_adaptive_problem,
    assembled_metrics,
    at_points,
    make_adaptive_problem,
)
from jurs.internal import build_hierarchy, cascade, hierarchy_values, refine_near


def _hierarchy(ndim, levels=None, band=1, seed=0):
    levels = (2 if ndim == 2 else 1) if levels is None else levels
    rng = np.random.default_rng(seed)
    base = (5, 4) if ndim == 2 else (3, 4, 3)
    lower, upper = np.zeros(ndim), np.asarray(base, float) / 2
    points = rng.uniform(0.3, 1.2, (6, ndim))
    return build_hierarchy(
        lower, upper, base, refine_near(lower, upper, base, levels, points, band)
    )


def _random_points(hierarchy, count, seed=1):
    rng = np.random.default_rng(seed)
    lower, upper = np.asarray(hierarchy.lower), np.asarray(hierarchy.upper)
    return jnp.asarray(rng.uniform(lower, upper, (count, hierarchy.ndim)))


@pytest.mark.parametrize("ndim", [2, 3])
def test_partition_of_unity_and_nonnegative(ndim):
    hierarchy = _hierarchy(ndim)
    assert hierarchy.num_levels > 1  # the test is about a real hierarchy
    x = _random_points(hierarchy, 400 if ndim == 3 else 2000)
    values = hierarchy_values(hierarchy, jnp.eye(hierarchy.num_active), x)  # (n, m)
    np.testing.assert_allclose(values.sum(axis=0), 1.0, atol=1e-13)
    assert float(values.min()) >= -1e-15


@pytest.mark.parametrize("ndim", [2, 3])
def test_parent_weights_are_the_subdivision_rule_and_not_stored(ndim):
    """A function takes from its parents the cubic subdivision weights of its index's
    parity along each axis (``(1, 6, 1) / 8`` or ``(4, 4) / 8``, products over the axes),
    computed from its key on the host and in JAX alike; the hierarchy stores no float per
    parent (that was most of a fine hierarchy's memory)."""
    hierarchy = _hierarchy(ndim, levels=2)
    for level in range(1, hierarchy.num_levels):
        keys = np.asarray(hierarchy.function_keys[level])
        index = unravel_keys(keys, hierarchy.functions(level))
        odd = (index + 3) % 2 == 1
        one_axis = np.where(odd[..., None], [0.5, 0.5, 0.0], [0.125, 0.75, 0.125])  # (k, d, 3)
        expected = one_axis[:, 0]
        for axis in range(1, ndim):
            expected = (expected[:, :, None] * one_axis[:, axis, None, :]).reshape(len(keys), -1)
        host = hierarchy.parent_weights(level, np)
        np.testing.assert_array_equal(host, expected)
        np.testing.assert_array_equal(
            np.asarray(jax.jit(lambda h: h.parent_weights(level))(hierarchy)), expected
        )
    floats = [
        leaf for leaf in jax.tree.leaves(hierarchy) if jnp.issubdtype(leaf.dtype, jnp.floating)
    ]
    relevant = sum(int(k.size) for k in hierarchy.function_keys)
    assert sum(int(leaf.size) for leaf in floats) < 3**ndim * relevant // 2  # keep, edges


@pytest.mark.parametrize("ndim", [2, 3])
def test_table_and_sorted_key_lookups_build_the_same_hierarchy(ndim, monkeypatch):
    """``build_hierarchy`` looks keys up in tables where their range is small and by a
    sorted search beyond (and checks supports by a box sum where there is a table, cell by
    cell beyond): both build the same arrays."""
    from jurs._model import hierarchy as module

    table = _hierarchy(ndim, levels=3)
    monkeypatch.setattr(module, "TABLE_KEYS", 0)
    searched = _hierarchy(ndim, levels=3)
    assert table.num_levels == 4
    for a, b in zip(jax.tree.leaves(table), jax.tree.leaves(searched), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("ndim", [2, 3])
def test_gradient_of_a_rational_spline_is_the_quotient_rule(ndim):
    """``AdaptiveSpline.grad`` (numerator and denominator in one cascade) against the
    quotient rule on the two polynomial splines' own gradients."""
    from jurs._model.leaves import hierarchy_gradient

    hierarchy = _hierarchy(ndim)
    rng = np.random.default_rng(3)
    control = jnp.asarray(rng.normal(size=hierarchy.num_active))
    weights = jnp.asarray(rng.uniform(0.5, 2.0, hierarchy.num_active))
    spline = jurs.AdaptiveSpline(hierarchy, control, weights)
    x = _random_points(hierarchy, 200)
    top = hierarchy_values(hierarchy, weights * control, x)
    bottom = hierarchy_values(hierarchy, weights, x)
    expected = (
        hierarchy_gradient(hierarchy, weights * control, x) * bottom[:, None]
        - top[:, None] * hierarchy_gradient(hierarchy, weights, x)
    ) / (bottom * bottom)[:, None]
    np.testing.assert_allclose(spline.grad(x), expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(spline.grad(x[0]), expected[0], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_one_search_over_levels_equals_a_search_per_level(ndim, monkeypatch):
    """``leaf_terms`` searches the keys of all levels at once; where those would leave
    int32 it searches level by level. Both give the same positions."""
    from jurs._model import leaves as module

    hierarchy = _hierarchy(ndim)
    x = _random_points(hierarchy, 300)
    level, cell = module.locate_leaves(hierarchy, x)
    positions, t = module.leaf_terms(hierarchy, x, level, cell)
    monkeypatch.setattr(module, "MAX_KEY", 0)
    per_level, t_per_level = module.leaf_terms(hierarchy, x, level, cell)
    np.testing.assert_array_equal(positions, per_level)
    np.testing.assert_array_equal(t, t_per_level)
    assert len(np.unique(np.asarray(level))) > 1  # points on several levels' leaves


@pytest.mark.parametrize("ndim", [2, 3])
def test_active_functions_are_linearly_independent(ndim):
    """A THB spline is 0 iff its cascaded coefficients over every leaf are 0 (B-splines are
    locally independent on a cell): the map from active coefficients to those has full
    column rank."""
    hierarchy = _hierarchy(ndim)
    cascaded = np.asarray(cascade(hierarchy, jnp.eye(hierarchy.num_active)))
    columns, start = [], 0
    for level in range(hierarchy.num_levels):
        cells, extent = hierarchy.cells(level), hierarchy.functions(level)
        leaves = unravel_keys(np.asarray(hierarchy.leaf_keys[level]), cells)
        over = ravel_keys(
            (leaves[:, None, :] + cube_offsets(ndim, 4)[None]).reshape(-1, ndim), extent
        )
        keys = np.asarray(hierarchy.function_keys[level])
        columns.append(np.searchsorted(keys, np.unique(over)) + start)
        start += hierarchy.level_sizes[level]
    on_leaves = cascaded[:, np.concatenate(columns)]
    assert np.linalg.matrix_rank(on_leaves) == hierarchy.num_active


def test_coarse_spline_is_represented_exactly():
    hierarchy = _hierarchy(2, levels=3)
    coarse = build_hierarchy(hierarchy.lower, hierarchy.upper, hierarchy.base, [])
    rng = np.random.default_rng(2)
    x = _random_points(hierarchy, 3000)
    target = np.asarray(
        hierarchy_values(coarse, jnp.asarray(rng.normal(size=coarse.num_active)), x)
    )
    basis = np.asarray(hierarchy_values(hierarchy, jnp.eye(hierarchy.num_active), x)).T
    coeffs = np.linalg.lstsq(basis, target, rcond=None)[0]
    np.testing.assert_allclose(basis @ coeffs, target, atol=1e-12)


def test_unrefined_hierarchy_is_the_uniform_basis():
    hierarchy = _hierarchy(2, levels=0)
    rng = np.random.default_rng(3)
    coeffs = rng.normal(size=hierarchy.num_active)
    spline = jurs.ImplicitSpline.bspline(
        coeffs.reshape(hierarchy.functions(0)), hierarchy.lower, hierarchy.upper
    )
    x = _random_points(hierarchy, 500)
    np.testing.assert_allclose(
        hierarchy_values(hierarchy, jnp.asarray(coeffs), x), spline(x), atol=1e-13
    )


def test_refined_everywhere_fit_equals_uniform_fit():
    """Every level-0 cell split once: the THB basis is the uniform basis of the finer grid,
    the hierarchical regulariser is eq. 31 on it, so the fits agree."""
    points, normals = jurs.datasets.example1(100)
    lower, upper = np.min(points, 0) - 1.0, np.max(points, 0) + 1.0
    base = (6, 6)
    problem = make_adaptive_problem(
        points, normals, offset=0.2, eps=0.2, lower=lower, upper=upper, base=base, levels=1, band=99
    )
    assert problem.hierarchy.active_counts == (0, 15 * 15)
    lam = 1e-3
    control = solve_adaptive(problem, lam, rtol=1e-13)[0]
    uniform = jurs.fit(
        points,
        normals,
        grid=(15, 15),
        offset=0.2,
        eps=0.2,
        domain=(lower, upper),
        solver=jurs.LeastSquares(lam=lam, ridge=0.0),
    )
    np.testing.assert_allclose(control, uniform.spline.control.ravel(), rtol=1e-8, atol=1e-10)


def test_direct_solve_falls_back_to_superlu(monkeypatch):
    """QDLDL refuses a matrix with a zero pivot (RuntimeError); the direct solve then
    takes SuperLU, whose pivoting still answers, and both agree on a regular matrix."""
    import qdldl

    points, normals = jurs.datasets.example1(100)
    lower, upper = np.min(points, 0) - 1.0, np.max(points, 0) + 1.0
    problem, matrices = assemble_adaptive_problem(
        points, normals, offset=0.2, eps=0.2, lower=lower, upper=upper, base=(6, 6), levels=2
    )
    control, residual = solve_direct(problem, 1e-3, matrices)
    assert residual < 1e-12
    # The host metrics of a direct solve are the traced ones.
    host = assembled_metrics(problem, matrices, control, 1e-3)
    traced = adaptive_metrics(problem, jnp.asarray(control), 1e-3)
    for name, value in traced.items():
        np.testing.assert_allclose(host[name], value, rtol=1e-9, err_msg=name)

    def refuse(matrix, upper=False):
        raise RuntimeError("Input matrix is not quasi-definite")

    monkeypatch.setattr(qdldl, "Solver", refuse)
    fallback, residual = solve_direct(problem, 1e-3)  # assembled again: the same matrix
    assert residual < 1e-12
    np.testing.assert_allclose(fallback, control, rtol=1e-9, atol=1e-12)


def test_layout_has_square_cells_and_a_coarse_base():
    lower, upper, base, levels = adaptive_layout(np.zeros(2), np.array([10.0, 3.0]), 0.01)
    width = (upper - lower) / (np.asarray(base) * 2**levels)
    np.testing.assert_allclose(width, 0.01)
    assert max(base) >= 8 and np.all(upper >= [10.0, 3.0])


def test_fit_adaptive_follows_a_circle_finely():
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    sol = jurs.fit_adaptive(points, points, finest=128)
    assert sol.status == "successful"
    assert max(sol.stats["finest"]) == 128
    # The active set follows the curve: far fewer functions than the uniform 131^2 grid.
    assert sum(sol.stats["active"]) < 0.35 * 131**2
    # Each point within a small fraction of a finest cell of the zero set (|g| / |grad g|).
    distance = np.abs(sol.spline(points)) / np.linalg.norm(sol.spline.grad(points), axis=1)
    assert distance.max() < 0.05 * sol.spline.cell_width
    # Outside positive, inside negative (outward normals).
    assert float(sol.spline(jnp.array([0.0, 0.0]))) < 0 < float(sol.spline(jnp.array([1.5, 0.0])))


@pytest.mark.slow
def test_gradient_through_an_adaptive_fit_matches_finite_differences():
    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    points = np.stack([1.3 * np.cos(t), np.sin(t)], 1)
    normals = np.stack([np.cos(t) / 1.3, np.sin(t)], 1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lower, upper, base, levels = adaptive_layout(
        np.array([-2.0, -2.0]), np.array([2.0, 2.0]), 0.125
    )
    problem = make_adaptive_problem(
        points, normals, offset=0.05, eps=0.05, lower=lower, upper=upper, base=base, levels=levels
    )
    query = jnp.array([[0.3, 0.2], [1.2, 0.4], [-0.5, 0.95]])

    @jax.jit
    def loss(p):
        control = solve_adaptive(at_points(problem, p, jnp.asarray(normals)), 1e-4, rtol=1e-14)[0]
        return jnp.sum(hierarchy_values(problem.hierarchy, control, query) ** 2)

    p0 = jnp.asarray(points)
    grad = jax.grad(loss)(p0)
    step = 1e-6
    for i, a in [(0, 0), (7, 1), (23, 0)]:
        e = jnp.zeros_like(p0).at[i, a].set(step)
        fd = (loss(p0 + e) - loss(p0 - e)) / (2 * step)
        np.testing.assert_allclose(grad[i, a], fd, rtol=1e-5, atol=1e-9)


def test_adaptive_spline_file_round_trip(tmp_path):
    hierarchy = _hierarchy(2)
    rng = np.random.default_rng(4)
    spline = jurs.AdaptiveSpline(
        hierarchy,
        jnp.asarray(rng.normal(size=hierarchy.num_active)),
        jnp.asarray(rng.uniform(0.5, 2.0, hierarchy.num_active)),
    )
    path = tmp_path / "adaptive.npz"
    jurs.save_spline(path, spline)
    loaded = jurs.load_spline(path)
    assert isinstance(loaded, jurs.AdaptiveSpline)
    assert loaded.hierarchy.active_counts == hierarchy.active_counts
    x = _random_points(hierarchy, 200)
    np.testing.assert_array_equal(loaded(x), spline(x))
    # A file whose arrays do not match its hierarchy is refused, naming the file.
    with np.load(path) as data:
        arrays = dict(data)
    arrays["control"] = arrays["control"][:-1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match="bad.npz"):
        jurs.load_spline(tmp_path / "bad.npz")


@pytest.mark.slow
def test_adaptive_surface_fit_meshes_a_sphere():
    points, normals = jurs.datasets.sphere3d(1500)
    sol = jurs.fit_adaptive(points, normals)
    # On a CPU a surface's CG runs on the host (SciPy); elsewhere in JAX.
    assert sol.status == "successful"
    assert sol.stats["method"] == ("host_cg" if jax.default_backend() == "cpu" else "cg")
    vertices, faces = jurs.levelset.mesh(sol.spline, resolution=40)
    report = jurs.levelset.analyze_mesh(vertices, faces, points)
    assert report.num_components == 1 and report.components[0].genus == 0
    radius = float(np.mean(np.linalg.norm(np.asarray(points), axis=1)))
    assert np.abs(np.linalg.norm(vertices, axis=1) - radius).max() < 0.02 * radius


def test_fit_adaptive_checks_its_input_even_with_settings_given():
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    settings = jurs.auto_settings(points, points)
    bad = points.copy()
    bad[5, 0] = np.nan
    with pytest.raises(ValueError, match="NaN|finite"):
        jurs.fit_adaptive(bad, points, settings=settings)
    with pytest.raises(ValueError, match="band"):
        jurs.fit_adaptive(points, points, band=0)
    with pytest.raises(ValueError, match="method"):
        jurs.fit_adaptive(points, points, method="lu")
    with pytest.raises(ValueError, match="finest"):
        jurs.fit_adaptive(points, points, finest=4)


def test_fit_adaptive_in_float32_converges():
    """In float32 CG stops at a tolerance above rounding, not at its step cap."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    sol = jurs.fit_adaptive(points, points, finest=64, method="cg", dtype=jnp.float32)
    assert sol.spline.control.dtype == jnp.float32
    assert sol.status == "successful" and sol.stats["num_steps"] < 1000
    assert (
        float(sol.spline(jnp.zeros(2, jnp.float32)))
        < 0
        < float(sol.spline(jnp.ones(2, jnp.float32)))
    )


def test_fit_adaptive_gives_the_fits_verdicts():
    """The adaptive fit is judged as ``jurs.fit`` judges its automatic fits: half-flipped
    normals give ``inconsistent_normals`` (raised with ``throw``), two rings a gap
    narrower than the finest cell apart are ``doubtful`` (bridged), and the same rings
    on cells the data ask for are not."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], 1)
    points = np.concatenate([ring - [1.02, 0.0], ring + [1.02, 0.0]])
    normals = np.concatenate([ring, ring])
    fine = jurs.fit_adaptive(points, normals)
    assert fine.status == "successful", fine.stats["doubts"]
    coarse = jurs.fit_adaptive(points, normals, finest=8, throw=False)
    assert coarse.status == "doubtful"
    assert any("narrow gap" in doubt for doubt in coarse.stats["doubts"])
    half = normals.copy()
    half[::2] *= -1
    flipped = jurs.fit_adaptive(points, half, settings=fine.settings, throw=False)
    assert flipped.status == "inconsistent_normals"
    with pytest.raises(eqx.EquinoxRuntimeError, match="inconsistent_normals"):
        jurs.fit_adaptive(points, half, settings=fine.settings)


def test_size_classes_are_four_an_octave():
    from jurs._fit.adaptive import MIN_CLASS, size_class

    counts = np.arange(1, 5000)
    classes = np.array([size_class(int(c)) for c in counts])
    assert np.all(classes >= counts) and np.all(classes >= MIN_CLASS)
    assert np.all(classes[counts > MIN_CLASS] < 1.25 * counts[counts > MIN_CLASS] + 1)
    assert len(np.unique(classes[(counts > 1024) & (counts <= 2048)])) == 4


def test_assembled_cg_solve_equals_the_traced_one():
    """The padded CG on the host-assembled matrices (fit_adaptive's surface path) and the
    matrix-free CG in JAX reach the same control and the same metrics."""
    from jurs._fit.adaptive import solve_assembled

    points, normals = jurs.datasets.example1(100)
    lower, upper = np.min(points, 0) - 1.0, np.max(points, 0) + 1.0
    problem, matrices = assemble_adaptive_problem(
        points, normals, offset=0.2, eps=0.2, lower=lower, upper=upper, base=(6, 6), levels=2
    )
    traced, traced_steps, _, metrics = solve_adaptive(problem, 1e-3, rtol=1e-13)
    control, steps, residual = solve_assembled(problem, matrices, 1e-3, 1e-13, 10_000, jnp.float64)
    assert control.shape == (problem.hierarchy.num_active,) and residual <= 1e-13
    assert abs(steps - int(traced_steps)) <= 2
    np.testing.assert_allclose(control, traced, rtol=1e-9, atol=1e-11)
    host = assembled_metrics(problem, matrices, control, 1e-3)
    for name, value in metrics.items():
        np.testing.assert_allclose(host[name], value, rtol=1e-9, err_msg=name)


def test_host_cg_solve_equals_the_jax_one():
    """SciPy's CG on the host (a surface's path on a CPU) reaches the padded JAX CG's
    control, in about as many steps (the same preconditioner and stop rule)."""
    from jurs._fit.adaptive import solve_assembled, solve_host_cg

    points, normals = jurs.datasets.example1(100)
    lower, upper = np.min(points, 0) - 1.0, np.max(points, 0) + 1.0
    problem, matrices = assemble_adaptive_problem(
        points, normals, offset=0.2, eps=0.2, lower=lower, upper=upper, base=(6, 6), levels=2
    )
    device, device_steps, _ = solve_assembled(problem, matrices, 1e-3, 1e-12, 10_000, jnp.float64)
    host, steps, residual = solve_host_cg(problem, matrices, 1e-3, 1e-12, 10_000)
    assert residual <= 1e-12 and abs(steps - device_steps) <= 0.05 * device_steps + 2
    np.testing.assert_allclose(host, device, rtol=1e-8, atol=1e-10)
    # The step cap is kept, and says so by its residual.
    _, capped, capped_residual = solve_host_cg(problem, matrices, 1e-3, 1e-12, 5)
    assert capped == 5 and capped_residual > 1e-6


def test_fit_adaptive_methods_agree_on_a_surface():
    """``method="host_cg"``, ``"cg"`` and ``"direct"`` fit the same spline on a small
    sphere (CG run to a tight tolerance)."""
    points, normals = jurs.datasets.sphere3d(300, seed=1)
    fits = {
        method: jurs.fit_adaptive(
            points, normals, finest=8, method=method, checks=False, rtol=1e-10
        )
        for method in ("host_cg", "cg", "direct")
    }
    for method, sol in fits.items():
        assert sol.status == "successful" and sol.stats["method"] == method
    reference = np.asarray(fits["direct"].spline.control)
    for method in ("host_cg", "cg"):
        np.testing.assert_allclose(
            np.asarray(fits[method].spline.control), reference, rtol=1e-6, atol=1e-8
        )


def _compiled_cg_solves(fits):
    """Compilations of the padded CG solve for each fit in ``fits`` (thunks), and the
    active functions of each fit."""
    from test_compile import _CompileCounter

    counts, actives = [], []
    for fit in fits:
        with _CompileCounter("_assembled_cg") as counter:
            sol = fit()
        assert sol.status == "successful" and sol.stats["method"] == "cg"
        counts.append(counter.count)
        actives.append(sol.stats["active"])
    return counts, actives


def test_cg_fits_of_two_clouds_share_one_compiled_solve():
    """A circle and an ellipse of other point counts fit on different hierarchies; their CG
    solves (padded to size classes) run one compiled program. In float32 it is another
    program (the counter counts)."""

    def ellipse(m, stretch, dtype=None):
        t = np.linspace(0, 2 * np.pi, m, endpoint=False)
        points = np.stack([np.cos(t), stretch * np.sin(t)], 1)
        normals = np.stack([stretch * np.cos(t), np.sin(t)], 1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return lambda: jurs.fit_adaptive(
            points, normals, finest=64, method="cg", dtype=dtype, lam=1e-3
        )

    counts, actives = _compiled_cg_solves(
        [ellipse(150, 1.0), ellipse(160, 0.8), ellipse(150, 1.0, jnp.float32)]
    )
    assert actives[0] != actives[1], actives  # two hierarchies
    # The first may reuse a program an earlier test compiled for its classes.
    assert counts[1] == 0 and counts[2] == 1, counts


@pytest.mark.slow  # three 3D fits of 30k functions; the circles' test above is fast
def test_surface_fits_of_two_clouds_share_one_compiled_solve():
    """A sphere and an ellipsoid of other point counts fit on different hierarchies (of
    the same size classes) and share one compiled CG solve (the JAX CG, a surface's
    default off a CPU)."""

    def ellipsoid(m, seed, stretch, dtype=None):
        points, normals = jurs.datasets.sphere3d(m, seed=seed)
        scale = np.array([1.0, stretch, 1.0])
        normals = normals / scale
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return lambda: jurs.fit_adaptive(
            points * scale, normals, finest=32, dtype=dtype, method="cg"
        )

    counts, actives = _compiled_cg_solves(
        [ellipsoid(300, 0, 1.0), ellipsoid(320, 1, 0.9), ellipsoid(300, 0, 1.0, jnp.float32)]
    )
    assert actives[0] != actives[1], actives
    assert counts[1] == 0 and counts[2] == 1, counts


def test_a_curve_fit_keeps_a_band_of_one_cell_by_default():
    """A curve's default band is one cell a level (as accurate as two on traced outlines,
    with fewer functions); a wider band is asked for explicitly."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    points = np.stack([np.cos(t), np.sin(t)], 1)
    default = jurs.fit_adaptive(points, points, finest=64)
    one = jurs.fit_adaptive(points, points, finest=64, band=1)
    two = jurs.fit_adaptive(points, points, finest=64, band=2)
    assert default.stats["active"] == one.stats["active"]
    assert sum(one.stats["active"]) < sum(two.stats["active"])
    x = np.array([[0.0, 0.0], [0.5, 0.5], [1.2, 0.1]])
    np.testing.assert_array_equal(default.spline(x), one.spline(x))


@pytest.mark.parametrize("ndim", [2, 3])
def test_host_evaluation_equals_the_hierarchys(ndim):
    """Outside a transformation a rational adaptive spline evaluates on the host, by its
    finest level's coefficients (``AdaptiveSpline.on_host``, kept while the spline
    lives); inside one, through its hierarchy. Values and gradients agree to rounding,
    for many points and for one."""
    hierarchy = _hierarchy(ndim)
    rng = np.random.default_rng(5)
    control = jnp.asarray(rng.normal(size=hierarchy.num_active))
    weights = jnp.asarray(rng.uniform(0.5, 2.0, hierarchy.num_active))
    spline = jurs.AdaptiveSpline(hierarchy, control, weights)
    assert spline.on_host() is spline.on_host()  # one evaluator for the spline's life
    x = _random_points(hierarchy, 300)
    traced = jax.jit(lambda s, p: (s(p), s.grad(p)))(spline, x)
    np.testing.assert_allclose(spline(x), traced[0], rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(spline.grad(x), traced[1], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(spline(x[7]), traced[0][7], rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(spline.grad(x[7]), traced[1][7], rtol=1e-10, atol=1e-12)
    # jax.grad with respect to the coefficients goes through the hierarchy, as before.
    slope = jax.grad(lambda c: jnp.sum(jurs.AdaptiveSpline(hierarchy, c, weights)(x)))(control)
    assert slope.shape == control.shape and np.isfinite(np.asarray(slope)).all()
    # A spline and points closed over by a jitted function are concrete there: evaluated
    # on the host, constants of the trace, the same values.
    closed = jax.jit(lambda w: w * spline(np.asarray(x)))(2.0)
    np.testing.assert_allclose(closed, 2.0 * np.asarray(spline(x)), rtol=1e-12, atol=1e-13)


def test_evaluating_a_new_adaptive_fit_compiles_nothing():
    """A user's first ``sol.spline(x)`` and ``sol.spline.grad(x)`` on a new fit (another
    hierarchy of the same size class, another number of points) reuse the programs the
    last fit compiled."""
    from test_compile import _CompileCounter

    t = np.linspace(0, 2 * np.pi, 150, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)], 1)
    x = np.random.default_rng(2).uniform(-1.5, 1.5, (300, 2))
    first = jurs.fit_adaptive(circle, circle, finest=64).spline
    first(x), first.grad(x)
    second = jurs.fit_adaptive(1.3 * circle[:140], circle[:140], finest=64).spline
    assert second.hierarchy.num_active != first.hierarchy.num_active  # a new hierarchy
    with _CompileCounter("") as counter:
        values, gradient = second(x[:280]), second.grad(x[:280])
    assert counter.count == 0
    assert values.shape == (280,) and gradient.shape == (280, 2)
    inside = np.linalg.norm(x[:280], axis=1) < 1.3
    assert np.all((np.asarray(values) < 0) == inside)
