"""Reading and writing point clouds and triangle meshes.

Point clouds are read and written by [`load_points`][jurs.datasets.load_points] /
[`save_points`][jurs.datasets.save_points] (CSV, TXT and NPY tables in 2D; PLY, OBJ, XYZ
and PTS in 3D), triangle meshes by [`load_mesh`][jurs.datasets.load_mesh] /
[`save_mesh`][jurs.datasets.save_mesh] (3D files through trimesh, an optional
dependency). Public through [`jurs.datasets`][]; the built-in clouds are in
``jurs/datasets/_examples.py``.
"""

from __future__ import annotations

import csv
import os

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

COLUMNS = ("x", "y", "nx", "ny")


def _from_table(rows: np.ndarray, path: str, row_numbers=None):
    """``(points, normals)`` of a table of 4 columns, ``(points, None)`` of 2, checked;
    errors name the row by ``row_numbers`` (the file's 1-based line of each row; default
    1, 2, ...)."""
    if rows.ndim != 2 or rows.shape[1] not in (2, 4):
        raise ValueError(
            f"{path}: expected an (m, 4) table with columns x, y, nx, ny "
            f"(or (m, 2): x, y, without normals), got shape {rows.shape}"
        )
    if rows.shape[0] == 0:
        raise ValueError(f"{path}: no data rows")
    if row_numbers is None:
        row_numbers = np.arange(1, rows.shape[0] + 1)
    bad = ~np.isfinite(rows).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: row {row_numbers[int(np.argmax(bad))]} has NaN or Inf")
    if rows.shape[1] == 2:
        return rows.copy(), None
    zero = np.linalg.norm(rows[:, 2:], axis=1) == 0
    if zero.any():
        raise ValueError(
            f"{path}: row {row_numbers[int(np.argmax(zero))]} has a zero-length normal"
        )
    return rows[:, :2].copy(), rows[:, 2:].copy()


