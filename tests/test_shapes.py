"""jurs.shapes: sizes, sampling, and outward normals on shapes with several components and holes."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

import jurs.shapes as shapes


def _dense(components, spacing):
    """Points along the outline at most ``spacing`` apart (for distance queries)."""
    from jurs.levelset import resample

    return np.concatenate([resample(np.vstack([c, c[:1]]), spacing) for c in components])


@pytest.mark.parametrize("name", shapes.NAMES)
def test_normals_point_out_of_the_filled_region(name):
    """P + h n lies outside the even-odd filled region and P - h n inside.

    Where a step of h crosses another part of the outline (a glyph's sharp inner notch
    narrower than 2h), the test point lies within h of the outline and the side is not a
    property of the normal; those points are excluded, and must be rare.
    """
    points, normals = shapes.get(name, 600)
    comps = shapes.outline(name)
    h = 0.02
    tree = cKDTree(_dense(comps, h / 10))
    checked = 0
    for sign, want_inside in ((+1, False), (-1, True)):
        probe = points + sign * h * normals
        clear = tree.query(probe)[0] > 0.9 * h
        assert clear.mean() > 0.97, f"{name}: {np.sum(~clear)} probes near the outline"
        inside = shapes.contains(comps, probe[clear])
        bad = inside != want_inside
        assert not bad.any(), f"{name}: wrong side at {probe[clear][bad][:5]}"
        checked += clear.sum()
    assert checked > 1100


@pytest.mark.parametrize(
    "name,expected",
    [
        ("annulus", [1, -1]),
        ("glyph_B", [1, -1, -1]),
        ("glyph_8", [1, -1, -1]),
        ("glyph_a", [1, -1]),
        ("glyph_g", [1, -1]),
        ("rose", [1]),
        ("horse", [1]),
    ],
)
def test_holes_are_clockwise(name, expected):
    """Outer boundaries anticlockwise, holes clockwise (filled region on the left)."""
    comps = sorted(shapes.outline(name), key=lambda c: -abs(shapes.signed_area(c)))
    signs = [int(np.sign(shapes.signed_area(c))) for c in comps]
    assert signs == expected


def test_coins_has_24_separate_discs():
    comps = shapes.outline("coins")
    assert len(comps) == 24
    assert all(shapes.signed_area(c) > 0 for c in comps)  # no holes


@pytest.mark.parametrize("name", shapes.NAMES)
def test_size_centre_and_unit_normals(name):
    points, normals = shapes.get(name, 257, size=9.0, center=(1.0, -2.0))
    assert points.shape == normals.shape == (257, 2)
    assert points.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    comps = shapes.outline(name, size=9.0, center=(1.0, -2.0))
    allv = np.concatenate(comps)
    lo, hi = allv.min(axis=0), allv.max(axis=0)
    assert np.max(hi - lo) == pytest.approx(9.0)
    np.testing.assert_allclose(0.5 * (lo + hi), [1.0, -2.0], atol=1e-12)
    # The samples lie on the outline.
    assert cKDTree(_dense(comps, 1e-3)).query(points)[0].max() < 1e-3
    assert shapes.origin(name)


def test_uniform_arc_length_spacing():
    points, _ = shapes.get("ellipse", 400)
    step = np.linalg.norm(np.diff(np.vstack([points, points[:1]]), axis=0), axis=1)
    assert step.max() / step.min() < 1.01


def test_spacing_is_shared_between_components():
    """Each component gets points in proportion to its length."""
    comps = shapes.outline("annulus")
    points, _ = shapes.get("annulus", 500)
    lengths = np.array([np.sum(np.linalg.norm(np.roll(c, -1, 0) - c, axis=1)) for c in comps])
    on_hole = cKDTree(comps[1]).query(points)[0] < cKDTree(comps[0]).query(points)[0]
    assert abs(on_hole.mean() - lengths[1] / lengths.sum()) < 0.01


def test_nonuniform_and_gap():
    points, _ = shapes.get("ellipse", 400, nonuniform=0.5)
    step = np.linalg.norm(np.diff(np.vstack([points, points[:1]]), axis=0), axis=1)
    assert step.max() / step.min() == pytest.approx(3.0, rel=0.05)  # (1 + a) / (1 - a)

    full, _ = shapes.get("rose", 400)
    gapped, _ = shapes.get("rose", 400, gap=0.25, gap_at=0.5)
    assert len(gapped) == 400
    step_full = np.linalg.norm(full[1] - full[0])
    step_gap = np.linalg.norm(np.diff(np.vstack([gapped, gapped[:1]]), axis=0), axis=1)
    # Going round: one jump across the gap (a quarter of the outline), the other steps
    # 0.75 x the full spacing.
    assert np.sum(step_gap > 5 * step_full) == 1
    assert np.median(step_gap) == pytest.approx(0.75 * step_full, rel=0.02)


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown shape"):
        shapes.get("teapot", 10)
    with pytest.raises(ValueError, match="num_points"):
        shapes.get("rose", 2)
    with pytest.raises(ValueError, match="gap"):
        shapes.get("rose", 10, gap=1.0)
    with pytest.raises(ValueError, match="size"):
        shapes.get("rose", 10, size=0.0)


@pytest.mark.slow
def test_fits_as_input_to_jurs():
    """The outlines feed straight into jurs.fit (normals outward, so g < 0 inside)."""
    import jurs

    points, normals = shapes.get("glyph_a", 200)
    sol = jurs.fit(
        points,
        normals,
        grid=(10, 10),
        offset=0.1,
        eps=0.01,
        solver=jurs.IPIA(max_steps=100, tol=0.0),
    )
    inner = points - 0.1 * normals
    g = np.asarray(sol.spline(inner))
    assert np.mean(g < 0) > 0.9
