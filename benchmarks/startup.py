"""Start-up benchmark: what a new user meets first, as whole processes.

    python -m benchmarks.startup              # about 3-6 minutes on 2 cores
    python -m benchmarks.startup --quick      # smoke test: small clouds, one run each, no file
    python -m benchmarks.startup --from-json  # re-render results/startup.md from its JSON
    python -m benchmarks.startup --overhead   # host work of a warm call: results/overhead.md

Every measurement is a fresh Python process with a clean environment (PATH, HOME and
XDG_CACHE_HOME in a temporary folder, JAX on the CPU, no JAX_* variables), running a
snapshot of this checkout's ``jurs`` package (copied first, so that edits made while it
runs do not change what is measured), with a fresh cache folder:

1. import time: ``import jax`` against ``import jurs`` (interleaved, median of 5);
2. first fit and new-cloud fit in one process, at 100, 1e3, 1e4 and 1e5 points: a cloud A
   of a similar size in the same size band (``jurs._problem.sizes.padded_count``) is fitted
   first (compiling), then a new cloud B (Example 1 at the target size): its first fit
   against its warm fit (median of 3), all with automatic settings (``jurs.fit(p, n)``);
3. a ladder of new clouds in one process (Example 1 at 1000, 1050, 1130, 1300, 1600 and
   2000 points, then an ellipse of another aspect at 1700 points): before the first cloud
   of each shape, one cloud of that shape at half its size (another octave,
   ``padded_count``) is fitted (compiling), and no cloud of a later octave; each ladder
   cloud's first fit is reported against its own warm fit (median of 3), with the XLA
   compilations it triggered;
4. many files in one process: ``jurs fit folder -o out`` on 20 files of 1000 points
   (Example 1, scaled and moved), the cache filled, against 20 runs of the SciPy script
   below (their sum);
5. the command line ``jurs fit cloud.csv -o out`` on a 1000-point cloud: the first run
   (fresh cache folder), later runs (the cache filled), and a run with
   ``--no-compilation-cache``, against a SciPy script that loads the same CSV, fits a
   thin-plate RBF (``scipy.interpolate.RBFInterpolator``) to the 3000 offset samples,
   evaluates it on a 200 x 200 grid and extracts the zero contour with contourpy
   (later runs and SciPy runs interleaved, median of 3). What bounds the command line is
   measured in the same run: a process doing the command line's work up to the end of the
   fit and writing nothing (``cli.prepare_fit`` and ``cli._solve``: import, read, checks,
   automatic settings, the fit; then ``cli.end_process``), with a fresh cache and with
   the cache filled, and ``import jax`` alone. Each run's CPU time (user + system) is
   recorded beside its wall time.

Writes ``benchmarks/results/startup.{md,json}``. ``--parts ladder,batch,cli`` runs only the
parts named (``imports``, ``fits``, ``ladder``, ``batch``, ``cli``); the report says which
were skipped. ``--sizes 100`` (or ``100,1000``) re-runs only those rows of part 2 and puts
them in place of the committed rows of ``results/startup.json``, each re-run row with its
own date and load (the report says which); the other rows and parts are kept.

``--overhead`` measures, in this process, what a warm top-level call of ``jurs.fit`` costs
beyond its compiled work: Example 1 (120 points, 9 x 9, ``LeastSquares``, every setting
given) fitted inside ``jax.jit`` (the baseline: no host work at all), then at top level
from arrays (input checks, layout, orientation check each call), from a reused
``jurs.Cloud`` (checked, laid out and orientation-checked once) and from arrays with
``checks=False``; medians of interleaved rounds, ratios against the baseline. Writes
``benchmarks/results/overhead.{md,json}``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from ._common import elapsed_log, write_results

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SIZES = (100, 1000, 10_000, 100_000)
CLI_POINTS = 1000
REPEATS = 3
IMPORT_REPEATS = 5

SCIPY_SCRIPT = """
import sys
import contourpy
import numpy as np
from scipy.interpolate import RBFInterpolator

