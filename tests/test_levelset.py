"""Zero-level sets: extraction, supplementary components, tiny loops, distances."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jurs  # noqa: E402
from jurs import levelset as ls  # noqa: E402
from jurs.levelset._trimming import Support  # noqa: E402


class Analytic:
    """An analytic implicit function on a box, callable like an ImplicitSpline."""

    def __init__(self, f, lower=(-1.5, -1.5), upper=(1.5, 1.5)):
        self.f = f
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)

    def __call__(self, xy):
        return self.f(jnp.asarray(xy))


def circle_samples(n, radius=1.0, centre=(0.0, 0.0)):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], axis=1)


def dist(xy, centre):
    return jnp.linalg.norm(xy - jnp.asarray(centre), axis=1)


@pytest.fixture(scope="module")
def circle_fit():
    points, normals = jurs.datasets.ellipse(100, a=2.0, b=2.0)
    sol = jurs.fit(
        points, normals, grid=(9, 9), offset=0.1, eps=0.01, solver=jurs.IPIA(max_steps=200, tol=0.0)
    )
    return points, sol


def test_well_fitted_circle_has_one_component(circle_fit):
    points, sol = circle_fit
    report = ls.analyze(sol.spline, points, offset=0.1, reference=circle_samples(2000, 2.0))
    assert report.num_components == 1
    assert report.num_supplementary == 0
    assert report.num_tiny_loops == 0
    (c,) = report.components
    assert c.closed
    assert c.length == pytest.approx(2 * np.pi * 2.0, rel=0.01)
    assert c.mean_distance < report.threshold
    assert report.threshold == pytest.approx(0.2)
    assert report.chamfer < 0.02  # the fit follows the circle closely
    assert report.zero_area_fraction == 0.0


def test_extra_closed_curve_far_from_data_is_supplementary():
    # Zero set: the unit circle (the data) and a circle of radius 0.3 around (1.1, 1.1).
    f = Analytic(lambda xy: (dist(xy, (0, 0)) - 1.0) * (dist(xy, (1.1, 1.1)) - 0.3))
    data = circle_samples(200)
    report = ls.analyze(f, data, offset=0.05)
    assert report.num_components == 2
    assert report.num_supplementary == 1
    (extra,) = report.supplementary
    assert extra.closed
    assert extra.length == pytest.approx(2 * np.pi * 0.3, rel=0.01)
    assert report.supplementary_length == pytest.approx(extra.length)
    # Its mean distance to the data: the mean over the small circle of | |p| - 1 |.
    phi = np.linspace(0, 2 * np.pi, 10000, endpoint=False)
    ring = np.stack([1.1 + 0.3 * np.cos(phi), 1.1 + 0.3 * np.sin(phi)], axis=1)
    expected = np.mean(np.abs(np.linalg.norm(ring, axis=1) - 1.0))
    assert extra.mean_distance == pytest.approx(expected, abs=0.01)  # data spacing 0.03
    assert extra.far_fraction == 1.0  # all of it beyond 2 d = 0.1 (its nearest is 0.26)
    main = [c for c in report.components if not c.supplementary][0]
    assert main.length == pytest.approx(2 * np.pi, rel=0.01)
    assert extra.carried_fraction == 0.0 and main.carried_fraction == 1.0
    # A threshold above the extra loop's distance puts all of it near the data, but the
    # data it is near lie on the unit circle: it carries none of them, and stays
    # supplementary (it was counted ordinary).
    near = ls.analyze(f, data, threshold=1.0)
    (extra,) = near.supplementary
    assert extra.far_fraction == 0.0 and extra.carried_fraction == 0.0


def test_curve_bridging_a_sampling_gap_is_not_supplementary():
    """The unit circle sampled on two thirds of its length: the zero set (the whole circle)
    has the unsampled third's large distances in its mean, above the threshold, but only
    about a third of its length beyond the threshold, so it is the curve, not an extra one."""
    f = Analytic(lambda xy: dist(xy, (0, 0)) - 1.0)
    t = np.linspace(0, 4 * np.pi / 3, 140)
    data = np.stack([np.cos(t), np.sin(t)], axis=1)
    report = ls.analyze(f, data, offset=0.05)  # threshold 0.1
    (c,) = report.components
    assert c.mean_distance > report.threshold
    # Beyond 0.1 from both ends of the sampled arc: the gap less 2 x 0.1 (chord ~ arc).
    assert c.far_fraction == pytest.approx((2 * np.pi / 3 - 0.2) / (2 * np.pi), abs=0.01)
    assert not c.supplementary and report.num_supplementary == 0


def test_arc_of_a_circle_is_trimmed_to_its_end_points():
    """A profile: the unit circle sampled on a third of its length (evenly, spacing
    a = 2 pi / 3 / 69). The zero set is the whole circle; trimmed it is one open curve
    whose ends lie ``DEFAULT_RIM`` spacings past the arc's (the rim test: past an end
    every sample lies to one side), or about ``DEFAULT_TRIM`` by the distance alone (the
    spacing near an end reads a little more than a: its neighbours are on one side)."""
    f = Analytic(lambda xy: dist(xy, (0, 0)) - 1.0)
    t = np.linspace(0, 2 * np.pi / 3, 70)
    a = t[1] - t[0]
    data = np.stack([np.cos(t), np.sin(t)], axis=1)
    report = ls.analyze(f, data, offset=0.05, resolution=200, trim=True)
    assert report.trim == ls.DEFAULT_TRIM
    (c,) = report.components
    assert not c.closed and c.ends is not None
    angles = np.sort(np.arctan2(c.ends[:, 1], c.ends[:, 0]))
    past = np.array([-angles[0], angles[1] - 2 * np.pi / 3])  # beyond each end, in arc
    assert ((past > 0.8 * ls.DEFAULT_RIM * a) & (past < 1.5 * ls.DEFAULT_RIM * a)).all()
    assert c.length == pytest.approx(2 * np.pi / 3 + past.sum(), rel=0.01)
    (far,) = ls.analyze(f, data, offset=0.05, resolution=200, trim=True, rim=None).components
    ends = np.sort(np.arctan2(far.ends[:, 1], far.ends[:, 0]))  # pyright: ignore[reportOptionalSubscript]
    past = np.array([-ends[0], ends[1] - 2 * np.pi / 3])
    assert ((past > 2 * a) & (past < 1.5 * ls.DEFAULT_TRIM * a)).all()
    d = report.as_dict()
    assert d["trim"] == ls.DEFAULT_TRIM and d["num_open"] == 1
    np.testing.assert_allclose(d["end_points"], [c.ends.tolist()])
    # Untrimmed, it is the closed circle (no end points); a closed curve the data cover
    # stays closed when trimmed.
    whole = ls.analyze(f, data, offset=0.05, resolution=200)
    assert whole.components[0].closed and whole.components[0].ends is None
    assert whole.as_dict()["trim"] is None and whole.as_dict()["end_points"] == [None]
    full = ls.analyze(f, circle_samples(200), offset=0.05, resolution=200, trim=3.0)
    assert full.components[0].closed and full.num_components == 1


def test_randomly_sampled_arc_trims_to_one_piece_ending_at_its_ends():
    """100 samples at random along a third of a circle leave gaps of up to about ln(100)
    spacings: by the distance alone the trimmed circle often falls into pieces there;
    with the rim test a gap (samples on both sides) is bridged and the one piece ends
    about ``DEFAULT_RIM`` spacings past the arc's ends."""
    phi = np.linspace(0, 2 * np.pi, 2001)
    circle = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    split = 0
    for seed in range(10):
        t = np.sort(np.random.default_rng(seed).uniform(0, 2 * np.pi / 3, 100))
        data = np.stack([np.cos(t), np.sin(t)], axis=1)
        spacing = np.median(Support(data).spacing)
        (piece, closed), *rest = ls.trim_curves([(circle, True)], data)
        assert not rest and not closed
        angle = np.arctan2(piece[:, 1], piece[:, 0])
        past = np.array([t[0] - angle.min(), angle.max() - t[-1]]) / spacing
        assert ((past > 0.3 * ls.DEFAULT_RIM) & (past < 3 * ls.DEFAULT_RIM)).all()
        split += len(ls.trim_curves([(circle, True)], data, rim=None)) > 1
    assert split > 0


