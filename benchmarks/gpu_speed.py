"""The speed benchmark on an accelerator: jurs at 1e6 to 1e7 points on a GPU, beside the CPU run.

    python -m benchmarks.gpu_speed [--quick] [--out DIR]
    python -m benchmarks.gpu_speed --from-json benchmarks/results/speed_gpu.json   # re-render

Runs the measurements of ``benchmarks/speed.py`` that mean something on an accelerator,
with the same workers, each in a fresh process, in float64:

* one step of ``IURS(tau=1e-2, lam=1e-3)``, ``IPIA()`` and ``NormalIPIA()`` (its assembly
  of D^T D timed apart) on Example 1 clouds of 1e6 to 1e7 points;
* ``LeastSquares`` end to end through ``jurs.fit`` (problem building on the host included);
* the IURS step inside ``jurs.fit`` (fits of 1 and 21 steps);
* the Example-4-size fits (cold and warm), where a GPU is the wrong tool: every step is a
  few dozen small kernels, each paying a launch.

Beside each GPU figure it puts the CPU figure of the committed ``speed.json`` where the
CPU run measured the same configuration, and their ratio. The baselines (the dense NumPy
port, SciPy's RBF) run on the CPU only and are not repeated here.

It refuses to run unless JAX's default backend is an accelerator (``--quick`` on a CPU is
allowed, to check the script). Results go to ``benchmarks/results/speed_gpu.{json,md}``
(``speed_gpu_quick`` for ``--quick``), or under ``--out``; the JSON is rewritten after every
measurement, so a run stopped early keeps what it measured.
"""

from __future__ import annotations

import argparse
import json
import os
import time

HERE = os.path.dirname(os.path.abspath(__file__))

from . import _speed_workers as workers  # noqa: E402  (the workers and their orchestration)
from ._common import (  # noqa: E402  (the report's helpers)
    bytes_text,
    elapsed_log,
    error_text,
    find_row,
    machine,
    md_table,
    measured_row,
    ms_text,
    ratio_text,
    rerender_beside,
    s_text,
    where_cells,
    write_results,
)
from ._speed_workers import step_passes_s  # noqa: E402

#: Points -> grids of the step sweep (Example 1 clouds, 3m samples); sized so that the whole
#: run takes minutes, not hours, on one accelerator (the report gives its duration).
GPU_SWEEP = {1_000_000: (128, 256), 10_000_000: (128, 256)}
QUICK_SWEEP = {100_000: (64,)}
#: Points -> steps k of the in-fit step measurement (fits of 1 and 1 + k steps, the
#: large grid). A GPU step is so short next to the host's problem building, which both fits
#: repeat, that the CPU run's k = 20 leaves the difference in the noise.
FIT_STEPS = {1_000_000: 200, 10_000_000: 50}
QUICK_FIT_STEPS = {100_000: 200}
CPU_RESULTS = os.path.join(HERE, "results", "speed.json")


def run(quick: bool, out_dir: str, log) -> dict:
    """Every measurement, the JSON and markdown rewritten after each."""
    import jax

    name = "speed_gpu_quick" if quick else "speed_gpu"
    data = {
        "quick": quick,
        "machine": machine(),
        "device": workers.device_name(jax),
        "devices": [str(d) for d in jax.devices()],
        "sweep": [],
        "fit_steps": [],
        "example4": [],
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }
    start = time.perf_counter()

    def save():
        data["runtime_s"] = time.perf_counter() - start
        write(data, out_dir, name)

    for m, grids in (QUICK_SWEEP if quick else GPU_SWEEP).items():
        for g in grids:
            row = {"m": m, "samples": 3 * m, "grid": g}
            data["sweep"].append(row)
            for key in workers.STEP_SOLVERS:
                row[key] = workers.run_worker(
                    {"kind": "step", "m": m, "grid": g, "solver": key}, log
                )
                save()
            row["lstsq"] = workers.run_worker(
                {"kind": "lstsq", "m": m, "grid": g, "lam": workers.LSQ_LAM}, log
            )
            save()
    for m, k in (QUICK_FIT_STEPS if quick else FIT_STEPS).items():
        data["fit_steps"].append(
            {
                "m": m,
                "grid": workers.LARGE_GRID,
                **workers.run_worker(
                    {"kind": "fit_steps", "m": m, "grid": workers.LARGE_GRID, "steps": k}, log
                ),
            }
        )
        save()
    # One process a fit: here they show what a GPU does with small problems.
    data["example4"] = workers.run_example4(log, runs=1)
    save()
    return data


