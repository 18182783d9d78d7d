"""Sharded fits: time and memory per device of ``jurs.fit`` over 1, 2, 4 and 8 devices.

Each configuration runs in a process of its own, started with
``--xla_force_host_platform_device_count=D`` (JAX fixes its devices when it starts), on
Example 1 at m points with a fixed 128 x 128 grid (so that only the samples grow with m)
and ``LeastSquares(lam=1e-4)``, float64; the points are split along their axis over a 1-D
mesh of the D devices (D = 1: a plain NumPy fit). Per device it records what XLA's
buffer assignment of the compiled solve asks for (arguments, temporaries, outputs:
``Compiled.memory_analysis``, one device's share of the partitioned program) and the
largest share of the problem's arrays a device holds; per process the wall time of a warm
fit (median of 2) and the peak resident set of the whole process. The largest m (1e7)
runs on 1 and 8 devices only.

CPU devices forced on one host share its cores and memory: these figures show that the
work and memory per device split (and that results agree), not speed; the time includes
the host-side layout, which every fit builds from the whole cloud (docs/sharding.md).

Several processes (``--processes``): the same fit of Example 1 (1e6 and 1e7 points, the
same fixed settings, every one given: grid 128 x 128, offset, eps, domain, solver, so that
nothing is measured on the cloud) by 1, 2 and 4 CPU processes of one device each,
started by ``python -m jurs.distributed``. The cloud is one ``.npy`` (m, 4) that each
process reads its own rows of (``jurs.datasets.load_rows``, memory-mapped) and makes
global arrays of (``jurs.datasets.global_arrays``); one process is the plain one-process
fit (its host builds the whole layout). Per process: its peak resident set
(``resource.getrusage``, maxrss, reported back by each), the read, the first fit
(compiling) and a second fit; control points against the one-process fit's, all of them;
the load average before and after each run (the host is shared).

    python -m benchmarks.sharding [--quick]      # --quick: m = 1e4 only, not written
    python -m benchmarks.sharding --processes [--sizes 1e6,1e7] [--counts 1,2,4] [--dry]
    python -m benchmarks.sharding --render       # the report again from its JSON

Writes ``benchmarks/results/sharding.{md,json}``; ``--processes`` adds its rows to the
JSON's ``processes`` section (a row per size and process count, replaced when measured
again) and keeps the rest.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import textwrap

from ._common import RESULTS, write_results

DEVICES = (1, 2, 4, 8)
SIZES = (10_000, 100_000, 1_000_000, 10_000_000)
#: The largest size runs on these device counts only (each takes minutes and several GB).
LARGEST_DEVICES = (1, 8)
GRID = (128, 128)
TIMEOUT_S = 900

CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    import jurs
    from jurs._fit import call as _fit
    from jurs._jit import as_arrays
    from jurs._problem import padding as _problem
    from jurs._fit.sharding import place_fit

    m, grid = int(sys.argv[1]), tuple(json.loads(sys.argv[2]))
    devices = len(jax.devices())
    p, n = jurs.datasets.example1(m)
    solver = jurs.LeastSquares(lam=1e-4)
    kw = dict(grid=grid, offset=0.005, eps=0.005, solver=solver)
    if devices > 1:
        split = NamedSharding(Mesh(np.array(jax.devices()), ("points",)), P("points"))
        p, n = jax.device_put(p, split), jax.device_put(n, split)
    t0 = time.perf_counter()
    sol = jax.block_until_ready(jurs.fit(p, n, **kw))
    first = time.perf_counter() - t0
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        sol = jax.block_until_ready(jurs.fit(p, n, **kw))
        times.append(time.perf_counter() - t0)
    # The solve that fit compiled, compiled again to read XLA's buffer assignment.
    problem = _problem.padded_problem(
        np.asarray(p), np.asarray(n), None, grid, 0.005, 0.005, None, 0.1, None, jnp.float64
    )
    dyn = as_arrays(solver, jnp.float64)
    problem, dyn, _ = place_fit(p, n, problem, dyn, None)
    reassoc = _fit._reassociation_pays(problem, dyn)
    run = _fit._solve_reassociating if reassoc else _fit._solve
    compiled = run.lower(problem, dyn, None, False).compile(
        jurs.COMPILER_OPTIONS if reassoc else None
    ).compiled
    memory = compiled.memory_analysis()
    shares = {}
    for leaf in jax.tree.leaves(problem):
        for shard in leaf.addressable_shards:
            shares[shard.device.id] = shares.get(shard.device.id, 0) + shard.data.nbytes
    print(json.dumps(dict(
        m=m, devices=devices, slots=int(problem.samples.shape[0]),
        first_s=first, warm_s=float(np.median(times)),
        argument_mb=memory.argument_size_in_bytes / 1e6,
        temp_mb=memory.temp_size_in_bytes / 1e6,
        output_mb=memory.output_size_in_bytes / 1e6,
        problem_share_mb=max(shares.values()) / 1e6,
        process_peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
        control=np.asarray(sol.spline.control).ravel()[::97].tolist(),
        status=sol.status,
    )))
    """
)


