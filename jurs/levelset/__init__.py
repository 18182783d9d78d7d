"""The zero-level set of a fitted spline: extraction, supplementary components, distances.

A user judges an implicit fit by its zero set {g = 0}: does it follow the data, and does it
grow extra curves away from the data (the paper's *supplementary zero-level sets*, Section
IV)? This module measures both. It depends on NumPy, SciPy and contourpy only (no
matplotlib), so it can run in scripts and on servers without a display.

Definitions (all lengths in data units):

* **Sampling grid.** g is evaluated on a regular grid over the box (default the spline's
  own box) with ``resolution`` nodes along the longer side and the same spacing ``h`` (the
  *cell size*) along the shorter one.
* **Zero-level set.** The polylines of marching squares (``contourpy``, ``serial``
  algorithm) at level 0 on that grid. Each connected polyline is a *component*; it is
  *closed* when it returns to its start, *open* when it ends on the box border.
* **Length** of a component: the sum of its segment lengths.
* **Distance of a component to the data**: the distance from each segment midpoint to the
  nearest data point (a KD-tree query), weighted by segment length. A component is
  **supplementary** when more than half of its length lies farther than ``threshold``
  (default ``2 d``, twice the offset of the fit, or an eighth of a cell of the fit's grid
  where that is more: a grid capped far coarser than a dense cloud's spacing follows the
  data to within a fraction of its cells, not to within 2 d) from the data, i.e. its
  arc-length median
  distance exceeds the threshold. The median, not the mean: a true curve that bridges a
  gap in the sampling has the gap's large distances in its mean (a rose with 8 % of its
  outline unsampled, clean data: the mean was above 2 d and flagged the curve itself) but
  most of its length on the data, while an extra curve away from the data has most of its
  length off it. The arc-length mean is kept too (``mean_distance``). A **closed**
  component is supplementary, too, when less than half of its length lies by data it
  *carries* (``carried_fraction``): the nearest data point within ``threshold`` and no
  other component nearer to that point. A small loop beside the data, whose points the
  true curve passes through (a traced horse's tail grew one, 2 components and 0
  supplementary before), carries none. Surfaces
  ([`analyze_mesh`][jurs.levelset.analyze_mesh]) follow the same rules by area.
* A **tiny loop** is a closed component shorter than ``tiny_cells * h`` (default 4 cells):
  a sign flip at one or two grid nodes, at the resolution limit of the grid.
* **Chamfer and Hausdorff distances** between the zero set Z and a reference set Y: Z is
  resampled along its arc length at spacing ``h / 2``; with ``d(a, B) = min_b |a - b|``,
  ``chamfer = (mean_{z in Z} d(z, Y) + mean_{y in Y} d(y, Z)) / 2`` (symmetric, mean of
  unsquared distances) and ``hausdorff = max(max_z d(z, Y), max_y d(y, Z))``. Y is the given
  reference curve (dense samples) or, when none is given, the data points. Against sparse
  data points the Z -> Y half includes the gaps between points (up to half the spacing).
  With an empty zero set both are ``inf``.
* **Refined distances**
  ([`refined_chamfer_hausdorff`][jurs.levelset.refined_chamfer_hausdorff]): the same two
  distances with the sampling floor removed, for comparing accurate fits. The floor above is
  about ``h / 8`` whatever the fit (marching squares' own error and the resampling), so two
  fits whose zero sets lie far closer to the curve than that measure alike. Here zero-set
  samples are moved onto the zero set by Newton steps and measured to the reference
  polyline's segments, and reference points are projected onto the zero set the same way.
* **Zero-area fraction**: the fraction of grid nodes where ``|g| <= zero_tol * max|g|``
  (default ``1e-12``). Where g vanishes identically (e.g. coefficients that no sample
  touches stay exactly 0 under I-PIA started from C = 0) the zero set is an area, not a
  curve; the contour then traces the border of that plateau, and the component count
  there describes the plateau's shape on the grid. A large fraction flags this case.
* Caveat: the distance of a curve that passes through every data point is about a
  quarter of the data spacing on average; the default threshold ``2 d`` suits clouds whose
  spacing is below ``8 d``. Pass ``threshold`` for sparser data.

For 3D splines the same questions are asked of a triangle mesh of the zero set:
[`mesh`][jurs.levelset.mesh], [`analyze_mesh`][jurs.levelset.analyze_mesh],
[`mesh_distances`][jurs.levelset.mesh_distances] and friends (meshing in
``jurs/levelset/_meshing.py``, measuring in ``jurs/levelset/_mesh_analysis.py``; see
docs/surfaces.md).

Open scans and open curves: [`trim_mesh`][jurs.levelset.trim_mesh] (or ``mesh(...,
points=, trim=, rim=)``) and [`trim_curves`][jurs.levelset.trim_curves] (or
``analyze(..., trim=, rim=)``) keep the part of a zero set the data support: within
``trim`` local point spacings amid the samples, ``rim`` past the data's rim
(``jurs/levelset/_trimming.py``; docs/surfaces.md, "Open scans").
"""

# Curves (2D) in _curves, their refined distances in _distances; surfaces (3D) meshed in
# _meshing and measured in _mesh_analysis; one public namespace.
from ._curves import (
    BYTES_PER_NODE,
    DEFAULT_RESOLUTION,
    DEFAULT_THRESHOLD_FACTOR,
    DEFAULT_TINY_CELLS,
    FIT_CELL_FRACTION,
    Component,
    LevelSetReport,
    analyze,
    analyze_grid,
    chamfer_hausdorff,
    classify,
    contour_lines,
    evaluate_grid,
    polyline_length,
    polylines_table,
    resample,
    sampling_grid,
    zero_level_set,
)
from ._distances import distance_to_polyline, project_to_zero_set, refined_chamfer_hausdorff
from ._faces import face_areas
from ._mesh_analysis import (
    MeshComponent,
    MeshReport,
    analyze_mesh,
    boundary_loops,
    genus,
    mesh_components,
    mesh_distances,
)
from ._meshing import mesh
from ._trimming import DEFAULT_RIM, DEFAULT_TRIM, trim_curves, trim_mesh

__all__ = [
    "DEFAULT_RESOLUTION",
    "FIT_CELL_FRACTION",
    "BYTES_PER_NODE",
    "DEFAULT_TINY_CELLS",
    "DEFAULT_THRESHOLD_FACTOR",
    "DEFAULT_RIM",
    "DEFAULT_TRIM",
    "sampling_grid",
    "evaluate_grid",
    "contour_lines",
    "zero_level_set",
    "polyline_length",
    "resample",
    "chamfer_hausdorff",
    "distance_to_polyline",
    "project_to_zero_set",
    "refined_chamfer_hausdorff",
    "Component",
    "LevelSetReport",
    "classify",
    "analyze",
    "analyze_grid",
    "polylines_table",
    "MeshComponent",
    "MeshReport",
    "analyze_mesh",
    "boundary_loops",
    "face_areas",
    "genus",
    "mesh",
    "mesh_components",
    "mesh_distances",
    "trim_mesh",
    "trim_curves",
]

# Public names report the public module (help(), the docs, pickles), not the private one
# they are defined in.
for _name in __all__:
    if hasattr(globals()[_name], "__module__"):
        try:
            globals()[_name].__module__ = __name__
        except (AttributeError, TypeError):  # constants
            pass
del _name
