"""The ``jurs`` command line's argument parser: the ``demo`` and ``fit`` subcommands and their
options."""

from __future__ import annotations

import argparse

from ._batch import FilesAction
from ._inputs import face_count, grid_option, nonnegative, positive_number


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


#: ``jurs fit --help``'s last paragraphs: what the exit status says, and what an output
#: folder holding another kind of run's outputs becomes.
EXIT_CODES = """\
exit status:
  0    fitted and written: the verdict is successful, max_steps_reached or doubtful
       (a doubtful fit: one warning line on stderr, its doubts in metrics.json)
  1    the fit is not a reconstruction (verdict failed, nonfinite: diverged,
       inconsistent_normals, weights_at_floor or weights_at_ceiling), or the outputs
       could not be written: one line on stderr, nothing written
  2    bad input file or options: one line on stderr, nothing written
  130  interrupted (Ctrl-C)
  Several files: each goes on after another fails; the exit status is the worst.

output folder:
  Written whole or not at all. Where it holds the outputs of the other kind of fit
  (a curve's fit.png and zero_level.csv, a surface's mesh.ply and preview.png, told
  by jurs's metrics.json there), those files are removed in the same write; no other
  file is touched.
"""


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Option defaults shown; a text of one paragraph (the description) reflowed to the
    terminal, one laid out in lines (the epilog, ``EXIT_CODES``) kept as written."""

    def _fill_text(self, text, width, indent):
        if "\n" in text.strip():
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def _fit_parser(sub) -> argparse.ArgumentParser:
    """The ``jurs fit`` subcommand and its options."""
    f = sub.add_parser(
        "fit",
        help="fit a point cloud from a CSV, TXT or NPY file (2D) or a PLY, OBJ, XYZ "
        "or PTS file, or an STL or OFF mesh (3D)",
        description="Fit an implicit spline to points with outward normals (columns x, y, "
        "nx, ny; or x, y alone, whose normals are then estimated) and write "
        "metrics.json, spline.npz, fit.png and zero_level.csv to --output. A 3D "
        "cloud (PLY, OBJ, XYZ or PTS, or a CSV, TXT or NPY table of columns x, y, z or "
        "x, y, z, nx, ny, nz; normals estimated where the file has none) "
        "gets a surface: metrics.json, spline.npz, mesh.ply and preview.png. A triangle "
        "mesh (PLY, OBJ, STL or OFF with faces) is read as the surface it describes: "
        "points and normals are drawn uniformly by area on its faces.",
        epilog=EXIT_CODES,
        formatter_class=_HelpFormatter,
    )
    f.add_argument(
        "file",
        nargs="+",
        action=FilesAction,
        help="CSV/TXT (columns x, y, nx, ny; optional header) or NPY (m, 4); "
        "x, y alone: normals estimated; 3 columns x, y, z or 6 x, y, z, nx, ny, nz: a "
        "3D cloud (a header naming the columns decides, else their number); "
        "3D: PLY or OBJ (vertices, vertex normals) or XYZ/PTS (rows "
        "x y z [nx ny nz]); a PLY, OBJ, STL or OFF mesh with faces is sampled on its "
        "faces. Several files, a folder or a glob pattern: each "
        "cloud is fitted into its own sub-folder of --output, named from its file",
    )
    f.add_argument(
        "--grid",
        type=grid_option,
        default=None,
        metavar="N[xM[xK]]",
        help="basis functions along x and y (and z: N or NxMxK for a 3D cloud); "
        "None chooses from the data (jurs.auto_settings)",
    )
    f.add_argument(
        "--basis",
        default="auto",
        choices=("auto", "uniform", "adaptive"),
        help="auto: the adaptive basis where the data ask for finer cells than the "
        "automatic uniform grid affords and its fit leaves them (as jurs.fit), else the "
        "uniform grid; uniform: always the grid; adaptive: as --adaptive. --grid, --lam "
        "or a --solver other than auto keeps the uniform grid",
    )
    f.add_argument(
        "--adaptive",
        action="store_true",
        help="fit on an adaptive basis (jurs.fit_adaptive): fine cells in a band around "
        "the data, coarse ones elsewhere, so that detail of about one point spacing "
        "(2D) costs the outline, not the box; exact least squares with the automatic "
        "lambda (--lam and --smoothing as for auto); not with --grid",
    )
    f.add_argument(
        "--finest",
        type=int,
        default=None,
        metavar="CELLS",
        help="--adaptive: cells of the finest level along the longest side (None: "
        "from the point spacing and noise)",
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
        type=nonnegative,
        default=None,
        help="regularisation weight: eq. 33's lambda for iurs (keep it well below "
        "1/16; None is 0), the objective's lambda in E_d + lam R for lstsq "
        "and auto (None chooses); ipia has none",
    )
    f.add_argument(
        "--smoothing",
        type=nonnegative,
        default=None,
        help="auto only: the dimensionless strength the automatic lambda is made "
        "from (jurs.auto_settings; about 1e-6 on clean clouds to 1e-3 on "
        "noisy ones); None chooses",
    )
    f.add_argument("--tau", type=nonnegative, default=1e-2, help="weight step size (iurs, eq. 20)")
    f.add_argument(
        "-d",
        "--offset",
        type=positive_number,
        default=None,
        help="offset distance d; None chooses from the data",
    )
    f.add_argument(
        "--eps",
        type=positive_number,
        default=None,
        help="target value at the offsets; None takes d",
    )
    f.add_argument(
        "--steps",
        type=int,
        default=200,
        help="maximum number of steps (iurs, ipia; lstsq solves once)",
    )
    f.add_argument(
        "--tol",
        type=nonnegative,
        default=1e-7,
        help="stop when |E_new - E_old| < tol (eq. 38); 0 runs all steps",
    )
    f.add_argument(
        "-o",
        "--output",
        default="jurs-output",
        help="output folder (several clouds: one sub-folder each inside it)",
    )
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
        type=positive_number,
        default=None,
        help="distance to the data above which a zero-level component is "
        "supplementary; None means 2 d (2D), or 3 point spacings and at "
        "least 1%% of the cloud's diagonal (3D)",
    )
    f.add_argument(
        "--trim",
        type=positive_number,
        nargs="?",
        const=True,
        default=None,
        metavar="SPACINGS",
        help="open scans and open curves: keep only the zero set within SPACINGS local "
        "point spacings of the data (given alone: jurs.levelset.DEFAULT_TRIM, 2.5), and "
        "within jurs.levelset.DEFAULT_RIM (1) past the data's rim; "
        "mesh.ply (3D) or zero_level.csv (2D) then holds the trimmed surface or "
        "curve pieces, and metrics.json the trim, boundary loops (3D) and end points "
        "(2D). Put it after the file names",
    )
    f.add_argument(
        "--rim",
        type=nonnegative,
        default=None,
        metavar="SPACINGS",
        help="with --trim: the tolerance where the samples lie to one side of the zero set "
        "(past the data's rim), in local point spacings (default jurs.levelset.DEFAULT_RIM, "
        "1); a rim as large as the trim is the distance-only rule",
    )
    f.add_argument(
        "--faces",
        type=face_count,
        default=None,
        metavar="N",
        help="3D: decimate mesh.ply to N faces (N >= 4, after --trim), its vertices moved "
        "back onto the zero set (jurs.levelset.mesh's faces=; needs fast-simplification, "
        "in the surfaces extra); without it every marching-cubes face is kept",
    )
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    return f
