"""Built-in point clouds (the paper's analytic examples), noise, and file loading.

Every generator returns ``(points, normals)`` as float64 NumPy arrays of shape ``(m, 2)``
(the 3D ones [`sphere3d`][jurs.datasets.sphere3d], [`torus`][jurs.datasets.torus],
[`genus2`][jurs.datasets.genus2] and [`sample_mesh`][jurs.datasets.sample_mesh]:
``(m, 3)``), normals unit length and pointing out of the enclosed region. Point clouds are
read and written by [`load_points`][jurs.datasets.load_points] /
[`save_points`][jurs.datasets.save_points], triangle meshes by
[`load_mesh`][jurs.datasets.load_mesh] / [`save_mesh`][jurs.datasets.save_mesh] (3D files
through trimesh, an optional dependency).
"""

from __future__ import annotations

import csv
import os
from typing import Callable

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int


def _outward(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Unit normals from tangents of a closed curve, oriented outward by the signed area."""
    x, y = points[:, 0], points[:, 1]
    signed_area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    normals = np.stack([tangents[:, 1], -tangents[:, 0]], axis=1)  # outward if CCW
    if signed_area < 0:
        normals = -normals
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def parametric_curve(
    curve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    derivative: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    num_points: int,
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Sample a closed curve at ``num_points`` uniform parameters t in [0, 2 pi)."""
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    t = np.linspace(0.0, 2.0 * np.pi, num_points, endpoint=False)
    points = np.stack(curve(t), axis=1)
    return points, _outward(points, np.stack(derivative(t), axis=1))


def example1(num_points: int = 120) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """The paper's Example 1: x = 4 cos t, y = sin t (3 - 5 sin t), 120 points by default.

    A simple closed curve with a concave dent at the top (upper branch minus lower branch
    at the same x is 6 sin t > 0).
    """
    return parametric_curve(
        lambda t: (4.0 * np.cos(t), np.sin(t) * (3.0 - 5.0 * np.sin(t))),
        lambda t: (-4.0 * np.sin(t), 3.0 * np.cos(t) - 10.0 * np.sin(t) * np.cos(t)),
        num_points,
    )


def ellipse(
    num_points: int = 500, a: float = 4.0, b: float = 5.0
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """The ellipse x = a cos t, y = b sin t (Example 10's clean curve: a = 4, b = 5)."""
    return parametric_curve(
        lambda t: (a * np.cos(t), b * np.sin(t)),
        lambda t: (-a * np.sin(t), b * np.cos(t)),
        num_points,
    )


def add_noise(
    points: Float[np.ndarray, "m d"],
    normals: Float[np.ndarray, "m d"],
    *,
    sigma: float,
    normal_sigma: float | None = None,
    seed: int = 0,
) -> tuple[Float[np.ndarray, "m d"], Float[np.ndarray, "m d"]]:
    """Gaussian noise: ``sigma`` on point coordinates, ``normal_sigma`` (default ``sigma``
    relative to unit length) on normals, which are then re-normalised. Reproducible by seed."""
    if sigma < 0 or (normal_sigma is not None and normal_sigma < 0):
        raise ValueError("noise levels must be non-negative")
    rng = np.random.default_rng(seed)
    normal_sigma = sigma if normal_sigma is None else normal_sigma
    noisy_points = points + sigma * rng.standard_normal(points.shape)
    noisy_normals = normals + normal_sigma * rng.standard_normal(normals.shape)
    return noisy_points, noisy_normals / np.linalg.norm(noisy_normals, axis=1, keepdims=True)


def example9(
    seed: int = 0, sigma: float = 0.05
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Example 9: Example 1's curve with 400 noisy points. The paper gives no noise level;
    ``sigma = 0.05`` (0.5 % of the bounding-box diagonal) is this library's choice."""
    return add_noise(*example1(400), sigma=sigma, seed=seed)


def example10(
    seed: int = 0, sigma: float = 0.05
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Example 10: the ellipse 4 cos t, 5 sin t with 500 noisy points (``sigma`` as in
    [`example9`][jurs.datasets.example9]; the paper gives none)."""
    return add_noise(*ellipse(500), sigma=sigma, seed=seed)


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


def _count(m) -> int:
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
        raise ValueError(f"the number of points must be a positive int, got {m!r}")
    return int(m)


def sphere3d(
    m: int, radius: float = 1.0, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly (by area) on the sphere of ``radius`` about the origin,
    with their outward unit normals; ``(points (m, 3), normals (m, 3))``."""
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    # Normalised Gaussian vectors are uniform on the sphere (rotation invariance).
    normals = np.random.default_rng(seed).standard_normal((_count(m), 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return radius * normals, normals


def torus(
    m: int, major: float = 1.0, minor: float = 0.35, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly (by area) on the torus about the z axis with tube
    centre radius ``major`` and tube radius ``minor`` (``0 < minor < major``), with outward
    unit normals.

    The torus ``((R + r cos v) cos u, (R + r cos v) sin u, r sin v)`` has area element
    ``r (R + r cos v) du dv``: ``u`` is uniform, ``v`` is drawn by rejection against that
    density.
    """
    if not 0 < minor < major:
        raise ValueError(f"need 0 < minor < major, got minor={minor}, major={major}")
    m = _count(m)
    rng = np.random.default_rng(seed)
    v = np.empty(0)
    while len(v) < m:
        candidate = rng.uniform(0.0, 2.0 * np.pi, 2 * m)
        keep = rng.uniform(0.0, major + minor, 2 * m) < major + minor * np.cos(candidate)
        v = np.concatenate([v, candidate[keep]])
    v = v[:m]
    u = rng.uniform(0.0, 2.0 * np.pi, m)
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    centres = major * np.stack([np.cos(u), np.sin(u), np.zeros(m)], axis=1)
    return centres + minor * normals, normals


#: The double torus of [`genus2`][jurs.datasets.genus2]: two tori about parallel axes
#: through (+-GENUS2_SHIFT, 0), of radii GENUS2_MAJOR, GENUS2_MINOR, joined by a smooth
#: minimum of blend width GENUS2_BLEND.
GENUS2_SHIFT, GENUS2_MAJOR, GENUS2_MINOR, GENUS2_BLEND = 1.0, 1.0, 0.35, 0.1


def genus2_function(
    points: Float[npt.ArrayLike, "n 3"],
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, "n 3"]]:
    """The implicit double torus sampled by [`genus2`][jurs.datasets.genus2] and its
    gradient at ``points (n, 3)``: ``(values (n,), gradients (n, 3))``, negative inside.

    The smooth minimum ``-k log(exp(-a / k) + exp(-b / k))`` of the signed distances ``a``,
    ``b`` to two tori whose tube centre circles touch at the origin: the tubes merge there,
    so the union is one closed surface with two holes, and the smooth minimum rounds the
    crease where the tubes meet (width ``k``). Near the surface the value is close to the
    signed distance.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    values, gradients = [], []
    for shift in (-GENUS2_SHIFT, GENUS2_SHIFT):
        q = p - [shift, 0.0, 0.0]
        ring = np.hypot(q[:, 0], q[:, 1])
        tube = np.stack([ring - GENUS2_MAJOR, q[:, 2]], axis=1)  # (radial, z) in the tube
        length = np.linalg.norm(tube, axis=1)
        values.append(length - GENUS2_MINOR)
        # On a torus's axis and its tube's centre circle the distance has no gradient
        # (far inside or outside the surface): 0 there instead of NaN.
        radial = q[:, :2] / np.where(ring > 0, ring, 1.0)[:, None]
        gradients.append(
            np.column_stack([tube[:, :1] * radial, tube[:, 1:]])
            / np.where(length > 0, length, 1.0)[:, None]
        )
    a, b = values
    k = GENUS2_BLEND
    value = -k * np.logaddexp(-a / k, -b / k)
    share = 1.0 / (1.0 + np.exp((a - b) / k))  # weight of a's gradient: softmax of -a/k, -b/k
    return value, share[:, None] * gradients[0] + (1.0 - share[:, None]) * gradients[1]


def genus2(m: int, seed: int = 0) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points on a smooth double torus (genus 2;
    [`genus2_function`][jurs.datasets.genus2_function]), uniform by area, with outward unit
    normals (the normalised gradient).

    Points are drawn uniformly in a shell of half-width 0.01 about the surface (first-order
    distance ``|f| / |grad f|``) and moved onto it by Newton steps. A thin shell's volume
    is area times width, so the landing points are uniform by area, up to a relative
    error of the order of (width x curvature)^2, 1e-3 here.
    """
    m = _count(m)
    rng = np.random.default_rng(seed)
    half = (
        np.array(
            [GENUS2_SHIFT + GENUS2_MAJOR + GENUS2_MINOR, GENUS2_MAJOR + GENUS2_MINOR, GENUS2_MINOR]
        )
        + 0.1
    )
    width = 0.01
    accepted = []
    total = 0
    while total < m:
        candidate = rng.uniform(-half, half, (1 << 16, 3))
        value, gradient = genus2_function(candidate)
        keep = np.abs(value) < width * np.linalg.norm(gradient, axis=1)
        accepted.append(candidate[keep])
        total += int(keep.sum())
    points = np.concatenate(accepted)[:m]
    for _ in range(8):  # from 0.01 off, quadratic convergence: far below 1e-12 after 4
        value, gradient = genus2_function(points)
        points = points - (value / np.sum(gradient * gradient, axis=1))[:, None] * gradient
    gradient = genus2_function(points)[1]
    return points, gradient / np.linalg.norm(gradient, axis=1, keepdims=True)


def sample_mesh(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"], m: int, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly by area on a triangle mesh, with the unit normal of the
    face each lies on (right-hand rule); ``(points (m, 3), normals (m, 3))``. Faces without
    area are never drawn; ValueError for a mesh without area."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(
            f"vertices and faces must have shapes (V, 3) and (F, 3), got "
            f"{vertices.shape} and {faces.shape}"
        )
    m = _count(m)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no area to sample")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(faces), size=m, p=area / area.sum())
    # Uniform in a triangle: reflect the unit square's upper half onto the lower.
    s, t = rng.uniform(size=(2, m))
    flip = s + t > 1.0
    s[flip], t[flip] = 1.0 - s[flip], 1.0 - t[flip]
    points = a[face] + s[:, None] * (b - a)[face] + t[:, None] * (c - a)[face]
    return points, cross[face] / area[face, None]


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
