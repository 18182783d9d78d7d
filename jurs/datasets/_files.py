"""Reading and writing point clouds (triangle meshes: ``_meshes.py``).

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
from jaxtyping import Float

COLUMNS = ("x", "y", "nx", "ny")
#: The columns a table (CSV, TXT or ``.npy``) may hold, by their number: points in 2D or
#: 3D, with their normals or without. A header naming them decides which; without one,
#: the number of columns does.
TABLE_COLUMNS = {
    2: ("x", "y"),
    3: ("x", "y", "z"),
    4: ("x", "y", "nx", "ny"),
    6: ("x", "y", "z", "nx", "ny", "nz"),
}
_READINGS = {
    2: "2D points",
    3: "3D points",
    4: "2D points with normals",
    6: "3D points with normals",
}


def _columns_said(count: int) -> str:
    """``"x, y, z (3D points)"``: the columns of a table of ``count`` columns in words."""
    return f"{', '.join(TABLE_COLUMNS[count])} ({_READINGS[count]})"


def _all_readings() -> str:
    """``"2 (x y), 3 (x y z), 4 (x y nx ny) or 6 (x y z nx ny nz)"``."""
    said = [f"{n} ({' '.join(c)})" for n, c in TABLE_COLUMNS.items()]
    return ", ".join(said[:-1]) + " or " + said[-1]


def cloud_from_table(rows: np.ndarray, path: str, row_numbers=None):
    """``(points, normals)`` of a table of ``TABLE_COLUMNS`` columns, checked: 2 (x y) and
    4 (x y nx ny) give 2D points, 3 (x y z) and 6 (x y z nx ny nz) 3D points; normals None
    where the table has none. Errors name the row by ``row_numbers`` (the file's 1-based
    line of each row; default 1, 2, ...)."""
    if rows.ndim != 2 or rows.shape[1] not in TABLE_COLUMNS:
        raise ValueError(
            f"{path}: expected an (m, c) table of c = {_all_readings()} columns, "
            f"got shape {rows.shape}"
        )
    if rows.shape[0] == 0:
        raise ValueError(f"{path}: no data rows")
    if row_numbers is None:
        row_numbers = np.arange(1, rows.shape[0] + 1)
    if rows.shape[1] in (3, 6):  # 3D: the checks of a 3D cloud file
        normals = rows[:, 3:] if rows.shape[1] == 6 else None
        return checked_cloud(rows[:, :3], normals, path, row_numbers)
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


def _table_columns(path: str, first: list[str], lineno: int) -> tuple[tuple[str, ...], bool]:
    """``(columns, header)`` of a text table whose first row (line ``lineno``) splits into
    ``first``: a header of names decides the columns (``TABLE_COLUMNS``), else the number
    of cells in the first row does. ValueError naming both readings (the header's and the
    count's) where a header names other columns, and the readings there are for a count
    that has none."""
    names = tuple(c.lower() for c in first)
    if names in TABLE_COLUMNS.values():
        return names, True
    count = len(first)
    if all(_not_number(c) for c in first):
        known = " | ".join(",".join(c) for c in TABLE_COLUMNS.values())
        said = f"header {', '.join(first)} is not one of {known}"
        if {"z", "nz"} & set(names):
            said += " (its names read as 3D points)"
        elif {"nx", "ny"} & set(names):
            said += " (its names read as 2D points with normals)"
        if count in TABLE_COLUMNS:
            said += f"; without a header, {count} columns read as {_columns_said(count)}"
        raise ValueError(f"{path}: row {lineno}: {said}")
    if count not in TABLE_COLUMNS:
        raise ValueError(f"{path}: row {lineno}: expected {_all_readings()} columns, got {count}")
    # A row with a cell that is not a number is reported with its row when rows are read.
    return TABLE_COLUMNS[count], False


def load_points(
    path: str | os.PathLike[str],
    *,
    mesh_samples: int | None = None,
) -> tuple[Float[np.ndarray, "m d"], Float[np.ndarray, "m d"] | None]:
    """Read points and normals from ``.npy`` (an (m, c) array) or CSV/TXT (comma,
    whitespace or semicolon separated; an optional header line of names) tables of
    ``TABLE_COLUMNS``: 2 columns x, y or 4 x, y, nx, ny give 2D points, 3 columns x, y, z
    or 6 x, y, z, nx, ny, nz 3D points (normals None where the table has none). A header
    naming the columns decides; without one, the number of columns does. A header of other
    names is refused, naming its reading and the count's (``x,y,nx`` is neither 2D with
    normals nor 3D).

    3D clouds (``CLOUD_SUFFIXES``): ``.ply`` and ``.obj`` without faces give their
    vertices, and their vertex normals where the file has them (through trimesh, ``pip
    install ".[surfaces]"``); ``.xyz`` and ``.pts`` are text rows of 3 (x y z) or 6 (x y z
    nx ny nz) numbers. Points come back ``(m, 3)``, normals ``(m, 3)`` or None.

    Triangle meshes: a ``.ply``, ``.obj``, ``.stl`` or ``.off`` file with faces is read as
    the surface it describes, not as its vertices (which crowd where the mesh is fine and
    leave large faces empty): ``mesh_samples`` points are drawn uniformly by area on its
    faces, each with its face's unit normal (seed 0: the same file gives the same points),
    and a UserWarning says so. ``mesh_samples`` None takes the number of distinct vertices
    or ``MESH_SAMPLES``, whichever is larger. A closed mesh wound inward (negative volume)
    has its normals turned outward; an open one's follow its winding.

    Coordinates stored as float32 (PLY ``float``, binary STL) must resolve the cloud:
    ValueError, naming float32 precision, where their rounding at the cloud's distance
    from the origin exceeds ``FLOAT32_RESOLUTION`` of its bounding-box diagonal (points
    far from the origin collapse onto a few).

    A table without normals (x, y or x, y, z) gives normals None ([`jurs.fit`][] then
    estimates them). The header, or else the first data row, sets the number of columns
    for every row.

    Raises ValueError naming the file and the (1-based, as in an editor) row for missing
    columns, non-numbers, NaN/Inf, zero normals or an empty table, for an ASCII PLY whose
    body has other than the rows its header declares, for a file that is neither a point
    cloud nor a triangle mesh, and for a text file that is not UTF-8 text;
    FileNotFoundError if the file is missing.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
    if mesh_samples is not None:
        _positive_count(mesh_samples, "mesh_samples")
    if file_suffix(path) in CLOUD_SUFFIXES + MESH_SUFFIXES:
        return _load_cloud(path, mesh_samples)
    if path.lower().endswith(".npy"):
        try:
            rows = np.load(path, allow_pickle=False)
        except Exception as exc:  # corrupt header, pickled objects, ...
            raise ValueError(f"{path}: not a readable .npy array ({exc})") from None
        if not np.issubdtype(rows.dtype, np.number):
            raise ValueError(f"{path}: array dtype {rows.dtype} is not numeric")
        return cloud_from_table(np.asarray(rows, dtype=float), path)

    text = _read_text(path)
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
    columns, header = _table_columns(path, first, lines[0][0])
    if header:
        lines = lines[1:]
    if not lines:
        raise ValueError(f"{path}: no data rows")
    values = np.empty((len(lines), len(columns)))
    for k, (lineno, line) in enumerate(lines):
        cells = split(line)
        if len(cells) != len(columns):
            said = ", ".join(columns)
            if header:  # the header's reading, and the row's where it has one
                said = f"{_columns_said(len(columns))} as the header names them"
                if len(cells) in TABLE_COLUMNS:
                    said += f" (a row of {len(cells)} reads as {_columns_said(len(cells))})"
            raise ValueError(
                f"{path}: row {lineno}: expected {len(columns)} columns {said}, got {len(cells)}"
            )
        for j, c in enumerate(cells):
            if _not_number(c):
                raise ValueError(f"{path}: row {lineno}: {columns[j]} = {c!r} is not a number")
            values[k, j] = float(c)
    return cloud_from_table(values, path, [lineno for lineno, _ in lines])


