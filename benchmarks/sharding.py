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

    python benchmarks/sharding.py [--quick]      # --quick: m = 1e4 only, not written
    python benchmarks/sharding.py --render       # the report again from its JSON

Writes ``benchmarks/results/sharding.{md,json}``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import textwrap

sys.path.insert(0, os.path.dirname(__file__))
from _common import RESULTS, write_results  # noqa: E402

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
    dyn = _fit.as_arrays(solver, jnp.float64)
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
        f"Run {data['date']} on {data['machine']}. `python benchmarks/sharding.py`; "
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


def main() -> None:
    if sys.argv[1:2] == ["--render"]:  # re-render the committed JSON, no measuring
        from _common import rerender_beside

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
    text = render(data)
    print(text)
    if not quick:
        write_results("sharding", data, text)


if __name__ == "__main__":
    main()
