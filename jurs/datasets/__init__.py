"""Built-in point clouds (the paper's analytic examples), noise, and file loading.

Every generator returns ``(points, normals)`` as float64 NumPy arrays of shape ``(m, 2)``
(the 3D ones [`sphere3d`][jurs.datasets.sphere3d], [`torus`][jurs.datasets.torus],
[`genus2`][jurs.datasets.genus2], [`thin_plate`][jurs.datasets.thin_plate] and
[`sample_mesh`][jurs.datasets.sample_mesh]:
``(m, 3)``), normals unit length and pointing out of the enclosed region. Point clouds are
read and written by [`load_points`][jurs.datasets.load_points] /
[`save_points`][jurs.datasets.save_points], triangle meshes by
[`load_mesh`][jurs.datasets.load_mesh] / [`save_mesh`][jurs.datasets.save_mesh] (3D files
through trimesh, an optional dependency). A cloud no one process reads whole is read in
parts, one per process, by [`load_rows`][jurs.datasets.load_rows] and made global arrays
by [`global_arrays`][jurs.datasets.global_arrays] (docs/sharding.md).
"""

# The generators in _examples, file reading and writing in _files; one public namespace.
from ._examples import (
    GENUS2_BLEND,
    GENUS2_MAJOR,
    GENUS2_MINOR,
    GENUS2_SHIFT,
    add_noise,
    ellipse,
    example1,
    example9,
    example10,
    genus2,
    genus2_function,
    parametric_curve,
    sample_mesh,
    sphere3d,
    thin_plate,
    torus,
)
from ._files import (
    CLOUD_SUFFIXES,
    COLUMNS,
    FLOAT32_RESOLUTION,
    MESH_SAMPLES,
    MESH_SUFFIXES,
    TABLE_COLUMNS,
    load_points,
    save_points,
)
from ._meshes import load_mesh, save_mesh
from ._parts import NPY_COLUMNS, global_arrays, load_rows, part_files, part_rows

__all__ = [
    "parametric_curve",
    "example1",
    "ellipse",
    "add_noise",
    "example9",
    "example10",
    "COLUMNS",
    "TABLE_COLUMNS",
    "load_points",
    "save_points",
    "CLOUD_SUFFIXES",
    "MESH_SUFFIXES",
    "MESH_SAMPLES",
    "FLOAT32_RESOLUTION",
    "sphere3d",
    "torus",
    "thin_plate",
    "GENUS2_SHIFT",
    "GENUS2_MAJOR",
    "GENUS2_MINOR",
    "GENUS2_BLEND",
    "genus2_function",
    "genus2",
    "sample_mesh",
    "load_mesh",
    "save_mesh",
    "load_rows",
    "global_arrays",
    "part_rows",
    "part_files",
    "NPY_COLUMNS",
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
