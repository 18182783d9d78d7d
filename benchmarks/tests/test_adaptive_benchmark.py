"""The adaptive benchmark's scaling ladder: a child process stopped at its bound reports the
bound, and the scaling table turns rows into ratios per doubling against the target."""

import time

from .. import adaptive
from .._common import in_child
from ._tables import row_cells as _cells


def test_a_child_past_its_time_bound_is_stopped_and_says_so():
    start = time.perf_counter()
    out = in_child(time.sleep, 60, timeout_s=1.0, poll_s=0.1)
    assert time.perf_counter() - start < 30
    assert out["bound"]["kind"] == "time"
    assert out["bound"]["elapsed_s"] > 1.0
    assert "over the 1 s bound" in out["error"]


def test_a_child_returns_its_value_or_its_error():
    assert in_child(sum, [1, 2, 3], timeout_s=60) == 6
    assert in_child(int, "x")["error"].startswith("ValueError")


def _row(finest, active, warm_s, peak_gb, base_gb=0.5):
    return {
        "finest": finest,
        "cells": [finest, finest],
        "levels": 3,
        "active": active,
        "uniform_functions": (finest + 3) ** 2,
        "cg_steps": 0,
        "first_s": 2 * warm_s,
        "warm_s": warm_s,
        "base_rss": base_gb * adaptive.GB,
        "peak_rss": peak_gb * adaptive.GB,
    }


def test_the_scaling_table_gives_ratios_per_doubling_and_counts_the_target():
    rows = [
        _row(256, 1000, 1.0, 1.5),
        _row(512, 2000, 3.0, 2.5),
        {"finest": 1024, "error": "stopped at 361 s, 3.00 GB resident: over the 360 s bound"},
        {"finest": 2048, "skipped": "not run: the 1024 row failed"},
    ]
    payload = {"scaling_case": "camera", "timeout_s": 360.0, "max_gb": 12.0}
    lines = adaptive.scaling_table(rows, 2, payload)
    cells = _cells(lines, "512")
    # active x, time x, memory x (of the peak above the base: 2.0 / 1.0)
    assert cells[-3:] == ["2.00", "3.00", "2.00"]
    assert _cells(lines, "1024")[1].startswith("stopped at 361 s")
    assert _cells(lines, "2048")[1] == "not run: the 1024 row failed"
    summary = lines[-1]
    assert "(1/1 at most 2.2x)" in summary and "(0/1 at most 2.2x)" in summary


def test_a_row_without_a_warm_call_is_timed_by_its_first():
    first = {**_row(64, 100, 1.0, 1.0), "cg_steps": 10}
    second = {**_row(128, 400, 0.0, 2.0), "warm_s": None, "first_s": 8.0}
    lines = adaptive.scaling_table(
        [first, second],
        3,
        {"surface_origin": "a sphere", "surface_points": 100, "timeout_s": 10, "max_gb": 1},
    )
    cells = _cells(lines, "128")
    assert cells[7] == "8.000 (first call)"
    assert cells[-2] == "8.00"


def test_the_time_without_checks_gets_its_own_ratio():
    rows = [
        {**_row(256, 1000, 1.0, 1.5), "unchecked_s": 0.5},
        {**_row(512, 2000, 3.0, 2.5), "unchecked_s": 1.0},
    ]
    payload = {"scaling_case": "camera", "timeout_s": 360.0, "max_gb": 12.0}
    lines = adaptive.scaling_table(rows, 2, payload)
    cells = _cells(lines, "512")
    assert cells[8] == "1.000"
    # active x, time x, no checks x, memory x
    assert cells[-4:] == ["2.00", "3.00", "2.00", "2.00"]
    assert "time without checks by 2.00-2.00x (1/1 at most 2.2x)." in lines[-1]
    assert lines[-1].endswith(
        "Over the 1 doublings of the ladder: 2.00x a doubling in active functions, 3.00x in "
        "warm time, 2.00x without checks."
    )
