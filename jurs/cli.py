"""The ``jurs`` command line.

    jurs demo [--output DIR]      the paper's Example 1 by I-PIA and IURS (table + figure)
    jurs fit FILE [options]       fit a point cloud (CSV, TXT or NPY; columns x, y, nx, ny,
                                  or x, y alone: outward normals are then estimated)
                                  and write, into --output:
                                    metrics.json     fit and level-set metrics, settings
                                    spline.npz       the spline (jurs.load_spline reads it)
                                    fit.png          heatmap of g, zero set, data, offsets
                                    zero_level.csv   zero-level polylines: component, closed,
                                                     supplementary, x, y

Compiled fits are kept in JAX's persistent compilation cache in $XDG_CACHE_HOME/jurs (or
~/.cache/jurs), so later runs load them instead of compiling; --no-compilation-cache or
JURS_NO_COMPILATION_CACHE=1 turns that off.

Bad input files, and output folders that cannot be written or lack the space, give one
line on stderr naming the file (and the row), exit code 2, and write nothing; these are
checked before the fit. A fit that diverges (NaN energy), or outputs that fail to write
after all, exit with code 1; the output folder then keeps its whole previous set of
outputs. A fit that ends with another verdict than success or max_steps (inconsistent
normals, weights at their floor) is written, with a warning on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time

from ._compile import cache_disabled_by_environment, enable_compilation_cache

EXIT_BAD_INPUT = 2
EXIT_FIT_FAILED = 1
OUTPUTS = ("metrics.json", "spline.npz", "fit.png", "zero_level.csv")


class InputError(Exception):
    """A problem with the user's input file or options: one line, exit code 2."""


