"""The ``jurs`` command line.

    jurs demo [--output DIR]      the paper's Example 1 by I-PIA and IURS (table + figure)
    jurs fit FILE [options]       fit a point cloud (CSV, TXT or NPY; columns x, y, nx, ny,
                                  or x, y alone: outward normals are then estimated)
                                  and write, into --output:
                                    metrics.json     fit and level-set metrics (status:
                                                     the verdict's short name), settings
                                    spline.npz       the spline (jurs.load_spline reads it)
                                    fit.png          heatmap of g, zero set, data, offsets
                                    zero_level.csv   zero-level polylines: component, closed,
                                                     supplementary, x, y
    jurs fit SCAN [options]       fit a surface to a 3D cloud (PLY, OBJ, XYZ or PTS; vertex
                                  normals where the file has them, else estimated) and
                                  write, into --output:
                                    metrics.json     fit and mesh metrics, settings, timings
                                    spline.npz       the 3D spline (jurs.load_spline)
                                    mesh.ply         the zero set, meshed (marching cubes)
                                    preview.png      the mesh from three directions

Compiled fits are kept in JAX's persistent compilation cache in $XDG_CACHE_HOME/jurs (or
~/.cache/jurs), so later runs load them instead of compiling; --no-compilation-cache or
JURS_NO_COMPILATION_CACHE=1 turns that off.

Bad input files, options that do not fit the cloud's dimension, and output folders that
cannot be written or lack the space, give one line on stderr naming the file (and the row),
exit code 2, and write nothing; these are checked before the fit. A fit that diverges (NaN
energy), or outputs that fail to write after all, exit with code 1; the output folder then
keeps its whole previous set of outputs. A fit that ends with another verdict than success
or max_steps (inconsistent normals, weights at their floor) is written, with a warning on
stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import tempfile
import time
import warnings
from typing import TYPE_CHECKING, cast

from ._fit.compile import cache_disabled_by_environment, enable_compilation_cache

if TYPE_CHECKING:  # the command line imports NumPy and jurs's modules when it runs them
    import numpy as np

    from ._cloud.cloud import Cloud
    from ._fit.settings import Settings
    from .solvers import AbstractSolver

EXIT_BAD_INPUT = 2
EXIT_FIT_FAILED = 1
#: The outputs of a curve fit (a 2D cloud) ...
OUTPUTS = ("metrics.json", "spline.npz", "fit.png", "zero_level.csv")
#: ... and of a surface fit (a 3D cloud).
OUTPUTS_3D = ("metrics.json", "spline.npz", "mesh.ply", "preview.png")


class InputError(Exception):
    """A problem with the user's input file or options: one line, exit code 2."""


def _grid(text: str) -> tuple:
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


def _nonneg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return v


def _positive(text: str) -> float:
    v = _nonneg(text)
    if v == 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return v


def _solver_names():
    import jurs

    names = ["auto", "iurs", "ipia"]
    if hasattr(jurs, "LeastSquares"):
        names.append("lstsq")
    return names


