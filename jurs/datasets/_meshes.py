"""Reading and writing triangle meshes: [`load_mesh`][jurs.datasets.load_mesh] and
[`save_mesh`][jurs.datasets.save_mesh] (PLY written by jurs itself, in float64 and with
vertex colours; the other formats through trimesh), and the vertex colours of a PLY
cloud for the command line."""

from __future__ import annotations

import os

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

from ._examples import mesh_arrays
from ._files import MESH_SUFFIXES, file_suffix, trimesh_module, write_ply


def load_mesh(
    path: str | os.PathLike[str],
) -> tuple[Float[np.ndarray, "V 3"], Int[np.ndarray, "F 3"]]:
    """A triangle mesh from a PLY, OBJ, STL or OFF file (by suffix), through trimesh;
    ``(vertices (V, 3) float64, faces (F, 3) int64)``.

    The vertices keep the file's order; STL, which stores every triangle's corners apart,
    has its coincident corners merged. Raises FileNotFoundError for a missing file and
    ValueError naming the file for another suffix, an unreadable file or one without faces.
    """
    path = os.fspath(path)
    if file_suffix(path) not in MESH_SUFFIXES:
        raise ValueError(f"{path}: mesh files are {', '.join(MESH_SUFFIXES)}")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    trimesh = trimesh_module()
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for malformed files
        raise ValueError(f"{path}: not a readable mesh ({exc})") from None
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))))
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"{path}: no triangle faces")
    # force="mesh" makes it a Trimesh; trimesh.load is annotated as returning any Geometry.
    if file_suffix(path) == ".stl":
        loaded.merge_vertices()  # pyright: ignore[reportAttributeAccessIssue]
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, np.int64)  # pyright: ignore[reportAttributeAccessIssue]


def save_mesh(
    path: str | os.PathLike[str],
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
    colors: Float[npt.ArrayLike, "V 3"] | None = None,
) -> None:
    """Write a triangle mesh as PLY (binary, float64 coordinates), OBJ or OFF (text, all
    17 digits) or STL (float32 by the format), by the suffix of ``path``, through trimesh
    but for PLY. PLY, OBJ and OFF keep every coordinate as given, however far from the
    origin; STL rounds them to float32 (about 1e-7 of their distance from the origin).

    ``colors``: ``(V, 3)`` vertex colours (PLY only), written as ``uchar`` red, green
    and blue properties: integers are 0-255; floats are [0, 1] where none exceeds
    ``UNIT_COLOR_MAX`` (a colour field fitted to [0, 1] values overshoots 1 a little),
    0-255 otherwise; values outside the range are clipped. ValueError for another
    shape, NaN or another format."""
    path = os.fspath(path)
    suffix = file_suffix(path)
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: mesh files are {', '.join(MESH_SUFFIXES)}")
    vertices, faces = mesh_arrays(vertices, faces)
    rgb = None if colors is None else _vertex_colors(path, colors, len(vertices))
    if rgb is not None and suffix != ".ply":
        raise ValueError(f"{path}: vertex colours are written to PLY only")
    if suffix == ".ply":
        write_ply(path, vertices, faces=np.asarray(faces, dtype=np.int64), colors=rgb)
        return
    trimesh = trimesh_module()
    # OBJ and OFF are text: all digits (trimesh's defaults keep 8 and 10).
    options = {"digits": 17} if suffix in (".obj", ".off") else {}
    trimesh.Trimesh(vertices, faces, process=False).export(path, file_type=suffix[1:], **options)


#: Float colours whose largest value is at most this are read as [0, 1], larger ones as
#: 0-255 (``save_mesh``).
UNIT_COLOR_MAX = 2.0


def _vertex_colors(path: str, colors, count: int) -> np.ndarray:
    """``colors`` as ``(count, 3)`` uint8 (``save_mesh`` states the rule); clipped."""
    c = np.asarray(colors)
    if c.dtype.kind not in "iuf" or c.shape != (count, 3):
        raise ValueError(
            f"{path}: colors must be a ({count}, 3) array of numbers (one row a vertex), "
            f"got shape {c.shape} and dtype {c.dtype}"
        )
    if c.dtype.kind == "f":
        if not np.isfinite(c).all():
            bad = int(np.argmax(~np.isfinite(c).all(axis=1)))
            raise ValueError(f"{path}: colors contain NaN or Inf (first at row {bad})")
        if c.size and c.max() <= UNIT_COLOR_MAX:
            c = c * 255.0
        c = np.rint(c)
    return np.clip(c, 0, 255).astype(np.uint8)


def ply_vertex_colors(path: str) -> np.ndarray | None:
    """``(V, 3)`` uint8 red, green and blue of a PLY point cloud's vertices, one row a
    vertex in the file's order (the rows [`load_points`][jurs.datasets.load_points]
    returns); None where the file is not a PLY, has no vertex colours, or has faces (a
    mesh is read as points drawn on its faces, which carry no file colour)."""
    if file_suffix(path) != ".ply":
        return None
    trimesh = trimesh_module()
    try:
        with open(path, "rb") as fh:
            data = trimesh.exchange.ply.load_ply(fh)
    except Exception:  # load_points names what is wrong with the file
        return None
    colors = data.get("vertex_colors")
    faces = data.get("faces")
    if colors is None or (faces is not None and len(faces)):
        return None
    colors = np.asarray(colors)
    if colors.ndim != 2 or colors.shape[1] < 3:
        return None
    return colors[:, :3].astype(np.uint8)