def write(data: dict, out_dir: str, name: str) -> str:
    """``<out_dir>/<name>.{json,md}``; returns the markdown."""
    text = report(data)
    write_results(name, data, text, out_dir)
    return text


def _cpu_run() -> dict | None:
    """The committed CPU run of ``speed.py`` (None where it is missing)."""
    try:
        with open(CPU_RESULTS) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def _ratio(cpu_s, gpu_s):
    return cpu_s / gpu_s if cpu_s and gpu_s else None


def report(data: dict) -> str:
    cpu = _cpu_run()
    cpu_sweep = cpu["sweep"] if cpu else []
    lines = [
        f"# Speed on an accelerator{' (QUICK run)' if data['quick'] else ''}",
        "",
        f"Device of the measurements: **{data['device']}** ({', '.join(data['devices'])}). "
        f"Host: {data['machine']}. float64. Run began {data.get('started', '—')}; "
        f"whole run {data.get('runtime_s', 0) / 60:.1f} min.",
        "",
        "CPU columns: the committed `speed.json` of `benchmarks/speed.py` ("
        + (f"{cpu['machine']}" if cpu else "missing")
        + "), the same workers and "
        "configurations; *CPU / GPU* is the CPU time over the GPU time. Workers and "
        "what they time: `benchmarks/speed.py` (a fresh process each; warm = median, "
        "fastest in brackets; compile = first call minus warm). *Device peak*: the "
        "accelerator's `peak_bytes_in_use`; host RSS is in the JSON.",
        "",
    ]
    lines += _step_tables(data["sweep"], cpu_sweep)
    lines += _lstsq_table(data["sweep"], cpu_sweep)
    lines += _fit_steps_table(data["fit_steps"], cpu)
    lines += _example4_table(data["example4"], cpu)
    return "\n".join(lines) + "\n"


def _step_tables(sweep, cpu_sweep) -> list[str]:
    lines = []
    for key, (label, _, _) in workers.STEP_SOLVERS.items():
        rows = []
        for r in sweep:
            res = r.get(key)
            if res is None:
                continue
            c = (find_row(cpu_sweep, m=r["m"], grid=r["grid"]) or {}).get(key, {})
            extra = key == "normal_ipia"
            rows.append(
                measured_row(
                    where_cells(r),
                    res,
                    6 + extra,
                    lambda res=res, c=c: (
                        [
                            f"{ms_text(res['step_warm_s'])} ({ms_text(res['step_min_s'])})",
                            s_text(res["step_compile_s"]),
                            bytes_text(res.get("device_peak_b")),
                            s_text(res["build_s"]),
                        ]
                        + ([ms_text(res["init_warm_s"])] if extra else [])
                        + [
                            ms_text(c.get("step_warm_s")),
                            ratio_text(_ratio(c.get("step_warm_s"), res["step_warm_s"])),
                        ]
                    ),
                )
            )
        lines += [f"## {label}: one step", ""]
        lines += md_table(
            ["m", "grid", "warm step (min)", "compile", "device peak", "problem build (host)"]
            + (["assembly (init) warm"] if key == "normal_ipia" else [])
            + ["CPU warm step", "CPU / GPU"],
            rows,
        )
        lines.append("")
    return lines


def _lstsq_table(sweep, cpu_sweep) -> list[str]:
    rows = []
    for r in sweep:
        res = r.get("lstsq")
        if res is None:
            continue
        c = (find_row(cpu_sweep, m=r["m"], grid=r["grid"]) or {}).get("lstsq", {})
        rows.append(
            measured_row(
                where_cells(r),
                res,
                7,
                lambda res=res, c=c: [
                    f"{s_text(res['fit_warm_s'])} ({s_text(res['fit_min_s'])})",
                    s_text(res["fit_first_s"]),
                    bytes_text(res.get("device_peak_b")),
                    f"{res['E_ave']:.3e}",
                    s_text(c.get("fit_warm_s")),
                    f"{c['E_ave']:.3e}" if "E_ave" in c else "—",
                    ratio_text(_ratio(c.get("fit_warm_s"), res["fit_warm_s"])),
                ],
            )
        )
    lines = [
        f"## LeastSquares(lam={workers.LSQ_LAM:g}) end to end through jurs.fit",
        "",
        "From NumPy arrays to the solved spline: the host builds the sample layout, the "
        "device assembles D^T D and D^T b and solves. E_ave on both devices shows the "
        "same fit.",
        "",
    ]
    lines += md_table(
        [
            "m",
            "grid",
            "warm (min)",
            "first call",
            "device peak",
            "E_ave",
            "CPU warm",
            "CPU E_ave",
            "CPU / GPU",
        ],
        rows,
    )
    return lines + [""]