def build_parser() -> argparse.ArgumentParser:
    """The ``jurs`` command line's parser: subcommands ``demo`` and ``fit``."""
    parser = argparse.ArgumentParser(
        prog="jurs",
        description="Implicit curve and surface reconstruction with uniform rational splines.",
        epilog="Run 'jurs fit --help' for the fit options.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="fit the paper's Example 1 with IPIA and IURS")
    demo.add_argument("--output", default="demo-output", help="folder for the figure")
    f = _fit_parser(sub)
    for command in (demo, f):
        command.add_argument(
            "--no-compilation-cache",
            action="store_true",
            help="do not keep compiled fits in JAX's persistent compilation cache "
            "($XDG_CACHE_HOME/jurs or ~/.cache/jurs; JURS_NO_COMPILATION_CACHE=1 "
            "does the same)",
        )
    return parser


def _fit_parser(sub) -> argparse.ArgumentParser:
    """The ``jurs fit`` subcommand and its options."""
    f = sub.add_parser(
        "fit",
        help="fit a point cloud from a CSV, TXT or NPY file (2D) or a PLY, OBJ, XYZ "
        "or PTS file (3D)",
        description="Fit an implicit spline to points with outward normals (columns x, y, "
        "nx, ny; or x, y alone, whose normals are then estimated) and write "
        "metrics.json, spline.npz, fit.png and zero_level.csv to --output. A 3D "
        "cloud (PLY, OBJ, XYZ or PTS; normals estimated where the file has none) "
        "gets a surface: metrics.json, spline.npz, mesh.ply and preview.png.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    f.add_argument(
        "file",
        help="CSV/TXT (columns x, y, nx, ny; optional header) or NPY (m, 4); "
        "3D: PLY or OBJ (vertices, vertex normals) or XYZ/PTS (rows "
        "x y z [nx ny nz])",
    )
    f.add_argument(
        "--grid",
        type=_grid,
        default=None,
        metavar="N[xM[xK]]",
        help="basis functions along x and y (and z: N or NxMxK for a 3D cloud); "
        "None chooses from the data (jurs.auto_settings)",
    )
    f.add_argument(
        "--solver",
        default="auto",
        choices=_solver_names(),
        help="auto: exact least squares with the automatic lambda; iurs: "
        "Algorithm 1 (rational); ipia: I-PIA (B-spline); lstsq: exact least "
        "squares (B-spline) with --lam",
    )
    f.add_argument(
        "--lam",
        type=_nonneg,
        default=None,
        help="regularisation weight: eq. 33's lambda for iurs (keep it well below "
        "1/16; None is 0), the objective's lambda in E_d + lam R for lstsq "
        "and auto (None chooses); ipia has none",
    )
    f.add_argument(
        "--smoothing",
        type=_nonneg,
        default=None,
        help="auto only: the dimensionless strength the automatic lambda is made "
        "from (jurs.auto_settings; about 1e-6 on clean clouds to 1e-3 on "
        "noisy ones); None chooses",
    )
    f.add_argument("--tau", type=_nonneg, default=1e-2, help="weight step size (iurs, eq. 20)")
    f.add_argument(
        "-d",
        "--offset",
        type=_positive,
        default=None,
        help="offset distance d; None chooses from the data",
    )
    f.add_argument(
        "--eps", type=_positive, default=None, help="target value at the offsets; None takes d"
    )
    f.add_argument(
        "--steps",
        type=int,
        default=200,
        help="maximum number of steps (iurs, ipia; lstsq solves once)",
    )
    f.add_argument(
        "--tol",
        type=_nonneg,
        default=1e-7,
        help="stop when |E_new - E_old| < tol (eq. 38); 0 runs all steps",
    )
    f.add_argument("-o", "--output", default="jurs-output", help="output folder")
    f.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="2D: level-set grid nodes along the longer side of the box (None: "
        "512); 3D: marching-cubes lattice nodes along the longest side "
        "(None: 5 per spline cell, 32 to 256)",
    )
    f.add_argument(
        "--threshold",
        type=_positive,
        default=None,
        help="distance to the data above which a zero-level component is "
        "supplementary; None means 2 d (2D), or 3 point spacings and at "
        "least 1%% of the cloud's diagonal (3D)",
    )
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    return f


def printable(text) -> str:
    """``text`` safe to print and to draw: a file name that is not UTF-8 reaches Python with
    its bytes as lone surrogates, which stdout, JSON and the figure's title cannot encode;
    each such byte becomes U+FFFD."""
    return os.fsencode(text).decode("utf-8", "replace") if isinstance(text, str) else str(text)


def read_input(path: str):
    """Points and normals from ``path``; every problem raises ``InputError`` with a
    one-line message naming the file (and the row where there is one). A UTF-8 byte-order
    mark before a text file's header is skipped."""
    import numpy as np

    from . import datasets

    shown = printable(path)
    if os.path.isdir(path):
        raise InputError(f"{shown}: is a folder, not a file")
    if path.lower().endswith(".npy") and os.path.exists(path):
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except Exception as exc:
            raise InputError(f"{shown}: not a readable .npy array ({_one_line(exc)})") from None
        if arr.ndim != 2 or arr.shape[1] not in (2, 4):
            raise InputError(
                f"{shown}: expected an (m, 4) array of rows x, y, nx, ny "
                f"(or (m, 2): x, y), got shape {arr.shape}"
            )
    try:
        points, normals = datasets.load_points(path)
    except (ValueError, OSError) as exc:
        msg = printable(_one_line(exc))
        raise InputError(msg if msg.startswith(shown) else f"{shown}: {msg}") from None
    if len(points) < 3:
        raise InputError(f"{shown}: need at least 3 data rows, got {len(points)}")
    return points, normals