data = np.loadtxt(sys.argv[1], delimiter=",", skiprows=1)
points, normals = data[:, :2], data[:, 2:]
normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
d = 0.01 * np.ptp(points, axis=0).max()
samples = np.concatenate([points, points + d * normals, points - d * normals])
m = len(points)
targets = np.concatenate([np.zeros(m), np.full(m, d), np.full(m, -d)])
rbf = RBFInterpolator(samples, targets, kernel="thin_plate_spline")
lower, upper = samples.min(axis=0), samples.max(axis=0)
xs, ys = np.linspace(lower[0], upper[0], 200), np.linspace(lower[1], upper[1], 200)
grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
values = rbf(grid).reshape(200, 200)
lines = contourpy.contour_generator(xs, ys, values).lines(0.0)
print(len(lines), sum(len(line) for line in lines))
"""

FITS = """
import json, sys, time
t0 = time.perf_counter()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jurs
from jurs._problem.sizes import padded_count
imported = time.perf_counter() - t0
n = int(sys.argv[1])
band = padded_count(n)
# Cloud A: another size in n's band (7 % fewer points, else 7 % more), scaled and moved.
size_a = next(s for s in (round(0.93 * n), round(1.07 * n), n) if padded_count(s) == band)
points_a, normals_a = jurs.datasets.example1(size_a)
points_a = 1.3 * points_a + np.array([2.0, -1.0])
points_b, normals_b = jurs.datasets.example1(n)

def timed(points, normals):
    t = time.perf_counter()
    sol = jurs.fit(points, normals)
    jax.block_until_ready(sol.spline)
    return time.perf_counter() - t, sol

compiles, compile_s = [], []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **kw: (compiles.append(kw.get("fun_name")), compile_s.append(secs))
    if event == "/jax/core/compile/backend_compile_duration" else None)
first_a, sol_a = timed(points_a, normals_a)
compiles_a, compile_a_s = len(compiles), sum(compile_s)
first_b, sol_b = timed(points_b, normals_b)
compiles_b = len(compiles) - compiles_a
warm = [timed(points_b, normals_b)[0] for _ in range(3)]
print(json.dumps(dict(
    n=n, band=band, size_a=size_a, import_s=imported, first_a_s=first_a, grid_a=sol_a.settings.grid,
    new_cloud_s=first_b, grid_b=sol_b.settings.grid, warm_s=float(np.median(warm)),
    warm_min_s=min(warm), compiles_a=compiles_a, compiles_b=compiles_b, compile_a_s=compile_a_s,
    new_cloud_compiled=sorted(set(map(str, compiles[compiles_a:]))),
    jurs_file=jurs.__file__)))
"""


PARTS = ("imports", "fits", "ladder", "batch", "cli")
LADDER = (1000, 1050, 1130, 1300, 1600, 2000)
SECOND_SHAPE = ("ellipse 5 x 2.5", 1700)
BATCH_FILES = 20

LADDER_FITS = """
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jurs
from jurs._problem.sizes import padded_count

compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, secs, **kw: compiles.append((str(kw.get("fun_name")), secs))
    if event == "/jax/core/compile/backend_compile_duration" else None)

def timed(points, normals):
    t = time.perf_counter()
    sol = jurs.fit(points, normals)
    jax.block_until_ready(sol.spline)
    return time.perf_counter() - t, sol

shapes = {
    "example 1": jurs.datasets.example1,
    "ellipse 5 x 2.5": lambda n: jurs.datasets.ellipse(n, a=5.0, b=2.5),
}
cases = [("example 1", n) for n in json.loads(sys.argv[1])] + [tuple(json.loads(sys.argv[2]))]
primed, rows = set(), []
for shape, n in cases:
    band = padded_count(n)
    row = dict(shape=shape, n=n, band=band)
    if shape not in primed:  # one fit of the shape first, in another octave: the compiling one
        size_a = n // 2
        points_a, normals_a = shapes[shape](size_a)
        before = len(compiles)
        row["first_a_s"] = timed(1.3 * points_a + np.array([2.0, -1.0]), normals_a)[0]
        row["size_a"], row["compiles_a"] = size_a, len(compiles) - before
        primed.add(shape)
    points, normals = shapes[shape](n)
    before = len(compiles)
    first, sol = timed(points, normals)
    row["compiled"] = [name for name, _ in compiles[before:]]
    row["compile_s"] = sum(secs for _, secs in compiles[before:])
    warm = [timed(points, normals)[0] for _ in range(3)]
    row.update(first_s=first, warm_s=float(np.median(warm)), grid=list(sol.settings.grid))
    row["ratio"] = first / row["warm_s"]
    rows.append(row)
    print(json.dumps(row), flush=True)