def test_trim_curves_splits_where_a_curve_leaves_the_data():
    """Two arcs on opposite sides of a closed circle: two pieces, each around one arc,
    whichever vertex the polyline starts at."""
    phi = np.linspace(0, 2 * np.pi, 361)
    circle = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # closed: last point = first
    t = np.concatenate([np.linspace(-0.5, 0.5, 40), np.linspace(np.pi - 0.5, np.pi + 0.5, 40)])
    data = np.stack([np.cos(t), np.sin(t)], axis=1)
    for start in (0, 90):
        ring = np.roll(circle[:-1], -start, axis=0)
        pieces = ls.trim_curves([(np.concatenate([ring, ring[:1]]), True)], data, 2.0)
        assert len(pieces) == 2 and not any(closed for _, closed in pieces)
        for piece, _ in pieces:
            centre = np.arctan2(*piece.mean(axis=0)[::-1])
            assert min(abs(centre), abs(abs(centre) - np.pi)) < 0.05
            assert ls.polyline_length(piece) == pytest.approx(1.0, abs=0.15)
    assert ls.trim_curves([(circle + 5.0, True)], data) == []  # nowhere near the data
    with pytest.raises(ValueError, match="trim must be a positive"):
        ls.trim_curves([(circle, True)], data, -1.0)
    with pytest.raises(ValueError, match="trim must be a positive"):
        ls.analyze(Analytic(lambda xy: dist(xy, (0, 0)) - 1.0), data, trim=0.0)
    with pytest.raises(ValueError, match="at least 2 distinct"):
        ls.trim_curves([(circle, True)], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="rim must be a finite number of spacings >= 0"):
        ls.trim_curves([(circle, True)], data, 2.0, rim=-0.5)
    with pytest.raises(ValueError, match="rim must be a finite number"):
        ls.analyze(Analytic(lambda xy: dist(xy, (0, 0)) - 1.0), data, trim=True, rim=np.nan)


