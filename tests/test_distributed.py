"""Fits of clouds held by several processes (``jax.distributed``; jurs._fit.sharding,
docs/sharding.md).

Two child processes on localhost, two CPU devices each, joined by
``jax.distributed.initialize`` (cross-process collectives by gloo). Each holds half of the
cloud (a global ``jax.Array`` made by ``jax.make_array_from_process_local_data``), lays out
its own samples and fits, with explicit settings and with automatic ones (chosen over both
processes' points, ``jurs._fit.process_settings``); process 0 then fits the whole cloud
alone and compares. The children are started and stopped here, within ``TIMEOUT`` seconds.

Surfaces take the same path with one sample a slot; a 3D case on the uniform grid here
would double the time (one more compiled solve in each child), so it is not in the suite
(docs/sharding.md gives its measured agreement). Adaptive fits (a curve, and a small
surface, whose CG compiles in a few seconds) run over both processes too.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

#: Two processes compile and run four fits each (two on the uniform grid, two adaptive),
#: process 0 four more (about 70 s here, the machine loaded).
pytestmark = pytest.mark.slow

#: Seconds both children together may take before they are killed.
TIMEOUT = 240

# argv: process id, coordinator port. Prints one JSON line.
CHILD = textwrap.dedent(
    """
    import json, re, sys
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    pid, port = int(sys.argv[1]), sys.argv[2]
    jax.distributed.initialize(
        coordinator_address=f"localhost:{port}", num_processes=2, process_id=pid,
        initialization_timeout=60,
    )
    import jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
    import jurs
    from jurs._fit.sharding import process_problem

    assert jax.process_count() == 2 and len(jax.local_devices()) == 2
    assert jnp.result_type(float) == jnp.float64
    mesh = Mesh(np.array(jax.devices()), ("points",))  # process 0's devices first
    split, whole = NamedSharding(mesh, P("points")), NamedSharding(mesh, P())
    out = {}

    def spread(p, n):
        # This process's half of the rows only, made into global arrays.
        half = len(p) // 2
        mine = slice(pid * half, (pid + 1) * half)
        return [
            jax.make_array_from_process_local_data(split, np.ascontiguousarray(a[mine]), a.shape)
            for a in (p, n)
        ]

    def box(p):
        lo, hi = p.min(0), p.max(0)
        pad = 0.1 * (hi - lo).max()
        return tuple(map(tuple, (lo - pad, hi + pad)))

    def error(call):
        try:
            call()
        except (ValueError, RuntimeError) as e:
            return [type(e).__name__, str(e)]
        return None

    p, n = jurs.datasets.example1(4000)
    gp, gn = spread(p, n)
    grid, offset, eps, domain = (24, 24), 0.02, 0.02, box(p)
    kw = dict(grid=grid, offset=offset, eps=eps, domain=domain, solver=jurs.LeastSquares(lam=1e-4))

    # Normals estimated over both processes: the gathered cloud's exactly; past the
    # gathered size (forced: 500 probes) each process's PCA signed by the probes'.
    from jax.experimental.multihost_utils import process_allgather
    from jurs._cloud.normals import normals_across_processes

    gathered = lambda x: np.asarray(process_allgather(x, tiled=True))
    est = jurs.estimate_normals(gp)
    est_whole = gathered(est)  # a collective: every process gathers
    combined = gathered(normals_across_processes(gp, most=500))
    out["normals"] = dict(
        split=est.sharding == gp.sharding,
        outward=float(np.mean(np.sum(combined * n, axis=1) > 0)),
    )
    if pid == 0:
        out["normals"]["exact"] = bool(np.array_equal(est_whole, jurs.estimate_normals(p)))

    # Refusal: an input error in one process (process 1's points outside a box around
    # process 0's half), raised in both.
    bad = p.copy()
    bad[3000] = np.nan  # in process 1's half
    out["auto_nan"] = error(lambda: jurs.fit(*spread(bad, n)))
    out["outside"] = error(lambda: jurs.fit(gp, gn, **dict(kw, domain=box(p[:2000]))))

    # The layout: this process's slots only, every sample counted once in global order.
    problem = process_problem(gp, gn, grid, offset, eps, domain, 0.1, None, jnp.float64)
    counts = jax.jit(
        lambda i, w: jax.ops.segment_sum(w, i, 3 * len(p)), out_shardings=whole
    )(problem.sample_index, problem.mask)
    out["layout"] = dict(
        slots=problem.samples.shape[0],
        local_slots=sum(s.data.shape[0] for s in problem.samples.addressable_shards),
        local_points=sum(s.data.shape[0] for s in problem.points.addressable_shards),
        bucket_size=problem.local.bucket_size,
        each_sample_once=bool(np.all(np.asarray(counts) == 1)),
    )

    def compare(name, p, n, **kw):
        sol = jurs.fit(*spread(p, n), **kw)
        control = sol.spline.control
        entry = dict(
            status=sol.status,
            replicated=bool(control.is_fully_replicated),
            devices=len(control.sharding.device_set),
        )
        if pid == 0:  # the whole cloud in one process, on one device
            ref = jurs.fit(p, n, **kw)
            c0, c1 = np.asarray(ref.spline.control), np.asarray(control)
            entry.update(rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()), ref=ref.status)
        out[name] = entry

    compare("curve", p, n, **kw)

    # Automatic settings and normals: jurs.fit(points) alone, against one process's.
    q, m = jurs.datasets.example1(1000)
    auto = jurs.fit(spread(q, m)[0])
    entry = dict(status=auto.status, settings=auto.settings.as_dict())
    if pid == 0:
        ref = jurs.fit(q, basis="uniform")  # as over processes: the uniform grid
        c0, c1 = np.asarray(ref.spline.control), np.asarray(auto.spline.control)
        entry.update(
            ref=ref.status, ref_settings=ref.settings.as_dict(),
            rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()),
        )
    out["auto"] = entry

    # Clouds over PROBES points are measured per process and combined: forced here at 250
    # probes of Example 1; process 0 measures the same probes against the whole cloud.
    from jurs._cloud.measure import estimate_noise, point_spacing, strided_probes
    from jurs._fit.process_settings import settings_across_processes
    from jurs._problem.problem import auto_domain, offset_samples
    from jurs._problem.sizes import DEFAULT_MARGIN

    combined = settings_across_processes(*spread(q, m), gather_limit=250)
    entry = combined.as_dict()
    if pid == 0:
        at = strided_probes(len(q), 250)
        unit = m / np.linalg.norm(m, axis=1, keepdims=True)
        samples = offset_samples(q, unit, combined.offset, combined.eps, np)[0]
        box = auto_domain(samples, DEFAULT_MARGIN, xp=np)
        entry["whole"] = dict(
            spacing=point_spacing(q, None, at), noise=estimate_noise(q, unit, None, at=at),
            domain=[list(map(float, c)) for c in box],
            settings=jurs.auto_settings(q, m).as_dict(),
        )
    out["combined"] = entry

    # Adaptive fits (jurs._fit.adaptive_sharding): the hierarchy from every process's
    # cells to refine, each process's collocation rows on its devices, CG over all.
    from jurs._fit import adaptive_sharding

    ran = []  # the sharded CG solves as called: the collectives check reads the last one
    sharded_cg = adaptive_sharding._sharded_cg

    def recording(*args, **kw):
        ran.append((args, kw))
        return sharded_cg(*args, **kw)

    adaptive_sharding._sharded_cg = recording
    summed = []  # the direct path's sums of the processes' normal equations
    sum_rows = adaptive_sharding._sum_rows

    def recording_sum(x, replicated):
        summed.append((x, replicated))
        return sum_rows(x, replicated)

    adaptive_sharding._sum_rows = recording_sum

    def compare_adaptive(name, fit, p, n, **kw):
        sol = fit(*spread(p, n), **kw)
        entry = dict(
            status=sol.status, method=sol.stats["method"], devices=sol.stats["devices"],
            processes=sol.stats["processes"], active=sol.stats["active"],
        )
        if pid == 0:  # the whole cloud in one process
            ref = fit(p, n, **kw)
            c0, c1 = np.asarray(ref.spline.control), np.asarray(sol.spline.control)
            entry.update(
                ref=ref.status, ref_active=ref.stats["active"],
                same_settings=ref.settings.as_dict() == sol.settings.as_dict(),
                rel=float(np.abs(c1 - c0).max() / np.abs(c0).max()),
            )
        out[name] = entry

    compare_adaptive("adaptive_curve", jurs.fit, q, m, basis="adaptive")
    sphere = jurs.datasets.sphere3d(800)  # CG to a tight tolerance: the sums agree closely
    compare_adaptive("adaptive_sphere", jurs.fit_adaptive, *sphere, finest=16, rtol=1e-10)
    collective = (
        r"(all-reduce|all-gather|all-to-all|reduce-scatter|collective-permute)(?:-start)?\\("
    )
    args, kw = ran[-1]  # the sphere's CG
    hlo = sharded_cg.lower(*args, **kw).compile().as_text()
    out["adaptive_cg_collectives"] = sorted(set(re.findall(collective, hlo)))
    hlo = sum_rows.lower(*summed[-1]).compile().as_text()  # the curve's summed matrix
    out["adaptive_direct_collectives"] = sorted(set(re.findall(collective, hlo)))
    print(json.dumps(out), flush=True)
    jax.distributed.shutdown()
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run_processes() -> list[dict]:
    """Both children's JSON reports; each is killed past ``TIMEOUT``, and a failure
    shows their errors."""
    env = dict(
        os.environ,
        XLA_FLAGS="--xla_force_host_platform_device_count=2",
        JAX_ENABLE_X64="1",
        JAX_PLATFORMS="cpu",
    )
    port = str(_free_port())
    children = [
        subprocess.Popen(
            [sys.executable, "-c", CHILD, str(i), port],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    deadline = time.monotonic() + TIMEOUT
    outputs = []
    try:
        for child in children:
            outputs.append(child.communicate(timeout=max(1.0, deadline - time.monotonic())))
    except subprocess.TimeoutExpired:
        pass
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
    if len(outputs) < 2 or any(c.returncode != 0 for c in children):
        errors = [err[-3000:] for _, err in outputs]
        pytest.fail(f"children exited {[c.returncode for c in children]}: {errors}")
    return [json.loads(out.strip().splitlines()[-1]) for out, _ in outputs]


@pytest.fixture(scope="module")
def reports():
    return _run_processes()


def test_fit_over_two_processes_equals_one_process_fit(reports):
    """Control points of the fit over 2 processes x 2 devices within 1e-9 (relative) of the
    one-process fit of the whole cloud; the spline replicated in both processes."""
    for report in reports:
        curve = report["curve"]
        assert curve["status"] == "successful"
        assert curve["replicated"] and curve["devices"] == 4
    assert reports[0]["curve"]["ref"] == "successful"
    assert reports[0]["curve"]["rel"] < 1e-9


def test_each_process_lays_out_its_own_points(reports):
    """Each process holds half the points and half the slots (equal counts, whole buckets
    a device), and the global layout holds every sample of the cloud exactly once."""
    for report in reports:
        layout = report["layout"]
        assert layout["local_points"] == 2000
        assert layout["local_slots"] * 2 == layout["slots"]
        assert layout["local_slots"] % (2 * layout["bucket_size"]) == 0
        assert layout["bucket_size"] > 1  # the bucketed layout, not the table form
        assert layout["each_sample_once"]


def test_automatic_settings_across_processes_equal_one_process(reports):
    """``jurs.fit(points)`` over 2 processes: the small cloud is gathered, so the normals
    and settings are one process's exactly (grid, offset, eps, domain, lam), and the
    control points within 1e-9 (relative) of the one-process automatic fit."""
    for report in reports:
        assert report["auto"]["status"] == "successful"
        assert report["auto"]["settings"] == reports[0]["auto"]["settings"]
    auto = reports[0]["auto"]
    assert auto["ref"] == "successful"
    assert auto["settings"] == auto["ref_settings"]
    assert auto["rel"] < 1e-9


def test_settings_measured_per_process_and_combined(reports):
    """Past the gathered size, each process measures its own probes against its own rows:
    the same settings in every process; the spacing and noise off those of the whole cloud
    at the same probes only by the probes next to a boundary between the parts (the
    medians absorb them), the grid and smoothing the same; the domain exact."""
    combined = [report["combined"] for report in reports]
    whole = combined[0].pop("whole")
    assert combined[0] == combined[1]
    ref = whole["settings"]
    assert abs(combined[0]["spacing"] / whole["spacing"] - 1) < 0.01
    assert abs(combined[0]["noise"] / whole["noise"] - 1) < 0.01
    assert combined[0]["grid"] == ref["grid"] and combined[0]["smoothing"] == ref["smoothing"]
    # The box of the offsets chosen (up to the rounding of the unit normals).
    assert np.allclose(combined[0]["domain"], whole["domain"], rtol=1e-14, atol=0)


def test_normals_estimated_across_processes(reports):
    """``jurs.estimate_normals`` of a cloud over 2 processes: split like the points; a
    small cloud's are the one-process estimate exactly; past the gathered size each
    process's own estimate, signed by the gathered probes', points outward."""
    for report in reports:
        assert report["normals"]["split"]
        assert report["normals"]["outward"] > 0.99
    assert reports[0]["normals"]["exact"]


def test_input_errors_across_processes(reports):
    """An input error found in one process is raised in every process, not left to
    hang."""
    kind, message = reports[1]["auto_nan"]
    assert kind == "ValueError" and "process 1, its own part" in message
    kind, message = reports[0]["auto_nan"]
    assert kind == "RuntimeError" and "process [1] failed checking its points" in message
    kind, message = reports[1]["outside"]
    assert kind == "ValueError" and "outside the given domain" in message
    kind, message = reports[0]["outside"]
    assert kind == "RuntimeError" and "process [1] failed" in message


# A cloud read in parts and a result written once, through the launcher: argv the folder.
PARTS_CHILD = textwrap.dedent(
    """
    import json, os, sys
    import jurs.distributed

    jurs.distributed.initialize(initialization_timeout=60)
    import jax, numpy as np
    import jurs
    from jurs._cloud.parts import local_rows

    folder, pid = sys.argv[1], jax.process_index()
    out = dict(processes=jax.process_count(), devices=len(jax.devices()))
    whole = np.load(os.path.join(folder, "whole.npy"))  # to compare against, small

    def error(call):
        try:
            call()
        except Exception as e:
            return [type(e).__name__, str(e)]
        return None

    # Files of 300, 340 and 360 points: process 0 reads one, process 1 two; the global
    # arrays move 200 rows to process 0's devices.
    p, n = jurs.datasets.load_rows(os.path.join(folder, "scan_*.ply"))
    out["read"] = len(p)
    gp, gn = jurs.datasets.global_arrays(p, n)
    rows, mine = local_rows(gp)
    out["files"] = dict(
        shape=list(gp.shape), held=len(rows),
        exact=bool(np.array_equal(mine, whole[rows, :3]))
        and bool(np.array_equal(local_rows(gn)[1], whole[rows, 3:])),
    )
    # One .npy of 1000 rows: the rows each reads are its devices' rows, nothing moves.
    q, m = jurs.datasets.load_rows(os.path.join(folder, "cloud.npy"))
    gq, gm = jurs.datasets.global_arrays(q, m)
    rows, mine = local_rows(gq)
    out["npy"] = dict(read=len(q), shape=list(gq.shape), first=int(rows[0]),
                      same=bool(np.array_equal(mine, q) and np.array_equal(local_rows(gm)[1], m)))
    # Of 1002 rows: 501 read by each, 2 left over on 4 devices; dropped, one row moves.
    q, m = jurs.datasets.load_rows(os.path.join(folder, "whole.npy"))
    out["odd_error"] = error(lambda: jurs.datasets.global_arrays(q, m))
    gq, _ = jurs.datasets.global_arrays(q, m, drop_remainder=True)
    rows, mine = local_rows(gq)
    out["odd"] = dict(read=len(q), shape=list(gq.shape),
                      exact=bool(np.array_equal(mine, whole[rows, :3])))

    sol = jurs.fit(gp, gn, grid=(8, 8, 8), offset=0.05, eps=0.05,
                   domain=((-1.3,) * 3, (1.3,) * 3), solver=jurs.LeastSquares(lam=1e-4))
    out["status"] = sol.status
    target = os.path.join(folder, "out")
    jurs.distributed.write_once(os.path.join(target, "fit.npz"),
                                lambda f: jurs.save_spline(f, sol.spline))
    jurs.distributed.write_once(
        os.path.join(target, "surface.ply"),
        lambda f: jurs.datasets.save_mesh(f, *jurs.levelset.mesh(sol.spline, 24)),
    )
    # Every process sees both files there; process 0 may already be writing the next one
    # (a hidden partial file), as nothing holds it back once the last write agreed.
    out["after_write"] = sorted(f for f in os.listdir(target) if not f.startswith("."))

    def broken(f):
        with open(f, "w") as fh:
            fh.write("half")
        raise OSError("disk full")

    out["write_error"] = error(
        lambda: jurs.distributed.write_once(os.path.join(target, "broken.ply"), broken)
    ) or "none"
    with open(os.path.join(folder, f"report_{pid}.json"), "w") as fh:
        json.dump(out, fh)
    jax.distributed.shutdown()
    """
)


def test_read_in_parts_fit_and_write_once(tmp_path):
    """``python -m jurs.distributed --processes 2`` (2 CPU devices each) runs a script that
    reads a cloud in parts (files of unequal sizes, and rows of one ``.npy``), makes the
    global arrays (the rows read where they are the devices' split, else rows exchanged
    to it; a remainder refused, then dropped),
    fits, and writes the spline and the surface's mesh once: exactly one whole copy of
    each in the folder, no partial file, and a failed write raised in both processes."""
    import jurs

    p, n = jurs.datasets.sphere3d(1002)
    whole = np.concatenate([p, n], axis=1)
    np.save(tmp_path / "whole.npy", whole)
    np.save(tmp_path / "cloud.npy", whole[:1000])
    for i, (a, b) in enumerate([(0, 300), (300, 640), (640, 1000)]):
        jurs.datasets.save_points(tmp_path / f"scan_{i:03d}.ply", p[a:b], n[a:b])
    (tmp_path / "out").mkdir()
    script = tmp_path / "child.py"
    script.write_text(PARTS_CHILD)
    root = os.path.dirname(os.path.dirname(os.path.abspath(jurs.__file__)))
    env = dict(
        os.environ,
        JAX_ENABLE_X64="1",
        JAX_PLATFORMS="cpu",
        PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])),
    )
    command = [sys.executable, "-m", "jurs.distributed", "--processes", "2", "--cpu-devices", "2"]
    run = subprocess.run(
        [*command, str(script), str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=TIMEOUT,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    reports = [json.loads((tmp_path / f"report_{i}.json").read_text()) for i in range(2)]
    for pid, report in enumerate(reports):
        assert report["processes"] == 2 and report["devices"] == 4
        assert report["read"] == (300, 700)[pid]
        assert report["files"] == dict(shape=[1000, 3], held=500, exact=True)
        assert report["npy"] == dict(read=500, shape=[1000, 3], first=500 * pid, same=True)
        kind, message = report["odd_error"]
        assert kind == "ValueError" and "2 are left over" in message
        assert report["odd"] == dict(read=501, shape=[1000, 3], exact=True)
        assert report["status"] == "successful"
        assert report["after_write"] == ["fit.npz", "surface.ply"]
    assert reports[0]["write_error"] == ["OSError", "disk full"]
    kind, message = reports[1]["write_error"]
    assert kind == "RuntimeError" and "process [0] failed writing" in message
    assert sorted(os.listdir(tmp_path / "out")) == ["fit.npz", "surface.ply"]
    vertices, faces = jurs.datasets.load_mesh(tmp_path / "out" / "surface.ply")
    radius = np.linalg.norm(vertices, axis=1)
    assert len(faces) > 100 and np.abs(radius - 1).max() < 0.05
    spline = jurs.load_spline(tmp_path / "out" / "fit.npz")
    assert spline.control.shape == (8, 8, 8)


def test_adaptive_fit_over_two_processes_equals_one_process_fit(reports):
    """An adaptive fit over 2 processes x 2 devices builds the one-process hierarchy (the
    same active functions a level, from the union of the processes' refinements) and
    agrees with the one-process fit: a curve (``jurs.fit(basis="adaptive")``, the direct
    solve of the processes' summed normal equations) to rounding, a surface
    (``jurs.fit_adaptive``, CG over the 4 devices) to CG's tolerance."""
    cases = (("adaptive_curve", "direct", 1e-9), ("adaptive_sphere", "cg", 1e-7))
    for name, method, bound in cases:
        for report in reports:
            entry = report[name]
            assert entry["status"] == "successful" and entry["method"] == method
            assert entry["devices"] == 4 and entry["processes"] == 2
        ref = reports[0][name]
        assert ref["ref"] == "successful" and ref["same_settings"]
        assert ref["active"] == ref["ref_active"]
        assert ref["rel"] < bound
    for report in reports:  # the compiled programs' collectives: reductions only
        assert report["adaptive_cg_collectives"] == ["all-reduce"]
        assert report["adaptive_direct_collectives"] == ["all-reduce"]