"""


# The command line's work up to the end of the fit, writing nothing, and its way out of the
# process (cli.end_process): what no change to its outputs (figure, level-set analysis,
# files) can go below.
FIT_ONLY = """
import sys
import jax
jax.config.update("jax_enable_x64", True)
from jurs import cli, enable_compilation_cache
args = cli.build_parser().parse_args(["fit", sys.argv[1], "-o", "unused-out", "-q"])
enable_compilation_cache()
job = cli.prepare_fit(args)
assert cli._solve(job, args) is not None
cli.end_process(0)
"""


def clean_environment(home: str, cache: str, pythonpath: str) -> dict:
    return {
        "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
        "HOME": home,
        "XDG_CACHE_HOME": cache,
        "JAX_PLATFORMS": "cpu",
        "PYTHONPATH": pythonpath,
        "LANG": "C.UTF-8",
        "MPLBACKEND": "Agg",
    }


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def wall(cmd, env, cwd, timeout=600) -> tuple[float, str, float]:
    """Seconds of one whole process, its stdout, and the CPU seconds (user + system, all
    its threads) it used. Fails loudly if the process fails."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    seconds, cpu = time.perf_counter() - t0, _children_cpu() - cpu0
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds, proc.stdout, cpu


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh if "model name" in line)
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def measure_imports(py, env, cwd, log) -> dict:
    times = {"none": [], "jax": [], "jurs": []}
    for _ in range(IMPORT_REPEATS):
        for name in times:
            code = "pass" if name == "none" else f"import {name}"
            times[name].append(wall([py, "-c", code], env, cwd)[0])
    result = {
        k: {"median_s": statistics.median(v), "min_s": min(v), "all_s": v} for k, v in times.items()
    }
    log(f"imports: {json.dumps({k: round(v['median_s'], 3) for k, v in result.items()})}")
    return result


def measure_fits(py, env, cwd, log) -> list:
    rows = []
    for n in SIZES:
        out = wall([py, "-c", FITS, str(n)], env, cwd)[1]
        row = json.loads(out.splitlines()[-1])
        row["ratio"] = row["new_cloud_s"] / row["warm_s"]
        rows.append(row)
        log(
            f"fits at {n}: first A {row['first_a_s']:.2f} s, new cloud {row['new_cloud_s']:.3f} "
            f"s, warm {row['warm_s']:.3f} s, ratio {row['ratio']:.2f}"
        )
    return rows


def measure_ladder(py, env, cwd, log) -> list:
    out = wall(
        [py, "-c", LADDER_FITS, json.dumps(list(LADDER)), json.dumps(list(SECOND_SHAPE))],
        env,
        cwd,
        timeout=1800,
    )[1]
    rows = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    for r in rows:
        log(
            f"ladder {r['shape']} {r['n']}: first {r['first_s']:.3f} s, warm {r['warm_s']:.3f} "
            f"s, ratio {r['ratio']:.2f}, compiled {r['compiled']}"
        )
    return rows


def measure_batch(py, env, cwd, log) -> dict:
    """20 files of CLI_POINTS points through one ``jurs fit folder -o out`` (the cache
    filled first by a run on one of them), against 20 runs of the SciPy script."""
    folder = os.path.join(cwd, "batch")
    make = (
        "import os, sys, numpy as np, jurs\n"
        f"p, n = jurs.datasets.example1({CLI_POINTS})\n"
        f"for i in range({BATCH_FILES}):\n"
        "    s = 0.8 + 0.02 * i\n"
        "    jurs.datasets.save_points(os.path.join(sys.argv[1], f'cloud{i:02d}.csv'),\n"
        "                              s * p + np.array([0.1 * i, -0.05 * i]), n)\n"
    )
    os.makedirs(folder, exist_ok=True)
    wall([py, "-c", make, folder], env, cwd)
    with open(os.path.join(cwd, "scipy_rbf.py"), "w") as fh:
        fh.write(SCIPY_SCRIPT)
    files = sorted(os.listdir(folder))
    # A cache folder of its own (the command line's first run below needs a fresh one),
    # filled by one run on the first file, as later runs of the command find it.
    filled_env = dict(env, XDG_CACHE_HOME=os.path.join(cwd, "batch-cache"))
    first_file = os.path.join(folder, files[0])
    wall([py, "-m", "jurs.cli", "fit", first_file, "-o", "warm", "-q"], filled_env, cwd)
    batch, _, batch_cpu = wall(
        [py, "-m", "jurs.cli", "fit", folder, "-o", "batch-out", "-q"],
        filled_env,
        cwd,
        timeout=1800,
    )
    written = sorted(os.listdir(os.path.join(cwd, "batch-out")))
    assert len(written) == BATCH_FILES, written
    scipy, scipy_cpu = [], 0.0
    for name in files:
        seconds, _, cpu_s = wall([py, "scipy_rbf.py", os.path.join(folder, name)], env, cwd)
        scipy.append(seconds)
        scipy_cpu += cpu_s
    fresh_env = dict(env, XDG_CACHE_HOME=os.path.join(cwd, "batch-fresh-cache"))
    fresh, _, fresh_cpu = wall(
        [py, "-m", "jurs.cli", "fit", folder, "-o", "batch-fresh", "-q"],
        fresh_env,
        cwd,
        timeout=1800,
    )
    result = {
        "files": BATCH_FILES,
        "points": CLI_POINTS,
        "batch_s": batch,
        "batch_cpu_s": batch_cpu,
        "batch_fresh_s": fresh,
        "batch_fresh_cpu_s": fresh_cpu,
        "scipy_s": scipy,
        "scipy_total_s": sum(scipy),
        "scipy_cpu_s": scipy_cpu,
    }
    result["ratio"] = batch / result["scipy_total_s"]
    result["fresh_ratio"] = fresh / result["scipy_total_s"]
    log(
        f"batch of {BATCH_FILES}: {batch:.2f} s (fresh cache {fresh:.2f} s) against "
        f"{result['scipy_total_s']:.2f} s of SciPy runs: {result['ratio']:.2f}x"
    )
    return result


