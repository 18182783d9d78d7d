"""Built-in point clouds (the paper's analytic examples), noise, and file loading.

Every generator returns ``(points, normals)`` as float64 NumPy arrays of shape ``(m, 2)``,
normals unit length and pointing out of the enclosed region.
"""

from __future__ import annotations

import csv
import os
from typing import Callable

import numpy as np


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
) -> tuple[np.ndarray, np.ndarray]:
    """Sample a closed curve at ``num_points`` uniform parameters t in [0, 2 pi)."""
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    t = np.linspace(0.0, 2.0 * np.pi, num_points, endpoint=False)
    points = np.stack(curve(t), axis=1)
    return points, _outward(points, np.stack(derivative(t), axis=1))


def example1(num_points: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """The paper's Example 1: x = 4 cos t, y = sin t (3 - 5 sin t), 120 points by default.

    A simple closed curve with a concave dent at the top (upper branch minus lower branch
    at the same x is 6 sin t > 0).
    """
    return parametric_curve(
        lambda t: (4.0 * np.cos(t), np.sin(t) * (3.0 - 5.0 * np.sin(t))),
        lambda t: (-4.0 * np.sin(t), 3.0 * np.cos(t) - 10.0 * np.sin(t) * np.cos(t)),
        num_points,
    )


def ellipse(num_points: int = 500, a: float = 4.0, b: float = 5.0):
    """The ellipse x = a cos t, y = b sin t (Example 10's clean curve: a = 4, b = 5)."""
    return parametric_curve(
        lambda t: (a * np.cos(t), b * np.sin(t)),
        lambda t: (-a * np.sin(t), b * np.cos(t)),
        num_points,
    )


def add_noise(points, normals, *, sigma: float, normal_sigma: float | None = None, seed: int = 0):
    """Gaussian noise: ``sigma`` on point coordinates, ``normal_sigma`` (default ``sigma``
    relative to unit length) on normals, which are then re-normalised. Reproducible by seed."""
    if sigma < 0 or (normal_sigma is not None and normal_sigma < 0):
        raise ValueError("noise levels must be non-negative")
    rng = np.random.default_rng(seed)
    normal_sigma = sigma if normal_sigma is None else normal_sigma
    noisy_points = points + sigma * rng.standard_normal(points.shape)
    noisy_normals = normals + normal_sigma * rng.standard_normal(normals.shape)
    return noisy_points, noisy_normals / np.linalg.norm(noisy_normals, axis=1, keepdims=True)


def example9(seed: int = 0, sigma: float = 0.05):
    """Example 9: Example 1's curve with 400 noisy points. The paper gives no noise level;
    ``sigma = 0.05`` (0.5 % of the bounding-box diagonal) is this library's choice."""
    return add_noise(*example1(400), sigma=sigma, seed=seed)


def example10(seed: int = 0, sigma: float = 0.05):
    """Example 10: the ellipse 4 cos t, 5 sin t with 500 noisy points (``sigma`` as in
    :func:`example9`; the paper gives none)."""
    return add_noise(*ellipse(500), sigma=sigma, seed=seed)


COLUMNS = ("x", "y", "nx", "ny")


def _from_table(rows: np.ndarray, path: str, row_numbers=None):
    """``(points, normals)`` of a table of 4 columns, ``(points, None)`` of 2, checked;
    errors name the row by ``row_numbers`` (the file's 1-based line of each row; default
    1, 2, ...)."""
    if rows.ndim != 2 or rows.shape[1] not in (2, 4):
        raise ValueError(f"{path}: expected an (m, 4) table with columns x, y, nx, ny "
                         f"(or (m, 2): x, y, without normals), got shape {rows.shape}")
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
        raise ValueError(f"{path}: row {row_numbers[int(np.argmax(zero))]} has a "
                         "zero-length normal")
    return rows[:, :2].copy(), rows[:, 2:].copy()


def load_points(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read points and normals from ``.npy`` (an (m, 4) array) or CSV/TXT (columns x, y, nx,
    ny; comma, whitespace or semicolon separated; an optional header line of names).

    A table of two columns (x, y; header ``x,y``) holds points without normals: the normals
    come back as None (:func:`jurs.fit` then estimates them). The header, or else the first
    data row, sets the number of columns for every row.

    Raises ValueError naming the file and the (1-based, as in an editor) row for missing
    columns, non-numbers, NaN/Inf, zero normals or an empty table; FileNotFoundError if
    the file is missing.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file")
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
    lines = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip()
             and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{path}: no data rows")
    delimiter = "," if "," in lines[0][1] else (";" if ";" in lines[0][1] else None)

    def split(line):
        if delimiter is None:
            return line.split()
        return [c.strip() for c in next(csv.reader([line], delimiter=delimiter))]

    first = split(lines[0][1])
    names = [c.lower() for c in first]
    columns = COLUMNS[:len(first)] if len(first) in (2, 4) else COLUMNS
    if names in (list(COLUMNS), list(COLUMNS[:2])):
        lines = lines[1:]
    elif any(_not_number(c) for c in first) and not all(_not_number(c) for c in first):
        pass  # a malformed data row: reported below with its row number
    elif all(_not_number(c) for c in first):
        raise ValueError(f"{path}: row {lines[0][0]}: header must be x, y, nx, ny (or x, y "
                         f"without normals), got {first}")
    if not lines:
        raise ValueError(f"{path}: no data rows")
    values = np.empty((len(lines), len(columns)))
    for k, (lineno, line) in enumerate(lines):
        cells = split(line)
        if len(cells) != len(columns):
            raise ValueError(f"{path}: row {lineno}: expected {len(columns)} columns "
                             f"{', '.join(columns)}, got {len(cells)}")
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


def save_points(path, points, normals=None) -> None:
    """Write points and normals as ``.npy`` (m, 4) or CSV with an ``x,y,nx,ny`` header;
    ``normals=None`` writes the points alone ((m, 2), header ``x,y``)."""
    path = os.fspath(path)
    parts = [np.asarray(points, float)] + ([] if normals is None else [np.asarray(normals, float)])
    table = np.concatenate(parts, axis=1)
    if path.lower().endswith(".npy"):
        np.save(path, table)
    else:
        np.savetxt(path, table, delimiter=",", header=",".join(COLUMNS[:table.shape[1]]),
                   comments="", fmt="%.17g")