def test_extra_loop_in_a_spline_is_counted(circle_fit):
    points, sol = circle_fit
    s = sol.spline
    # Push two corner coefficients (far from the circle) well below zero: g < 0 there
    # makes a closed loop in the positive outside region.
    control = s.control.at[0:2, 0:2].set(-0.2)
    bumped = jurs.ImplicitSpline(control, s.weights, s.lower, s.upper)
    report = ls.analyze(bumped, points, offset=0.1)
    assert report.num_supplementary == 1
    assert report.num_components == 2
    assert ls.analyze(s, points, offset=0.1).num_supplementary == 0


def test_chamfer_of_exact_circle_is_at_grid_spacing_level():
    f = Analytic(lambda xy: dist(xy, (0, 0)) - 1.0)
    ref = circle_samples(4000)
    for resolution in (64, 512):
        report = ls.analyze(f, ref[::40], reference=ref, resolution=resolution)
        h = report.cell_size
        assert report.chamfer < 0.25 * h
        assert report.hausdorff < h
        assert report.reference == "reference curve"
    # Not trivially small: a circle of radius 1.05 is 0.05 away.
    shifted = Analytic(lambda xy: dist(xy, (0, 0)) - 1.05)
    report = ls.analyze(shifted, ref[::40], reference=ref)
    assert report.chamfer == pytest.approx(0.05, abs=0.002)
    assert report.hausdorff == pytest.approx(0.05, abs=0.002)


def test_default_distances_are_to_the_data_points():
    f = Analytic(lambda xy: dist(xy, (0, 0)) - 1.0)
    data = circle_samples(50)
    report = ls.analyze(f, data)
    assert report.reference == "data points"
    # Gaps between data points: the zero set's farthest point is half a chord away.
    half_gap = np.sin(np.pi / 50)
    assert report.hausdorff == pytest.approx(half_gap, rel=0.05)


def test_tiny_loop_is_counted():
    xs, ys, h = ls.sampling_grid((-1.5, -1.5), (1.5, 1.5), 128)
    node = np.array([xs[100], ys[100]])  # a loop around one grid node
    f = Analytic(lambda xy: (dist(xy, (0, 0)) - 1.0) * (dist(xy, node) - 0.4 * h))
    report = ls.analyze(f, circle_samples(200), resolution=128)
    assert report.num_components == 2
    assert report.num_tiny_loops == 1
    assert report.num_supplementary == 1
    tiny = [c for c in report.components if c.tiny][0]
    assert tiny.closed and tiny.length < 4 * h