def load_points(
    path: str | os.PathLike[str],
) -> tuple[Float[np.ndarray, "m d"], Float[np.ndarray, "m d"] | None]:
    """Read points and normals from ``.npy`` (an (m, 4) array) or CSV/TXT (columns x, y, nx,
    ny; comma, whitespace or semicolon separated; an optional header line of names).

    3D clouds (``CLOUD_SUFFIXES``): ``.ply`` and ``.obj`` give their vertices, and
    their vertex normals where the file has them (through trimesh, ``pip install
    "jurs[surfaces]"``); ``.xyz`` and ``.pts`` are text rows of 3 (x y z) or 6 (x y z nx
    ny nz) numbers. Points come back ``(m, 3)``, normals ``(m, 3)`` or None.

    A table of two columns (x, y; header ``x,y``) holds points without normals: the normals
    come back as None ([`jurs.fit`][] then estimates them). The header, or else the first
    data row, sets the number of columns for every row.

    Raises ValueError naming the file and the (1-based, as in an editor) row for missing
    columns, non-numbers, NaN/Inf, zero normals or an empty table; FileNotFoundError if
    the file is missing.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    if _suffix(path) in CLOUD_SUFFIXES:
        return _load_cloud(path)
    if path.lower().endswith(".npy"):
        try:
            rows = np.load(path, allow_pickle=False)
        except Exception as exc:  # corrupt header, pickled objects, ...
            raise ValueError(f"{path}: not a readable .npy array ({exc})") from None
        if not np.issubdtype(rows.dtype, np.number):
            raise ValueError(f"{path}: array dtype {rows.dtype} is not numeric")
        return _from_table(np.asarray(rows, dtype=float), path)

    # utf-8-sig: a byte-order mark before the header (spreadsheet programs write one) is
    # skipped, not read as part of the first column's name.
    with open(path, newline="", encoding="utf-8-sig") as fh:
        text = fh.read()
    lines = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise ValueError(f"{path}: no data rows")
    delimiter = "," if "," in lines[0][1] else (";" if ";" in lines[0][1] else None)

    def split(line):
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader([line], delimiter=delimiter))]

    first = split(lines[0][1])
    names = [c.lower() for c in first]
    columns = COLUMNS[: len(first)] if len(first) in (2, 4) else COLUMNS
    if names in (list(COLUMNS), list(COLUMNS[:2])):
        lines = lines[1:]
    elif any(_not_number(c) for c in first) and not all(_not_number(c) for c in first):
        pass  # a malformed data row: reported below with its row number
    elif all(_not_number(c) for c in first):
        raise ValueError(
            f"{path}: row {lines[0][0]}: header must be x, y, nx, ny (or x, y "
            f"without normals), got {first}"
        )
    if not lines:
        raise ValueError(f"{path}: no data rows")
    values = np.empty((len(lines), len(columns)))
    for k, (lineno, line) in enumerate(lines):
        cells = split(line)
        if len(cells) != len(columns):
            raise ValueError(
                f"{path}: row {lineno}: expected {len(columns)} columns "
                f"{', '.join(columns)}, got {len(cells)}"
            )
        for j, c in enumerate(cells):
            if _not_number(c):
                raise ValueError(f"{path}: row {lineno}: {columns[j]} = {c!r} is not a number")
            values[k, j] = float(c)
    return _from_table(values, path, [lineno for lineno, _ in lines])


def _not_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return True
    return False


def save_points(
    path: str | os.PathLike[str],
    points: Float[npt.ArrayLike, "m d"],
    normals: Float[npt.ArrayLike, "m d"] | None = None,
) -> None:
    """Write points and normals as ``.npy`` (m, 4) or CSV with an ``x,y,nx,ny`` header;
    ``normals=None`` writes the points alone ((m, 2), header ``x,y``).

    3D points ``(m, 3)`` go to the suffixes of ``CLOUD_SUFFIXES``: ``.xyz``/``.pts``
    as text rows (all digits), ``.ply`` (binary, float32, through trimesh) and ``.obj``
    (``v`` and ``vn`` lines) with vertex normals when given.
    """
    path = os.fspath(path)
    if _suffix(path) in CLOUD_SUFFIXES:
        _save_cloud(path, points, normals)
        return
    if np.ndim(points) == 2 and np.shape(points)[1] == 3:
        raise ValueError(f"{path}: 3D points go to {', '.join(CLOUD_SUFFIXES)} files")
    parts = [np.asarray(points, float)] + ([] if normals is None else [np.asarray(normals, float)])
    table = np.concatenate(parts, axis=1)
    if path.lower().endswith(".npy"):
        np.save(path, table)
    else:
        np.savetxt(
            path,
            table,
            delimiter=",",
            header=",".join(COLUMNS[: table.shape[1]]),
            comments="",
            fmt="%.17g",
        )


# --- 3D: surfaces, meshes and point-cloud files -------------------------------------------

#: Suffixes [`load_points`][jurs.datasets.load_points] and
#: [`save_points`][jurs.datasets.save_points] read and write as 3D clouds.
CLOUD_SUFFIXES = (".ply", ".obj", ".xyz", ".pts")
#: Suffixes [`load_mesh`][jurs.datasets.load_mesh] and
#: [`save_mesh`][jurs.datasets.save_mesh] handle (through trimesh).
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off")


def _trimesh():
    """trimesh, imported on first use (an optional dependency)."""
    try:
        # ``import trimesh`` loads its exchange modules; named here for a type checker.
        import trimesh
        import trimesh.exchange.obj
        import trimesh.exchange.ply
    except ImportError:
        raise ImportError(
            '3D point-cloud and mesh files need trimesh: pip install "jurs[surfaces]"'
        ) from None
    return trimesh


def _suffix(path: str) -> str:
    return os.path.splitext(path)[1].lower()


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
    if _suffix(path) not in MESH_SUFFIXES:
        raise ValueError(f"{path}: mesh files are {', '.join(MESH_SUFFIXES)}")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    trimesh = _trimesh()
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for malformed files
        raise ValueError(f"{path}: not a readable mesh ({exc})") from None
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))))
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"{path}: no triangle faces")
    # force="mesh" makes it a Trimesh; trimesh.load is annotated as returning any Geometry.
    if _suffix(path) == ".stl":
        loaded.merge_vertices()  # pyright: ignore[reportAttributeAccessIssue]
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, np.int64)  # pyright: ignore[reportAttributeAccessIssue]


def save_mesh(
    path: str | os.PathLike[str],
    vertices: Float[npt.ArrayLike, "V 3"],
    faces: Int[npt.ArrayLike, "F 3"],
) -> None:
    """Write a triangle mesh as PLY (binary, float32 coordinates), OBJ, STL (float32) or
    OFF, by the suffix of ``path``, through trimesh."""
    path = os.fspath(path)
    suffix = _suffix(path)
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: mesh files are {', '.join(MESH_SUFFIXES)}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(
            f"vertices and faces must have shapes (V, 3) and (F, 3), got "
            f"{vertices.shape} and {faces.shape}"
        )
    trimesh = _trimesh()
    # OBJ is text: all digits (trimesh's default keeps 8 decimals).
    options = {"digits": 17} if suffix == ".obj" else {}
    trimesh.Trimesh(vertices, faces, process=False).export(path, file_type=suffix[1:], **options)


def _load_cloud(path: str):
    """``(points (m, 3), normals (m, 3) or None)`` of a ``.ply``/``.obj`` (through trimesh:
    vertices, and vertex normals where the file has them) or ``.xyz``/``.pts`` file."""
    if _suffix(path) in (".xyz", ".pts"):
        return _load_xyz(path)
    trimesh = _trimesh()
    try:
        with open(path, "rb") as fh:
            if _suffix(path) == ".ply":
                data = trimesh.exchange.ply.load_ply(fh)
            else:
                data = trimesh.exchange.obj.load_obj(fh, maintain_order=True)
    except Exception as exc:  # trimesh raises many kinds for malformed files
        raise ValueError(
            f"{path}: not a readable {_suffix(path)[1:].upper()} file ({exc})"
        ) from None
    # An OBJ with faces comes back as named geometries; a cloud of "v" lines as one.
    parts = list(data["geometry"].values()) if "geometry" in data else [data]
    points = [np.asarray(p.get("vertices", np.empty((0, 3))), dtype=np.float64) for p in parts]
    normals = [p.get("vertex_normals") for p in parts]
    points = np.concatenate(points) if points else np.empty((0, 3))
    if any(n is None for n in normals) or not normals:
        return _checked_cloud(points, None, path)
    # No None left in normals (returned above); the checker cannot see that in a list.
    return _checked_cloud(points, np.concatenate(normals).astype(np.float64), path)  # pyright: ignore[reportCallIssue, reportArgumentType]


def _load_xyz(path: str):
    """Whitespace (or comma) separated rows ``x y z`` or ``x y z nx ny nz``; ``#`` starts
    a comment line. Errors name the file's 1-based row."""
    with open(path, encoding="utf-8-sig") as fh:
        lines = [
            (i + 1, line.replace(",", " ").split())
            for i, line in enumerate(fh)
            if line.strip() and not line.lstrip().startswith("#")
        ]
    if not lines:
        raise ValueError(f"{path}: no data rows")
    width = len(lines[0][1])
    if width not in (3, 6):
        raise ValueError(
            f"{path}: row {lines[0][0]}: expected 3 columns x y z or 6 x y z nx ny nz, got {width}"
        )
    values = np.empty((len(lines), width))
    for k, (lineno, cells) in enumerate(lines):
        if len(cells) != width:
            raise ValueError(f"{path}: row {lineno}: expected {width} columns, got {len(cells)}")
        try:
            values[k] = [float(c) for c in cells]
        except ValueError:
            raise ValueError(f"{path}: row {lineno}: not all numbers: {' '.join(cells)}") from None
    rows = [lineno for lineno, _ in lines]
    return _checked_cloud(values[:, :3], values[:, 3:] if width == 6 else None, path, rows)