def _read_text(path: str) -> str:
    """The text of ``path``, newlines kept as written; ValueError naming the file for bytes
    that are not UTF-8 (a binary file under a text suffix)."""
    # utf-8-sig: a byte-order mark before the header (spreadsheet programs write one) is
    # skipped, not read as part of the first column's name.
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            return fh.read()
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{path}: not a text file (byte {exc.start} is not UTF-8); points are read from "
            f"CSV, TXT, NPY, {', '.join(s[1:].upper() for s in _3D_SUFFIXES)} files"
        ) from None


def _positive_count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return int(value)


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
    as text rows (all digits), ``.ply`` (binary, float64) and ``.obj`` (``v`` and ``vn``
    lines, all digits, through trimesh) with vertex normals when given.
    """
    path = os.fspath(path)
    if file_suffix(path) in CLOUD_SUFFIXES:
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
_3D_SUFFIXES = tuple(dict.fromkeys(CLOUD_SUFFIXES + MESH_SUFFIXES))
#: Points [`load_points`][jurs.datasets.load_points] draws on a triangle mesh's faces
#: at least (more where the mesh has more vertices). 20 000 points drawn on a sphere or a
#: torus give the automatic settings (cells of 3 point spacings) their largest default
#: grid, 48 a side (``DEFAULT_MAX_GRID_3D``): fewer would coarsen the fit, more would cost
#: time for the same grid. A mesh with more vertices gets a point per vertex, as the same
#: surface given as a cloud would.
MESH_SAMPLES = 20_000
#: Float32 coordinates are refused where their rounding (the float32 spacing at the
#: largest coordinate) exceeds this share of the cloud's bounding-box diagonal: a fit's
#: cells are a few hundredths of the diagonal, and a 1e-4 rounding is far below them.
FLOAT32_RESOLUTION = 1e-4


def trimesh_module():
    """trimesh, imported on first use (an optional dependency)."""
    try:
        # ``import trimesh`` loads its exchange modules; named here for a type checker.
        import trimesh
        import trimesh.exchange.obj
        import trimesh.exchange.off
        import trimesh.exchange.ply
        import trimesh.exchange.stl
        import trimesh.repair
    except ImportError:
        raise ImportError(
            "3D point-cloud and mesh files need trimesh: from a clone of jurs, "
            'pip install ".[surfaces]"'
        ) from None
    return trimesh


def file_suffix(path: str) -> str:
    return os.path.splitext(path)[1].lower()


def write_ply(path: str, vertices, faces=None, normals=None, colors=None) -> None:
    """A binary little-endian PLY of float64 (``double``) vertices, with vertex normals
    where given, ``uchar`` red, green and blue where ``colors`` (uint8 ``(V, 3)``) are
    given, and triangle faces (``uchar`` count, ``int`` indices) where given. Written
    here, not by trimesh, whose PLY writer rounds every coordinate to float32: a mesh far
    from the origin would come back off by the float32 spacing there."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        fields += [("nx", "<f8"), ("ny", "<f8"), ("nz", "<f8")]
    channels = [("red", "u1"), ("green", "u1"), ("blue", "u1")] if colors is not None else []
    body = np.empty(len(vertices), dtype=fields + channels)
    for k, axis in enumerate("xyz"):
        body[axis] = vertices[:, k]
        if normals is not None:
            body["n" + axis] = normals[:, k]
    for k, (name, _) in enumerate(channels):
        body[name] = colors[:, k]  # pyright: ignore[reportOptionalSubscript]
    header = ["ply", "format binary_little_endian 1.0", "comment written by jurs"]
    header += [f"element vertex {len(vertices)}"]
    header += [f"property double {name}" for name, _ in fields]
    header += [f"property uchar {name}" for name, _ in channels]
    if faces is not None:
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise ValueError(f"faces must index the {len(vertices)} vertices")
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        rows["n"], rows["v"] = 3, faces
    with open(path, "wb") as fh:
        fh.write(("\n".join(header + ["end_header"]) + "\n").encode("ascii"))
        fh.write(body.tobytes())
        if faces is not None:
            fh.write(rows.tobytes())