def measure_cli(py, env, cwd, log) -> dict:
    snapshot_jurs = [py, "-c", "import jurs, sys; print(jurs.__file__)"]
    log(f"jurs from {wall(snapshot_jurs, env, cwd)[1].strip()}")
    wall(
        [
            py,
            "-c",
            "import jurs; jurs.datasets.save_points('cloud.csv', "
            f"*jurs.datasets.example1({CLI_POINTS}))",
        ],
        env,
        cwd,
    )
    with open(os.path.join(cwd, "scipy_rbf.py"), "w") as fh:
        fh.write(SCIPY_SCRIPT)
    cli = [py, "-m", "jurs.cli", "fit", "cloud.csv", "-o", "out", "-q"]
    scipy = [py, "scipy_rbf.py", "cloud.csv"]
    fit_only = [py, "-c", FIT_ONLY, "cloud.csv"]
    jax_only = [py, "-c", "import jax"]
    cpu = {}  # CPU seconds (user + system) of each run, by its key below

    def run(key, cmd, environment):
        seconds, _, cpu_s = wall(cmd, environment, cwd)
        cpu.setdefault(key, []).append(cpu_s)
        return seconds

    first = run("first", cli, env)
    log(f"cli first run (fresh cache): {first:.2f} s")
    # The bound of the first run: the fit alone, with a cache folder of its own, fresh.
    fit_only_env = dict(env, XDG_CACHE_HOME=os.path.join(cwd, "fit-only-cache"))
    fit_only_first = run("fit_only_first", fit_only, fit_only_env)
    later, baseline, fit_only_later, jax_import = [], [], [], []
    for _ in range(REPEATS):
        later.append(run("later", cli, env))
        baseline.append(run("scipy", scipy, env))
        fit_only_later.append(run("fit_only_later", fit_only, fit_only_env))
        jax_import.append(run("jax_import", jax_only, env))
    no_cache_env = dict(env, XDG_CACHE_HOME=os.path.join(cwd, "unused-cache"))
    no_cache = run("no_cache", cli + ["--no-compilation-cache"], no_cache_env)
    result = {
        "cpu_s": cpu,
        "cpu_median_s": {k: statistics.median(v) for k, v in cpu.items()},
        "first_s": first,
        "later_s": later,
        "later_median_s": statistics.median(later),
        "scipy_s": baseline,
        "scipy_median_s": statistics.median(baseline),
        "no_cache_s": no_cache,
        "fit_only_first_s": fit_only_first,
        "fit_only_later_s": fit_only_later,
        "fit_only_later_median_s": statistics.median(fit_only_later),
        "jax_import_s": jax_import,
        "jax_import_median_s": statistics.median(jax_import),
    }
    scipy_s = result["scipy_median_s"]
    for key in ("first", "later_median", "no_cache", "fit_only_first", "fit_only_later_median"):
        result[key.replace("_median", "") + "_ratio"] = result[key + "_s"] / scipy_s
    result["jax_import_ratio"] = result["jax_import_median_s"] / scipy_s
    log(
        f"cli later {result['later_median_s']:.2f} s, no cache {no_cache:.2f} s, scipy "
        f"{scipy_s:.2f} s; fit only {fit_only_first:.2f} s first, "
        f"{result['fit_only_later_median_s']:.2f} s later"
    )
    return result