def _one_line(exc) -> str:
    return " ".join(str(exc).split())


def make_solver(name: str, *, lam: float | None, tau: float, steps: int, tol: float, chosen=None):
    """The solver named on the command line; None for ``auto`` without ``--lam`` where
    settings were ``chosen``: [`jurs.fit`][] then takes the solver of those settings."""
    import jurs

    if steps < 0:
        raise InputError(f"--steps must be >= 0, got {steps}")
    if name == "auto" and lam is None and chosen is not None:
        return None  # jurs.fit's own, from the automatic settings
    if name == "auto":
        return jurs.LeastSquares(lam=0.0 if lam is None else lam)
    lam = 0.0 if lam is None else lam
    if name == "ipia":
        if lam:
            raise InputError(
                "--lam is not supported by ipia (I-PIA has no regulariser); use --solver iurs"
            )
        return jurs.IPIA(max_steps=steps, tol=tol)
    if name == "iurs":
        return jurs.IURS(tau=tau, lam=lam, max_steps=steps, tol=tol)
    if name == "lstsq":
        return jurs.LeastSquares(lam=lam)
    raise InputError(f"unknown solver {name!r}")


class ProgressBar:
    """A one-line progress bar on stderr, drawn only once a run has taken over ``delay``
    seconds (short fits print nothing)."""

    def __init__(
        self, label: str, delay: float = 1.0, width: int = 30, stream=None, enabled: bool = True
    ):
        self.label, self.delay, self.width = label, delay, width
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.start = time.perf_counter()
        self.drawn = False

    def __call__(self, done: int, total: int) -> None:
        elapsed = time.perf_counter() - self.start
        if not self.enabled or (elapsed < self.delay and not self.drawn):
            return
        frac = done / total if total else 1.0
        bar = "#" * int(round(frac * self.width))
        self.stream.write(
            f"\r{self.label} [{bar:<{self.width}}] {done}/{total} steps {elapsed:5.1f} s"
        )
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.drawn:
            self.stream.write("\n")
            self.stream.flush()


def _json_safe(value):
    """Floats for 0-d arrays; non-finite numbers as null (strict JSON has no NaN/Inf)."""
    import numpy as np

    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, (str, bool)) or value is None:
        return value
    arr = np.asarray(value)
    if arr.ndim == 0:
        if np.issubdtype(arr.dtype, np.integer):
            return int(arr)
        v = float(arr)
        return v if math.isfinite(v) else None
    return [_json_safe(v) for v in arr.tolist()]


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


def write_outputs(out: str, write, names=OUTPUTS) -> None:
    """Write the whole set of output ``names`` into ``out``, or none: ``write(folder)``
    writes them all into a temporary folder made inside ``out`` (the same file system, so
    no parent folder need be writable, ``-o .`` included), then each is renamed into
    place, the old file set aside first. Any failure renames back what was already
    replaced, so ``out`` keeps its whole old set. A folder ``out`` made here is removed
    again on failure. Files and the folder take the user's umask."""
    made = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".jurs-", dir=out)
    moved = []  # (name, had an old file), in the order replaced
    done = False
    try:
        write(tmp)
        for name in names:
            target, old = os.path.join(out, name), os.path.join(tmp, name + ".old")
            had_old = os.path.lexists(target)
            if had_old:
                os.replace(target, old)
            moved.append((name, had_old))
            os.replace(os.path.join(tmp, name), target)
        done = True
    except BaseException:
        for name, had_old in reversed(moved):
            target, old = os.path.join(out, name), os.path.join(tmp, name + ".old")
            if not os.path.exists(os.path.join(tmp, name)) and os.path.lexists(target):
                os.remove(target)  # the new file had been moved in
            if had_old:
                os.replace(old, target)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if made and not done and not os.listdir(out):
            os.rmdir(out)


#: Vertices of a surface mesh per node of a lattice plane (resolution^2), assumed by the
#: checks before a 3D fit: a sphere filling its box has about 2 (docs/surfaces.md,
#: "Meshing a spline"); four times that leaves room for folded surfaces.
MESH_VERTICES_PER_PLANE_NODE = 8
#: Peak bytes per vertex of jurs.levelset.mesh (measured about 450, docs/surfaces.md), and
#: bytes per vertex of mesh.ply (12 for the vertex, two faces of 13).
MESH_BYTES_PER_VERTEX, PLY_BYTES_PER_VERTEX = 450, 38


