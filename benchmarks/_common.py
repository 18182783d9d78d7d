"""Shared helpers for the benchmark scripts: timing, machine description, result files."""

from __future__ import annotations

import json
import os
import platform
import time

import jax
import numpy as np

RESULTS = os.path.join(os.path.dirname(__file__), "results")


def machine() -> str:
    device = jax.devices()[0]
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"JAX {jax.__version__} on {device.platform}:{device.device_kind}")


def time_call(fn, *args, repeats: int = 20):
    """``(first_call_s, median_warm_s, output)``; the first call includes compilation."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return first, float(np.median(times)), out


def write_results(name: str, payload: dict, markdown: str, folder: str = RESULTS) -> None:
    """``<folder>/<name>.json`` and ``<folder>/<name>.md`` (default: benchmarks/results)."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, f"{name}.json"), "w") as fh:
        json.dump(payload, fh, indent=2)
    with open(os.path.join(folder, f"{name}.md"), "w") as fh:
        fh.write(markdown)