def test_open_components_and_empty_zero_set():
    line = Analytic(lambda xy: xy[:, 0] - 0.25)
    report = ls.analyze(line, np.array([[0.25, -1.0], [0.25, 0.0], [0.25, 1.0]]))
    assert report.num_components == 1 and not report.components[0].closed
    assert report.components[0].length == pytest.approx(3.0, rel=1e-6)
    empty = Analytic(lambda xy: jnp.sum(xy**2, axis=1) + 1.0)
    report = ls.analyze(empty, circle_samples(10))
    assert report.num_components == 0 and report.num_supplementary == 0
    assert report.chamfer == np.inf and report.hausdorff == np.inf
    assert report.as_dict()["num_components"] == 0


def test_plateau_of_zeros_is_reported():
    # g vanishes identically for x < 0: the zero set there is an area.
    f = Analytic(lambda xy: jnp.maximum(xy[:, 0], 0.0) * (dist(xy, (0, 0)) - 1.0))
    report = ls.analyze(f, circle_samples(100), resolution=128)
    assert report.zero_area_fraction == pytest.approx(0.5, abs=0.02)


def test_resolution_default_and_grid():
    xs, ys, h = ls.sampling_grid((0, 0), (4, 2))
    assert len(xs) == ls.DEFAULT_RESOLUTION >= 512
    assert len(ys) == 257 and h == pytest.approx(4 / 511)
    with pytest.raises(ValueError):
        ls.sampling_grid((0, 0), (0, 1))
    with pytest.raises(ValueError, match="points"):
        ls.analyze(Analytic(lambda xy: xy[:, 0]), np.zeros((3, 3)))


def test_float32_spline_does_not_crash(circle_fit):
    points, sol = circle_fit
    s = sol.spline
    s32 = jurs.ImplicitSpline(
        *(jnp.asarray(getattr(s, k), jnp.float32) for k in ("control", "weights", "lower", "upper"))
    )
    r32 = ls.analyze(s32, points, resolution=256)
    r64 = ls.analyze(s, points, resolution=256)
    assert r32.num_components == r64.num_components == 1
    assert r32.chamfer == pytest.approx(r64.chamfer, rel=1e-3)


def test_polylines_table_and_zero_level_set(circle_fit):
    points, sol = circle_fit
    lines = ls.zero_level_set(sol.spline, resolution=200)
    assert len(lines) == 1 and lines[0][1]
    report = ls.analyze(sol.spline, points, resolution=200)
    table = ls.polylines_table(report.components)
    assert table.shape == (len(report.components[0].polyline), 5)
    np.testing.assert_allclose(table[:, 3:], lines[0][0])


@pytest.mark.slow
def test_spline_save_load_roundtrip(tmp_path, circle_fit):
    _, sol = circle_fit
    path = tmp_path / "s.npz"
    jurs.save_spline(path, sol.spline)
    back = jurs.load_spline(path)
    xy = np.random.default_rng(0).uniform(-2, 2, (50, 2))
    np.testing.assert_array_equal(np.asarray(back(xy)), np.asarray(sol.spline(xy)))
    np.savez(tmp_path / "bad.npz", control=np.zeros((9, 9)))
    with pytest.raises(ValueError, match="missing"):
        jurs.load_spline(tmp_path / "bad.npz")
    with pytest.raises(FileNotFoundError):
        jurs.load_spline(tmp_path / "nope.npz")


def _brute_polyline_distance(p, v):
    a, b = v[:-1], v[1:]
    ab = b - a
    t = np.clip(np.einsum("kij,ij->ki", p[:, None] - a[None], ab) / np.sum(ab * ab, 1), 0, 1)
    foot = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(foot - p[:, None], axis=2), axis=1)


def test_distance_to_polyline_is_to_segments_not_vertices():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    points = np.array([[0.5, -0.25], [1.5, 0.5], [0.5, 0.5], [0.5, 1e-9], [-1.0, -1.0]])
    closed = ls.distance_to_polyline(points, square, closed=True)
    np.testing.assert_allclose(closed, [0.25, 0.5, 0.5, 1e-9, np.sqrt(2.0)], rtol=1e-12)
    # Open: the left side (last vertex back to the first) is not a segment.
    assert ls.distance_to_polyline([[-0.5, 0.5]], square)[0] == pytest.approx(np.hypot(0.5, 0.5))
    assert ls.distance_to_polyline([[-0.5, 0.5]], square, closed=True)[0] == pytest.approx(0.5)
    # Against brute force on an irregular polyline with long and short segments.
    rng = np.random.default_rng(0)
    v = np.cumsum(rng.normal(size=(40, 2)) * rng.uniform(0.01, 1.0, (40, 1)), axis=0)
    p = rng.uniform(v.min(0) - 1, v.max(0) + 1, (300, 2))
    np.testing.assert_allclose(
        ls.distance_to_polyline(p, v), _brute_polyline_distance(p, v), rtol=1e-12, atol=1e-15
    )
    assert np.all(np.isinf(ls.distance_to_polyline(p[:3], np.empty((0, 2)))))