def measure(m: int, devices: int) -> dict:
    env = dict(
        os.environ,
        XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
        JAX_ENABLE_X64="1",
        JAX_PLATFORMS="cpu",
    )
    run = subprocess.run(
        [sys.executable, "-c", CHILD, str(m), json.dumps(GRID)],
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    if run.returncode != 0:
        return dict(m=m, devices=devices, error=run.stderr.strip().splitlines()[-1][:300])
    return json.loads(run.stdout.strip().splitlines()[-1])


def agreement(rows: list[dict]) -> None:
    """Each row's largest relative difference of (a sample of) its control points from the
    one-device fit of the same m."""
    import numpy as np

    reference = {r["m"]: np.asarray(r["control"]) for r in rows if r.get("devices") == 1}
    for r in rows:
        ref = reference.get(r["m"])
        if "control" in r and ref is not None:
            c = np.asarray(r.pop("control"))
            r["rel_diff"] = float(np.abs(c - ref).max() / np.abs(ref).max())
    for r in rows:
        r.pop("control", None)


def render(data: dict) -> str:
    lines = [
        "# Sharded fits: time and memory per device",
        "",
        f"Run {data['date']} on {data['machine']}. `python -m benchmarks.sharding`; "
        f"Example 1 at m points, grid {data['grid'][0]} x {data['grid'][1]}, "
        "`LeastSquares(lam=1e-4)`, float64, the points split over a 1-D mesh of D forced "
        "CPU devices (D = 1: the plain fit), each configuration in a process of its own.",
        "",
        "**CPU devices on one 2-core host share its cores and memory: these rows show the "
        "per-device memory and the agreement, not speed.** Per device: XLA's buffer "
        "assignment for the compiled solve (arguments + temporaries + outputs, one "
        "device's share) and the largest share of the problem's arrays one device holds. "
        "Time: a warm `jurs.fit` (median of 2), host-side layout included. Process peak: "
        "the resident set of the whole process (every device and the host's copy of the "
        "cloud; the layout is built on the host from the whole cloud).",
        "",
        "| m | D | slots | warm fit s | first fit s | per device: args MB | temp MB | "
        "total MB | problem share MB | process peak MB | rel. diff. to D = 1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in data["rows"]:
        if "error" in r:
            lines.append(f"| {r['m']} | {r['devices']} | failed: {r['error']} |")
            continue
        total = r["argument_mb"] + r["temp_mb"] + r["output_mb"]
        lines.append(
            f"| {r['m']:.0e} | {r['devices']} | {r['slots']} | {r['warm_s']:.2f} | "
            f"{r['first_s']:.1f} | {r['argument_mb']:.1f} | {r['temp_mb']:.1f} | "
            f"{total:.1f} | {r['problem_share_mb']:.1f} | {r['process_peak_mb']:.0f} | "
            f"{r.get('rel_diff', float('nan')):.1e} |"
        )
    lines += ["", summary(data["rows"]), ""]
    if data.get("processes"):
        # The floor of a process: the one-device fit of the smallest m (runtime, compiled
        # programs, the grid's arrays; the cloud's share negligible there).
        small = [r for r in data["rows"] if r.get("devices") == 1 and "process_peak_mb" in r]
        floor = min(small, key=lambda r: r["m"])["process_peak_mb"] if small else None
        lines += render_processes(data["processes"], floor)
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """A paragraph on the largest m: how the per-device memory splits."""
    ok = [r for r in rows if "error" not in r]
    if not ok:
        return ""
    m = max(r["m"] for r in ok)
    by_d = {r["devices"]: r for r in ok if r["m"] == m}
    total = {d: r["argument_mb"] + r["temp_mb"] + r["output_mb"] for d, r in by_d.items()}
    small = min(r["temp_mb"] for r in ok if r["m"] == min(x["m"] for x in ok))
    worst = max(r.get("rel_diff", 0.0) for r in ok)
    lo, hi = min(by_d), max(by_d)
    # Proportional to m / devices: the D-device total over the one-device total / D.
    proportion = total[hi] / (total[lo] * lo / hi)
    return (
        f"At m = {m:.0e} the memory per device falls from {total[lo]:.0f} MB on {lo} "
        f"device(s) to {total[hi]:.0f} MB on {hi}: the samples' arguments split exactly "
        f"({by_d[lo]['argument_mb']:.0f} -> {by_d[hi]['argument_mb']:.0f} MB), and the "
        f"temporaries approach a floor of about {small:.0f} MB that every device holds "
        "whatever m: the grid's arrays (the 49-point stencil, the block Cholesky of "
        "the 128 x 128 system), which each device keeps and solves whole (replicated). "
        f"Per device that is {proportion:.2f}x the one-device total divided by {hi} (1.00: "
        "exactly proportional to m / devices). "
        "The process peak grows with D: every forced device and the host's copy of the "
        "cloud live in one process. Control points agree with the one-device fit within "
        f"{worst:.0e} (relative, a sample of every 97th)."
    )


# --- several processes ---------------------------------------------------------------------

PROCESS_SIZES = (1_000_000, 10_000_000)
PROCESS_COUNTS = (1, 2, 4)
#: The fixed settings of every multi-process row (those of the device rows above).
OFFSET = 0.005

PROCESS_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    import jurs.distributed

    jurs.distributed.initialize(initialization_timeout=300)
    import jax, numpy as np
    import jurs

    npy, out, box, grid = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), json.loads(sys.argv[4])
    pid = jax.process_index()
    peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    stages = dict(started=peak())
    t0 = time.perf_counter()
    p, n = jurs.datasets.load_rows(npy)
    held = len(p)
    gp, gn = jurs.datasets.global_arrays(p, n)
    del p, n
    read = time.perf_counter() - t0
    stages["read"] = peak()
    kw = dict(grid=tuple(grid), offset=OFFSET, eps=OFFSET, domain=box,
              solver=jurs.LeastSquares(lam=1e-4))
    t0 = time.perf_counter()
    sol = jax.block_until_ready(jurs.fit(gp, gn, **kw))
    first = time.perf_counter() - t0
    stages["fit 1"] = peak()
    del sol  # fit 2 as fit 1: not beside the first fit's result
    t0 = time.perf_counter()
    sol = jax.block_until_ready(jurs.fit(gp, gn, **kw))
    second = time.perf_counter() - t0
    control = np.asarray(sol.spline.control)  # replicated in every process
    jurs.distributed.write_once(out + "_control.npy", lambda f: np.save(f, control))
    with open(f"{out}_{pid}.json", "w") as fh:
        json.dump(dict(
            process=pid, held=held, read_s=read, first_s=first, second_s=second, stages=stages,
            peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
            status=sol.status,
        ), fh)
    jax.distributed.shutdown() if jax.process_count() > 1 else None
    """
).replace("OFFSET", repr(OFFSET))


def measure_processes(npy: str, m: int, count: int, box, folder: str) -> dict:
    """One run of ``count`` processes (one CPU device each) fitting the cloud of ``npy``."""
    import time

    script = os.path.join(folder, "child.py")
    with open(script, "w") as fh:
        fh.write(PROCESS_CHILD)
    out = os.path.join(folder, f"run_{m}_{count}")
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    load = list(os.getloadavg())
    start = time.perf_counter()
    launcher = [sys.executable, "-m", "jurs.distributed", "--processes", str(count)]
    run = subprocess.run(
        [*launcher, "--cpu-devices", "1", script, npy, out, json.dumps(box), json.dumps(GRID)],
        env=env, capture_output=True, text=True, timeout=TIMEOUT_S,
    )  # fmt: skip
    wall = time.perf_counter() - start
    row = dict(
        m=m, processes=count, wall_s=wall, load_before=load, load_after=list(os.getloadavg()),
        date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    )  # fmt: skip
    if run.returncode != 0:
        return dict(row, error=(run.stderr.strip().splitlines() or ["?"])[-1][:300])
    import numpy as np

    reports = []
    for i in range(count):
        with open(f"{out}_{i}.json") as fh:
            reports.append(json.load(fh))
    row.update(
        per_process=reports,
        peak_mb=max(r["peak_mb"] for r in reports),
        first_s=max(r["first_s"] for r in reports),
        second_s=max(r["second_s"] for r in reports),
        read_s=max(r["read_s"] for r in reports),
        status=reports[0]["status"],
        control=np.load(f"{out}_control.npy").ravel().tolist(),  # written by process 0
    )
    return row


def processes_main(args: list[str]) -> None:
    """``--processes``: measure, merge into the JSON's ``processes`` section, render."""
    import tempfile

    import numpy as np

    def option(name, default):
        if name in args:
            return [int(float(x)) for x in args[args.index(name) + 1].split(",")]
        return list(default)

    sizes, counts = option("--sizes", PROCESS_SIZES), option("--counts", PROCESS_COUNTS)
    path = os.path.join(RESULTS, "sharding.json")
    with open(path) as fh:
        data = json.load(fh)
    section = data.setdefault("processes", dict(grid=list(GRID), offset=OFFSET, rows=[]))
    import jurs

    for m in sizes:
        with tempfile.TemporaryDirectory() as folder:
            p, n = jurs.datasets.example1(m)
            lo, hi = p.min(0), p.max(0)
            pad = 0.1 * float((hi - lo).max())
            box = [list(map(float, lo - pad)), list(map(float, hi + pad))]
            npy = os.path.join(folder, "cloud.npy")
            np.save(npy, np.concatenate([p, n], axis=1))
            del p, n
            rows = []
            for count in counts:
                row = measure_processes(npy, m, count, box, folder)
                shown = {k: v for k, v in row.items() if k not in ("control", "per_process")}
                print(json.dumps(shown), flush=True)
                rows.append(row)
        one = next((r for r in rows if r["processes"] == 1 and "control" in r), None)
        for r in rows:  # against this run's one-process fit; the control points not kept
            if "control" in r and one is not None:
                c, c1 = np.asarray(r["control"]), np.asarray(one["control"])
                r["rel_diff"] = float(np.abs(c - c1).max() / np.abs(c1).max())
        for r in rows:
            r.pop("control", None)
            section["rows"] = [  # a row per size and count: the new one replaces
                x for x in section["rows"]
                if (x["m"], x["processes"]) != (r["m"], r["processes"])
            ] + [r]  # fmt: skip
    section["rows"].sort(key=lambda r: (r["m"], r["processes"]))
    text = render(data)
    print(text[text.index("## Several processes") :])
    if "--dry" not in args:
        write_results("sharding", data, text)


def render_processes(section: dict, floor: float | None = None) -> list[str]:
    """The multi-process table and what it shows."""
    grid = section["grid"]
    lines = [
        "## Several processes",
        "",
        "`python -m benchmarks.sharding --processes`: Example 1 at m points, every setting "
        f"given (grid {grid[0]} x {grid[1]}, offset = eps = {section['offset']}, the domain, "
        "`LeastSquares(lam=1e-4)`; nothing measured on the cloud), float64, by P CPU "
        "processes of one device each on this one 2-core host, started by "
        "`python -m jurs.distributed`. Each reads its own rows of one `.npy` "
        "(`jurs.datasets.load_rows`, memory-mapped) and makes the global arrays "
        "(`jurs.datasets.global_arrays`); P = 1 is the one-process fit (the whole layout "
        "on its host). Peak: the largest of the processes' own peak resident sets "
        "(`getrusage` maxrss in each), at the end and after fit 1. Times: the slowest "
        "process; fit 1 compiles, fit 2 reuses it (the first's result dropped before). "
        "The P processes share the 2 cores (and the host is shared with other work: the "
        "load average is recorded), so times show cost, not speed-up.",
        "",
        "| m | P | date | load before | read s | fit 1 s | fit 2 s | wall s | peak MB a "
        "process | after fit 1 MB | P = 1's peak / this | rel. diff. to P = 1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = section["rows"]
    one = {r["m"]: r.get("peak_mb") for r in rows if r["processes"] == 1}
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r['m']:.0e} | {r['processes']} | {r['date']} | failed: {r['error']} |"
            )
            continue
        ratio = one.get(r["m"])
        ratio = f"{ratio / r['peak_mb']:.2f}x" if ratio else "-"
        lines.append(
            f"| {r['m']:.0e} | {r['processes']} | {r['date']} | {r['load_before'][0]:.1f} | "
            f"{r['read_s']:.1f} | {r['first_s']:.1f} | {r['second_s']:.1f} | "
            f"{r['wall_s']:.0f} | {r['peak_mb']:.0f} | {first_fit(r)} | {ratio} | "
            f"{r.get('rel_diff', float('nan')):.1e} |"
        )
    lines += ["", summary_processes(section, floor), *section.get("notes", []), ""]
    return lines


