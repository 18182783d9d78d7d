"""Per-point values carried onto the zero set (``jurs.fit_attributes``), vertex colours in
PLY, and clouds far from the origin (georeferenced coordinates)."""

import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

import jurs
from jurs._fit.attributes import AttributeField, side_weights

RED, BLUE = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])


def _two_sheets_2d(spacing=0.05, gap=1.5):
    """A thin rectangle: two long sides ``gap`` spacings apart (red on top, blue below,
    normals facing away from each other), closed by short ends (purple)."""
    xs = np.arange(-1.0, 1.0 + 1e-9, spacing)
    half = gap * spacing / 2
    top = np.stack([xs, np.full_like(xs, half)], 1)
    bottom = np.stack([xs, np.full_like(xs, -half)], 1)
    ys = np.arange(-half + spacing / 2, half, spacing / 2)
    ends = np.concatenate([np.stack([np.full_like(ys, x), ys], 1) for x in (-1.0, 1.0)])
    points = np.concatenate([top, bottom, ends])
    normals = np.concatenate(
        [
            np.tile([0.0, 1.0], (len(top), 1)),
            np.tile([0.0, -1.0], (len(bottom), 1)),
            np.sign(ends[:, :1]) * np.array([[1.0, 0.0]]),
        ]
    )
    colours = np.concatenate(
        [np.tile(RED, (len(top), 1)), np.tile(BLUE, (len(bottom), 1))]
        + [np.tile((RED + BLUE) / 2, (len(ends), 1))]
    )
    return points, normals, colours


def _unsided(field: AttributeField) -> AttributeField:
    """The same field with the direction split taken out: the single smooth fit of the
    values, which averages sheets nearer than a cell."""
    coefficients = field.coefficients.at[1:].set(0.0)
    return AttributeField(field.geometry, coefficients, field.lower, field.upper)


@pytest.fixture(scope="module")
def slab_2d():  # a fit and its attributes compiled: about 20 s on 2 busy cores
    points, normals, colours = _two_sheets_2d()
    solver = jurs.LeastSquares(lam=1e-6)
    sol = jurs.fit(points, normals, grid=(24, 8), offset=0.0125, eps=0.0125, solver=solver)
    return sol, points, colours


@pytest.mark.slow  # the fixture's fit and attribute solves compile (the planted case)
def test_two_sheets_nearer_than_a_cell_keep_their_colours_2d(slab_2d):
    """Sheets 1.5 spacings apart, under one cell: every zero-set point of each sheet reads
    its own colour; the single smooth field would mix them."""
    sol, points, colours = slab_2d
    gap = np.ptp(points[:, 1])
    assert sol.spline.cell_width > gap
    field = jurs.fit_attributes(sol, points, colours)
    curves = jurs.levelset.zero_level_set(sol.spline, resolution=400)
    on = np.concatenate([np.asarray(c) for c, _ in curves])
    on = on[np.abs(on[:, 0]) < 0.8]  # the long sides, away from the purple ends
    assert np.abs(on[:, 1]).max() < gap  # the two sheets, nothing else
    top = on[:, 1] > 0
    assert top.sum() > 50 and (~top).sum() > 50
    values = np.asarray(field(on))
    sided = max(np.abs(values[top] - RED).max(), np.abs(values[~top] - BLUE).max())
    assert sided < 0.02
    mixed = np.asarray(_unsided(field)(on))
    assert np.abs(mixed[top] - RED).max() > 5 * sided


@pytest.mark.slow  # a 3D fit and its attribute solves, compiled: about 30 s on 2 cores
def test_two_sheets_nearer_than_a_cell_keep_their_colours_3d():
    """The same in 3D, on the vertices of the mesh: a thin plate whose faces, 1.5
    spacings apart (under a cell), are red above and blue below."""
    half = 0.075
    points, normals = jurs.datasets.thin_plate(step=0.1, thickness=2 * half)
    side = np.sign(normals[:, 2])[:, None]  # +1 the top face, -1 the bottom, 0 the rim
    colours = np.where(side > 0, RED, np.where(side < 0, BLUE, (RED + BLUE) / 2))
    solver = jurs.LeastSquares(lam=1e-3)
    sol = jurs.fit(points, normals, grid=(14, 14, 6), offset=0.025, eps=0.025, solver=solver)
    h = (np.asarray(sol.spline.upper) - np.asarray(sol.spline.lower)) / (np.array([14, 14, 6]) - 3)
    assert h.min() > 2 * half  # every side of a cell spans the gap
    field = jurs.fit_attributes(sol, points, colours)
    vertices = jurs.levelset.mesh(sol.spline, resolution=64)[0]
    vertices = vertices[(np.abs(vertices[:, :2]) < 0.7).all(axis=1)]
    assert np.abs(vertices[:, 2]).max() < 2 * half
    top = vertices[:, 2] > 0
    values = np.asarray(field(vertices))
    sided = max(np.abs(values[top] - RED).max(), np.abs(values[~top] - BLUE).max())
    assert sided < 0.01
    assert np.abs(np.asarray(_unsided(field)(vertices))[top] - RED).max() > 5 * sided