@dataclasses.dataclass(frozen=True)
class FitJob:
    """What ``jurs fit`` has read and checked before the fit: the cloud (``(m, 2)`` or
    ``(m, 3)``, normals given or estimated), the absolute output folder, the settings
    (``jurs.Settings``, with the options given), the solver and the level-set or
    marching-cubes resolution (None: the 3D default)."""

    path: str
    points: np.ndarray
    normals: np.ndarray
    estimated: bool
    out: str
    chosen: Settings
    solver: AbstractSolver | None  # None: jurs.fit's own, from ``chosen``
    resolution: int | None
    cloud: Cloud

    @property
    def dim(self) -> int:
        return int(self.points.shape[1])

    @property
    def shown(self) -> str:
        return printable(self.path)

    @property
    def grid(self) -> tuple:
        return tuple(self.chosen.grid)

    @property
    def lam(self) -> float:
        if self.solver is None:
            return float(self.chosen.lam)
        return float(getattr(self.solver, "lam", 0.0))

    @property
    def outputs(self) -> tuple:
        return outputs_for(self.dim)


def outputs_for(dim: int) -> tuple:
    """The output names of a fit to a ``dim``-D cloud."""
    return OUTPUTS if dim == 2 else OUTPUTS_3D


def _check_options(resolution, dim: int, out: str, names) -> None:
    """The options checked before anything is computed: the level-set (2D) or
    marching-cubes (3D) resolution, also against memory, and the output folder."""
    from . import levelset as ls
    from ._problem.memory import check_memory

    if resolution is not None:
        if resolution < 16:
            raise InputError(f"--resolution must be >= 16, got {resolution}")
        # 2D: the level-set grid is square at most. 3D: a mesh has about
        # MESH_VERTICES_PER_PLANE_NODE vertices per node of a lattice plane.
        per_node = (
            ls.BYTES_PER_NODE if dim == 2 else MESH_BYTES_PER_VERTEX * MESH_VERTICES_PER_PLANE_NODE
        )
        try:
            check_memory(
                f"--resolution {resolution}", per_node * float(resolution) ** 2, device=False
            )
        except ValueError as exc:
            raise InputError(_one_line(exc)) from None
    check_output_folder(out, names=names)


def _surface_libraries() -> None:
    """InputError unless the libraries a surface's outputs need are installed
    (scikit-image meshes, trimesh writes mesh.ply): found out before the fit, not after."""
    from .datasets._files import _trimesh
    from .levelset._meshing import _marching_cubes

    try:
        _marching_cubes()
        _trimesh()
    except ImportError as exc:
        raise InputError(f"a 3D cloud needs the surface extras: {_one_line(exc)}") from None


def _output_bytes(job: FitJob) -> int:
    """Bytes the outputs take: the spline (two grids of float64 in the .npz), the figure
    and the metrics, and in 2D the polylines (at most about resolution^2 / 2 vertices of
    ~40 bytes as text), in 3D the mesh (``MESH_VERTICES_PER_PLANE_NODE``)."""
    from .levelset._meshing import MAX_RESOLUTION

    spline = 16 * math.prod(job.grid)
    if job.dim == 2:
        r = job.resolution
        assert r is not None  # prepare_fit gives a 2D job the level-set default
        return OUTPUT_OVERHEAD + spline + 20 * min(r**2, 10 * r * len(job.points))
    r = job.resolution or MAX_RESOLUTION
    return OUTPUT_OVERHEAD + spline + PLY_BYTES_PER_VERTEX * MESH_VERTICES_PER_PLANE_NODE * r**2


