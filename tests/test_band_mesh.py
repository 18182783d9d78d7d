"""Meshing an adaptive spline over the blocks where g may reach the level: the same mesh as
the full lattice's, watertight across block boundaries, surface far from the data kept."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs._model.adaptive import AdaptiveSpline
from jurs._model.band import plan_band
from jurs._model.hierarchy import build_hierarchy, refine_near
from jurs._model.lattice import FinestSpline, adaptive_lattice_values, values_and_gradients
from jurs.levelset import _meshing


def _quasi_interpolant(f, lower, upper, base, levels, samples, band=1):
    """The THB spline with each active function's coefficient ``f`` at its Greville point
    (its support's centre, node ``i - 1`` of its level): exact for linear ``f``, close to
    a smooth one."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    hierarchy = build_hierarchy(
        lower, upper, base, refine_near(lower, upper, base, levels, samples, band)
    )
    coeffs = []
    for lev in range(hierarchy.num_levels):
        keys = np.asarray(hierarchy.function_keys[lev])[np.asarray(hierarchy.active[lev])]
        multi = np.stack(np.unravel_index(keys, hierarchy.functions(lev)), -1)
        width = (upper - lower) / np.asarray(hierarchy.cells(lev))
        coeffs.append(f(lower + (multi - 1) * width))
    control = jnp.asarray(np.concatenate(coeffs))
    return AdaptiveSpline(hierarchy, control, jnp.ones_like(control))


def _sphere_samples(centre, radius, n=400):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(n, 3))
    return centre + radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def _torus(major=0.55, minor=0.22):
    def f(x):
        ring = np.sqrt(x[:, 0] ** 2 + x[:, 1] ** 2) - major
        return np.sqrt(ring**2 + x[:, 2] ** 2) - minor

    t = np.random.default_rng(1).uniform(0, 2 * np.pi, (1500, 2))
    samples = np.stack(
        [
            (major + minor * np.cos(t[:, 1])) * np.cos(t[:, 0]),
            (major + minor * np.cos(t[:, 1])) * np.sin(t[:, 0]),
            minor * np.sin(t[:, 1]),
        ],
        -1,
    )
    return _quasi_interpolant(f, [-1.0] * 3, [1.0] * 3, (4, 4, 4), 3, samples)


def _full_lattice_mesh(spline, resolution):
    """Marching cubes over every node of the lattice (the slab path), with the nudge of
    the band path: the reference the band's mesh must reproduce."""
    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    axes = _meshing.lattice_axes(lower, upper, resolution)
    spacing = _meshing._spacing(axes)
    nudge = _meshing.NUDGE * float(np.max(spacing * spline.slope_bound()))
    vertices, faces = _meshing._march_in_slabs(spline, axes, 0.0, nudge, 1 << 16)
    return lower + vertices * spacing, faces


def _assert_same_mesh(a, b):
    """The same vertices bit for bit (``_meshing.lattice_vertices`` puts a block's vertices
    where marching cubes over the whole lattice puts them; the weld sorts them) and the
    same faces, orientation kept, in any order."""

    def canonical(faces):
        turn = (np.argmin(faces, axis=1)[:, None] + np.arange(3)) % 3
        rows = np.take_along_axis(faces, turn, axis=1)
        return rows[np.lexsort(rows.T[::-1])]

    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(canonical(a[1]), canonical(b[1]))


def _assert_watertight(faces):
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()


def test_finest_coefficients_evaluate_the_spline_and_agree_bitwise():
    """The finest level's coefficients (``finest_coefficients``, through ``FinestSpline``)
    give g and its gradient as the hierarchy's own evaluation does, and a sub-lattice gets
    bitwise the values of the lattice."""
    rng = np.random.default_rng(0)
    lower, upper = np.zeros(3), np.ones(3)
    refine = refine_near(lower, upper, (3, 3, 3), 2, rng.uniform(0.3, 0.6, (20, 3)), 1)
    hierarchy = build_hierarchy(lower, upper, (3, 3, 3), refine)
    assert hierarchy.num_levels == 3
    c = rng.normal(size=hierarchy.num_active)
    w = rng.uniform(0.5, 2.0, size=hierarchy.num_active)
    spline = AdaptiveSpline(hierarchy, jnp.asarray(c), jnp.asarray(w))
    # Lattices (box and beyond it) and scattered points against the JAX evaluation.
    axes = [np.linspace(-0.05, 1.05, n) for n in (23, 19, 17)]
    values = adaptive_lattice_values(spline, axes)
    grid = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1)
    jax_values = eqx.filter_jit(lambda s, p: s(p))(spline, jnp.asarray(grid))
    np.testing.assert_allclose(values.ravel(), np.asarray(jax_values), atol=1e-12)
    g, gradient = values_and_gradients(spline, grid)
    np.testing.assert_allclose(g, values.ravel(), atol=1e-13)
    jax_gradient = eqx.filter_jit(lambda s, p: s.grad(p))(spline, jnp.asarray(grid))
    np.testing.assert_allclose(gradient, np.asarray(jax_gradient), atol=1e-10)
    sub = adaptive_lattice_values(spline, [a[5:14] for a in axes])
    assert np.array_equal(sub, values[5:14, 5:14, 5:14])


