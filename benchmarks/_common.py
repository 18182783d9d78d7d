"""Shared helpers for the benchmark scripts: timing, machine description, result files and
the markdown tables of the reports. Imports no JAX at module level (``time_repeated`` and
``machine`` import it when called)."""

from __future__ import annotations

import importlib
import json
import multiprocessing
import os
import platform
import resource
import sys
import time
from typing import Any

import numpy as np

RESULTS = os.path.join(os.path.dirname(__file__), "results")
#: A first call slower than this gets a single warm repeat (LeastSquares at 256 x 256).
LONG_CALL_S = 20.0


def import_open3d() -> Any:
    """``open3d``, the benchmarks' reference (an optional extra). Its wheel links the
    system's ``libusb-1.0``; where the system lacks it, the copy in the ``libusb-package``
    wheel (in the ``bench`` extra) is loaded first. ImportError when Open3D is missing."""
    import ctypes
    import ctypes.util

    if ctypes.util.find_library("usb-1.0") is None:
        try:
            import libusb_package  # pyright: ignore[reportMissingImports]
        except ImportError:
            pass
        else:
            ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
    import open3d  # pyright: ignore[reportMissingImports]

    return open3d


def optional(name):
    """The module ``name`` (``open3d`` through ``import_open3d``), or None when it
    cannot be imported."""
    try:
        return import_open3d() if name == "open3d" else importlib.import_module(name)
    except Exception:  # noqa: BLE001 - any import failure means "not available"
        return None


def machine() -> str:
    import jax  # here, not at import: the speed report re-renders without JAX

    device = jax.devices()[0]
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"JAX {jax.__version__} on {device.platform}:{device.device_kind}"
    )


def time_repeated(fn, *args, budget_s: float = 2.0, max_repeats: int = 20) -> dict:
    """Time ``fn(*args)``: one first call (compiling, if ``fn`` is jitted), then warm calls
    until ``budget_s`` is spent, at least 3 and at most ``max_repeats``, fewer when a call
    is slow (2 after a first call above ``budget_s``, 1 after one above ``LONG_CALL_S``)
    so that slow configurations do not take minutes each.

    Returns ``{"first_s", "warm_s" (median), "min_s", "compile_s" (first - warm, >= 0),
    "repeats", "output"}``; the minimum shows the uncontended speed on a shared machine.
    """
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    min_repeats = 1 if first > LONG_CALL_S else 2 if first > budget_s else 3
    times = []
    while len(times) < max_repeats and (len(times) < min_repeats or sum(times) < budget_s):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    warm = float(np.median(times))
    return {
        "first_s": first,
        "warm_s": warm,
        "min_s": min(times),
        "compile_s": max(first - warm, 0.0),
        "repeats": len(times),
        "output": out,
    }


def _status_bytes(field: str, pid: int | str = "self") -> int:
    """``field`` (``VmHWM``, ``VmRSS``) of ``/proc/<pid>/status`` in bytes; 0 where there is
    no such file (off Linux, or the process is gone)."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith(f"{field}:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def peak_rss_bytes() -> int:
    """Peak resident set of this process: ``VmHWM``, which ``exec`` resets. ``ru_maxrss``
    is the fallback off Linux, but on Linux a spawned child inherits its parent's resident
    set at the fork into it, so there it would count the parent's memory too."""
    peak = _status_bytes("VmHWM")
    if peak:
        return peak
    scale = 1 if sys.platform == "darwin" else 1024  # bytes on macOS, KiB elsewhere
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def current_rss_bytes() -> int:
    """Resident set of this process now (0 off Linux)."""
    return _status_bytes("VmRSS")


def _child_main(conn, fn, args) -> None:
    try:
        message = ("ok", fn(*args))
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which goes on
        message = ("error", f"{type(exc).__name__}: {exc}")
    conn.send(message)
    conn.close()


