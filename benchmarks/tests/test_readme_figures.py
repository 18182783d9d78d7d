"""The README's headline figures are those of the committed results files.

Each figure quoted in the README's "Headline results" table is read from the README, the
cell it comes from is read from ``benchmarks/results/*.md``, and the two must agree to the
README's precision (the cell rounded half up to the README's last digit; counts exactly).
Ranges, medians and counts are computed from the table's cells (one count, which the
table's rounded ratios only bound, also from the JSON the table is rendered from), so a
results file re-run with other numbers, or a README figure edited by hand, fails here.
"""

import json
import os
import re
import statistics
from decimal import ROUND_HALF_UP, Decimal

import pytest

BENCHMARKS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(BENCHMARKS)
RESULTS = os.path.join(BENCHMARKS, "results")
HEADLINE = "## Headline results"

#: Seconds per unit of the time cells.
UNITS = {"us": Decimal("1e-6"), "ms": Decimal("1e-3"), "s": Decimal(1)}


# --------------------------------------------------------------------------- reading


def _read(path):
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def _cells(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _is_rule(line):
    return bool(re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", line.strip()))


def headline_section():
    """The README's headline section: its text up to the next heading."""
    text = _read(os.path.join(ROOT, "README.md"))
    start = text.index(HEADLINE)
    end = text.find("\n## ", start + len(HEADLINE))
    return text[start : end if end >= 0 else None]


def readme_row(key):
    """The cells of the headline table's row whose first cell contains ``key``."""
    rows = [
        _cells(line)
        for line in headline_section().splitlines()
        if line.startswith("|") and not _is_rule(line)
    ]
    found = [r for r in rows if key in r[0]]
    assert len(found) == 1, f"{len(found)} headline rows contain {key!r}"
    return found[0]


def quoted(cell, pattern):
    """The groups of ``pattern`` in a README cell (the figures it quotes)."""
    match = re.search(pattern, cell)
    assert match, f"README cell {cell!r} does not match {pattern!r}"
    return match.groups()


class Table:
    """A markdown table of a results file: its header and rows (lists of cells)."""

    def __init__(self, heading, header, rows):
        self.heading, self.header, self.rows = heading, header, rows

    def col(self, name, nth=0):
        """Index of the ``nth`` column called ``name``."""
        indices = [i for i, h in enumerate(self.header) if h == name]
        assert len(indices) > nth, f"no column {name!r} in {self.header}"
        return indices[nth]

    def column(self, name, rows=None, nth=0):
        i = self.col(name, nth)
        return [r[i] for r in (self.rows if rows is None else rows)]

    def where(self, **cells):
        """Rows whose cells equal ``cells`` (column name -> text; a callable tests it)."""
        out = []
        for r in self.rows:
            ok = True
            for name, want in cells.items():
                have = r[self.col(name)]
                ok &= want(have) if callable(want) else have == want
            if ok:
                out.append(r)
        assert out, f"no row {cells} in table {self.heading!r}"
        return out

    def cell(self, name, nth=0, **cells):
        rows = self.where(**cells)
        assert len(rows) == 1, f"{len(rows)} rows {cells} in table {self.heading!r}"
        return rows[0][self.col(name, nth)]


def results_text(name):
    return _read(os.path.join(RESULTS, f"{name}.md"))


def table(name, heading, having=None):
    """The table of ``benchmarks/results/<name>.md`` under the heading that starts with
    ``heading`` (``## ...``); ``having``: the one with a column of that name."""
    lines = results_text(name).splitlines()
    current, found = None, []
    for i, line in enumerate(lines):
        if line.startswith("## "):
            current = line[3:]
        if (
            current is not None
            and current.startswith(heading)
            and line.startswith("|")
            and i + 1 < len(lines)
            and _is_rule(lines[i + 1])
        ):
            header = _cells(line)
            rows = []
            for row in lines[i + 2 :]:
                if not row.startswith("|"):
                    break
                rows.append(_cells(row))
            if having is None or having in header:
                found.append(Table(current, header, rows))
    assert len(found) == 1, f"{len(found)} tables under {heading!r} in {name}.md"
    return found[0]


def date_of(name):
    """The run's date in a results file's opening lines (``Date: ...`` or ``Run ...``)."""
    return re.search(r"(?:Date:|Run) (\d{4}-\d\d-\d\d)", results_text(name)).group(1)


# --------------------------------------------------------------------------- comparing


def number(text):
    """The first number in ``text``, as a Decimal."""
    return Decimal(re.search(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", text).group(0))


def seconds(text):
    """The first time in a cell (``"25.4 ms (23 ms)"`` -> 0.0254), as Decimal seconds."""
    value, unit = re.search(r"(\d+(?:\.\d+)?) (us|ms|s)\b", text).groups()
    return Decimal(value) * UNITS[unit]


def rounds_to(figure, value):
    """Whether ``value`` rounded half up to the last digit of ``figure`` (text) is it."""
    figure = Decimal(figure)
    return Decimal(value).quantize(figure, rounding=ROUND_HALF_UP) == figure


def assert_figure(figure, value, what):
    assert rounds_to(figure, value), f"README says {figure} for {what}; results give {value}"


def assert_time(figure, unit, value_s, what):
    """A README time ``figure`` ``unit`` against ``value_s`` seconds from a results cell."""
    assert_figure(figure, Decimal(value_s) / UNITS[unit], f"{what} (in {unit})")


def percent(text):
    """``"0.2 %"`` -> Decimal("0.2")."""
    return number(text)


# --------------------------------------------------------------------------- the figures


def test_the_intro_names_the_speed_run():
    """'Measured on a 2-core x86_64 CPU in float64 (and one H100 GPU where marked), <date>'
    is the speed run's machine, date and GPU (the date of the rows that name none)."""
    cores, arch, gpu, date = quoted(
        headline_section(),
        r"Measured on a (\d+)-core (\S+) CPU in float64 \(and one (\w+) GPU where marked\), "
        r"(\d{4}-\d\d-\d\d)",
    )
    assert f"Machine: {arch}, {cores} cores" in results_text("speed")
    assert date == date_of("speed")
    assert gpu in re.search(
        r"Device of the measurements: \*\*(.*?)\*\*", results_text("speed_gpu")
    ).group(1)


def test_quality_row():
    task, jurs, other = readme_row("`jurs.fit(points, normals)` defaults")
    per_case = table("quality", "Per case")
    rows = per_case.rows

    shapes, noise_lo, noise_hi, m_lo, m_hi, date = quoted(
        task, r"(\d+) shapes x noise (\S+)-(\S+) % \((\d+)-(\d+) points; (\d{4}-\d\d-\d\d)\)"
    )
    assert int(shapes) == len(set(per_case.column("case")))
    noise = [percent(c) for c in per_case.column("noise")]
    assert (Decimal(noise_lo), Decimal(noise_hi)) == (min(noise), max(noise))
    m = [int(c) for c in per_case.column("m")]
    assert (int(m_lo), int(m_hi)) == (min(m), max(m))
    assert date == date_of("quality")

    clean, runs, warm_lo, warm_hi, warm_median = quoted(
        jurs, r"clean zero set in (\d+)/(\d+) runs; (\d+)-(\d+) ms warm \(median (\d+)\)"
    )
    assert int(runs) == len(rows)
    no_extra = per_case.where(supp="0", tiny="0")  # no supplementary component, no tiny loop
    assert int(clean) == len(no_extra)
    # Runs whose fit raised (their row says "error: ...") have no times or ratios.
    fitted = [r for r in rows if not r[3].startswith("error")]
    warm = [seconds(c) for c in per_case.column("jurs time", fitted)]  # "91 ms (5.7 s)": warm first
    assert_time(warm_lo, "ms", min(warm), "the fastest warm fit")
    assert_time(warm_hi, "ms", max(warm), "the slowest warm fit")
    assert_time(warm_median, "ms", statistics.median(warm), "the median warm fit")

    rbf_lo, rbf_hi, no_worse, runs_c = quoted(
        other,
        r"SciPy thin-plate RBF: ([\d.]+)-([\d.]+) s; jurs's Chamfer distance no worse in "
        r"(\d+)/(\d+)",
    )
    rbf = [seconds(c) for c in per_case.column("RBF time", fitted)]
    assert_time(rbf_lo, "s", min(rbf), "the fastest RBF fit")
    assert_time(rbf_hi, "s", max(rbf), "the slowest RBF fit")
    # The C ratio (jurs's Chamfer over the reference RBF's) has two decimals: a cell of 1.00
    # may be either side of 1, so the table bounds the count, and the JSON beside it, which
    # the table is rendered from, gives it.
    ratios = [Decimal(c) for c in per_case.column("C ratio", fitted)]
    assert int(runs_c) == len(ratios)
    assert sum(r < 1 for r in ratios) <= int(no_worse) <= sum(r <= 1 for r in ratios)
    runs_json = json.loads(_read(os.path.join(RESULTS, "quality.json")))["runs"]
    assert int(no_worse) == sum(r["chamfer_ratio"] <= 1 for r in runs_json if "error" not in r)


def test_realdata_row():
    task, jurs, other = readme_row("outlines traced")
    targets = table("realdata_default", "Targets")
    text = results_text("realdata_default")

    outlines, outliers, date = quoted(
        task, r"defaults on (\d+) outlines .*? ([\d.]+) % outliers \((\d{4}-\d\d-\d\d)\)"
    )
    assert int(outlines) == int(targets.cell("runs", variant="clean"))
    share = re.search(r"\*outlier\*: ([\d.]+) % of the points", text).group(1)
    assert Decimal(outliers) == Decimal(share)
    assert date == date_of("realdata_default")

    matched, runs, clean_tol, other_tol, within, runs_h = quoted(
        jurs,
        r"every ring matched in (\d+)/(\d+) runs; Hausdorff within ([\d.]+) % \(clean\) or "
        r"([\d.]+) % of the diagonal in (\d+)/(\d+)",
    )
    runs_all = int(targets.cell("runs", variant="all"))
    assert int(runs) == int(runs_h) == runs_all
    topology = targets.cell("exact topology: jurs (RBF)", variant="all")  # "32 (26)"
    hausdorff = targets.cell("Hausdorff target: jurs (RBF)", variant="all")
    assert int(matched) == int(number(topology))
    assert int(within) == int(number(hausdorff))
    tol = re.search(
        r"Hausdorff target: <= ([\d.]+) % of diag on clean data, <= ([\d.]+) % on the other", text
    )
    assert (Decimal(clean_tol), Decimal(other_tol)) == tuple(map(Decimal, tol.groups()))

    rbf_matched, runs_r, no_worse, runs_c = quoted(
        other, r"rings matched in (\d+)/(\d+); jurs's Chamfer no worse in (\d+)/(\d+)"
    )
    assert int(runs_r) == int(runs_c) == runs_all
    assert int(rbf_matched) == int(re.search(r"\((\d+)\)", topology).group(1))
    assert int(no_worse) == int(targets.cell("Chamfer <= RBF's", variant="all"))
    if "every miss flagged" in jurs:
        verdicts = table("realdata_default", "Misses", having="count")
        for row in ("topology not exact", "Hausdorff over its target"):
            flagged = verdicts.cell("flagged by the fit (status not successful)", runs=row)
            assert int(flagged) == int(verdicts.cell("count", runs=row))


def test_example4_row():
    task, jurs, other = readme_row("Example 4")
    ex4 = table("speed", "Full regularised IURS fits", having="warm (fastest)")
    paper_example4 = lambda fit: fit.startswith("paper's Example 4")  # noqa: E731
    (steps,) = quoted(task, r"(\d+) IURS steps")
    assert int(steps) == int(ex4.cell("steps", fit=paper_example4))
    warm, unit = quoted(jurs, r"^([\d.]+) (ms|s)\b")
    assert_time(warm, unit, seconds(ex4.cell("warm (fastest)", fit=paper_example4)), "warm fit")

    (paper_s,) = quoted(other, r"the paper's Table 2: ([\d.]+) s")
    table2 = table("paper", "Table 2")
    start = next(i for i, r in enumerate(table2.rows) if r[0].startswith("Example 4 "))
    rows = table2.rows[start : start + 2]  # the example's rows: without, with
    with_reg = [r for r in rows if r[table2.col("regulariser")] == "with"]
    assert len(with_reg) == 1
    ours_paper = with_reg[0][table2.col("time (s)")]  # "ours / paper"
    assert_figure(paper_s, Decimal(ours_paper.split("/")[1].strip()), "the paper's time")


def _where_sweep(text):
    """``1e6 points, 128 x 128`` in a README cell -> the sweep tables' m and grid cells."""
    m, n, k = quoted(text, r"(\d+e\d+) points, (\d+) x (\d+)")
    return f"{float(m):.0e}", f"{n}x{k}", int(float(m)), int(n) * int(k)


def test_iurs_step_in_fit_row():
    task, jurs, other = readme_row("one IURS step")
    m_cell, grid_cell, m, coefficients = _where_sweep(task)
    assert f"The same workers at {m_cell} points, {grid_cell}." in results_text("speed")
    cpu, cpu_unit, gpu, gpu_unit = quoted(jurs, r"^([\d.]+) (ms|s); H100: ([\d.]+) (ms|s)")
    in_fit = table("speed", "Large problems", having="environment")
    cell = in_fit.cell("step (from fastest fits)", environment="as it is")
    assert_time(cpu, cpu_unit, seconds(cell), "the step inside jurs.fit")
    gpu_table = table("speed_gpu", "The IURS step inside jurs.fit")
    cell = gpu_table.cell("step (from fastest fits)", m=m_cell, grid=grid_cell)
    assert_time(gpu, gpu_unit, seconds(cell), "the step inside jurs.fit on the GPU")

    # The dense port's matrix D: 3m rows (samples) x N M columns of float64 (speed.md says
    # how the port builds it, and runs it only where it fits).
    (gigabytes,) = quoted(other, r"dense D needs (\d+) GB")
    assert "dense B (3m x NM)" in results_text("speed")
    assert_figure(gigabytes, Decimal(3 * m * coefficients * 8) / Decimal(10**9), "dense D")


def test_exact_solve_row():
    task, jurs, _ = readme_row("exact regularised solve")
    m_cell, grid_cell, _, _ = _where_sweep(task)
    cpu, cpu_unit, gpu, gpu_unit = quoted(jurs, r"^([\d.]+) (ms|s); H100: ([\d.]+) (ms|s)")
    lstsq = table("speed", "LeastSquares")
    cell = lstsq.cell("warm (min)", m=m_cell, grid=grid_cell)
    assert_time(cpu, cpu_unit, seconds(cell), "the exact solve")
    lstsq_gpu = table("speed_gpu", "LeastSquares")
    cell = lstsq_gpu.cell("warm (min)", m=m_cell, grid=grid_cell)
    assert_time(gpu, gpu_unit, seconds(cell), "the exact solve on the GPU")


def test_normals_row():
    task, jurs, other = readme_row("`jurs.estimate_normals`")
    m, noise, date = quoted(
        task, r"(\d+e\d+) points of a sphere, torus and bunny with ([\d.]+) % noise \((\S+)\)"
    )
    assert date == date_of("normals")
    assert Decimal(noise) == number(
        re.search(r"Noise: Gaussian, ([\d.]+) %", results_text("normals")).group(1)
    )
    surfaces = table("normals", "3D")
    rows = [
        surfaces.where(case=f"{name}/noise", m=str(int(float(m))))[0]
        for name in ("sphere", "torus", "bunny")
    ]

    def outward(name):  # "99.96 / 99.96": strictly outward / up to one flip
        return [number(c) for c in surfaces.column(name, rows)]

    lo, hi, s_lo, s_hi = quoted(
        jurs, r"([\d.]+)-([\d.]+) % of the signs outward, ([\d.]+)-([\d.]+) s"
    )
    signs, times = outward("jurs sign %"), [Decimal(c) for c in surfaces.column("s", rows)]
    assert_figure(lo, min(signs), "jurs's fewest outward signs")
    assert_figure(hi, max(signs), "jurs's most outward signs")
    assert_figure(s_lo, min(times), "jurs's fastest estimation")
    assert_figure(s_hi, max(times), "jurs's slowest estimation")

    lo, hi, s_lo, s_hi = quoted(
        other, r"Open3D \(PCA \+ spanning tree\): ([\d.]+)-([\d.]+) %, ([\d.]+)-([\d.]+) s"
    )
    signs = outward("Open3D sign %")
    times = [Decimal(c) for c in surfaces.column("s", rows, nth=2)]  # jurs, mst, Open3D
    assert_figure(lo, min(signs), "Open3D's fewest outward signs")
    assert_figure(hi, max(signs), "Open3D's most outward signs")
    assert_figure(s_lo, min(times), "Open3D's fastest estimation")
    assert_figure(s_hi, max(times), "Open3D's slowest estimation")


SMOOTH = ("sphere", "torus", "genus2")  # analytic surfaces
SCANNED = ("bunny", "airplane")  # "the bunny and the airplane"


def test_surfaces_row():
    """The default fit at 1e5 points against Poisson's best depth (surfaces_default.md)."""
    task, jurs, other = readme_row("surfaces,")
    name = "surfaces_default"
    ratios = table(name, "jurs / Poisson")
    accuracy = table(name, "Accuracy")
    cost = table(name, "Cost")

    m, shapes, date = quoted(
        task, r"surfaces, (\d+e\d+) points, (\d+) shapes, clean and 0.5 % noise, defaults \((\S+)\)"
    )
    assert date == date_of(name)
    cases = {c.split("/")[0] for c in ratios.column("case")}
    assert int(shapes) == len(cases) and cases == set(SMOOTH + SCANNED)
    assert set(ratios.column("m")) == {str(int(float(m)))}
    assert "Noise: Gaussian, 0.5 % of the bounding-box diagonal" in results_text(name)

    assert "one component on every cloud, no bubbles" in jurs
    for row in accuracy.where(method="jurs"):
        assert row[accuracy.col("components (bubbles)")] == "1 (0)", row

    lo, hi, h_lo, h_hi, below, clouds, hierarchy = quoted(
        jurs,
        r"Chamfer ([\d.]+)-([\d.]+)x and Hausdorff ([\d.]+)-([\d.]+)x Poisson's best depth, "
        r"both below it on (\d+) of (\d+) clouds; the hierarchy on (\d+)",
    )
    chamfer = [Decimal(c) for c in ratios.column("Chamfer")]
    hausdorff = [Decimal(c) for c in ratios.column("Hausdorff")]
    assert_figure(lo, min(chamfer), "the smallest Chamfer ratio")
    assert_figure(hi, max(chamfer), "the largest Chamfer ratio")
    assert_figure(h_lo, min(hausdorff), "the smallest Hausdorff ratio")
    assert_figure(h_hi, max(hausdorff), "the largest Hausdorff ratio")
    assert int(clouds) == len(chamfer)
    assert int(below) == sum(c <= 1 and h <= 1 for c, h in zip(chamfer, hausdorff))
    settings = cost.column("setting", cost.where(method="jurs"))
    assert int(hierarchy) == sum(s.startswith("finest") for s in settings)

    depths, slow_lo, slow_hi = quoted(
        other,
        r"Poisson \(best of depths ([\d, ]+)\): ([\d.]+)-([\d.]+)x faster, fit and mesh",
    )
    assert "Poisson at each depth" in results_text(name)
    tried = table(name, "Poisson at each depth").column("depth")
    assert {d.strip() for d in depths.split(",")} == {t.split()[-1] for t in tried}
    slower = [Decimal(c) for c in ratios.column("total time")]
    assert_figure(slow_lo, min(slower), "jurs's fit and mesh time over Poisson's, smallest")
    assert_figure(slow_hi, max(slower), "jurs's fit and mesh time over Poisson's, largest")


def test_open_scans_row():
    """The open scans' ratios, loops and times (open_scans_default.json, the default fit)."""
    task, jurs, other = readme_row("open scans,")
    with open(os.path.join(RESULTS, "open_scans_default.json"), encoding="utf-8") as fh:
        runs = json.load(fh)["runs"]
    m, date = quoted(task, r"open scans, (\d+) points .*?\((\d{4}-\d\d-\d\d)\)")
    assert {str(r["m"]) for r in runs} == {m} and date == date_of("open_scans_default")

    def ratios(key, best):
        return [r["rows"]["jurs"][key] / r["rows"][best][key] for r in runs]

    c_lo, c_hi, h_lo, h_hi, loops, cases, t_lo, t_hi = quoted(
        jurs,
        r"Chamfer ([\d.]+)-([\d.]+)x Poisson's at its best density trim, Hausdorff "
        r"([\d.]+)-([\d.]+)x; boundary loops = true rims on (\d+)/(\d+); (\d+)-(\d+) s",
    )
    chamfer = ratios("chamfer", "Poisson best-Chamfer trim")
    hausdorff = ratios("hausdorff", "Poisson best-Hausdorff trim")
    assert_figure(c_lo, Decimal(min(chamfer)), "the smallest Chamfer ratio")
    assert_figure(c_hi, Decimal(max(chamfer)), "the largest Chamfer ratio")
    assert_figure(h_lo, Decimal(min(hausdorff)), "the smallest Hausdorff ratio")
    assert_figure(h_hi, Decimal(max(hausdorff)), "the largest Hausdorff ratio")
    assert int(cases) == len(runs)
    assert int(loops) == sum(r["rows"]["jurs"]["loops"] == r["rims"] for r in runs)
    times = [r["rows"]["jurs"]["time_s"] for r in runs]
    assert_figure(t_lo, Decimal(min(times)), "jurs's shortest fit + mesh + trim")
    assert_figure(t_hi, Decimal(max(times)), "jurs's longest fit + mesh + trim")
    p_lo, p_hi = quoted(other, r"Open3D Poisson: ([\d.]+)-([\d.]+) s")
    poisson = [r["rows"]["Poisson"]["time_s"] for r in runs]
    assert_figure(p_lo, Decimal(min(poisson)), "Poisson's shortest call")
    assert_figure(p_hi, Decimal(max(poisson)), "Poisson's longest call")


@pytest.mark.parametrize(
    "figure, value, ok",
    [("0.62", "0.619", True), ("2.1", "2.05", True), ("175", "152", False), ("89", "89.5", False)],
)
def test_rounding_is_to_the_readme_digit(figure, value, ok):
    assert rounds_to(figure, Decimal(value)) is ok
