"""What ``jurs fit`` reads: its argument types, and the cloud file.

The option types of the parser (``--grid``'s numbers, non-negative and positive numbers),
``grid_for``, which matches ``--grid`` to the cloud's dimension, and ``read_input``, which
reads the cloud; every problem raises ``InputError``, which the command reports in one line
with exit code 2. ``printable`` makes a file name safe to print.
"""

from __future__ import annotations

import argparse
import math
import os
import sys


class InputError(Exception):
    """A problem with the user's input file or options: one line, exit code 2."""


def grid_option(text: str) -> tuple:
    """``--grid``: one, two or three numbers >= 4 (``N``, ``NxM``, ``NxMxK``), as given;
    ``grid_for`` matches them to the cloud's dimension once the file is read."""
    try:
        parts = tuple(int(p) for p in text.lower().replace("*", "x").split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"grid must be N, NxM (2D) or NxMxK (3D), got {text!r}"
        ) from None
    if len(parts) > 3 or min(parts) < 4:
        raise argparse.ArgumentTypeError(
            f"grid must be N, NxM (2D) or NxMxK (3D) with every number >= 4, got {text!r}"
        )
    return parts


def grid_for(parts, dim: int, shown: str):
    """``--grid``'s numbers for the ``dim``-D cloud of the file ``shown``: None (chosen from
    the data), one number for every axis, or one per axis; InputError for a 2D grid on a
    3D cloud and the reverse."""
    if parts is None or len(parts) == dim:
        return parts
    if len(parts) == 1:
        return parts * dim
    given = "x".join(map(str, parts))
    wanted = "N or NxM" if dim == 2 else "N or NxMxK"
    raise InputError(
        f"{shown}: --grid {given} is for a {len(parts)}D cloud; this cloud is {dim}D: give {wanted}"
    )


def nonnegative(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return v


def positive_number(text: str) -> float:
    v = nonnegative(text)
    if v == 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return v


def face_count(text: str) -> int:
    """``--faces``: an integer >= 4 (``jurs.levelset.mesh``'s face budget)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < 4:
        raise argparse.ArgumentTypeError(f"must be at least 4, got {text!r}")
    return v


def printable(text) -> str:
    """``text`` safe to print and to draw: a file name that is not UTF-8 reaches Python with
    its bytes as lone surrogates, which stdout, JSON and the figure's title cannot encode;
    each such byte becomes U+FFFD."""
    return os.fsencode(text).decode("utf-8", "replace") if isinstance(text, str) else str(text)


def read_input(path: str):
    """Points and normals from ``path``; every problem raises ``InputError`` with a
    one-line message naming the file (and the row where there is one). A UTF-8 byte-order
    mark before a text file's header is skipped. What the reader notes (a triangle mesh
    read as points drawn on its faces) is printed on stderr as ``jurs: note: ...``."""
    import warnings

    import numpy as np

    from .. import datasets
    from ..datasets._files import TABLE_COLUMNS

    shown = printable(path)
    if os.path.isdir(path):
        raise InputError(f"{shown}: is a folder, not a file")
    if path.lower().endswith(".npy") and os.path.exists(path):
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except Exception as exc:
            raise InputError(f"{shown}: not a readable .npy array ({one_line(exc)})") from None
        if arr.ndim != 2 or arr.shape[1] not in TABLE_COLUMNS:
            raise InputError(
                f"{shown}: expected an (m, c) array of c = 2 (x y), 3 (x y z), 4 "
                f"(x y nx ny) or 6 (x y z nx ny nz) columns, got shape {arr.shape}"
            )
    try:
        with warnings.catch_warnings(record=True) as notes:
            warnings.simplefilter("always", UserWarning)
            points, normals = datasets.load_points(path)
    except (ValueError, OSError) as exc:
        msg = printable(one_line(exc))
        raise InputError(msg if msg.startswith(shown) else f"{shown}: {msg}") from None
    for note in notes:
        print(f"jurs: note: {printable(one_line(note.message))}", file=sys.stderr)
    if len(points) < 3:
        raise InputError(f"{shown}: need at least 3 data rows, got {len(points)}")
    return points, normals


def one_line(exc) -> str:
    return " ".join(str(exc).split())