def _checked_cloud(points, normals, path, row_numbers=None):
    """``(points, normals)`` with the checks of
    [`load_points`][jurs.datasets.load_points], 3D."""
    if len(points) == 0:
        raise ValueError(f"{path}: no points")
    if normals is not None and normals.shape != points.shape:
        raise ValueError(f"{path}: {len(normals)} normals for {len(points)} points")
    rows = np.arange(1, len(points) + 1) if row_numbers is None else np.asarray(row_numbers)
    label = "row" if row_numbers is not None else "point"
    table = points if normals is None else np.concatenate([points, normals], axis=1)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {label} {rows[int(np.argmax(bad))]} has NaN or Inf")
    if normals is not None:
        zero = np.linalg.norm(normals, axis=1) == 0
        if zero.any():
            raise ValueError(
                f"{path}: {label} {rows[int(np.argmax(zero))]} has a zero-length normal"
            )
    return points.copy(), None if normals is None else normals.copy()


def _save_cloud(path: str, points, normals) -> None:
    """[`save_points`][jurs.datasets.save_points]
    for the 3D suffixes."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: {_suffix(path)} files hold 3D points, got shape {points.shape}")
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(
                f"normals must have the shape of points {points.shape}, got {normals.shape}"
            )
    if _suffix(path) in (".xyz", ".pts"):
        table = points if normals is None else np.concatenate([points, normals], axis=1)
        np.savetxt(path, table, fmt="%.17g")
        return
    trimesh = _trimesh()
    cloud = trimesh.Trimesh(
        points, np.empty((0, 3), dtype=np.int64), vertex_normals=normals, process=False
    )
    if _suffix(path) == ".ply":
        data = trimesh.exchange.ply.export_ply(cloud, vertex_normal=normals is not None)
    else:
        data = trimesh.exchange.obj.export_obj(
            cloud, include_normals=normals is not None, digits=17
        ).encode()
    with open(path, "wb") as fh:
        fh.write(data)
