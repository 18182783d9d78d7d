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
                                                     supplementary, x, y (trimmed to
                                                     the data with --trim)
    jurs fit SCAN [options]       fit a surface to a 3D cloud (PLY, OBJ, XYZ or PTS, or a
                                  CSV, TXT or NPY table of columns x, y, z [nx, ny, nz];
                                  normals where the file has them, else estimated; a PLY,
                                  OBJ, STL or OFF mesh with faces is sampled on its faces) and
                                  write, into --output:
                                    metrics.json     fit and mesh metrics, settings, timings
                                    spline.npz       the 3D spline (jurs.load_spline)
                                    mesh.ply         the zero set, meshed (marching cubes;
                                                     trimmed to the data with --trim)
                                    preview.png      the mesh from three directions

Compiled fits are kept in JAX's persistent compilation cache in $XDG_CACHE_HOME/jurs (or
~/.cache/jurs), so later runs load them instead of compiling; --no-compilation-cache or
JURS_NO_COMPILATION_CACHE=1 turns that off.

Bad input files, options that do not fit the cloud's dimension, and output folders that
cannot be written or lack the space, give one line on stderr naming the file (and the row),
exit code 2, and write nothing; these are checked before the fit. A fit whose verdict is
not a reconstruction (``RAISED_RESULTS``: failed, nonfinite (diverged), inconsistent_normals,
weights_at_floor, weights_at_ceiling), or outputs that fail to write after all, exit with
code 1 and one line on stderr; nothing is written, and the output folder keeps its whole
previous set of outputs. A ``doubtful`` fit is written and exits 0, with one short warning
line on stderr (its doubts in words in metrics.json). Several clouds exit with the worst
code of their files. A curve fit into a folder that holds a surface fit's outputs from
jurs (told by its metrics.json), or the reverse, removes those outputs of the other kind
with the same atomic write: the folder never mixes the files of two runs. Ctrl-C ends the
command with one line on stderr and exit code 130; the output folder keeps its previous
outputs.

