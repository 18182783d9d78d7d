"""The spanning-tree orientation baseline of benchmarks/normals.py (``_baselines.orient_mst``,
Hoppe et al. 1992): it fails where nested rings need more than propagation, and is right on a
single convex curve, so the benchmark's planted cases can tell the methods apart."""

import numpy as np

import jurs
import jurs.datasets
import jurs.shapes

from .._baselines import orient_mst


def correct_sign(normals, truth):
    """Share of points whose normal points the true (outward) way."""
    return float(np.mean(np.sum(normals * truth, axis=1) > 0))


def circles(m, radii, centres):
    """Circles sampled by arc length, oriented as jurs.shapes does (even-odd filling)."""
    t = np.linspace(0.0, 2 * np.pi, 2048, endpoint=False)
    comps = [np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)] for r, c in zip(radii, centres)]
    return jurs.shapes.sample_outline(jurs.shapes.orient(comps), m)


def test_baseline_fails_where_the_field_is_needed():
    """Hoppe's spanning tree flips a whole ring of nested rings (and gives holes the wrong
    sign); a single convex curve is easy for it."""
    points, truth = circles(800, (1.0, 0.85), ((0, 0), (0, 0)))
    unsigned = jurs.estimate_normals(points, orient=False)
    share = correct_sign(orient_mst(points, unsigned), truth)
    assert max(share, 1 - share) < 0.9
    circle, circle_truth = jurs.datasets.parametric_curve(
        lambda t: (np.cos(t), np.sin(t)), lambda t: (-np.sin(t), np.cos(t)), 300
    )
    unsigned = jurs.estimate_normals(circle, orient=False)
    share = correct_sign(orient_mst(circle, unsigned), circle_truth)
    assert share == 1.0


def test_the_topmost_point_of_each_tree_points_up():
    """Each tree's sign is set by its topmost point (largest last coordinate): its normal
    points up, whatever the input's signs."""
    points, truth = circles(400, (1.0,), ((0, 0),))
    flipped = -truth * np.where(np.arange(len(truth)) % 3 == 0, -1.0, 1.0)[:, None]
    normals = orient_mst(points, flipped)
    top = np.argmax(points[:, -1])
    assert normals[top, -1] > 0
    assert correct_sign(normals, truth) == 1.0