def test_finest_coefficients_do_not_depend_on_their_grouping(monkeypatch):
    """Leaves subdivided a few at a time give bitwise the coefficients of one group."""
    from jurs._model import finest as module

    rng = np.random.default_rng(2)
    lower, upper = np.zeros(2), np.ones(2)
    refine = refine_near(lower, upper, (3, 3), 3, rng.uniform(0.4, 0.5, (10, 2)), 1)
    hierarchy = build_hierarchy(lower, upper, (3, 3), refine)
    cascaded = rng.normal(size=(2, sum(hierarchy.level_sizes)))
    functions = np.argwhere(np.ones(np.asarray(hierarchy.cells(3)) + 3, bool))
    whole = module.finest_coefficients(hierarchy, cascaded, functions)
    monkeypatch.setattr(module, "TABLE_ENTRIES", 200)
    assert np.array_equal(module.finest_coefficients(hierarchy, cascaded, functions), whole)


@pytest.mark.parametrize("ndim", [2, 3])
def test_finest_coefficients_one_by_one_are_the_tables_entries(monkeypatch, ndim):
    """Functions subdivided one by one (where few of a leaf's are asked) get bitwise the
    coefficients read off their leaves' whole tables, whether a few or all are asked."""
    from jurs._model import finest as module

    rng = np.random.default_rng(3)
    lower, upper = np.zeros(ndim), np.ones(ndim)
    base = (3,) * ndim
    refine = refine_near(lower, upper, base, 3, rng.uniform(0.4, 0.5, (10, ndim)), 1)
    hierarchy = build_hierarchy(lower, upper, base, refine)
    cascaded = rng.normal(size=(2, sum(hierarchy.level_sizes)))
    every = np.argwhere(np.ones(np.asarray(hierarchy.cells(3)) + 3, bool))
    for functions in (every, every[rng.choice(len(every), 40, replace=False)]):
        answers = []
        for few in (True, False):
            monkeypatch.setattr(module, "_asks_few", lambda *args, few=few: few)
            answers.append(module.finest_coefficients(hierarchy, cascaded, functions))
        assert np.array_equal(answers[0], answers[1])


def test_band_mesh_of_a_torus_is_the_full_lattice_mesh():
    spline = _torus()
    resolution = 61
    band_v, band_f = jurs.levelset.mesh(spline, resolution, newton_steps=0)
    full_v, full_f = _full_lattice_mesh(spline, resolution)
    _assert_watertight(band_f)
    assert band_v.shape == full_v.shape and band_f.shape == full_f.shape
    _assert_same_mesh((band_v, band_f), (full_v, full_f))
    report = jurs.levelset.analyze_mesh(band_v, band_f)
    assert report.num_components == 1 and report.components[0].genus == 1
    # And fewer nodes were evaluated than the lattice holds.
    evaluator = FinestSpline(spline)
    lower, upper = np.asarray(spline.lower), np.asarray(spline.upper)
    plan = plan_band(evaluator, _meshing.lattice_axes(lower, upper, resolution), 0.0, 1e-6, 8)
    assert plan.nodes < 0.6 * plan.lattice_nodes


def test_band_mesh_keeps_a_component_far_from_the_data():
    """A bubble of g < 0 in the coarse region (no data, no fine cells) is meshed: the
    per-leaf bound lets its blocks through."""
    centre = np.array([0.5, 0.5, 0.5])
    samples = _sphere_samples(centre, 0.35)
    spline = _quasi_interpolant(
        lambda x: np.linalg.norm(x - centre, axis=1) - 0.35,
        [-1.0] * 3,
        [2.0] * 3,
        (6, 6, 6),
        2,
        samples,
    )
    hierarchy = spline.hierarchy
    keys = np.asarray(hierarchy.function_keys[0])[np.asarray(hierarchy.active[0])]
    multi = np.stack(np.unravel_index(keys, hierarchy.functions(0)), -1)
    # The level-0 function whose support is centred at (1.5, 1.5, 1.5), far from the data.
    far = int(np.flatnonzero(np.all(multi == 6, axis=1))[0])
    spline = AdaptiveSpline(hierarchy, spline.control.at[far].set(-10.0), spline.weights)
    resolution = 49
    band_v, band_f = jurs.levelset.mesh(spline, resolution, newton_steps=0)
    full_v, full_f = _full_lattice_mesh(spline, resolution)
    assert band_v.shape == full_v.shape and band_f.shape == full_f.shape
    _assert_same_mesh((band_v, band_f), (full_v, full_f))
    report = jurs.levelset.analyze_mesh(band_v, band_f)
    assert report.num_components == 2
    assert np.any(np.all(band_v > 1.2, axis=1))  # the far piece is there