def in_child(
    fn,
    *args,
    timeout_s: float | None = None,
    max_rss_bytes: float | None = None,
    poll_s: float = 0.5,
) -> Any:
    """``fn(*args)`` in a fresh spawned process (own peak memory, own JAX); ``fn`` must be
    importable (a module-level function) and its result picklable.

    An exception or a killed child comes back as ``{"error": ...}``. With ``timeout_s``
    (wall seconds from the child's start, its imports included) or ``max_rss_bytes`` (its
    resident set, read every ``poll_s`` seconds, so a spike shorter than that can pass
    unseen) the parent kills a child that passes either; the answer is then
    ``{"error": ..., "bound": {"kind": "time" | "memory", "limit", "elapsed_s",
    "rss_bytes"}}``, ``rss_bytes`` the largest resident set read (a lower bound of the
    child's peak).
    """
    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    child = context.Process(target=_child_main, args=(send, fn, args))
    start = time.perf_counter()
    child.start()
    send.close()  # the child holds the other end: its exit reads as end of file here
    largest = 0
    try:
        while not receive.poll(poll_s):
            elapsed = time.perf_counter() - start
            largest = max(largest, _status_bytes("VmRSS", child.pid or 0))
            bound = None
            if timeout_s is not None and elapsed > timeout_s:
                bound = ("time", float(timeout_s), f"{timeout_s:.0f} s")
            elif max_rss_bytes is not None and largest > max_rss_bytes:
                bound = ("memory", float(max_rss_bytes), f"{max_rss_bytes / 1e9:.1f} GB")
            if bound is not None:
                child.kill()
                kind, limit, text = bound
                return {
                    "error": f"stopped at {elapsed:.0f} s, {largest / 1e9:.2f} GB resident: "
                    f"over the {text} bound",
                    "bound": {
                        "kind": kind,
                        "limit": limit,
                        "elapsed_s": elapsed,
                        "rss_bytes": largest,
                    },
                }
        try:
            status, value = receive.recv()
        except EOFError:
            child.join()
            return {"error": f"the child process exited with code {child.exitcode}"}
        return {"error": value} if status == "error" else value
    finally:
        if child.is_alive():
            child.join(timeout=10)
            if child.is_alive():
                child.kill()
        child.join()
        receive.close()


def write_results(name: str, payload: dict, markdown: str, folder: str = RESULTS) -> None:
    """``<folder>/<name>.json`` and ``<folder>/<name>.md`` (default: benchmarks/results)."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, f"{name}.json"), "w") as fh:
        json.dump(payload, fh, indent=2)
    with open(os.path.join(folder, f"{name}.md"), "w") as fh:
        fh.write(markdown)


def rerender_beside(path: str, render) -> str:
    """Re-render a saved results JSON without measuring: ``render(data)`` returns the
    markdown (and may recompute parts of ``data``); ``<name>.{json,md}`` are rewritten
    beside ``path``, ``<name>`` being the JSON file's name, so a copy re-renders where it
    lies and committed results only from their own JSON. Returns the markdown."""
    with open(path) as fh:
        data = json.load(fh)
    text = render(data)
    path = os.path.abspath(path)
    write_results(os.path.splitext(os.path.basename(path))[0], data, text, os.path.dirname(path))
    return text


def elapsed_log():
    """A ``log(msg)`` that prints to stderr with the seconds since this call."""
    start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - start:7.1f} s] {msg}", file=sys.stderr, flush=True)

    return log


# --------------------------------------------------------------------------- markdown tables
# Cell formatters and table helpers of the speed reports (speed.py, gpu_speed.py).


def find_row(rows, **keys):
    """The first of ``rows`` (dicts) whose entries equal ``keys``; None if none does."""
    for r in rows:
        if all(r.get(k) == v for k, v in keys.items()):
            return r
    return None


def ms_text(s):
    """Seconds as ms below one second (3 significant digits)."""
    return "—" if s is None else (f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s")


def range_text(runs) -> str:
    """``low-high`` of a list of per-process times."""
    return f"{s_text(min(runs))}-{s_text(max(runs))}"


def us_text(s):
    return "—" if s is None else f"{s * 1e6:.3g} us"


def s_text(s):
    return "—" if s is None else f"{s:.3g} s"


def bytes_text(b):
    if b is None:
        return "—"
    return f"{b / 2**30:.2f} GiB" if abs(b) >= 2**30 else f"{b / 2**20:.0f} MiB"


def ratio_text(ratio):
    """A speed ratio: 2 significant digits, so that 0.61x does not print as 1x."""
    return "—" if ratio is None else f"{ratio:.2g}x" if ratio < 100 else f"{ratio:.0f}x"


def md_table(header, rows):
    """A markdown table: the header line, the rule and one line per row."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def error_text(res):
    """The cell of a failed measurement (``res`` holds ``error``), else None."""
    return f"error: {res['error'][:80]}" if "error" in res else None


def grid_text(grid) -> str:
    """``128`` -> ``128x128``; ``(92, 96)`` -> ``92x96``."""
    return "x".join(map(str, grid)) if isinstance(grid, (list, tuple)) else f"{grid}x{grid}"


def where_cells(r) -> list:
    """The m and grid cells of a sweep row."""
    return [f"{r['m']:.0e}", grid_text(r["grid"])]


def measured_row(cells, res, width: int, values) -> list:
    """``cells``, then ``values()`` (``width`` cells), or ``res``'s error padded to ``width``."""
    return cells + ([error_text(res)] + [""] * (width - 1) if error_text(res) else values())