def render(data: dict) -> str:
    lines = [
        "# Start-up: import, first fits, new clouds, many files, the command line",
        "",
        f"Run {data['date']} on {data['machine']} (load average {data['load_before']} before, "
        f"{data['load_after']} after, over 1, 5 and 15 minutes). `python "
        "benchmarks/startup.py`; whole processes, clean environment, fresh cache folder.",
        "",
    ]
    skipped = [part for part in PARTS if part not in data]
    if skipped:
        lines += [
            f"Parts skipped in this run (`--parts`): {', '.join(skipped)}.",
            "",
        ]
    loads = [float(data[k].split()[0]) for k in ("load_before", "load_after")]
    if max(loads) > data.get("cores", os.cpu_count() or 1):
        lines += [
            "Caution: other jobs kept the machine's cores busy during this run (load average "
            "above the core count). Absolute times are inflated; the ratios below are "
            "measured within one run (a fit against its own warm fit in the same process; "
            "jurs against the SciPy script in the same minutes), and even these move with "
            "the load (the SciPy script's multithreaded linear algebra loses more to it).",
            "",
        ]
    if "imports" in data:
        lines += _render_imports(data["imports"])
    if "fits" in data:
        lines += _render_fits(data["fits"])
    if "ladder" in data:
        lines += _render_ladder(data["ladder"])
    if "batch" in data:
        lines += _render_batch(data["batch"])
    if "cli" in data:
        lines += _render_cli(data["cli"], data.get("fits", []))
    return "\n".join(lines)


def _render_imports(imp: dict) -> list:
    extra = imp["jurs"]["median_s"] - imp["jax"]["median_s"]
    lines = [
        "## Import (median of 5 processes)",
        "",
        "| process | median s | min s |",
        "|---|---|---|",
    ]
    for name, label in (
        ("none", "`python -c pass`"),
        ("jax", "`import jax`"),
        ("jurs", "`import jurs`"),
    ):
        lines.append(f"| {label} | {imp[name]['median_s']:.2f} | {imp[name]['min_s']:.2f} |")
    return lines + [
        "",
        f"`import jurs` - `import jax` = {extra:+.2f} s (median; min "
        f"{imp['jurs']['min_s'] - imp['jax']['min_s']:+.2f} s).",
        "",
    ]


