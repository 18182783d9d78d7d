"""The committed speed reports are what their scripts print from the committed JSON, and
the GPU benchmark refuses a CPU-only JAX."""

import json
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

import gpu_speed  # noqa: E402
import speed  # noqa: E402


def _load(name):
    with open(os.path.join(RESULTS, name)) as fh:
        return fh.read()


def test_speed_md_is_rendered_from_speed_json():
    data = json.loads(_load("speed.json"))
    data["bounds"] = speed.arithmetic_bounds(data["sweep"], data["example4"], data.get("ceiling"))
    data["targets"] = speed.evaluate_targets(
        data["sweep"],
        data["rbf"],
        data["example4"],
        data["bounds"],
        data.get("tuned"),
        data.get("fit_steps"),
    )
    assert speed.report(data) == _load("speed.md")


def test_speed_gpu_md_is_rendered_from_its_json_and_the_cpu_run():
    """speed_gpu.md's CPU columns come from speed.json: a CPU re-run without re-rendering
    the GPU report fails here."""
    data = json.loads(_load("speed_gpu.json"))
    assert data["device"].startswith("gpu:")
    assert gpu_speed.report(data) == _load("speed_gpu.md")


def test_gpu_speed_refuses_a_cpu_only_jax():
    with pytest.raises(SystemExit) as excinfo:
        gpu_speed.main([])
    assert excinfo.value.code == 2


def test_speed_rerender_writes_beside_its_json(tmp_path, capsys):
    copy = tmp_path / "copy.json"
    copy.write_text(_load("speed.json"))
    committed = os.path.join(RESULTS, "speed.md")
    before = os.stat(committed).st_mtime_ns
    speed.rerender(str(copy))
    assert (tmp_path / "copy.md").read_text() == _load("speed.md")
    assert os.stat(committed).st_mtime_ns == before