def first_fit(row: dict) -> str:
    """The largest of the processes' peaks after their first fit (MB), where recorded."""
    peaks = [p["stages"]["fit 1"] for p in row.get("per_process", []) if "stages" in p]
    return f"{max(peaks):.0f}" if peaks else "-"


def summary_processes(section: dict, floor: float | None) -> str:
    """A paragraph on the largest m: the per-process peak against the memory targets
    (1.7x less from 1 to 2 processes, 3x from 1 to 4), what bounds it, the agreement."""
    ok = [r for r in section["rows"] if "error" not in r]
    if not ok:
        return ""
    m = max(r["m"] for r in ok)
    peak = {r["processes"]: r["peak_mb"] for r in ok if r["m"] == m}
    if 1 not in peak:
        return ""
    parts = []
    for count, target in ((2, 1.7), (4, 3.0)):
        if count in peak:
            ratio = peak[1] / peak[count]
            verdict = "met" if ratio >= target else "missed"
            goal = f" (target at 1e7: {target}x, {verdict})" if m >= 10_000_000 else ""
            parts.append(f"{count} processes {ratio:.2f}x less{goal}")
    text = (
        f"At m = {m:.0e} the peak a process falls from {peak[1]:.0f} MB in one process to "
        + ", ".join(f"{peak[c]:.0f} MB with {c}" for c in sorted(peak) if c > 1)
        + ": "
        + "; ".join(parts)
        + "."
    )
    # What a process holds whatever its share (the runtime, the compiled programs, the
    # grid's arrays): measured per P where the section has a run of few points (under
    # 1e5), else the one-device process peak at the smallest m of the table above.
    small = {r["processes"]: r for r in ok if r["m"] < 100_000}
    floors = {c: small[c]["peak_mb"] if c in small else floor for c in peak}
    if all(f is not None for f in floors.values()):
        above = {c: peak[c] - floors[c] for c in peak}
        if small:
            m_small = min(r["m"] for r in small.values())
            said = ", ".join(f"{floors[c]:.0f} MB with {c}" for c in sorted(peak))
            text += (
                f" A fit of {m_small:.0e} points on this grid (the rows above) peaks at {said} "
                "process(es): the floor, which does not split (the JAX runtime and its "
                "collectives, the compiled programs, the grid-sized arrays, i.e. the 128 x 128 "
                "system and its Cholesky factor, replicated)."
            )
        else:
            text += (
                f" A process fitting 1e4 points on this grid peaks at {floor:.0f} MB (the "
                "table above: the JAX runtime and compiled programs, the grid-sized arrays): "
                "that floor does not split."
            )
        per_point = ", ".join(
            f"{above[c] * 1e6 / (m / c):.0f} with {c}" for c in sorted(peak) if c > 1
        )
        text += (
            f" Above it the peak falls from {above[1]:.0f} MB to "
            + ", ".join(
                f"{above[c]:.0f} MB with {c} ({above[1] / above[c]:.2f}x)"
                for c in sorted(peak)
                if c > 1
            )
            + f"; bytes a point held: {above[1] * 1e6 / m:.0f} in one process, {per_point}."
        )
    after = {r["processes"]: first_fit(r) for r in ok if r["m"] == m}
    if "-" not in after.values() and 1 in after:
        ratios = ", ".join(
            f"{float(after[1]) / float(after[c]):.2f}x with {c}" for c in sorted(after) if c > 1
        )
        rise = max(  # a process's own end peak over its own peak after fit 1
            p["peak_mb"] - p["stages"]["fit 1"]
            for r in ok
            if r["m"] == m
            for p in r.get("per_process", [])
        )
        text += (
            f" After the first fit alone the peak falls from {after[1]} MB by {ratios}; "
            f"the second fit raised a process's peak by at most {rise:.0f} MB."
        )
    worst = max((r.get("rel_diff", 0.0) for r in ok), default=0.0)
    return (
        text + f" Control points agree with the one-process fit within {worst:.0e} (relative, "
        "all of them; a direct solve)."
    )