def _render_fits(fits: list) -> list:
    lines = [
        "## A new cloud in a process that has fitted one of a similar size",
        "",
        "Automatic settings (`jurs.fit(points, normals)`). A: Example 1 at `size A` points, "
        "scaled 1.3x and moved, fitted first (its first fit compiles); B: Example 1 at n "
        "points, new to the process. Both pad to `band` points. Ratio: B's first fit / B's "
        "warm fit (median of 3).",
        "",
        "| n | band | size A | grid A | grid B | first fit A s (XLA compile s) | new cloud B s "
        "| warm B s | ratio | compilations A / B |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in fits:
        lines.append(
            f"| {r['n']} | {r['band']} | {r['size_a']} | {tuple(r['grid_a'])} | "
            f"{tuple(r['grid_b'])} | {r['first_a_s']:.2f} ({r['compile_a_s']:.2f}) | "
            f"{r['new_cloud_s']:.3f} | "
            f"{r['warm_s']:.3f} | {r['ratio']:.2f} | {r['compiles_a']} / {r['compiles_b']} |"
        )
    worst = max(r["ratio"] for r in fits)
    lines += [
        "",
        f"Worst ratio {worst:.2f}. (Without padded shapes: 35x at 1000 -> 1100 points, a "
        "full recompilation.)",
        "",
    ]
    rerun = [f"n = {r['n']} on {r['run']}" for r in fits if "run" in r]
    if rerun:
        lines += [
            f"Rows re-run on their own (`--sizes`), after the rest: {'; '.join(rerun)}.",
            "",
        ]
    regridded = [str(r["n"]) for r in fits if list(r["grid_a"]) != list(r["grid_b"])]
    if regridded:
        lines += [
            f"At n = {', '.join(regridded)}, A and B got different automatic grids (below "
            "the grid cap, a curve's longest side takes one cell count an octave, and "
            "clouds on either side of a rung differ): B compiles a fit of its own grid, "
            "whatever its point count.",
            "",
        ]
    return lines


def _render_ladder(rows: list) -> list:
    lines = [
        "## A ladder of new clouds in one process",
        "",
        "Automatic settings. Before the first cloud of each shape, one cloud of that shape "
        "at half its size (`size A`: another octave of points, `band` being the padded "
        "point count; scaled 1.3x and moved) is fitted: its first fit compiles. No cloud "
        "of a later octave is fitted first. Then each cloud of the ladder, new to the "
        "process: its first fit, the XLA programs it compiled, and the ratio to its own "
        "warm fit (median of 3) in the same process.",
        "",
        "| shape | n | band | grid | fitted first (size A: s, compilations) | new cloud s "
        "| warm s | ratio | compiled |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        first = (
            f"{r['size_a']}: {r['first_a_s']:.2f} s, {r['compiles_a']}" if "size_a" in r else "-"
        )
        compiled = ", ".join(r["compiled"]) or "nothing"
        lines.append(
            f"| {r['shape']} | {r['n']} | {r['band']} | {tuple(r['grid'])} | {first} | "
            f"{r['first_s']:.3f} | {r['warm_s']:.3f} | {r['ratio']:.2f} | {compiled} |"
        )
    worst = max(r["ratio"] for r in rows)
    return lines + ["", f"Worst ratio {worst:.2f} (target: at most 3).", ""]


def _render_batch(b: dict) -> list:
    return [
        f"## {b['files']} files of {b['points']} points in one process",
        "",
        f"`jurs fit folder -o out -q` on {b['files']} files (Example 1, scaled and moved: "
        "one grid, one octave), each into its own sub-folder, against "
        f"{b['files']} runs of the SciPy script (their sum).",
        "",
        "| run | wall s | / SciPy | CPU s | CPU / SciPy's |",
        "|---|---|---|---|---|",
        f"| {b['files']} SciPy runs (sum) | {b['scipy_total_s']:.2f} | 1.00 | "
        f"{b['scipy_cpu_s']:.2f} | 1.00 |",
        f"| one `jurs fit folder`, cache filled | {b['batch_s']:.2f} | {b['ratio']:.2f} | "
        f"{b['batch_cpu_s']:.2f} | {b['batch_cpu_s'] / b['scipy_cpu_s']:.2f} |",
        f"| one `jurs fit folder`, fresh cache | {b['batch_fresh_s']:.2f} | "
        f"{b['fresh_ratio']:.2f} | {b['batch_fresh_cpu_s']:.2f} | "
        f"{b['batch_fresh_cpu_s'] / b['scipy_cpu_s']:.2f} |",
        "",
        "Target: at most 0.3x.",
        "",
    ]


def _render_cli(cli: dict, fits: list) -> list:
    cpu = cli["cpu_median_s"]
    lines = [
        f"## The command line on {CLI_POINTS} points against the SciPy script",
        "",
        "CPU s: user + system seconds of the process, all its threads (medians): less "
        "sensitive to other jobs on the machine than wall time. The SciPy script's linear "
        "algebra runs on every core, jurs's start-up mostly on one.",
        "",
        "| run | wall s | / SciPy | CPU s | CPU / SciPy's |",
        "|---|---|---|---|---|",
        f"| SciPy RBF script (median of 3) | {cli['scipy_median_s']:.2f} | 1.00 | "
        f"{cpu['scipy']:.2f} | 1.00 |",
        f"| `jurs fit`, first run, fresh cache | {cli['first_s']:.2f} | {cli['first_ratio']:.2f} "
        f"| {cpu['first']:.2f} | {cpu['first'] / cpu['scipy']:.2f} |",
        f"| `jurs fit`, later runs (median of 3) | {cli['later_median_s']:.2f} | "
        f"{cli['later_ratio']:.2f} | {cpu['later']:.2f} | {cpu['later'] / cpu['scipy']:.2f} |",
        f"| `jurs fit --no-compilation-cache` | {cli['no_cache_s']:.2f} | "
        f"{cli['no_cache_ratio']:.2f} | {cpu['no_cache']:.2f} | "
        f"{cpu['no_cache'] / cpu['scipy']:.2f} |",
        "| *bounds, in the same run:* | | | | |",
        f"| the command line's work to the end of the fit, no outputs, fresh cache | "
        f"{cli['fit_only_first_s']:.2f} | {cli['fit_only_first_ratio']:.2f} | "
        f"{cpu['fit_only_first']:.2f} | {cpu['fit_only_first'] / cpu['scipy']:.2f} |",
        f"| the same, cache filled (median of 3) | {cli['fit_only_later_median_s']:.2f} | "
        f"{cli['fit_only_later_ratio']:.2f} | {cpu['fit_only_later']:.2f} | "
        f"{cpu['fit_only_later'] / cpu['scipy']:.2f} |",
        f"| `import jax` alone (median of 3) | {cli['jax_import_median_s']:.2f} | "
        f"{cli['jax_import_ratio']:.2f} | {cpu['jax_import']:.2f} | "
        f"{cpu['jax_import'] / cpu['scipy']:.2f} |",
        "",
        f"What bounds later runs: the process that stops after the fit took "
        f"{cli['fit_only_later_median_s']:.2f} s ({cli['fit_only_later_ratio']:.2f}x the SciPy "
        f"script), `import jax` alone {cli['jax_import_median_s']:.2f} s "
        f"({cli['jax_import_ratio']:.2f}x); the outputs (level-set analysis, figure, files) "
        f"added {cli['later_median_s'] - cli['fit_only_later_median_s']:.2f} s "
        f"({cpu['later'] - cpu['fit_only_later']:.2f} CPU s).",
        "",
    ]
    same = [r for r in fits if r["n"] == CLI_POINTS]
    compiled = ""
    if same:  # compiling the fit, measured above at this size
        compile_s = same[0]["compile_a_s"]
        compiled = (
            f" XLA compiling the default fit of {CLI_POINTS} points took {compile_s:.2f} s in "
            f"the first-fit row above, {compile_s / cli['scipy_median_s']:.2f}x the SciPy "
            "script's whole run."
        )
    return lines + [
        f"What bounds the first run: the process that stops after the fit took "
        f"{cli['fit_only_first_s']:.2f} s with a fresh cache "
        f"({cli['fit_only_first_ratio']:.2f}x the SciPy script).{compiled}",
        "",
    ]


OVERHEAD_ROUNDS = 15
OVERHEAD_CALLS = 20


def measure_overhead() -> dict:
    """Per-call milliseconds of a warm, fully specified fit of Example 1: inside jax.jit,
    and at top level from arrays, from a reused Cloud and with checks=False (medians over
    interleaved rounds of OVERHEAD_CALLS calls each)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np

    import jurs

    points, normals = jurs.datasets.example1(120)
    solver = jurs.LeastSquares(lam=1e-6)
    settings = dict(grid=(9, 9), offset=0.1, eps=0.01, solver=solver)
    jitted = jax.jit(lambda p, n: jurs.fit(p, n, **settings).spline.control)
    device_points, device_normals = jnp.asarray(points), jnp.asarray(normals)
    cloud = jurs.Cloud(points, normals)
    cases = {
        "inside jax.jit": lambda: jitted(device_points, device_normals),
        "top level, arrays": lambda: jurs.fit(points, normals, **settings).spline.control,
        "top level, a Cloud reused": lambda: jurs.fit(cloud, **settings).spline.control,
        "top level, checks=False": lambda: (
            jurs.fit(points, normals, checks=False, **settings).spline.control
        ),
    }
    for case in cases.values():  # compile and warm
        for _ in range(3):
            jax.block_until_ready(case())
    times = {name: [] for name in cases}
    for _ in range(OVERHEAD_ROUNDS):
        for name, case in cases.items():
            start = time.perf_counter()
            for _ in range(OVERHEAD_CALLS):
                jax.block_until_ready(case())
            times[name].append((time.perf_counter() - start) / OVERHEAD_CALLS * 1e3)
    median = {name: float(np.median(t)) for name, t in times.items()}
    base = median["inside jax.jit"]
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "cores": os.cpu_count(),
        "load": " ".join(f"{x:.1f}" for x in os.getloadavg()),
        "cases": [
            {"case": name, "ms": median[name], "ratio": median[name] / base} for name in cases
        ],
    }


def render_overhead(data: dict) -> str:
    lines = [
        "# Host work of a warm fit",
        "",
        f"{data['date']}, {data['machine']}, load {data['load']}.",
        "Example 1 (120 points), grid 9 x 9, `LeastSquares(lam=1e-6)`, every setting given;",
        f"per call, median of {OVERHEAD_ROUNDS} interleaved rounds of {OVERHEAD_CALLS} calls"
        " (`python -m benchmarks.startup --overhead`).",
        "",
        "| call | ms | x inside jax.jit |",
        "|---|---|---|",
    ]
    for row in data["cases"]:
        lines.append(f"| {row['case']} | {row['ms']:.3f} | {row['ratio']:.2f} |")
    lines += [
        "",
        "Inside `jax.jit` no host work runs: the layout is traced and no check is made. A",
        "top-level call from arrays checks the cloud, lays out its problem on the host and",
        "checks the orientation of its normals every call; a reused `jurs.Cloud` does all",
        "three once, and `checks=False` skips the orientation check.",
        "",
    ]
    return "\n".join(lines)


def merged_rows(data: dict) -> dict:
    """The committed results (``results/startup.json``) with the rows of part 2 just
    measured in ``data`` in place of those of the same size, each marked with its run's
    date and load."""
    with open(os.path.join(ROOT, "benchmarks", "results", "startup.json")) as fh:
        committed = json.load(fh)
    run = f"{data['date']}, load average {data['load_before']} before, {data['load_after']} after"
    fresh = {r["n"]: dict(r, run=run) for r in data["fits"]}
    kept = [r for r in committed.get("fits", []) if r["n"] not in fresh]
    committed["fits"] = sorted(kept + list(fresh.values()), key=lambda r: r["n"])
    return committed


def main() -> None:
    global SIZES, REPEATS, IMPORT_REPEATS, LADDER, SECOND_SHAPE, BATCH_FILES
    if "--overhead" in sys.argv[1:]:
        data = measure_overhead()
        text = render_overhead(data)
        write_results("overhead", data, text)
        print(text)
        return
    if "--from-json" in sys.argv[1:]:  # re-render the committed results from their JSON
        with open(os.path.join(ROOT, "benchmarks", "results", "startup.json")) as fh:
            data = json.load(fh)
        write_results("startup", data, render(data))
        return
    parts = PARTS
    if "--parts" in sys.argv[1:]:
        parts = tuple(sys.argv[sys.argv.index("--parts") + 1].split(","))
        unknown = set(parts) - set(PARTS)
        if unknown:
            raise SystemExit(f"--parts: unknown {sorted(unknown)}; the parts are {PARTS}")
    merge = "--sizes" in sys.argv[1:]  # rows of part 2 re-run into the committed results
    if merge:
        SIZES = tuple(int(n) for n in sys.argv[sys.argv.index("--sizes") + 1].split(","))
        parts = ("fits",)
    quick = "--quick" in sys.argv[1:]  # a smoke test: 100 points, one of each, not written
    if quick:
        SIZES, REPEATS, IMPORT_REPEATS = (100,), 1, 1
        LADDER, SECOND_SHAPE, BATCH_FILES = (100, 120), ("ellipse 5 x 2.5", 150), 2
    log = elapsed_log()
    py = sys.executable
    load_before = " ".join(f"{x:.1f}" for x in os.getloadavg())
    with tempfile.TemporaryDirectory(prefix="jurs-startup-") as tmp:
        snapshot = os.path.join(tmp, "src")
        shutil.copytree(
            os.path.join(ROOT, "jurs"),
            os.path.join(snapshot, "jurs"),
            ignore=shutil.ignore_patterns("__pycache__"),
        )
        home, work = os.path.join(tmp, "home"), os.path.join(tmp, "work")
        os.makedirs(home)
        os.makedirs(work)
        env = clean_environment(home, os.path.join(tmp, "cache"), snapshot)
        # Byte-compile the snapshot once, as an installed package is.
        wall([py, "-m", "compileall", "-q", snapshot], env, work)
        data = {
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "machine": machine(),
            "cores": os.cpu_count(),
            "load_before": load_before,
        }
        measures = {
            "imports": measure_imports,
            "fits": measure_fits,
            "ladder": measure_ladder,
            "batch": measure_batch,
            "cli": measure_cli,
        }
        for part in PARTS:
            if part in parts:
                data[part] = measures[part](py, env, work, log)
    data["load_after"] = " ".join(f"{x:.1f}" for x in os.getloadavg())
    if merge and not quick:
        data = merged_rows(data)
    text = render(data)
    if not quick:
        write_results("startup", data, text)
    print(text)


if __name__ == "__main__":
    main()
