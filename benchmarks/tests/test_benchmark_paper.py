"""Smoke test: ``python -m benchmarks.paper --quick``, run in the repository root, writes its
report, data and figures."""

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.slow
def test_paper_quick_writes_its_files(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.paper", "--quick", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]

    markdown = (tmp_path / "paper_quick.md").read_text()
    for heading in ("## Table 1", "## Table 2", "## Table 3", "## Table 4"):
        assert heading in markdown
    assert "QUICK" in markdown

    data = json.loads((tmp_path / "paper_quick.json").read_text())
    assert data["quick"] is True
    for table in ("table1", "table2", "table3", "table4"):
        assert data[table]["rows"], table
        for name in data[table]["figures"]:
            png = tmp_path / "paper_quick" / name
            assert png.stat().st_size > 10_000, name
            assert f"paper_quick/{name}" in markdown
    # The paper's lambda, as printed, diverges in eq. 33 and the report says so.
    literal = [r for r in data["table4"]["rows"] if "literal" in r["method"]]
    assert literal and all(r["result"] == "nonfinite" for r in literal)
    # With vs without regularisation: the pair is there, with eta computed.
    with_rows = [r for r in data["table2"]["rows"] if r["regularisation"] == "with"]
    assert with_rows and all("eta_E_ave" in r for r in with_rows)
    # The committed results are never overwritten by a quick run.
    assert not (tmp_path / "paper.md").exists()