def prepare_fit(args) -> FitJob:
    """Read the cloud and check everything that can be checked before the fit (options
    against the cloud's dimension, normals, settings, solver, output folder and its free
    space); every problem raises ``InputError``."""
    import jurs

    from . import levelset as ls

    path = args.file
    shown = printable(path)
    points, normals = read_input(path)
    dim = int(points.shape[1])
    grid = grid_for(args.grid, dim, shown)
    if dim == 3:
        _surface_libraries()
    estimated = normals is None
    if estimated:  # no normals in the file: outward ones estimated first, as jurs.fit does
        try:
            # return_info=False: the normals alone, not the (normals, info) pair
            normals = cast("np.ndarray", jurs.estimate_normals(points))
        except (ValueError, TypeError) as exc:
            raise InputError(f"{shown}: {_one_line(exc)}") from None
    out = os.path.abspath(args.output)
    resolution = args.resolution
    if dim == 2 and resolution is None:
        resolution = ls.DEFAULT_RESOLUTION
    _check_options(resolution, dim, out, outputs_for(dim))
    if args.smoothing is not None and (args.solver != "auto" or args.lam is not None):
        raise InputError(
            "--smoothing sets the automatic lambda of --solver auto; give --lam instead"
        )
    try:  # the cloud checked once, then measured for the settings and fitted
        cloud = jurs.Cloud(points, normals)
        chosen = jurs.auto_settings(
            cloud, grid=grid, offset=args.offset, eps=args.eps, smoothing=args.smoothing
        )
    except (ValueError, TypeError) as exc:
        raise InputError(f"{shown}: {_one_line(exc)}") from None
    solver = make_solver(
        args.solver, lam=args.lam, tau=args.tau, steps=args.steps, tol=args.tol, chosen=chosen
    )
    job = FitJob(path, points, normals, estimated, out, chosen, solver, resolution, cloud)
    check_output_folder(out, _output_bytes(job), job.outputs)
    return job


def _solve(job: FitJob, args):
    """``(solution, seconds)`` of the fit, with a progress bar; None (said on stderr) when
    it diverged. Settings the fit refuses (memory, precision) raise InputError."""
    import jax

    import jurs

    bar = ProgressBar(f"{args.solver} {'x'.join(map(str, job.grid))}", enabled=not args.quiet)
    t0 = time.perf_counter()
    try:
        # The automatic settings as chosen up front: with solver None jurs.fit takes their
        # solver, sets aside their stray points and checks its doubts, said below as the
        # verdict (not warned).
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            sol = jurs.fit(
                job.cloud, settings=job.chosen, solver=job.solver, callback=bar, throw=False
            )
    except (ValueError, TypeError) as exc:
        bar.close()
        raise InputError(f"{job.shown}: {_one_line(exc)}") from None
    jax.block_until_ready(sol.spline)
    seconds = time.perf_counter() - t0
    bar.close()
    if sol.result == jurs.RESULTS.nonfinite:
        print(
            f"jurs: error: {job.shown}: the fit diverged ({sol.message}); nothing written",
            file=sys.stderr,
        )
        return None
    if not sol.succeeded and sol.result != jurs.RESULTS.max_steps_reached:
        # Written all the same (the figure shows what went wrong), but said on stderr too.
        doubts = sol.stats.get("doubts") or ()
        said = "; ".join(doubts) if doubts else sol.message
        print(
            f"jurs: warning: {job.shown}: the fit's verdict is {sol.status}: {said}",
            file=sys.stderr,
        )
    return sol, seconds


def fit_record(job: FitJob, args, sol, seconds: float) -> dict:
    """The part of metrics.json that curves and surfaces share: input, settings and the
    fit's own metrics (the level-set or mesh measures are added to ``metrics``)."""
    metrics = {k: v for k, v in sol.metrics.items()}
    metrics.update(
        num_steps=int(sol.stats["num_steps"]),
        status=sol.status,
        result=sol.message,
        converged=bool(sol.succeeded),
        time_s=seconds,
    )
    return {
        "input": printable(os.path.abspath(job.path)),
        "num_points": int(len(job.points)),
        "normals": "estimated" if job.estimated else "given",
        "settings": {
            "solver": args.solver,
            "grid": list(job.grid),
            "lam": job.lam,
            "tau": args.tau if args.solver == "iurs" else None,
            "offset": job.chosen.offset,
            "eps": job.chosen.eps,
            "steps": args.steps,
            "tol": args.tol,
            "chosen_from_data": job.chosen.as_dict(),
        },
        "metrics": metrics,
    }


def _fit_title(job: FitJob, args, sol) -> str:
    """First lines of the figures' titles: file, solver, grid, lambda, E_ave."""
    return (
        f"{printable(os.path.basename(job.path))}: {args.solver}, grid "
        f"{'x'.join(map(str, job.grid))}, lam = {job.lam:.3g}\nE_ave = "
        f"{float(sol.metrics['E_ave']):.3e}, "
    )


