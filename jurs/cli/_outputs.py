"""Where ``jurs fit`` writes: the output folder's checks and the atomic write.

The output names (``OUTPUTS``, ``OUTPUTS_3D``), the bytes they take (checked against the
free space before the fit), ``check_output_folder``, ``write_outputs`` (the whole set of
outputs or none, and no outputs of the other kind of run left beside them), and the files
every fit writes: metrics.json (strict JSON) and spline.npz,
and the figures.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import tempfile
import threading

from ._inputs import InputError, printable

#: The outputs of a curve fit (a 2D cloud) ...
OUTPUTS = ("metrics.json", "spline.npz", "fit.png", "zero_level.csv")
#: ... and of a surface fit (a 3D cloud).
OUTPUTS_3D = ("metrics.json", "spline.npz", "mesh.ply", "preview.png")


def json_safe(value):
    """Floats for 0-d arrays; non-finite numbers as null (strict JSON has no NaN/Inf)."""
    import numpy as np

    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (str, bool)) or value is None:
        return value
    arr = np.asarray(value)
    if arr.ndim == 0:
        if np.issubdtype(arr.dtype, np.integer):
            return int(arr)
        v = float(arr)
        return v if math.isfinite(v) else None
    return [json_safe(v) for v in arr.tolist()]


#: Bytes the outputs take beyond the spline and the polylines (the figure, the metrics).
OUTPUT_OVERHEAD = 8 << 20


def check_output_folder(out: str, need: int = OUTPUT_OVERHEAD, names=OUTPUTS) -> None:
    """Before the fit: InputError unless ``out`` is (or can be made) a folder we can write
    ``need`` bytes into, whose output ``names`` are free or plain files. A fit of minutes
    should not end in a traceback about permissions or a full disk."""
    shown = printable(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"{shown}: exists and is not a folder")
    for name in names:
        target = os.path.join(out, name)
        if os.path.lexists(target) and not os.path.isfile(target):
            raise InputError(f"{printable(target)}: exists and is not a file; move it away")
    existing = out
    while not os.path.isdir(existing):  # the folder that the output folder will be made in
        parent = os.path.dirname(existing)
        if parent == existing:
            break
        existing = parent
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{printable(existing)}: folder is not writable")
    free = shutil.disk_usage(existing).free
    if free < need:
        raise InputError(
            f"{printable(existing)}: only {free / 2**20:.1f} MiB free, the "
            f"outputs need about {need / 2**20:.1f} MiB"
        )


def previous_run_kind(out: str) -> int | None:
    """The dimension (2 or 3) of the fit whose outputs ``out`` holds, read from its
    metrics.json where jurs wrote that (a record with ``input``, ``settings`` and
    ``metrics``; a surface's also has ``mesh``); None where there is none or it is not
    jurs's."""
    try:
        with open(os.path.join(out, "metrics.json"), encoding="utf-8") as fh:
            record = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or not {"input", "settings", "metrics"} <= set(record):
        return None
    return 3 if "mesh" in record else 2


def stale_outputs(out: str, names) -> tuple:
    """The outputs of the other kind of run that ``out`` holds from jurs: a surface fit
    into a folder of a curve fit would leave fit.png and zero_level.csv beside its new
    files (and a curve fit mesh.ply and preview.png), which then read as this run's.
    Only files jurs wrote are named, told by the folder's metrics.json
    (``previous_run_kind``); files of those names without it are the user's, and kept."""
    kind = previous_run_kind(out)
    if kind is None:
        return ()
    theirs = outputs_for(kind)
    return tuple(n for n in theirs if n not in names and os.path.isfile(os.path.join(out, n)))


@contextlib.contextmanager
def _no_interrupts():
    """Ctrl-C held off while the old outputs are put back (in the main thread, where
    signal handlers live): a second Ctrl-C then cannot leave the folder half restored."""
    # A handler installed outside Python reads as None and could not be put back: then
    # Ctrl-C stays as it is (ignoring it would outlast the call, for this process and
    # the processes it starts).
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is None
    ):
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def write_outputs(out: str, write, names=OUTPUTS) -> None:
    """Write the whole set of output ``names`` into ``out``, or none: ``write(folder)``
    writes them all into a temporary folder made inside ``out`` (the same file system, so
    no parent folder need be writable, ``-o .`` included), then each is renamed into
    place, the old file set aside first. The outputs of the other kind of run that jurs
    wrote there before (``stale_outputs``) are set aside too, and go with the temporary
    folder: the folder then holds this run's outputs alone. Any failure, Ctrl-C included,
    renames back what was already replaced or set aside, so ``out`` keeps its whole old
    set. A folder ``out`` made here is removed again on failure. Files and the folder
    take the user's umask."""
    made = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".jurs-", dir=out)
    moved = []  # (name, had an old file, is a new output), in the order replaced
    done = False
    try:
        stale = stale_outputs(out, names)
        write(tmp)
        for name in names:
            target, old = os.path.join(out, name), os.path.join(tmp, name + ".old")
            had_old = os.path.lexists(target)
            if had_old:
                os.replace(target, old)
            moved.append((name, had_old, True))
            os.replace(os.path.join(tmp, name), target)
        for name in stale:
            os.replace(os.path.join(out, name), os.path.join(tmp, name + ".old"))
            moved.append((name, True, False))
        done = True
    except BaseException:
        with _no_interrupts():
            for name, had_old, new in reversed(moved):
                target, old = os.path.join(out, name), os.path.join(tmp, name + ".old")
                if new and not os.path.exists(os.path.join(tmp, name)) and os.path.lexists(target):
                    os.remove(target)  # the new file had been moved in
                if had_old:
                    os.replace(old, target)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if made and not done and not os.listdir(out):
            os.rmdir(out)


def outputs_for(dim: int) -> tuple:
    """The output names of a fit to a ``dim``-D cloud."""
    return OUTPUTS if dim == 2 else OUTPUTS_3D


#: Vertices of a surface mesh per node of a lattice plane (resolution^2), assumed by the
#: checks before a 3D fit: a sphere filling its box has about 2 (docs/surfaces.md,
#: "Meshing a spline"); four times that leaves room for folded surfaces.
MESH_VERTICES_PER_PLANE_NODE = 8
#: Peak bytes per vertex of jurs.levelset.mesh (measured about 450, docs/surfaces.md), and
#: bytes per vertex of mesh.ply (24 for the vertex in float64, two faces of 13).
MESH_BYTES_PER_VERTEX, PLY_BYTES_PER_VERTEX = 450, 50


#: The largest level-set grid side an adaptive curve gets without ``--resolution``.
MAX_ADAPTIVE_RESOLUTION = 2049


def write_record_and_spline(folder: str, record: dict, spline) -> None:
    """metrics.json and spline.npz into ``folder``: the outputs every fit writes."""
    import jurs

    with open(os.path.join(folder, "metrics.json"), "w", encoding="utf-8") as fh:
        json.dump(json_safe(record), fh, indent=2, allow_nan=False)
        fh.write("\n")
    jurs.save_spline(os.path.join(folder, "spline.npz"), spline)


def save_figure(fig, path: str, dpi: int) -> None:
    """Save ``fig``, a standalone figure on matplotlib's Agg canvas (``pyplot=False`` in
    [`jurs.plot`][]: pyplot and its backends never load, and nothing needs closing)."""
    fig.savefig(path, dpi=dpi)