def _fit_steps_table(fit_steps, cpu) -> list[str]:
    if not fit_steps:
        return []
    cpu_step = ((cpu or {}).get("fit_steps") or {}).get("default", {})
    rows = []
    for r in fit_steps:
        on_cpu = cpu_step.get("step_s") if r["m"] == workers.LARGE_POINTS else None
        rows.append(
            measured_row(
                where_cells(r),
                r,
                6,
                lambda r=r, on_cpu=on_cpu: [
                    r["steps"],
                    f"{ms_text(r['step_s'])} ({ms_text(r['step_min_s'])})",
                    ms_text(r["fits"]["1"]["warm_s"]),
                    bytes_text(r.get("device_peak_b")),
                    ms_text(on_cpu),
                    ratio_text(_ratio(on_cpu, r["step_s"])),
                ],
            )
        )
    lines = [
        "## The IURS step inside jurs.fit",
        "",
        "`jurs.fit(..., solver=IURS(tau=1e-2, lam=1e-3, tol=0, max_steps=n))` for n = 1 "
        "and n = 1 + k: a step is the difference of the warm medians over k (the CPU "
        "run's k is 20).",
        "",
    ]
    lines += md_table(
        [
            "m",
            "grid",
            "k",
            "step (from fastest fits)",
            "fit of 1 step",
            "device peak",
            "CPU step",
            "CPU / GPU",
        ],
        rows,
    )
    return lines + [""]


def _example4_table(rows_in, cpu) -> list[str]:
    if not rows_in:
        return []
    cpu_rows = (cpu or {}).get("example4", [])
    rows = []
    for r in rows_in:
        c = find_row(cpu_rows, label=r["label"]) or {}
        rows.append(
            measured_row(
                [r["label"]],
                r,
                8,
                lambda r=r, c=c: [
                    f"{r['num_steps']} ({c.get('num_steps', '—')})",
                    f"{r['E_ave']:.3e} ({c['E_ave']:.3e})" if "E_ave" in c else f"{r['E_ave']:.3e}",
                    f"{ms_text(r['warm_s'])} ({ms_text(r['min_s'])})",
                    s_text(r["cold_s"]),
                    ms_text(c.get("warm_s")),
                    s_text(c.get("cold_s")),
                    ratio_text(_ratio(c.get("warm_s"), r["warm_s"])),
                    ms_text(step_passes_s(r) and step_passes_s(r) * r["num_steps"]),
                ],
            )
        )
    lines = [
        "## Full regularised IURS fits of Example-4 size",
        "",
        "As in `speed.md` (15 x 15, tol 1e-7; cold = the first call in a fresh "
        "process, here one process a fit). In brackets: the CPU run's steps and E_ave, which the "
        "GPU should repeat up to rounding. *Passes x steps*: the passes of a step, each "
        "timed alone in a jitted loop, times the steps (see `speed.md`).",
        "",
    ]
    lines += md_table(
        [
            "fit",
            "steps (CPU)",
            "E_ave (CPU)",
            "warm (fastest)",
            "cold",
            "CPU warm",
            "CPU cold",
            "CPU / GPU warm",
            "passes x steps",
        ],
        rows,
    )
    return lines + [""]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="one small configuration of each measurement (about a minute)",
    )
    parser.add_argument(
        "--out",
        default=os.path.join(HERE, "results"),
        help="folder of the results files (default: benchmarks/results)",
    )
    parser.add_argument(
        "--from-json", metavar="PATH", help="re-render the markdown beside a results JSON"
    )
    args = parser.parse_args(argv)
    if args.from_json:
        print(rerender_beside(args.from_json, report))
        return

    import jax

    jax.config.update("jax_enable_x64", True)
    if jax.default_backend() == "cpu" and not args.quick:
        parser.error(
            "JAX sees no accelerator (default backend: cpu); benchmarks/speed.py "
            "is the CPU benchmark"
        )
    log = elapsed_log()
    data = run(args.quick, args.out, log)
    print(report(data))
    failed = [
        e
        for r in data["sweep"]
        for k, v in r.items()
        if isinstance(v, dict)
        for e in [error_text(v)]
        if e
    ]
    if failed:
        log(f"{len(failed)} measurements failed: " + "; ".join(failed[:3]))


if __name__ == "__main__":
    main()