def test_band_mesh_counts_marched_nodes_against_max_nodes():
    spline = _torus()
    with pytest.raises(ValueError, match="blocks where it may reach the level"):
        jurs.levelset.mesh(spline, 97, max_nodes=20_000)
    # The default resolution is lowered to fit instead of refused.
    vertices, faces = jurs.levelset.mesh(spline, max_nodes=60_000)
    assert len(faces) and jurs.levelset.analyze_mesh(vertices, faces).components[0].genus == 1


def test_adaptive_default_density_is_coarser_unless_trimmed():
    """An adaptive spline's default lattice takes ``ADAPTIVE_SAMPLES_PER_CELL`` nodes a
    finest cell, a trimmed mesh ``SAMPLES_PER_CELL`` (the trim clips along the faces);
    ``mesh`` passes whether it trims."""
    spline = _torus()
    lower, upper = np.asarray(spline.lower), np.asarray(spline.upper)
    cells = float(np.max(upper - lower) / np.min(spline.cell_widths))
    plain = _meshing.default_resolution(spline, lower, upper)
    trimmed = _meshing.default_resolution(spline, lower, upper, trimmed=True)
    assert plain == int(np.ceil(_meshing.ADAPTIVE_SAMPLES_PER_CELL * cells)) + 1
    assert trimmed == int(np.ceil(_meshing.SAMPLES_PER_CELL * cells)) + 1
    assert plain < trimmed
    # The mesh's lattice follows: at the plain density a default mesh is the mesh of that
    # resolution, bit for bit.
    _assert_same_mesh(jurs.levelset.mesh(spline), jurs.levelset.mesh(spline, plain))


def test_trimmed_mesh_skips_blocks_the_trim_cuts_whole():
    """A trimmed mesh of an adaptive spline marches only the blocks near the data
    (``near_support``), and is bit for bit the trim of the whole mesh at its lattice."""
    from jurs.levelset._trimming import Support, near_support

    spline = _torus()
    t = np.random.default_rng(2).uniform(0.0, 0.8, (600, 2))  # a patch of the torus
    cap = np.stack(
        [
            (0.55 + 0.22 * np.cos(t[:, 1])) * np.cos(t[:, 0]),
            (0.55 + 0.22 * np.cos(t[:, 1])) * np.sin(t[:, 0]),
            0.22 * np.sin(t[:, 1]),
        ],
        -1,
    )
    lower, upper = np.asarray(spline.lower, float), np.asarray(spline.upper, float)
    resolution = _meshing.default_resolution(spline, lower, upper, trimmed=True)
    trimmed = jurs.levelset.mesh(spline, points=cap, trim=True)
    whole = jurs.levelset.mesh(spline, resolution)
    again = jurs.levelset.trim_mesh(*whole, cap, True, rim=True)
    assert len(trimmed[1]) > 0
    np.testing.assert_array_equal(trimmed[0], again[0])
    np.testing.assert_array_equal(trimmed[1], again[1])
    # The filter left most of the torus's blocks out.
    evaluator = spline.on_host()
    axes = _meshing.lattice_axes(lower, upper, resolution)
    near = near_support(Support(cap), jurs.levelset.DEFAULT_TRIM, 2)
    every = plan_band(evaluator, axes, 0.0, 0.0)
    kept = plan_band(evaluator, axes, 0.0, 0.0, near=near)
    assert 0 < len(kept.blocks) < 0.5 * len(every.blocks)


@pytest.mark.slow
def test_band_mesh_of_an_adaptive_sphere_fit_is_watertight_and_matches_the_lattice():
    """A fit (not a constructed spline): its band-only mesh is closed, of genus 0, and the
    full lattice's mesh at the same resolution."""
    points, normals = jurs.datasets.sphere3d(2000)
    spline = jurs.fit_adaptive(points, normals, finest=24).spline
    band_v, band_f = jurs.levelset.mesh(spline, 97, newton_steps=0)
    full_v, full_f = _full_lattice_mesh(spline, 97)
    _assert_watertight(band_f)
    report = jurs.levelset.analyze_mesh(band_v, band_f)
    assert report.num_components == 1 and report.components[0].genus == 0
    assert band_v.shape == full_v.shape and band_f.shape == full_f.shape
    _assert_same_mesh((band_v, band_f), (full_v, full_f))