def _write_record_and_spline(folder: str, record: dict, spline) -> None:
    """metrics.json and spline.npz into ``folder``: the outputs every fit writes."""
    import jurs

    with open(os.path.join(folder, "metrics.json"), "w", encoding="utf-8") as fh:
        json.dump(_json_safe(record), fh, indent=2, allow_nan=False)
        fh.write("\n")
    jurs.save_spline(os.path.join(folder, "spline.npz"), spline)


def _save_figure(fig, path: str, dpi: int) -> None:
    """Save ``fig``, a standalone figure on matplotlib's Agg canvas (``pyplot=False`` in
    [`jurs.plot`][]: pyplot and its backends never load, and nothing needs closing)."""
    fig.savefig(path, dpi=dpi)


def curve_outputs(job: FitJob, args, sol, seconds: float):
    """A curve's outputs (``OUTPUTS``): ``(write, summary line)``, ``write(folder)``
    writing them all. The level set is analysed here, before anything is written."""
    import numpy as np

    from . import levelset as ls
    from . import plot

    assert job.resolution is not None  # prepare_fit gives a 2D job the level-set default
    report = ls.analyze(
        sol.spline,
        job.points,
        offset=job.chosen.offset,
        threshold=args.threshold,
        resolution=job.resolution,
    )
    record = fit_record(job, args, sol, seconds)
    record["metrics"].update(report.as_dict())
    title = (
        _fit_title(job, args, sol) + f"{report.num_components} component(s), "
        f"{report.num_supplementary} supplementary"
    )

    def write(folder):
        _write_record_and_spline(folder, record, sol.spline)
        np.savetxt(
            os.path.join(folder, "zero_level.csv"),
            ls.polylines_table(report.components),
            delimiter=",",
            header="component,closed,supplementary,x,y",
            comments="",
            fmt=["%d", "%d", "%d", "%.10g", "%.10g"],
        )
        fig, ax = plot._new_axes(None, pyplot=False)
        plot.plot_fit(
            sol.spline,
            job.points,
            job.normals,
            job.chosen.offset,
            ax=ax,
            levelset=report,
            title=title,
        )
        _save_figure(fig, os.path.join(folder, "fit.png"), dpi=130)

    summary = (
        f"  E_ave = {float(sol.metrics['E_ave']):.4e}, E_max = "
        f"{float(sol.metrics['E_max']):.4e}, zero set: {report.num_components} "
        f"component(s), {report.num_supplementary} supplementary, chamfer = "
        f"{report.chamfer:.3g}"
    )
    return write, summary


def mesh_record(vertices, faces, report, distances, resolution: int) -> dict:
    """metrics.json's ``mesh`` entry: size, lattice resolution and every component."""
    components = [
        {
            "num_faces": c.num_faces,
            "area": c.area,
            "closed": c.closed,
            "genus": c.genus,
            "median_distance": c.median_distance,
            "supplementary": c.supplementary,
        }
        for c in report.components
    ]
    return {
        "num_vertices": int(len(vertices)),
        "num_faces": int(len(faces)),
        "resolution": int(resolution),
        "samples": distances["samples"],
        "components": components,
    }


def _mesh_counts(report) -> str:
    """The mesh's components in words, e.g. "1 component(s), 1 closed, genus 0, 0
    supplementary" (an open component's genus reads "open")."""
    closed = sum(c.closed for c in report.components)
    genera = ", ".join("open" if c.genus is None else str(c.genus) for c in report.components)
    return (
        f"{report.num_components} component(s), {closed} closed, genus {genera or '-'}, "
        f"{len(report.supplementary)} supplementary"
    )