def _line_spline(shape=(10, 10)):
    """g(x, y) = y on [-1, 1]^2, exactly (a B-spline reproduces linear functions): its
    zero set is the x axis, its normal +y."""
    n = shape[1]
    greville = -1.0 + (np.arange(n) - 1.0) * 2.0 / (n - 3)
    control = np.broadcast_to(greville[None, :], shape)
    return jurs.ImplicitSpline.bspline(control, np.full(2, -1.0), np.full(2, 1.0))


def test_smooth_values_and_labels_are_recovered_on_the_zero_set():
    spline = _line_spline()
    np.testing.assert_allclose(np.asarray(spline(jnp.array([[0.3, 0.2]]))), [0.2], atol=1e-12)
    x = np.linspace(-0.9, 0.9, 60)
    points = np.stack([x, np.zeros_like(x)], 1)
    labels = np.eye(3)[(x > 0).astype(int) + (x > 0.5)]  # one-hot
    field = jurs.fit_attributes(spline, points, np.column_stack([np.sin(2 * x), labels]))
    assert field.num_values == 4
    probe = np.stack([np.linspace(-0.8, 0.8, 25), np.full(25, 0.01)], 1)
    values = np.asarray(field(probe))
    assert values.shape == (25, 4) and np.asarray(field(probe[0])).shape == (4,)
    np.testing.assert_allclose(values[:, 0], np.sin(2 * probe[:, 0]), atol=5e-3)
    # One-hot labels come back as shares that sum to 1.
    np.testing.assert_allclose(values[:, 1:].sum(axis=1), 1.0, atol=1e-9)
    assert values[0, 1] > 0.95 and values[-1, 3] > 0.9


def test_side_weights_split_opposite_normals():
    n = np.array([[0.6, 0.8], [-0.6, -0.8], [1.0, 0.0]])
    beta = np.asarray(side_weights(jnp.asarray(n)))
    np.testing.assert_allclose(beta.sum(axis=1), 1.0)
    assert float(beta[0] @ beta[1]) == 0.0  # opposite sides share no direction


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(values=np.zeros((5, 3))), r"values must have shape \(m,\) or \(m, k\).*m = 6"),
        (dict(values=np.zeros((6, 0))), "at least one column"),
        (dict(values=np.array([0, 1, 2, np.nan, 4, 5.0])), r"values contain NaN.*row 3"),
        (dict(points=np.zeros((6, 3))), r"points must have shape \(m, 2\)"),
        (dict(points=np.full((6, 2), 2.0)), "outside the spline's box"),
        (dict(normals=np.zeros((6, 2))), "normals must be non-zero"),
        (dict(normals=np.zeros((5, 2))), "normals must have the same shape"),
        (dict(lam=-1.0), "lam"),
        (dict(offset=0.0), "offset"),
    ],
)
def test_bad_inputs_are_named(change, match):
    args: dict = dict(points=np.zeros((6, 2)), values=np.zeros(6))
    args.update(change)
    with pytest.raises(ValueError, match=match):
        jurs.fit_attributes(_line_spline(), args.pop("points"), args.pop("values"), **args)


def test_fit_must_be_a_solution_or_spline():
    with pytest.raises(TypeError, match="jurs.Solution, ImplicitSpline or AdaptiveSpline"):
        jurs.fit_attributes(np.zeros((4, 4)), np.zeros((6, 2)), np.zeros(6))  # pyright: ignore[reportArgumentType]


def test_vertex_colours_in_ply(tmp_path):
    """Colours in [0, 1] and 0-255 written as uchar red/green/blue, read by trimesh;
    coordinates far from the origin stay float64."""
    trimesh = pytest.importorskip("trimesh")
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 1e-3 + 6.5e5
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    unit = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.5, 1.002, -0.01]])
    path = tmp_path / "coloured.ply"
    jurs.datasets.save_mesh(path, vertices, faces, colors=unit)
    mesh = trimesh.load(path, process=False)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), vertices)
    rgb = np.asarray(mesh.visual.vertex_colors)[:, :3]
    np.testing.assert_array_equal(rgb, [[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 255, 0]])
    jurs.datasets.save_mesh(
        path, vertices, faces, colors=np.rint(unit * 255).clip(0, 255).astype(int)
    )
    again = np.asarray(trimesh.load(path, process=False).visual.vertex_colors)[:, :3]
    np.testing.assert_array_equal(again, rgb)
    with pytest.raises(ValueError, match=r"colors must be a \(4, 3\) array"):
        jurs.datasets.save_mesh(path, vertices, faces, colors=unit[:3])
    with pytest.raises(ValueError, match="NaN"):
        jurs.datasets.save_mesh(path, vertices, faces, colors=unit * np.nan)
    with pytest.raises(ValueError, match="PLY only"):
        jurs.datasets.save_mesh(tmp_path / "m.obj", vertices, faces, colors=unit)


