"""Automatic grids fall into few shape classes: clouds of one shape and similar size share
a grid, and so one compiled fit (jurs._fit.settings.choose_grid; docs/design.md section 5,
"Compiled shapes")."""

import jax
import numpy as np
import pytest
from test_compile import _CompileCounter  # counts jurs.fit's solve compilations

import jurs
from jurs._fit.settings import CELL_SPACINGS, DEFAULT_MAX_GRID, MIN_GRID, choose_grid
from jurs._problem.sizes import round_octave, round_size

jax.config.update("jax_enable_x64", True)

CAP = DEFAULT_MAX_GRID - 3


def _cells_asked(extent, spacing):
    """The cells a side that the data ask for: ``CELL_SPACINGS`` spacings wide (or as the
    cap allows)."""
    extent = np.asarray(extent, float)
    h = max(CELL_SPACINGS[2] * spacing, float(extent.max()) / CAP)
    return np.ceil(extent / h - 1e-9).astype(int)


def test_a_curves_grid_is_one_class_an_octave_and_never_coarser():
    """Over an octave of spacings (17-32 cells along the longest side) one box gets one
    grid: the longest side's cell count a power of two, the other side's on the
    ``round_size`` ladder; every side has at least the cells the data ask for, within the
    cap."""
    lower, extent = np.zeros(2), np.array([10.0, 7.0])
    grids = set()
    for spacing in np.geomspace(10.0 / (1.5 * 16.5), 10.0 / (1.5 * 32), 12):
        asked = _cells_asked(extent, spacing)
        assert 17 <= asked[0] <= 32
        grid = choose_grid(lower, extent, spacing, 0.0)
        grids.add(grid)
        cells = np.asarray(grid) - 3
        assert np.all(cells >= asked)  # never coarser than the data ask for
        assert cells[0] == round_octave(asked[0])
        assert cells[1] == round_size(cells[1])
    assert len(grids) == 1, grids


def test_the_grid_cap_and_the_smallest_grid_hold():
    """Above the last power of two under the cap (64 cells) the longest side keeps
    ``round_size``'s four sizes an octave, within the cap; tiny boxes get ``MIN_GRID``;
    the shorter side never exceeds the longer one's cells."""
    lower = np.zeros(2)
    for extent, spacing in (((10.0, 7.0), 0.08), ((10.0, 3.0), 0.1), ((10.0, 7.0), 5.0)):
        extent = np.asarray(extent)
        grid = choose_grid(lower, extent, spacing, 0.0)
        asked = _cells_asked(extent, spacing)
        assert max(grid) <= DEFAULT_MAX_GRID and min(grid) >= MIN_GRID
        assert grid[0] >= grid[1]
        assert np.all(np.asarray(grid) - 3 >= np.minimum(asked, CAP))
        if asked[0] > 64:
            assert grid[0] - 3 == min(round_size(asked[0]), CAP)


def _cloud_pair():
    """Example 1 at 93 points, scaled 1.3x and moved, and at 100 points: 7 % apart in
    spacing (one cell more or less on a side), both padded to 128 points."""
    points_a, normals_a = jurs.datasets.example1(93)
    return (1.3 * points_a + np.array([2.0, -1.0]), normals_a), jurs.datasets.example1(100)


def test_clouds_of_one_shape_and_similar_size_get_one_grid():
    """The 93- and 100-point clouds of Example 1 (on the ``round_size`` ladder alone they
    got 24 and 28 cells along x) get one automatic grid."""
    (pa, na), (pb, nb) = _cloud_pair()
    # A smoothing given skips the held-out choice of it (a compilation), not the grid's.
    grid_a = jurs.auto_settings(pa, na, smoothing=1e-6).grid
    assert grid_a == jurs.auto_settings(pb, nb, smoothing=1e-6).grid


@pytest.mark.slow  # one compilation of the default fit (10-20 s on a 2-core CPU)
def test_a_new_small_cloud_compiles_no_new_fit():
    """End to end, with automatic settings: after the 93-point cloud's fit, the 100-point
    cloud of the same shape compiles no fit of its own (the startup target below the
    grid cap, benchmarks/startup.py)."""
    # Another test in this process may have compiled the pair's program already: start
    # from empty caches, so that the first fit's compilation shows the counter counts.
    jax.clear_caches()
    counts = []
    for points, normals in _cloud_pair():
        with _CompileCounter(name="") as counter:
            jax.block_until_ready(jurs.fit(points, normals).spline)
        counts.append(counter.count)
    assert counts[0] >= 1 and counts[1] == 0, counts