def _load_cloud(path: str, mesh_samples: int | None = None):
    """``(points (m, 3), normals (m, 3) or None)`` of a 3D file: ``.xyz``/``.pts`` rows, or
    through trimesh a ``.ply``/``.obj`` cloud (vertices, and vertex normals where the file
    has them) or a ``.ply``/``.obj``/``.stl``/``.off`` mesh (points drawn on its faces,
    [`load_points`][jurs.datasets.load_points])."""
    if file_suffix(path) in (".xyz", ".pts"):
        return _load_xyz(path)
    if file_suffix(path) == ".ply":
        _check_ply_rows(path)
    vertices, faces, normals = _read_vertices_and_faces(path)
    if len(vertices) == 0:
        raise ValueError(f"{path}: neither a point cloud nor a triangle mesh (no vertices)")
    if len(faces):
        return _points_on_faces(path, vertices, faces, mesh_samples)
    if file_suffix(path) not in CLOUD_SUFFIXES:  # .stl, .off: meshes only
        raise ValueError(f"{path}: a {file_suffix(path)[1:].upper()} file without faces")
    points, normals = checked_cloud(vertices.astype(np.float64), normals, path)
    _check_float32(path, vertices, points)
    return points, normals


def _read_vertices_and_faces(path: str):
    """``(vertices (V, 3) in the file's float type, faces (F, 3) int64 (F may be 0),
    vertex normals (V, 3) float64 or None)`` of a PLY, OBJ, STL or OFF file, through
    trimesh's readers (an OBJ's groups joined); ValueError naming the file where trimesh
    cannot read it."""
    trimesh = trimesh_module()
    readers = {
        ".ply": trimesh.exchange.ply.load_ply,
        ".obj": lambda fh: trimesh.exchange.obj.load_obj(fh, maintain_order=True),
        ".stl": trimesh.exchange.stl.load_stl,
        ".off": trimesh.exchange.off.load_off,
    }
    try:
        with open(path, "rb") as fh:
            data = readers[file_suffix(path)](fh)
    except Exception as exc:  # trimesh raises many kinds for malformed files
        raise ValueError(
            f"{path}: not a readable {file_suffix(path)[1:].upper()} file ({_one_line(exc)})"
        ) from None
    # An OBJ with faces comes back as named geometries; a cloud of "v" lines as one.
    parts = list(data["geometry"].values()) if "geometry" in data else [data]
    vertices, faces, normals, offset = [], [], [], 0
    for part in parts:
        v = np.asarray(part.get("vertices", np.empty((0, 3))))
        f = part.get("faces")
        f = np.empty((0, 3), np.int64) if f is None else np.asarray(f, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or (len(f) and f.shape[1] != 3):
            raise ValueError(
                f"{path}: not a point cloud or a triangle mesh (vertices of shape {v.shape}, "
                f"faces of shape {f.shape})"
            )
        vertices.append(v)
        faces.append(f.reshape(-1, 3) + offset)
        normals.append(part.get("vertex_normals"))
        offset += len(v)
    if not vertices:
        return np.empty((0, 3)), np.empty((0, 3), np.int64), None
    vertices = np.concatenate(vertices)
    if any(n is None for n in normals):
        return vertices, np.concatenate(faces), None
    # No None left in normals (checked above); the checker cannot see that in a list.
    normals = np.concatenate(normals).astype(np.float64)  # pyright: ignore[reportCallIssue, reportArgumentType]
    return vertices, np.concatenate(faces), normals


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


def _check_ply_rows(path: str) -> None:
    """ValueError naming the file unless an ASCII PLY's body has the rows its header
    declares (one row per element; trimesh reads a body cut short without a word).
    Binary PLY is left to trimesh, which refuses a body of the wrong length."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
        marker = head.find(b"end_header")
        if not head.startswith(b"ply") or marker < 0:
            return  # not a PLY header trimesh can read either: trimesh's error names it
        lines = head[:marker].decode("ascii", "replace").splitlines()
        if not any(line.split()[:2] == ["format", "ascii"] for line in lines):
            return
        fh.seek(marker)
        fh.readline()  # the rest of the end_header line
        rows = sum(1 for line in fh if line.strip())
    elements = [line.split() for line in lines if line.split()[:1] == ["element"]]
    try:
        counts = [(e[1], int(e[2])) for e in elements]
    except (IndexError, ValueError):
        return  # a malformed element line: trimesh's error names it
    declared = sum(n for _, n in counts)
    if rows != declared:
        said = ", ".join(f"{n} {name}" for name, n in counts)
        short = "cut short" if rows < declared else "longer than its header says"
        raise ValueError(
            f"{path}: the header declares {declared} rows ({said}), the body has {rows}: "
            f"the file is {short}"
        )


def _check_float32(path: str, stored, points) -> None:
    """ValueError naming float32 precision where ``stored`` (the file's coordinates) are
    float32 whose rounding at the cloud's distance from the origin exceeds
    ``FLOAT32_RESOLUTION`` of the bounding-box diagonal of ``points`` (the same, float64):
    far from the origin float32 collapses a cloud onto a few points, which no later check
    could tell from coincident data."""
    if np.asarray(stored).dtype != np.float32 or len(points) == 0:
        return
    far = float(np.abs(points).max())
    rounding = float(np.spacing(np.float32(far)))
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    if rounding > FLOAT32_RESOLUTION * diagonal:
        distinct = len(np.unique(points, axis=0))
        raise ValueError(
            f"{path}: coordinates stored in float32 (single precision) are rounded to steps "
            f"of {rounding:.3g} at {far:.3g} from the origin, against a cloud "
            f"{diagonal:.3g} across ({distinct} distinct of {len(points)} points): float32 "
            f"cannot hold this cloud; write the file in float64 (PLY double) or move the "
            f"data near the origin"
        )


def _points_on_faces(path: str, vertices, faces, mesh_samples: int | None):
    """Points drawn uniformly by area on a mesh file's faces, with the faces' unit normals
    (outward where the mesh is closed), and a UserWarning saying so; ValueError naming the
    file for non-finite vertices, face indices out of range or no area."""
    import warnings

    from ._examples import sample_mesh

    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: vertex {int(np.argmax(bad)) + 1} has NaN or Inf")
    outside = (faces < 0) | (faces >= len(vertices))
    if outside.any():
        raise ValueError(
            f"{path}: face {int(np.argmax(outside.any(axis=1))) + 1} refers to vertex "
            f"index {int(faces[outside][0])}, the file has {len(vertices)} vertices"
        )
    float64 = vertices.astype(np.float64)
    _check_float32(path, vertices, float64)
    # Corners at the same place are one vertex (STL stores each triangle's apart): the
    # count of distinct vertices, and the edges that tell a closed mesh.
    unique, inverse = np.unique(float64, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    count = max(len(unique), MESH_SAMPLES) if mesh_samples is None else mesh_samples
    closed, volume = _closed_volume(unique, faces)
    rewound = None if closed else _rewound(unique, faces)
    if rewound is not None:
        faces = rewound
        closed, volume = _closed_volume(unique, faces)
    try:
        points, normals = sample_mesh(unique, faces, count, seed=0)
    except ValueError:
        raise ValueError(f"{path}: a triangle mesh whose faces have no area") from None
    if closed and volume < 0:
        normals = -normals  # wound inward: the faces' normals point into the solid
    if rewound is not None and closed:
        orientation = "outward (the mesh is closed; its faces, wound both ways, were re-wound)"
    elif closed:
        orientation = "outward (the mesh is closed)"
    else:
        orientation = "as its faces are wound (the mesh is not closed: check that they point out)"
    warnings.warn(
        f"{path}: a triangle mesh ({len(unique)} vertices, {len(faces)} faces), read as "
        f"{count} points drawn uniformly by area on its faces (seed 0), with the faces' "
        f"normals, {orientation}",
        UserWarning,
        stacklevel=4,
    )
    return points, normals


def _rewound(vertices, faces):
    """The faces of a closed mesh whose windings disagree (some faces listed clockwise,
    some anticlockwise), wound one way by trimesh's ``repair.fix_winding`` (a traversal of
    faces across their shared edges); None where that cannot make the mesh closed and
    consistent: a border edge, an edge of more than two faces, a non-orientable surface.
    Without it such a mesh's face normals point both ways, and a fit of them is refused."""
    trimesh = trimesh_module()
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if not mesh.is_watertight:  # each edge in exactly two faces, whatever their winding
        return None
    trimesh.repair.fix_winding(mesh)
    return np.asarray(mesh.faces, np.int64) if mesh.is_winding_consistent else None


def _closed_volume(vertices, faces) -> tuple[bool, float]:
    """``(closed, signed volume)`` of a mesh: closed when every directed edge appears once
    and its reverse once (a consistently wound surface without border); the volume is
    positive for outward winding."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = edges[edges[:, 0] != edges[:, 1]]
    forward = np.unique(edges, axis=0)
    if len(forward) != len(edges) or len(edges) == 0:
        return False, volume
    backward = np.unique(edges[:, ::-1], axis=0)
    return bool(np.array_equal(forward, backward)), volume


def _load_xyz(path: str):
    """Whitespace (or comma) separated rows ``x y z`` or ``x y z nx ny nz``; ``#`` starts
    a comment line. Errors name the file's 1-based row."""
    lines = [
        (i + 1, line.replace(",", " ").split())
        for i, line in enumerate(_read_text(path).splitlines())
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
    return checked_cloud(values[:, :3], values[:, 3:] if width == 6 else None, path, rows)


def checked_cloud(points, normals, path, row_numbers=None):
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
        raise ValueError(
            f"{path}: {file_suffix(path)} files hold 3D points, got shape {points.shape}"
        )
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(
                f"normals must have the shape of points {points.shape}, got {normals.shape}"
            )
    if file_suffix(path) in (".xyz", ".pts"):
        table = points if normals is None else np.concatenate([points, normals], axis=1)
        np.savetxt(path, table, fmt="%.17g")
        return
    if file_suffix(path) == ".ply":
        write_ply(path, points, normals=normals)
        return
    trimesh = trimesh_module()
    cloud = trimesh.Trimesh(
        points, np.empty((0, 3), dtype=np.int64), vertex_normals=normals, process=False
    )
    data = trimesh.exchange.obj.export_obj(
        cloud, include_normals=normals is not None, digits=17
    ).encode()
    with open(path, "wb") as fh:
        fh.write(data)