GEO_SHIFT = np.array([6.5e5, 5.4e6, 300.0])


def _sphere(m=800, radius=2.0, seed=0):
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(m, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return radius * normals, normals


@pytest.mark.slow  # one 3D fit compiled (the second reuses it): about 15 s on 2 cores
def test_georeferenced_cloud_fits_as_near_the_origin():
    """A 2 m sphere at [6.5e5, 5.4e6, 300] m fitted in float64 has the zero set and mesh of
    the same sphere at the origin, shifted. jurs needs no recentring for this: every
    kernel works in cell coordinates ``(x - lower) / h`` and the measurements take
    differences first. What is left is the input's own rounding (float64 steps of 9e-10
    m at 5.4e6), amplified by the solve's conditioning."""
    points, normals = _sphere()
    solver = jurs.LeastSquares(lam=1e-4, linear_solver=lx.Cholesky())  # exact: no CG stop
    settings: dict = dict(grid=(10, 10, 10), offset=0.05, eps=0.05, solver=solver)
    near = jurs.fit(points, normals, **settings)
    far = jurs.fit(points + GEO_SHIFT, normals, **settings)
    np.testing.assert_allclose(
        np.asarray(far.spline.lower) - GEO_SHIFT, np.asarray(near.spline.lower), atol=1e-9
    )
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0)))
    # The zero set moves by g's difference over |grad g| (about 1 here): below 1e-9 of
    # the diagonal on and around the surface.
    probes = np.concatenate([points, 1.1 * points, 0.9 * points])
    moved = np.abs(np.asarray(far.spline(probes + GEO_SHIFT)) - np.asarray(near.spline(probes)))
    slope = np.linalg.norm(np.asarray(near.spline.grad(jnp.asarray(points))), axis=1).min()
    assert moved.max() / slope < 1e-9 * diagonal
    # The same mesh, shifted: the same faces, vertices within the marching cubes'
    # amplification of that (an edge nearly tangent to the surface).
    v_near, f_near = jurs.levelset.mesh(near.spline, resolution=24)[:2]
    v_far, f_far = jurs.levelset.mesh(far.spline, resolution=24)[:2]
    np.testing.assert_array_equal(f_far, f_near)
    assert np.abs(v_far - GEO_SHIFT - v_near).max() < 1e-7 * diagonal


@pytest.mark.parametrize("estimated", [False, True])
def test_float32_georeferenced_cloud_is_refused(estimated):
    """In float32 the same sphere is rounded to steps of 0.06 to 0.5 m: passed straight to
    jurs.fit it ended "inconsistent_normals" (other clouds fitted silently wrong); now
    it is refused naming the precision, before anything is fitted."""
    points, normals = _sphere()
    given = ((points + GEO_SHIFT).astype(np.float32),)
    given += () if estimated else (normals.astype(np.float32),)
    with pytest.raises(ValueError, match=r"float32, which at \|x\| = 5.4e\+06 resolves only"):
        jurs.fit(*given)
    jurs.Cloud(points.astype(np.float32), normals)  # near the origin float32 resolves it


@pytest.mark.slow  # a 3D fit through the command line, meshed and measured
def test_command_line_carries_ply_colours_onto_the_mesh(tmp_path, monkeypatch):
    """``jurs fit scan.ply``: per-vertex red/green/blue of the input cloud come back on
    mesh.ply's vertices (red above the equator, blue below)."""
    trimesh = pytest.importorskip("trimesh")
    from jurs import cli
    from jurs.datasets._files import write_ply

    monkeypatch.setenv("JURS_NO_COMPILATION_CACHE", "1")  # as tests/test_cli_surfaces.py
    points, normals = jurs.datasets.sphere3d(1500)
    rgb = np.where(points[:, 2:] > 0, [[255, 0, 0]], [[0, 0, 255]]).astype(np.uint8)
    write_ply(str(tmp_path / "scan.ply"), points, normals=normals, colors=rgb)
    out = tmp_path / "result"
    assert cli.main(["fit", str(tmp_path / "scan.ply"), "-o", str(out), "--grid", "12", "-q"]) == 0
    mesh = trimesh.load(out / "mesh.ply", process=False)
    vertices = np.asarray(mesh.vertices)
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(int)
    # Two cells away from the equator, where the colour steps: the smooth field rings a
    # little there (a few levels of 255), and is exact on most vertices.
    above, below = vertices[:, 2] > 0.5, vertices[:, 2] < -0.5
    for side, colour in ((above, [255, 0, 0]), (below, [0, 0, 255])):
        error = np.abs(colours[side] - colour)
        assert error.max() <= 16 and error.mean() <= 1
    assert (out / "metrics.json").read_text().count('"vertex_colors": true') == 1