def main() -> None:
    if "--processes" in sys.argv[1:]:
        processes_main(sys.argv[1:])
        return
    if sys.argv[1:2] == ["--render"]:  # re-render the committed JSON, no measuring
        from ._common import rerender_beside

        print(rerender_beside(os.path.join(RESULTS, "sharding.json"), render))
        return
    quick = "--quick" in sys.argv[1:]
    sizes = SIZES[:1] if quick else SIZES
    rows = []
    for m in sizes:
        for devices in LARGEST_DEVICES if m == SIZES[-1] and not quick else DEVICES:
            row = measure(m, devices)
            print(json.dumps({k: v for k, v in row.items() if k != "control"}), flush=True)
            rows.append(row)
    agreement(rows)
    import jax

    data = dict(
        date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        machine=f"{platform.machine()}, {os.cpu_count()} cores, JAX {jax.__version__} (CPU)",
        grid=list(GRID),
        rows=rows,
        load=list(os.getloadavg()),
    )
    path = os.path.join(RESULTS, "sharding.json")
    if os.path.exists(path):  # the multi-process rows (--processes) are kept
        with open(path) as fh:
            data["processes"] = json.load(fh).get("processes")
    text = render(data)
    print(text)
    if not quick:
        write_results("sharding", data, text)


if __name__ == "__main__":
    main()