def surface_outputs(job: FitJob, args, sol, seconds: float):
    """A surface's outputs (``OUTPUTS_3D``): ``(write, summary line)``. The zero set is
    meshed and measured here (components, genus, supplementary ones; Chamfer and Hausdorff
    distances against the data points, normal consistency against their normals), before
    anything is written."""
    import numpy as np

    from . import datasets, plot
    from . import levelset as ls
    from .levelset._meshing import default_resolution

    spline = sol.spline
    resolution = job.resolution or default_resolution(
        spline, np.asarray(spline.lower, np.float64), np.asarray(spline.upper, np.float64)
    )
    t0 = time.perf_counter()
    vertices, faces = ls.mesh(spline, resolution)
    t1 = time.perf_counter()
    report = ls.analyze_mesh(vertices, faces, job.points, threshold=args.threshold)
    distances = ls.mesh_distances(vertices, faces, job.points, job.normals)
    t2 = time.perf_counter()
    record = fit_record(job, args, sol, seconds)
    record["metrics"].update(
        report.as_dict(),
        chamfer=distances["chamfer"],
        hausdorff=distances["hausdorff"],
        normal_consistency=distances["normal_consistency"],
    )
    record["mesh"] = mesh_record(vertices, faces, report, distances, resolution)
    record["timings"] = {"fit_s": seconds, "mesh_s": t1 - t0, "analysis_s": t2 - t1}
    counts = _mesh_counts(report)
    highlight = (
        np.concatenate([c.faces for c in report.supplementary]) if report.supplementary else None
    )

    def write(folder):
        _write_record_and_spline(folder, record, spline)
        datasets.save_mesh(os.path.join(folder, "mesh.ply"), vertices, faces)
        fig, axes = plot._mesh_axes(None, pyplot=False)
        plot.plot_mesh(
            vertices,
            faces,
            ax=axes,
            highlight=highlight,
            highlight_label="supplementary",
            title=_fit_title(job, args, sol) + counts,
        )
        _save_figure(fig, os.path.join(folder, "preview.png"), dpi=110)

    summary = (
        f"  E_ave = {float(sol.metrics['E_ave']):.4e}, E_max = "
        f"{float(sol.metrics['E_max']):.4e}, surface: {len(faces)} faces, {counts}, "
        f"chamfer = {distances['chamfer']:.3g}"
    )
    return write, summary


def run_fit(args) -> int:
    """``jurs fit``: read and check, fit, analyse (a 2D cloud's zero-level curves or a 3D
    cloud's meshed surface), then write all outputs at once (or none)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    job = prepare_fit(args)
    solved = _solve(job, args)
    if solved is None:
        return EXIT_FIT_FAILED
    sol, seconds = solved
    analyse = curve_outputs if job.dim == 2 else surface_outputs
    write, summary = analyse(job, args, sol, seconds)
    try:
        write_outputs(job.out, write, job.outputs)
    except OSError as exc:
        print(
            f"jurs: error: {printable(args.output)}: could not write the outputs "
            f"({printable(_one_line(exc))}); the folder keeps its previous outputs",
            file=sys.stderr,
        )
        return EXIT_FIT_FAILED

    if not args.quiet:
        print(
            f"{job.shown}: {len(job.points)} points, {args.solver}, grid "
            f"{'x'.join(map(str, job.grid))}: {int(sol.stats['num_steps'])} steps in "
            f"{seconds:.2f} s ({sol.status})"
        )
        print(summary)
        print(f"  wrote {', '.join(job.outputs)} to {printable(args.output)}")
    return 0


def main(argv=None) -> int:
    """Run the command line on ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    return _run(argv)


def command() -> None:
    """The ``jurs`` console script: ``main`` on ``sys.argv``, then the process ends
    (``end_process``) without the interpreter's teardown."""
    code = main()
    end_process(code)
    sys.exit(code)


def _run(argv) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not (args.no_compilation_cache or cache_disabled_by_environment()):
        try:  # later runs load the compiled fit instead of compiling it (seconds)
            enable_compilation_cache()
        except OSError as exc:
            print(f"jurs: warning: no compilation cache ({_one_line(exc)})", file=sys.stderr)
    if args.command == "demo":
        from .demo import run

        run(args.output)
        return 0
    try:
        return run_fit(args)
    except InputError as exc:
        print(f"jurs: error: {printable(str(exc))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except MemoryError:
        print("jurs: error: out of memory; use a smaller --grid or --resolution", file=sys.stderr)
        return EXIT_FIT_FAILED


def end_process(code: int) -> None:
    """End the command's process with exit status ``code``: stdout and stderr flushed and
    the ``atexit`` handlers run (JAX's clean-up, temporary folders), then ``os._exit``,
    skipping the interpreter's teardown. That teardown frees every loaded module and
    JAX's compiled code object by object, a noticeable share of a short ``jurs fit``
    (docs/startup.md, "The command line's own process"), with nothing left to write (the
    outputs are closed, JAX's cache entries written when compiled). Where a thread other than
    the main one is still running, this returns and the interpreter exits as usual,
    waiting for it."""
    import atexit
    import threading

    if any(t is not threading.main_thread() and t.is_alive() for t in threading.enumerate()):
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more to say
            pass
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):  # what the handlers printed
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


if __name__ == "__main__":
    command()