def test_project_to_zero_set_lands_on_the_curve():
    f = lambda xy: np.linalg.norm(xy, axis=1) - 1.0  # noqa: E731

    def grad(xy):
        with np.errstate(invalid="ignore"):  # 0 / 0 at the centre: no usable gradient
            return xy / np.linalg.norm(xy, axis=1, keepdims=True)

    start = np.array([[1.3, 0.0], [0.0, 0.7], [0.6, 0.6], [0.0, 0.0]])
    for g in (grad, None):  # exact gradient, then central differences
        x, ok = ls.project_to_zero_set(f, start, grad=g)
        np.testing.assert_array_equal(ok, [True, True, True, False])
        np.testing.assert_allclose(np.linalg.norm(x[:3], axis=1), 1.0, atol=1e-12)
        # Along each point's ray (the gradient direction), to its foot on the circle.
        np.testing.assert_allclose(
            x[:3] / np.linalg.norm(x[:3], axis=1, keepdims=True),
            start[:3] / np.linalg.norm(start[:3], axis=1, keepdims=True),
            atol=1e-12,
        )
        np.testing.assert_array_equal(x[3], [0.0, 0.0])  # no usable gradient: stays put
    with pytest.raises(ValueError, match="steps"):
        ls.project_to_zero_set(f, start, steps=-1)


@pytest.mark.slow
def test_refined_chamfer_resolves_what_the_sampled_one_cannot():
    ref = circle_samples(20000)
    coarse = circle_samples(400)  # the zero-set samples, e.g. from a contour
    for offset in (1e-6, 4e-6):
        f = lambda xy, r=1.0 + offset: np.linalg.norm(np.asarray(xy), axis=1) - r  # noqa: E731
        out = ls.refined_chamfer_hausdorff(f, coarse, ref, reference_samples=2000)
        assert out["chamfer"] == pytest.approx(offset, rel=1e-3)
        assert out["hausdorff"] == pytest.approx(offset, rel=1e-3)
        assert out["unconverged_zero"] == out["unconverged_reference"] == 0
        # The sampled distance sits on its floor (the 400 samples' spacing) for both.
        assert ls.chamfer_hausdorff(coarse * (1 + offset), ref)[0] > 1e-3
    # A spline's zero set, with its own gradient: what the first-order distance says.
    points, normals = jurs.datasets.ellipse(200, a=2.0, b=2.0)
    spline = jurs.fit(points, normals, grid=(12, 12), offset=0.1, eps=0.01).spline
    lines = ls.zero_level_set(spline, resolution=128)
    zero = np.concatenate([ls.resample(p, 0.01) for p, _ in lines])
    ref = circle_samples(20000, radius=2.0)
    out = ls.refined_chamfer_hausdorff(spline, zero, ref, grad=spline.grad, reference_samples=500)
    first_order = np.abs(np.asarray(spline(ref))) / np.linalg.norm(
        np.asarray(spline.grad(ref)), axis=1
    )
    assert out["unconverged_zero"] == out["unconverged_reference"] == 0
    assert out["chamfer"] == pytest.approx(first_order.mean(), rel=0.05)
    assert out["hausdorff"] == pytest.approx(first_order.max(), rel=0.05)
    assert out["chamfer"] < 0.5 * ls.chamfer_hausdorff(zero, ref)[0]  # the sampled floor
    # Without grad, a spline's own gradient (jitted) is the default.
    default = ls.refined_chamfer_hausdorff(spline, zero, ref, reference_samples=500)
    assert default == pytest.approx(out, rel=1e-9)
    empty = ls.refined_chamfer_hausdorff(spline, np.empty((0, 2)), ref)
    assert empty["chamfer"] == empty["hausdorff"] == np.inf
    no_reference = ls.refined_chamfer_hausdorff(spline, zero, np.empty((0, 2)))
    assert no_reference["chamfer"] == no_reference["hausdorff"] == np.inf
    with pytest.raises(ValueError, match="reference_samples"):
        ls.refined_chamfer_hausdorff(spline, zero, ref, reference_samples=0)