This package holds the parser and the run (``main``, ``prepare_fit``, the fit); reading the
input is in ``_inputs``, the output folder's checks and the atomic write in ``_outputs``,
the job a fit runs (``FitJob``) and the exit statuses in ``_job``, and what a curve fit and
a surface fit write in ``_results``.
"""

from __future__ import annotations

import os
import shutil  # noqa: F401  (cli.shutil: the tests patch cli.shutil.disk_usage)
import sys
import time
import warnings
from typing import TYPE_CHECKING, cast

from ._batch import is_batch, run_batch
from ._inputs import (
    InputError,
    grid_for,
    one_line,
    printable,
    read_input,
)
from ._job import EXIT_BAD_INPUT, EXIT_FIT_FAILED, FitJob, lattice_resolution, output_bytes
from ._outputs import (
    MESH_BYTES_PER_VERTEX,
    MESH_VERTICES_PER_PLANE_NODE,
    OUTPUT_OVERHEAD,
    OUTPUTS,
    OUTPUTS_3D,
    PLY_BYTES_PER_VERTEX,
    check_output_folder,
    outputs_for,
    write_outputs,
)
from ._parser import build_parser
from ._progress import ProgressBar, StageClock
from ._results import (
    basis_shown,
    curve_outputs,
    fit_record,
    mesh_record,
    surface_outputs,
)

__all__ = [
    "main",
    "command",
    "end_process",
    "build_parser",
    "run_fit",
    "prepare_fit",
    "FitJob",
    "make_solver",
    "ProgressBar",
    "InputError",
    "EXIT_BAD_INPUT",
    "EXIT_FIT_FAILED",
    "EXIT_INTERRUPTED",
    "VERDICT_LINES",
    "not_a_reconstruction",
    "OUTPUTS",
    "OUTPUTS_3D",
    "OUTPUT_OVERHEAD",
    "MESH_VERTICES_PER_PLANE_NODE",
    "MESH_BYTES_PER_VERTEX",
    "PLY_BYTES_PER_VERTEX",
    "grid_for",
    "printable",
    "read_input",
    "check_output_folder",
    "write_outputs",
    "outputs_for",
    "fit_record",
    "curve_outputs",
    "mesh_record",
    "surface_outputs",
]

if TYPE_CHECKING:  # the command line imports NumPy and jurs's modules when it runs them
    import numpy as np


#: Environment variable that turns the command line's compilation cache off ("1", "true").
NO_CACHE_VARIABLE = "JURS_NO_COMPILATION_CACHE"


def cache_disabled_by_environment() -> bool:
    """Whether ``NO_CACHE_VARIABLE`` asks for no compilation cache (any value but
    empty, ``0``, ``false`` or ``no``)."""
    value = os.environ.get(NO_CACHE_VARIABLE, "").strip().lower()
    return value not in ("", "0", "false", "no")


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


def _check_options(resolution, dim: int, out: str, names) -> None:
    """The options checked before anything is computed: the level-set (2D) or
    marching-cubes (3D) resolution, also against memory, and the output folder."""
    from .. import levelset as ls
    from .._problem.memory import check_memory

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
            raise InputError(one_line(exc)) from None
    check_output_folder(out, names=names)


def _surface_libraries(decimate: bool = False) -> None:
    """InputError unless the libraries a surface's outputs need are installed
    (scikit-image meshes, trimesh writes mesh.ply, fast-simplification decimates for
    ``--faces``): found out before the fit, not after."""
    from ..datasets._files import trimesh_module
    from ..levelset._meshing import fast_simplification_simplify, skimage_marching_cubes

    try:
        skimage_marching_cubes()
        trimesh_module()
        if decimate:
            fast_simplification_simplify()
    except ImportError as exc:
        raise InputError(f"a 3D cloud needs the surface extras: {one_line(exc)}") from None


def _check_adaptive(args, adaptive: bool, finest, dim: int) -> None:
    """``--adaptive`` and ``--finest`` against the other options: an adaptive fit is the
    exact least-squares fit with its own resolution."""
    from .._fit.adaptive import MAX_FINEST

    if finest is not None and not adaptive:
        raise InputError(
            "--finest sets the finest level of --adaptive; add --adaptive (or --basis adaptive)"
        )
    if not adaptive:
        return
    if args.grid is not None:
        raise InputError(
            "--adaptive chooses its own resolution (--finest); --grid is for the uniform fit"
        )
    if args.solver not in ("auto", "lstsq"):
        raise InputError(
            f"--adaptive fits by exact least squares; --solver {args.solver} runs on the "
            "uniform grid (leave out --adaptive, or use --solver auto)"
        )
    if finest is not None and not 8 <= finest <= MAX_FINEST[dim]:
        raise InputError(
            f"--finest must be between 8 and {MAX_FINEST[dim]} in {dim}D, got {finest}"
        )


def prepare_fit(args) -> FitJob:
    """Read the cloud and check everything that can be checked before the fit (options
    against the cloud's dimension, normals, settings, solver, output folder and its free
    space); every problem raises ``InputError``."""
    import jurs

    path = args.file
    shown = printable(path)
    points, normals = read_input(path)
    dim = int(points.shape[1])
    grid = grid_for(args.grid, dim, shown)
    faces = getattr(args, "faces", None)
    if dim == 3:
        _surface_libraries(decimate=faces is not None)
    elif faces is not None:
        raise InputError(
            f"{shown}: --faces sets the face budget of a surface's mesh; this cloud is 2D"
        )
    estimated = normals is None
    if estimated:  # no normals in the file: outward ones estimated first, as jurs.fit does
        try:
            # return_info=False: the normals alone, not the (normals, info) pair
            normals = cast("np.ndarray", jurs.estimate_normals(points))
        except (ValueError, TypeError) as exc:
            raise InputError(f"{shown}: {one_line(exc)}") from None
    basis = getattr(args, "basis", "auto")
    if getattr(args, "adaptive", False):
        if basis == "uniform":
            raise InputError("--adaptive and --basis uniform contradict each other")
        basis = "adaptive"
    adaptive = basis == "adaptive"
    finest = getattr(args, "finest", None)
    _check_adaptive(args, adaptive, finest, dim)
    out = os.path.abspath(args.output)
    resolution = args.resolution
    _check_options(resolution, dim, out, outputs_for(dim))
    if getattr(args, "rim", None) is not None and getattr(args, "trim", None) is None:
        raise InputError("--rim sets the trim's tolerance at the data's rim: add --trim")
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
        raise InputError(f"{shown}: {one_line(exc)}") from None
    solver = make_solver(
        args.solver, lam=args.lam, tau=args.tau, steps=args.steps, tol=args.tol, chosen=chosen
    )
    chooses = False
    if basis == "auto" and args.grid is None and args.solver == "auto" and args.lam is None:
        # As jurs.fit: where the uniform grid is capped, jurs.fit fits it and keeps it if
        # its zero set follows the data, else fits the adaptive basis (FitJob.settled).
        from .._fit.adaptive import auto_finest, wants_adaptive

        adaptive = chooses = wants_adaptive(chosen)
        finest = auto_finest(chosen) if adaptive else None
    resolution = lattice_resolution(resolution, dim, adaptive)
    if adaptive:
        solver = None  # fit_adaptive's exact solve, with --lam or the automatic lambda
    job = FitJob(
        path,
        points,
        normals,
        estimated,
        out,
        chosen,
        solver,
        resolution,
        cloud,
        adaptive,
        finest,
        chooses,
    )
    check_output_folder(out, output_bytes(job), job.outputs)
    return job


def _solve(job: FitJob, args):
    """``(solution, seconds)`` of the fit, with a progress bar; None (said on stderr in one
    line, ``not_a_reconstruction``) where its verdict is not a reconstruction (diverged
    included). A doubtful fit is returned, said in one short warning line. Settings the
    fit refuses (memory, precision) raise InputError."""
    import jax

    import jurs

    # An adaptive fit is one solve: no steps to show. Where the bar gets no steps (that
    # fit, and jurs.fit choosing its own solver), a long fit is said by the clock.
    bar = ProgressBar(f"{args.solver} {job.basis}", enabled=not (args.quiet or job.adaptive))
    stage = StageClock(f"{job.shown}: fitting ({job.basis})", enabled=not args.quiet)
    t0 = time.perf_counter()
    try:
        # The automatic settings as chosen up front: with solver None jurs.fit takes their
        # solver, sets aside their stray points and checks its doubts, said below as the
        # verdict (not warned).
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            if job.chooses:
                with stage:
                    sol = jurs.fit(job.cloud, settings=job.chosen, throw=False)
            elif job.adaptive:
                with stage:
                    sol = jurs.fit_adaptive(
                        job.cloud.points,
                        job.cloud.normals,
                        settings=job.chosen,
                        # lstsq's lambda is 0 unless given, as on the uniform grid
                        lam=0.0 if args.lam is None and args.solver == "lstsq" else args.lam,
                        finest=job.finest,
                        throw=False,
                    )
            else:
                sol = jurs.fit(
                    job.cloud, settings=job.chosen, solver=job.solver, callback=bar, throw=False
                )
    except (ValueError, TypeError) as exc:
        bar.close()
        raise InputError(f"{job.shown}: {one_line(exc)}") from None
    except KeyboardInterrupt:
        bar.close()  # Ctrl-C's line on a line of its own
        raise
    jax.block_until_ready(sol.spline)
    seconds = time.perf_counter() - t0
    bar.close()
    from .._solution.solution import RAISED_RESULTS  # jax is loaded by now

    if sol.status in RAISED_RESULTS:  # not a reconstruction: not written
        print(
            f"jurs: error: {job.shown}: "
            f"{not_a_reconstruction(sol.status, 'estimated_normals' in sol.stats)}; "
            "nothing written",
            file=sys.stderr,
        )
        return None
    if sol.status == "doubtful":
        # A usable fit, written; one short line here, the doubts in words in metrics.json.
        doubts = len(sol.stats.get("doubts") or ())
        print(
            f"jurs: warning: {job.shown}: doubtful fit ({doubts} doubt(s), in "
            "metrics.json's metrics.doubts)",
            file=sys.stderr,
        )
    return sol, seconds


#: What the command line says of each verdict that is not a reconstruction
#: (``RAISED_RESULTS``), and what to change; ``jurs.RESULTS`` holds the whole sentence.
VERDICT_LINES = {
    "failed": "the solver's inner method failed (for example a singular linear system)",
    "nonfinite": "the fit diverged (its energy became NaN or Inf): lower --tau or --lam",
    "inconsistent_normals": "the normals disagree (part of the cloud flipped, or random), "
    "or the fit cannot follow the data: orient them outward, or leave them out to have them "
    "estimated",
    "weights_at_floor": "the rational weights were driven to their floor: lower --tau",
    "weights_at_ceiling": "the rational weights grew past their ceiling: lower --tau",
}


#: The line for ``inconsistent_normals`` on normals that jurs estimated itself, where
#: "leave them out to have them estimated" is what was done.
ESTIMATED_NORMALS_LINE = (
    "the normals jurs estimated for this cloud disagree (the estimate could not orient "
    "it): give the file's own normals (x, y, nx, ny or x, y, z, nx, ny, nz; a mesh's faces)"
)


def not_a_reconstruction(status: str, estimated: bool = False) -> str:
    """The one line ``jurs fit`` prints (after ``jurs: error: FILE:``) for a fit whose
    verdict ``status`` is one of ``RAISED_RESULTS``: its short name and ``VERDICT_LINES``
    (``ESTIMATED_NORMALS_LINE`` for inconsistent normals that jurs ``estimated``)."""
    why = VERDICT_LINES[status]
    if estimated and status == "inconsistent_normals":
        why = ESTIMATED_NORMALS_LINE
    return f"the fit's verdict is {status}, not a reconstruction: {why}"


def run_fit(args) -> int:
    """``jurs fit``: read and check, fit, analyse (a 2D cloud's zero-level curves or a 3D
    cloud's meshed surface), then write all outputs at once (or none). Several clouds
    (``jurs.cli._batch``): each so, into its own sub-folder of ``--output``."""
    import jax

    if is_batch(args):
        return run_batch(args, run_fit)

    jax.config.update("jax_enable_x64", True)
    job = prepare_fit(args)
    solved = _solve(job, args)
    if solved is None:
        return EXIT_FIT_FAILED
    sol, seconds = solved
    job = job.settled(sol)
    analyse = curve_outputs if job.dim == 2 else surface_outputs
    write, summary = analyse(job, args, sol, seconds)
    try:
        write_outputs(job.out, write, job.outputs)
    except OSError as exc:
        print(
            f"jurs: error: {printable(args.output)}: could not write the outputs "
            f"({printable(one_line(exc))}); the folder keeps its previous outputs",
            file=sys.stderr,
        )
        return EXIT_FIT_FAILED

    if not args.quiet:
        print(
            f"{job.shown}: {len(job.points)} points, {args.solver}, {basis_shown(job, sol)}: "
            f"{int(sol.stats['num_steps'])} steps in "
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


#: Exit code after Ctrl-C: 128 + SIGINT, as shells report a command ended by it.
EXIT_INTERRUPTED = 130


def _run(argv) -> int:
    """Parse ``argv`` and run the command; Ctrl-C (KeyboardInterrupt) anywhere ends it with
    one line on stderr and ``EXIT_INTERRUPTED``, not a traceback. The outputs are renamed
    into place only once all are written (``write_outputs``, which puts the old set back
    when interrupted), so the folder keeps its previous outputs."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return _run_command(args)
    except KeyboardInterrupt:
        # A fit writes its outputs at once (or none); the demo writes as it goes.
        where = args.output if args.command == "fit" else None
        kept = f"; {printable(where)} keeps its previous outputs" if where else ""
        print(f"jurs: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED


def _run_command(args) -> int:
    if not (args.no_compilation_cache or cache_disabled_by_environment()):
        from .. import enable_compilation_cache

        try:  # later runs load the compiled fit instead of compiling it (seconds)
            enable_compilation_cache()
        except OSError as exc:
            print(f"jurs: warning: no compilation cache ({one_line(exc)})", file=sys.stderr)
    if args.command == "demo":
        from ..demo import run

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
