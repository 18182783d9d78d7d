"""The speed benchmarks' renderers turn results JSON into tables with the right ratios,
re-render a saved run beside its JSON, and the GPU benchmark refuses a CPU-only JAX."""

import json
import os

import pytest

from .. import gpu_speed, speed
from ._tables import row_cells as _cells

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")


def test_port_table_shows_the_ratio_to_jurs():
    port = {"build_s": 0.5, "step_warm_s": 0.08, "peak_over_base_b": 2**30}
    row = {
        "m": 1000,
        "grid": 16,
        "dense_b": 3 * 1000 * 256 * 8,
        "port": port,
        "jurs_iurs_step_s": 0.002,
        "ratio": 40.0,
    }
    cells = _cells(speed._port_table([row]), "1e+03")
    assert cells[1] == "16x16"
    assert cells[4:7] == ["80 ms", "2 ms", "40x"]
    assert cells[7] == "1.00 GiB"


def _fit(warm_s, chamfer, grid=64):
    return {
        "grid": [grid, grid],
        "offset": 0.01,
        "warm_s": warm_s,
        "first_s": 10 * warm_s,
        "refined_chamfer": chamfer,
        "refined_hausdorff": 4 * chamfer,
        "chamfer": 1.5e-3,
        "num_components": 1,
        "num_supplementary": 0,
    }


def test_rbf_table_divides_the_rbf_time_by_jurs():
    row = {
        "m": 2000,
        "grid": 48,
        "jurs_main": _fit(0.05, 1e-4),
        "jurs_coarse": _fit(0.01, 3e-4, grid=48),
        "rbf": {**_fit(1.0, 2e-4), "fit_s": 5.0},
    }
    lines = speed._rbf_table([row])
    cells = _cells(lines, "2000")
    assert cells[6] == "100x / 10x"  # warm: 5 / 0.05; first call: 5 / 0.5
    assert cells[7] == "1.00e-04 / 2.00e-04"
    assert cells[11].endswith("(500x)")  # the coarse grid: 5 / 0.01
    skipped = {"m": 5000, "grid": 64, "skipped": "RBF fit predicted to take 300 s"}
    assert "skipped" in _cells(speed._rbf_table([skipped]), "5000")[1]


def test_gpu_tables_divide_the_cpu_time_by_the_gpu_time():
    step = {
        "step_warm_s": 0.004,
        "step_min_s": 0.003,
        "step_compile_s": 1.0,
        "build_s": 2.0,
        "device_peak_b": 2**30,
    }
    gpu = [{"m": 1_000_000, "grid": 128, "iurs": step}]
    cpu = [{"m": 1_000_000, "grid": 128, "iurs": {"step_warm_s": 0.1}}]
    cells = _cells(gpu_speed._step_tables(gpu, cpu), "1e+06")
    assert cells[-2:] == ["100 ms", "25x"]
    # No CPU measurement of the configuration: no ratio.
    cells = _cells(gpu_speed._step_tables(gpu, []), "1e+06")
    assert cells[-2:] == ["—", "—"]


def test_an_error_fills_the_row():
    row = {"m": 100, "grid": 8, "port": {"error": "exit 1: out of memory"}, "dense_b": 0}
    row.update(jurs_iurs_step_s=None, ratio=None)
    cells = _cells(speed._port_table([row]), "1e+02")
    assert cells[3] == "error: exit 1: out of memory"


@pytest.mark.parametrize("name", ["speed", "speed_gpu"])
def test_a_saved_run_rerenders_beside_its_json(name, tmp_path):
    """The committed results are readable by the renderers; a copy re-renders where it lies
    (the committed files untouched), older runs' target verdicts dropped."""
    with open(os.path.join(RESULTS, f"{name}.json")) as fh:
        data = json.load(fh)
    data["targets"] = [{"verdict": "PASS"}]
    copy = tmp_path / "copy.json"
    copy.write_text(json.dumps(data))
    committed = os.path.join(RESULTS, f"{name}.md")
    before = os.stat(committed).st_mtime_ns
    if name == "speed":
        speed.rerender(str(copy))
        assert "targets" not in json.loads(copy.read_text())
    else:
        gpu_speed.main(["--from-json", str(copy)])
    text = (tmp_path / "copy.md").read_text()
    assert text.startswith("# Speed")
    assert "## IURS (tau=1e-2, lam=1e-3): one step" in text
    assert os.stat(committed).st_mtime_ns == before


def test_gpu_speed_refuses_a_cpu_only_jax():
    with pytest.raises(SystemExit) as excinfo:
        gpu_speed.main([])
    assert excinfo.value.code == 2