def _grid(text: str):
    try:
        parts = [int(p) for p in text.lower().replace("*", "x").split("x")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must be N or NxM, got {text!r}") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or min(parts) < 4:
        raise argparse.ArgumentTypeError(f"grid must be N or NxM with N, M >= 4, got {text!r}")
    return tuple(parts)


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
    parser = argparse.ArgumentParser(
        prog="jurs", description="Implicit curve reconstruction with uniform rational splines.",
        epilog="Run 'jurs fit --help' for the fit options.")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="fit the paper's Example 1 with IPIA and IURS")
    demo.add_argument("--output", default="demo-output", help="folder for the figure")

    f = sub.add_parser(
        "fit", help="fit a point cloud from a CSV, TXT or NPY file",
        description="Fit an implicit spline to points with outward normals (columns x, y, "
                    "nx, ny; or x, y alone, whose normals are then estimated) and write "
                    "metrics.json, spline.npz, fit.png and zero_level.csv to --output.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    f.add_argument("file", help="CSV/TXT (columns x, y, nx, ny; optional header) or NPY (m, 4)")
    f.add_argument("--grid", type=_grid, default=None, metavar="N[xM]",
                   help="basis functions along x and y; None chooses from the data "
                        "(jurs.auto_settings)")
    f.add_argument("--solver", default="auto", choices=_solver_names(),
                   help="auto: exact least squares with the automatic lambda; iurs: "
                        "Algorithm 1 (rational); ipia: I-PIA (B-spline); lstsq: exact least "
                        "squares (B-spline) with --lam")
    f.add_argument("--lam", type=_nonneg, default=None,
                   help="regularisation weight: eq. 33's lambda for iurs (keep it well below "
                        "1/16; None is 0), the objective's lambda in E_d + lam R for lstsq "
                        "and auto (None chooses); ipia has none")
    f.add_argument("--smoothing", type=_nonneg, default=None,
                   help="auto only: the dimensionless strength the automatic lambda is made "
                        "from (jurs.auto_settings; about 1e-6 on clean clouds to 1e-3 on "
                        "noisy ones); None chooses")
    f.add_argument("--tau", type=_nonneg, default=1e-2, help="weight step size (iurs, eq. 20)")
    f.add_argument("-d", "--offset", type=_positive, default=None,
                   help="offset distance d; None chooses from the data")
    f.add_argument("--eps", type=_positive, default=None,
                   help="target value at the offsets; None takes d")
    f.add_argument("--steps", type=int, default=200,
                   help="maximum number of steps (iurs, ipia; lstsq solves once)")
    f.add_argument("--tol", type=_nonneg, default=1e-7,
                   help="stop when |E_new - E_old| < tol (eq. 38); 0 runs all steps")
    f.add_argument("-o", "--output", default="jurs-output", help="output folder")
    f.add_argument("--resolution", type=int, default=512,
                   help="level-set grid nodes along the longer side of the box")
    f.add_argument("--threshold", type=_positive, default=None,
                   help="distance to the data above which a zero-level component is "
                        "supplementary; None means 2 d")
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    for command in (demo, f):
        command.add_argument(
            "--no-compilation-cache", action="store_true",
            help="do not keep compiled fits in JAX's persistent compilation cache "
                 "($XDG_CACHE_HOME/jurs or ~/.cache/jurs; JURS_NO_COMPILATION_CACHE=1 "
                 "does the same)")
    return parser


def printable(text) -> str:
    """``text`` safe to print and to draw: a file name that is not UTF-8 reaches Python with
    its bytes as lone surrogates, which stdout, JSON and the figure's title cannot encode;
    each such byte becomes U+FFFD."""
    return os.fsencode(text).decode("utf-8", "replace") if isinstance(text, str) else str(text)


def read_input(path: str):
    """Points and normals from ``path``; every problem raises :class:`InputError` with a
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
            raise InputError(f"{shown}: expected an (m, 4) array of rows x, y, nx, ny "
                             f"(or (m, 2): x, y), got shape {arr.shape}")
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


def make_solver(name: str, *, lam: float | None, tau: float, steps: int, tol: float,
                auto_lam: float = 0.0):
    """The solver named on the command line (``auto_lam``: the automatic lambda, used by
    ``auto`` when ``--lam`` is not given)."""
    import jurs

    if steps < 0:
        raise InputError(f"--steps must be >= 0, got {steps}")
    if name == "auto":
        return jurs.LeastSquares(lam=auto_lam if lam is None else lam)
    lam = 0.0 if lam is None else lam
    if name == "ipia":
        if lam:
            raise InputError("--lam is not supported by ipia (I-PIA has no regulariser); "
                             "use --solver iurs")
        return jurs.IPIA(max_steps=steps, tol=tol)
    if name == "iurs":
        return jurs.IURS(tau=tau, lam=lam, max_steps=steps, tol=tol)
    if name == "lstsq":
        return jurs.LeastSquares(lam=lam)
    raise InputError(f"unknown solver {name!r}")


class ProgressBar:
    """A one-line progress bar on stderr, drawn only once a run has taken over ``delay``
    seconds (short fits print nothing)."""

    def __init__(self, label: str, delay: float = 1.0, width: int = 30, stream=None,
                 enabled: bool = True):
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
        self.stream.write(f"\r{self.label} [{bar:<{self.width}}] {done}/{total} steps "
                          f"{elapsed:5.1f} s")
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


def check_output_folder(out: str, need: int = OUTPUT_OVERHEAD) -> None:
    """Before the fit: InputError unless ``out`` is (or can be made) a folder we can write
    ``need`` bytes into, whose output names are free or plain files. A fit of minutes
    should not end in a traceback about permissions or a full disk."""
    shown = printable(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"{shown}: exists and is not a folder")
    for name in OUTPUTS:
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
        raise InputError(f"{printable(existing)}: only {free / 2**20:.1f} MiB free, the "
                         f"outputs need about {need / 2**20:.1f} MiB")


def write_outputs(out: str, write) -> None:
    """Write the whole set of :data:`OUTPUTS` into ``out``, or none: ``write(folder)``
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
        for name in OUTPUTS:
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


def _output_writer(record, spline, report, points, normals, offset, title):
    """A function writing every one of :data:`OUTPUTS` into a given folder."""
    import matplotlib.pyplot as plt
    import numpy as np

    import jurs
    from . import levelset as ls
    from . import plot

    def write(folder):
        with open(os.path.join(folder, "metrics.json"), "w", encoding="utf-8") as fh:
            json.dump(_json_safe(record), fh, indent=2, allow_nan=False)
            fh.write("\n")
        jurs.save_spline(os.path.join(folder, "spline.npz"), spline)
        np.savetxt(os.path.join(folder, "zero_level.csv"), ls.polylines_table(report.components),
                   delimiter=",", header="component,closed,supplementary,x,y", comments="",
                   fmt=["%d", "%d", "%d", "%.10g", "%.10g"])
        fig = plot.plot_fit(spline, points, normals, offset, levelset=report, title=title)
        try:
            fig.savefig(os.path.join(folder, "fit.png"), dpi=130)
        finally:
            plt.close(fig)

    return write


def _check_options(args, out: str) -> None:
    """The options checked before anything is computed: the level-set resolution (also
    against memory: the grid is square at most) and the output folder."""
    from . import levelset as ls
    from ._problem import check_memory

    if args.resolution < 16:
        raise InputError(f"--resolution must be >= 16, got {args.resolution}")
    try:
        check_memory(f"--resolution {args.resolution}",
                     ls.BYTES_PER_NODE * float(args.resolution) ** 2, device=False)
    except ValueError as exc:
        raise InputError(_one_line(exc)) from None
    check_output_folder(out)


def run_fit(args) -> int:
    """``jurs fit``: read, check the output folder, fit, analyse, then write all outputs at
    once (or none)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import matplotlib

    matplotlib.use("Agg")

    import jurs
    from . import levelset as ls
    from ._progress import fit_in_chunks

    path = args.file
    shown = printable(path)
    points, normals = read_input(path)
    estimated = normals is None
    if estimated:  # an x, y file: outward normals estimated first, as jurs.fit(points) does
        try:
            normals = jurs.estimate_normals(points)
        except (ValueError, TypeError) as exc:
            raise InputError(f"{shown}: {_one_line(exc)}") from None
    out = os.path.abspath(args.output)
    _check_options(args, out)
    if args.smoothing is not None and (args.solver != "auto" or args.lam is not None):
        raise InputError("--smoothing sets the automatic lambda of --solver auto; "
                         "give --lam instead")
    try:  # auto_settings runs make_problem's input checks (e.g. degenerate clouds) first
        chosen = jurs.auto_settings(points, normals, grid=args.grid, offset=args.offset,
                                    eps=args.eps, smoothing=args.smoothing)
    except (ValueError, TypeError) as exc:
        raise InputError(f"{shown}: {_one_line(exc)}") from None
    settings = dict(grid=chosen.grid, offset=chosen.offset, eps=chosen.eps)
    solver = make_solver(args.solver, lam=args.lam, tau=args.tau, steps=args.steps,
                         tol=args.tol, auto_lam=chosen.lam)
    grid, offset = chosen.grid, chosen.offset
    lam = float(getattr(solver, "lam", 0.0))
    # The spline (two grids of float64 in the .npz) and the polylines (at most about
    # resolution^2 / 2 vertices of ~40 bytes as text) besides the figure and the metrics.
    check_output_folder(out, OUTPUT_OVERHEAD + 16 * grid[0] * grid[1]
                        + 20 * min(args.resolution ** 2, 10 * args.resolution * len(points)))

    bar = ProgressBar(f"{args.solver} {grid[0]}x{grid[1]}", enabled=not args.quiet)
    t0 = time.perf_counter()
    try:
        sol, _ = fit_in_chunks(points, normals, solver=solver, callback=bar, throw=False,
                               **settings)
    except (ValueError, TypeError) as exc:  # settings the fit refuses (memory, precision)
        bar.close()
        raise InputError(f"{shown}: {_one_line(exc)}") from None
    jax.block_until_ready(sol.spline)
    seconds = time.perf_counter() - t0
    bar.close()
    if sol.result == jurs.RESULTS.nonfinite:
        print(f"jurs: error: {shown}: the fit diverged ({sol.message}); nothing written",
              file=sys.stderr)
        return EXIT_FIT_FAILED
    if not sol.succeeded and sol.result != jurs.RESULTS.max_steps_reached:
        # Written all the same (the figure shows what went wrong), but said on stderr too.
        print(f"jurs: warning: {shown}: {sol.message}", file=sys.stderr)

    report = ls.analyze(sol.spline, points, offset=offset, threshold=args.threshold,
                        resolution=args.resolution)
    metrics = {k: v for k, v in sol.metrics.items()}
    metrics.update(num_steps=int(sol.stats["num_steps"]), result=sol.message,
                   converged=bool(sol.succeeded), time_s=seconds)
    metrics.update(report.as_dict())
    record = {
        "input": printable(os.path.abspath(path)),
        "num_points": int(len(points)),
        "normals": "estimated" if estimated else "given",
        "settings": {"solver": args.solver, "grid": list(grid), "lam": lam,
                     "tau": args.tau if args.solver == "iurs" else None, "offset": offset,
                     "eps": chosen.eps, "steps": args.steps, "tol": args.tol,
                     "chosen_from_data": chosen.as_dict()},
        "metrics": metrics,
    }

    write = _output_writer(record, sol.spline, report, points, normals, offset,
                           title=(f"{printable(os.path.basename(path))}: {args.solver}, grid "
                                  f"{grid[0]}x{grid[1]}, lam = {lam:.3g}\nE_ave = "
                                  f"{float(sol.metrics['E_ave']):.3e}, "
                                  f"{report.num_components} component(s), "
                                  f"{report.num_supplementary} supplementary"))
    try:
        write_outputs(out, write)
    except OSError as exc:
        print(f"jurs: error: {printable(args.output)}: could not write the outputs "
              f"({printable(_one_line(exc))}); the folder keeps its previous outputs",
              file=sys.stderr)
        return EXIT_FIT_FAILED

    if not args.quiet:
        print(f"{shown}: {len(points)} points, {args.solver}, grid {grid[0]}x{grid[1]}: "
              f"{metrics['num_steps']} steps in {seconds:.2f} s ({sol.message.split(':')[0]})")
        print(f"  E_ave = {float(sol.metrics['E_ave']):.4e}, E_max = "
              f"{float(sol.metrics['E_max']):.4e}, zero set: {report.num_components} "
              f"component(s), {report.num_supplementary} supplementary, chamfer = "
              f"{report.chamfer:.3g}")
        print(f"  wrote {', '.join(OUTPUTS)} to {printable(args.output)}")
    return 0


def main(argv=None) -> int:
    """Entry point of the ``jurs`` console script; returns the exit code."""
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
        print("jurs: error: out of memory; use a smaller --grid or --resolution",
              file=sys.stderr)
        return EXIT_FIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
