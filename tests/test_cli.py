"""The ``jurs`` command line: a fit round trip, bad files, the progress machinery."""

import jax

jax.config.update("jax_enable_x64", True)

import io  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import PAPER  # noqa: E402

import jurs  # noqa: E402
from jurs import cli  # noqa: E402

# 20 steps run in one chunk (see jurs._fit.progress.chunk_size): the command line's chunked
# fit compiles its start, one chunk and its end once for all the tests that share them.
FIT_ARGS = ["--steps", "20", "--tol", "0", "-q", "--resolution", "200"]
PAPER_ARGS = ["--solver", "iurs", "--grid", "9x9", "-d", "0.1", "--eps", "0.01"]


@pytest.fixture(autouse=True)
def no_compilation_cache(monkeypatch):
    """cli.main would turn JAX's persistent compilation cache on for the rest of the test
    process, where other tests count compilations."""
    monkeypatch.setenv("JURS_NO_COMPILATION_CACHE", "1")


@pytest.fixture(scope="module")
def example1_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "example1.csv"
    jurs.datasets.save_points(path, *jurs.datasets.example1(120))
    return path


@pytest.mark.slow
def test_fit_round_trip(example1_csv, tmp_path):
    out = tmp_path / "result"
    rc = cli.main(["fit", str(example1_csv), "-o", str(out), *PAPER_ARGS, *FIT_ARGS])
    assert rc == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".jurs-")]  # temp dir gone

    record = json.loads((out / "metrics.json").read_text())
    m = record["metrics"]
    for key in (
        "E",
        "E_d",
        "R",
        "E_ave",
        "E_max",
        "mu",
        "lam",
        "num_steps",
        "num_components",
        "num_supplementary",
        "supplementary_length",
        "num_tiny_loops",
        "chamfer",
        "hausdorff",
        "zero_area_fraction",
    ):
        assert key in m, key
    assert m["num_steps"] == 20
    assert record["settings"]["grid"] == [9, 9] and record["num_points"] == 120
    # The verdict: its short name (Solution.status) and its sentence (Solution.message).
    assert m["status"] == "max_steps_reached" and m["converged"] is False
    assert m["result"] == jurs.RESULTS[jurs.RESULTS.max_steps_reached]

    # The saved spline is the one jurs.fit gives with the same settings.
    points, normals = jurs.datasets.load_points(example1_csv)
    problem = jurs.make_problem(points, normals, grid=(9, 9))
    start = jurs.ImplicitSpline.bspline(np.zeros((9, 9)), problem.lower, problem.upper)
    direct = jurs.fit(
        points, normals, solver=jurs.IURS(max_steps=20, tol=0.0), init=start, throw=False, **PAPER
    )  # the CLI's defaults
    spline = jurs.load_spline(out / "spline.npz")
    assert isinstance(spline, jurs.ImplicitSpline)
    np.testing.assert_allclose(
        np.asarray(spline.control), np.asarray(direct.spline.control), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(spline.weights), np.asarray(direct.spline.weights), rtol=0, atol=1e-12
    )
    assert m["E_ave"] == pytest.approx(float(direct.metrics["E_ave"]), rel=1e-9)

    # The polylines lie on the zero set of the saved spline, one component per id.
    table = np.loadtxt(out / "zero_level.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(np.unique(table[:, 0])) == m["num_components"]
    assert int(table[:, 2].max(initial=0) > 0) == int(m["num_supplementary"] > 0)
    g = np.asarray(spline(table[:, 3:]))
    assert np.max(np.abs(g)) < 1e-2 * 0.01  # |g| << eps on the curve (linear interpolation)

    assert (out / "fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # Re-running into the same folder replaces the outputs.
    (out / "spline.npz").unlink()
    (out / "metrics.json").write_text("old")
    assert cli.main(["fit", str(example1_csv), "-o", str(out), *PAPER_ARGS, *FIT_ARGS]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    rerun = json.loads((out / "metrics.json").read_text())["metrics"]
    assert rerun.keys() == m.keys()
    for key in m.keys() - {"time_s"}:
        # Floats equal up to rounding: a GPU's scatter-adds sum in a new order each run.
        expected = pytest.approx(m[key], rel=1e-9, abs=0) if isinstance(m[key], float) else m[key]
        assert rerun[key] == expected, key


def test_summary_names_the_verdict_and_skips_pyplot(example1_csv, tmp_path, capsys, monkeypatch):
    """The summary line labels the run with Solution.status, not a piece of its message;
    the figure is drawn on a standalone Agg canvas: pyplot never makes a figure."""
    import matplotlib.pyplot as plt

    def no_pyplot(*args, **kwargs):
        raise AssertionError("jurs fit made a pyplot figure")

    monkeypatch.setattr(plt, "figure", no_pyplot)
    args = ["fit", str(example1_csv), "-o", str(tmp_path / "o"), *PAPER_ARGS, *FIT_ARGS]
    assert cli.main([a for a in args if a != "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert ": 20 steps in " in out[0] and out[0].endswith(" s (max_steps_reached)"), out
    assert (tmp_path / "o" / "fit.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _flipped_example1(path):
    """Example 1 with half its normals flipped: the fit's verdict is inconsistent_normals."""
    points, normals = jurs.datasets.example1(120)
    normals = normals.copy()
    normals[:60] *= -1
    jurs.datasets.save_points(path, points, normals)
    return path


def test_not_a_reconstruction_exits_1_and_writes_nothing(tmp_path, capsys):
    """A fit whose verdict is not a reconstruction (here half the normals flipped:
    inconsistent_normals) was written with a 771-character warning and exit status 0. Now:
    exit 1, one short line on stderr naming the verdict, no output folder; into a folder of
    earlier outputs, those stay as they were."""
    path = _flipped_example1(tmp_path / "flipped.csv")
    out = tmp_path / "o"
    assert cli.main(["fit", str(path), "-o", str(out), *PAPER_ARGS, *FIT_ARGS]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and len(err[0]) - len(str(path)) < 300, err  # was 771
    assert err[0].startswith(f"jurs: error: {path}: the fit's verdict is inconsistent_normals")
    assert err[0].endswith("nothing written"), err
    assert not out.exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".jurs-")]
    _old_outputs(out)
    assert cli.main(["fit", str(path), "-o", str(out), *PAPER_ARGS, *FIT_ARGS]) == 1
    assert sorted(os.listdir(out)) == sorted(set(cli.OUTPUTS) - {"fit.png"})
    assert all((out / n).read_text() == "old" for n in os.listdir(out))


def test_every_verdict_that_is_not_a_reconstruction_has_its_line():
    """The command line's lines cover exactly the verdicts throw=True raises."""
    from jurs._solution.solution import RAISED_RESULTS

    assert set(cli.VERDICT_LINES) == set(RAISED_RESULTS)
    for name in RAISED_RESULTS:
        line = cli.not_a_reconstruction(name)
        assert name in line and "not a reconstruction" in line and len(line) < 260


def test_a_doubtful_fit_is_written_with_one_short_line(example1_csv, tmp_path, capsys, monkeypatch):
    """A doubtful fit is usable: written, exit 0, one short warning line; the doubts in
    words are in metrics.json. (The fit is made doubtful here: a real one needs the
    automatic settings' checks on a larger cloud.)"""
    import dataclasses

    real_fit = jurs.fit
    doubts = ("a thin part " + "x" * 300, "a closed zero-set component away from the data")

    def doubtful_fit(*args, **kwargs):
        sol = real_fit(*args, **kwargs)
        stats = dict(sol.stats, doubts=doubts)
        return dataclasses.replace(sol, result=jurs.RESULTS.doubtful, stats=stats)

    monkeypatch.setattr(jurs, "fit", doubtful_fit)
    out = tmp_path / "o"
    args = ["fit", str(example1_csv), "-o", str(out), *PAPER_ARGS, *FIT_ARGS]
    assert cli.main([a for a in args if a != "-q"]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "doubtful fit (2 doubt(s)" in err[0] and len(err[0]) < 200, err
    assert captured.out.splitlines()[0].endswith("(doubtful)"), captured.out
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    record = json.loads((out / "metrics.json").read_text())
    assert record["metrics"]["status"] == "doubtful"
    assert record["metrics"]["doubts"] == list(doubts)


def test_standalone_figures():
    """jurs.plot's figures without pyplot (the command line's): an Agg canvas, not in
    pyplot's list of figures; by default they are pyplot's."""
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from jurs import plot

    before = plt.get_fignums()
    fig, ax = plot._new_axes(None, pyplot=False)
    assert isinstance(fig.canvas, FigureCanvasAgg) and ax.figure is fig
    fig, axes = plot._mesh_axes(None, pyplot=False)
    assert len(axes) == len(plot.MESH_VIEWS) and all(hasattr(a, "view_init") for a in axes)
    assert plt.get_fignums() == before
    fig, ax = plot._new_axes(None)
    assert plt.fignum_exists(fig.number)
    plt.close(fig)


@pytest.mark.slow
def test_npy_input(tmp_path):
    p, n = jurs.datasets.example1(120)
    path = tmp_path / "example1.npy"
    jurs.datasets.save_points(path, 0.5 * p + 1.0, n)
    rc = cli.main(["fit", str(path), "-o", str(tmp_path / "o"), *FIT_ARGS])
    assert rc == 0
    record = json.loads((tmp_path / "o" / "metrics.json").read_text())
    m = record["metrics"]
    assert m["num_components"] == 1 and m["num_supplementary"] == 0
    # The default solver is the exact solve with the settings chosen from the data.
    chosen = jurs.auto_settings(0.5 * p + 1.0, n)
    assert record["settings"]["solver"] == "auto" and m["num_steps"] == 1
    assert m["status"] == "successful" and m["converged"] is True
    assert record["settings"]["grid"] == list(chosen.grid)
    assert record["settings"]["lam"] == pytest.approx(chosen.lam, rel=1e-12)
    assert record["settings"]["offset"] == pytest.approx(chosen.offset, rel=1e-12)
    # --smoothing sets the automatic lambda's strength.
    rc = cli.main(["fit", str(path), "-o", str(tmp_path / "s"), *FIT_ARGS, "--smoothing", "1e-4"])
    record = json.loads((tmp_path / "s" / "metrics.json").read_text())
    smoothed = jurs.auto_settings(0.5 * p + 1.0, n, smoothing=1e-4)
    assert rc == 0 and record["settings"]["chosen_from_data"]["smoothing"] == 1e-4
    assert record["settings"]["lam"] == pytest.approx(smoothed.lam, rel=1e-12)


GOOD = "x,y,nx,ny\n1,0,1,0\n0,1,0,1\n-1,0,-1,0\n0,-1,0,-1\n"
BAD_TEXT = {
    "missing_column": ("x,y,nx,ny\n1,0,1,0\n0,1,0\n-1,0,-1,0\n", "row 3"),
    "non_number": ("x,y,nx,ny\n1,0,1,0\n0,abc,0,1\n-1,0,-1,0\n0,-1,0,-1\n", "row 3"),
    "nan": ("x,y,nx,ny\n1,0,1,0\n0,1,0,1\n-1,nan,-1,0\n0,-1,0,-1\n", "row 4"),
    "empty": ("", "no data rows"),
    "header_only": ("x,y,nx,ny\n", "no data rows"),
    "too_few_rows": ("x,y,nx,ny\n1,0,1,0\n0,1,0,1\n", "at least 3"),
    "zero_normal": ("1 0 1 0\n0 1 0 0\n-1 0 -1 0\n0 -1 0 -1\n", "row 2"),
    "extra_column": ("1;0;1;0\n0;1;0;1;5\n-1;0;-1;0\n", "row 2"),
}


def _check_failure(capsys, args, out, path, needle):
    rc = cli.main(args)
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(path) in lines[0] and needle in lines[0], lines[0]
    assert not out.exists()
    assert not [p for p in os.listdir(out.parent) if p.startswith(".jurs-")]


@pytest.mark.parametrize("kind", sorted(BAD_TEXT))
def test_bad_text_files(kind, tmp_path, capsys):
    text, needle = BAD_TEXT[kind]
    path = tmp_path / f"{kind}.csv"
    path.write_text(text)
    out = tmp_path / "out"
    _check_failure(capsys, ["fit", str(path), "-o", str(out), *FIT_ARGS], out, path, needle)


@pytest.mark.parametrize(
    "kind, array, needle",
    [
        ("five_columns", np.ones((5, 5)), "shape (5, 5)"),
        ("one_dimensional", np.ones(8), "shape (8,)"),
        ("three_dimensional", np.ones((2, 5, 4)), "shape (2, 5, 4)"),
        (
            "nan_row",
            np.array([[1, 0, 1, 0], [0, 1, 0, 1], [np.nan, 0, -1, 0], [0, -1, 0, -1.0]]),
            "row 3",
        ),
        ("strings", np.array([["a", "b", "c", "d"]] * 4), "not numeric"),
    ],
)
def test_bad_npy_files(kind, array, needle, tmp_path, capsys):
    path = tmp_path / f"{kind}.npy"
    np.save(path, array)
    out = tmp_path / "out"
    _check_failure(capsys, ["fit", str(path), "-o", str(out), *FIT_ARGS], out, path, needle)


def test_missing_file_and_folder(tmp_path, capsys):
    out = tmp_path / "out"
    missing = tmp_path / "nope.csv"
    _check_failure(capsys, ["fit", str(missing), "-o", str(out)], out, missing, "no such file")
    _check_failure(capsys, ["fit", str(tmp_path), "-o", str(out)], out, tmp_path, "folder")


def test_failed_run_leaves_existing_outputs_alone(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("old")
    path = tmp_path / "bad.csv"
    path.write_text(BAD_TEXT["nan"][0])
    assert cli.main(["fit", str(path), "-o", str(out), *FIT_ARGS]) == 2
    assert os.listdir(out) == ["metrics.json"] and (out / "metrics.json").read_text() == "old"


def test_bad_options_exit_2(tmp_path, capsys):
    path = tmp_path / "good.csv"
    path.write_text(GOOD)
    for args in (["--grid", "3"], ["--offset", "-1"], ["--lam", "nan"], ["--solver", "xyz"]):
        with pytest.raises(SystemExit) as exc:
            cli.main(["fit", str(path), "-o", str(tmp_path / "o"), *args])
        assert exc.value.code == 2
    assert (
        cli.main(["fit", str(path), "-o", str(tmp_path / "o"), "--solver", "ipia", "--lam", "0.1"])
        == 2
    )
    assert "ipia" in capsys.readouterr().err
    for args in (
        ["--smoothing", "1e-4", "--lam", "0.1"],
        ["--smoothing", "1e-4", "--solver", "iurs"],
    ):
        assert cli.main(["fit", str(path), "-o", str(tmp_path / "o"), *args]) == 2
        assert "--smoothing" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_adaptive_fit_and_its_options(tmp_path, capsys):
    """``--adaptive`` fits on the THB basis (``jurs.fit_adaptive``): the spline file holds
    an adaptive spline, metrics.json its basis, finest level and lambda; ``--grid``,
    ``--finest`` without ``--adaptive``, a uniform-grid solver and a bad ``--finest`` are
    refused before anything is fitted."""
    t = np.linspace(0.0, 2.0 * np.pi, 160, endpoint=False)
    circle = np.c_[np.cos(t), np.sin(t)]
    path = tmp_path / "circle.csv"
    jurs.datasets.save_points(path, circle, circle)
    out = tmp_path / "out"
    assert cli.main(["fit", str(path), "-o", str(out), "--adaptive", "--finest", "64", "-q"]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    settings = json.loads((out / "metrics.json").read_text())["settings"]
    assert settings["basis"] == "adaptive" and settings["grid"] is None
    assert max(settings["finest"]) == 64 and settings["lam"] > 0
    spline = jurs.load_spline(out / "spline.npz")
    assert isinstance(spline, jurs.AdaptiveSpline)
    np.testing.assert_allclose(np.abs(spline(circle)), 0.0, atol=1e-3)
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    assert metrics["num_components"] == 1 and metrics["resolution"] == 512
    for args, needle in (
        (["--adaptive", "--grid", "16"], "--grid is for the uniform fit"),
        (["--finest", "64"], "add --adaptive"),
        (["--adaptive", "--solver", "iurs"], "--solver iurs runs on the uniform grid"),
        (["--adaptive", "--finest", "4"], "--finest must be between 8"),
    ):
        bad = tmp_path / "bad"
        assert cli.main(["fit", str(path), "-o", str(bad), *args]) == 2
        assert needle in capsys.readouterr().err
        assert not bad.exists()


def test_console_script_exit_code(tmp_path):
    script = Path(sys.executable).parent / "jurs"
    if not script.exists():
        pytest.skip("console script not installed")
    path = tmp_path / "bad.csv"
    path.write_text(BAD_TEXT["non_number"][0])
    proc = subprocess.run(
        [str(script), "fit", str(path), "-o", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "row 3" in proc.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_command_process_ends_with_its_outputs(example1_csv, tmp_path):
    """The command as a process (``python -m jurs.cli``: ``cli.command``, which ends the
    process through ``cli.end_process``): its summary printed, every output written,
    exit status 0, and the compilation cache it filled kept."""
    env = {k: v for k, v in os.environ.items() if k != "JURS_NO_COMPILATION_CACHE"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    out = tmp_path / "o"
    args = [a for a in FIT_ARGS if a != "-q"]
    proc = subprocess.run(
        [sys.executable, "-m", "jurs.cli", "fit", str(example1_csv), "-o", str(out)]
        + PAPER_ARGS
        + args,
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    assert "(max_steps_reached)" in proc.stdout and "wrote metrics.json" in proc.stdout
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    assert json.loads((out / "metrics.json").read_text())["metrics"]["num_steps"] == 20
    cache = tmp_path / "cache" / "jurs"
    assert os.listdir(cache / "jurs-exported-fits")
    assert [p for p in os.listdir(cache) if p != "jurs-exported-fits"]  # JAX's entries


@pytest.mark.parametrize(
    "solver",
    [
        jurs.IURS(tau=1e-2, lam=0.005, max_steps=60, tol=0.0),
        jurs.IPIA(max_steps=60, tol=0.0),
        jurs.IURS(max_steps=300, tol=1e-6),  # converges early, mid-chunk
    ],
)
@pytest.mark.slow
def test_chunked_run_equals_one_run(solver):
    """The progress bar's chunked run follows the iterates of one run."""
    p, n = jurs.datasets.example1(120)
    one = jurs.fit(p, n, solver=solver, **PAPER)
    calls = []
    chunked, snaps = jurs.fit_in_chunks(
        p,
        n,
        solver=solver,
        checkpoints=(0, 10, 30),
        **PAPER,
        callback=lambda d, t: calls.append((d, t)),
    )
    for key in ("control", "weights"):
        np.testing.assert_allclose(
            np.asarray(getattr(chunked.spline, key)),
            np.asarray(getattr(one.spline, key)),
            rtol=0,
            atol=1e-13,
        )
    assert int(chunked.stats["num_steps"]) == int(one.stats["num_steps"])
    assert chunked.result == one.result
    np.testing.assert_allclose(
        chunked.stats["energy_history"], np.asarray(one.stats["energy_history"]), rtol=1e-12
    )
    assert len(calls) > 1 and calls[-1][0] == int(one.stats["num_steps"])
    assert sorted(snaps) == [0, 10, 30]
    assert float(np.abs(np.asarray(snaps[0].control)).max()) == 0.0
    if isinstance(solver, jurs.IURS) and solver.lam:  # one snapshot checked against a run
        ten = jurs.fit(p, n, solver=jurs.IURS(tau=1e-2, lam=0.005, max_steps=10, tol=0.0), **PAPER)
        np.testing.assert_allclose(
            np.asarray(snaps[10].control), np.asarray(ten.spline.control), rtol=0, atol=1e-13
        )


def test_progress_bar_only_after_delay():
    quiet = io.StringIO()
    bar = cli.ProgressBar("x", delay=60, stream=quiet)
    bar(5, 10)
    bar.close()
    assert quiet.getvalue() == ""
    loud = io.StringIO()
    bar = cli.ProgressBar("fit", delay=0, width=10, stream=loud, tty=True)
    bar(5, 10)
    bar(10, 10)
    bar.close()
    text = loud.getvalue()
    assert "5/10 steps" in text and "[##########]" in text and text.endswith("\n")
    assert text.count("\r") == 2


def test_progress_in_a_log_is_a_few_plain_lines():
    """Piped into a log, the bar wrote a carriage-return frame a chunk of steps: hundreds
    of them. Not on a terminal, it writes a line when first shown, one a quarter, and one
    where the run stopped."""
    log = io.StringIO()  # isatty() is False
    bar = cli.ProgressBar("iurs grid 9x9", delay=0, stream=log)
    for done in range(1, 201):
        bar(done, 200)
    bar.close()
    text = log.getvalue()
    lines = text.splitlines()
    assert "\r" not in text and text.endswith("\n")
    assert [line.split(": ")[1].split(" steps")[0] for line in lines] == [
        "1/200",
        "50/200",
        "100/200",
        "150/200",
        "200/200",
    ]
    assert all(line.startswith("iurs grid 9x9: ") and " %) " in line for line in lines)
    # A run that stops early (tol met) says where it stopped; nothing after close.
    log = io.StringIO()
    bar = cli.ProgressBar("ipia", delay=0, stream=log)
    for done in range(1, 71):
        bar(done, 200)
    bar.close()
    bar.close()
    assert [line.split(": ")[1].split(" steps")[0] for line in log.getvalue().splitlines()] == [
        "1/200",
        "50/200",
        "70/200",
    ]


def test_stage_clock_says_a_long_stage_and_nothing_of_a_short_one():
    """A stage with no steps to count (an adaptive fit's solve, a fine mesh) printed
    nothing however long it ran. The clock says it once its delay has passed, again as the
    elapsed time doubles, and how long it took; a short stage stays silent."""
    from jurs.cli._progress import StageClock

    log = io.StringIO()
    with StageClock("bunny.ply: meshing", delay=0.05, stream=log) as clock:
        time.sleep(0.35)  # lines at about 0.05, 0.15 and 0.3 s (fewer on a loaded machine)
    lines = log.getvalue().splitlines()
    assert 2 <= clock.lines <= 5 and len(lines) == clock.lines
    assert all(line.startswith("bunny.ply: meshing: ") for line in lines)
    assert lines[0].endswith(" s so far") and lines[-1].split(": ")[-1].startswith("done in ")
    quiet = io.StringIO()
    with StageClock("x", delay=60, stream=quiet):
        pass
    with StageClock("x", delay=0.0, stream=quiet, enabled=False):
        time.sleep(0.05)
    assert quiet.getvalue() == ""
    # A stage that raises says no "done"; the error is the caller's.
    log = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        with StageClock("fit", delay=0.01, stream=log):
            time.sleep(0.05)
            raise KeyboardInterrupt
    assert "done" not in log.getvalue()


def _old_outputs(out):
    out.mkdir()
    for name in cli.OUTPUTS:
        if name != "fit.png":
            (out / name).write_text("old")


def test_output_folder_checked_before_the_fit(example1_csv, tmp_path, capsys, monkeypatch):
    """Issue 20, defects 1 and 10: a folder in place of an output, an unwritable folder
    and a full disk are one-line errors (exit 2) found before the fit; nothing changes."""

    def no_fit(*args, **kwargs):
        raise AssertionError("the fit ran before the output folder was checked")

    monkeypatch.setattr("jurs.fit", no_fit)
    out = tmp_path / "out"
    _old_outputs(out)
    (out / "fit.png").mkdir()
    args = ["fit", str(example1_csv), "-o", str(out), *FIT_ARGS]

    def fails(needle):
        before = sorted(os.listdir(out))
        assert cli.main(args) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
        assert sorted(os.listdir(out)) == before
        assert (out / "zero_level.csv").read_text() == "old"

    fails("fit.png: exists and is not a file")
    (out / "fit.png").rmdir()
    monkeypatch.setattr(cli.os, "access", lambda path, mode: False)
    fails("folder is not writable")
    monkeypatch.undo()
    monkeypatch.setattr("jurs.fit", no_fit)
    monkeypatch.setattr(
        cli.shutil, "disk_usage", lambda path: SimpleNamespace(total=1, used=1, free=1000)
    )
    args[3] = str(tmp_path / "new" / "deeper")  # a folder to be made: its parent is checked
    assert cli.main(args) == 2
    assert "MiB free" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_resolution_refused_up_front(example1_csv, tmp_path, capsys, monkeypatch):
    """Issue 20, defect 8: --resolution 30000 ended in a MemoryError traceback."""
    monkeypatch.setattr("jurs._problem.memory.available_memory", lambda device=True: 4 << 30)
    out = tmp_path / "o"
    _check_failure(
        capsys,
        ["fit", str(example1_csv), "-o", str(out), "--resolution", "30000"],
        out,
        "--resolution 30000",
        "GiB",
    )


def test_failed_write_keeps_the_whole_old_set(example1_csv, tmp_path, capsys, monkeypatch):
    """Issue 20, defect 1: a failure part way through the renames rolls back the files
    already replaced; a folder made for the run is removed again."""
    out = tmp_path / "out"
    _old_outputs(out)
    real_replace = os.replace

    def replace(src, dst):
        if str(dst).endswith("fit.png") and ".jurs-" not in str(dst):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(cli.os, "replace", replace)
    args = ["fit", str(example1_csv), *PAPER_ARGS, *FIT_ARGS]
    assert cli.main([*args, "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left" in err[0] and "previous outputs" in err[0]
    assert sorted(os.listdir(out)) == sorted(set(cli.OUTPUTS) - {"fit.png"})
    assert all((out / n).read_text() == "old" for n in os.listdir(out))
    fresh = tmp_path / "fresh"
    assert cli.main([*args, "-o", str(fresh)]) == 1
    assert not fresh.exists()


def test_awkward_names_and_files(tmp_path, capsys, monkeypatch):
    """Issue 20, defect 10: a file name that is not UTF-8 crashed in the figure's title; a
    byte-order mark before the header was refused; output folders were made 0700; ``-o .``
    needed the parent folder writable."""
    p, n = jurs.datasets.example1(120)
    plain = tmp_path / "plain.csv"
    jurs.datasets.save_points(plain, p, n)
    name = os.path.join(os.fsencode(tmp_path), b"caf\xe9.csv")  # Latin-1, not UTF-8
    with open(name, "wb") as fh:
        fh.write(b"\xef\xbb\xbf" + plain.read_bytes())
    out = tmp_path / "out"
    old = os.umask(0o002)
    try:
        assert cli.main(["fit", os.fsdecode(name), "-o", str(out), *PAPER_ARGS, *FIT_ARGS]) == 0
    finally:
        os.umask(old)
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    assert (out.stat().st_mode & 0o777) == 0o775
    assert ((out / "spline.npz").stat().st_mode & 0o777) == 0o664
    record = json.loads((out / "metrics.json").read_text())
    assert record["input"].endswith("caf\ufffd.csv") and record["num_points"] == 120
    monkeypatch.chdir(out)  # -o . : the temporary folder is made inside it
    assert cli.main(["fit", str(plain), "-o", ".", *PAPER_ARGS, *FIT_ARGS]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    assert json.loads((out / "metrics.json").read_text())["input"] == str(plain)


def test_points_without_normals(tmp_path):
    """An x, y file: the CLI estimates outward normals, fits, and says so in metrics.json."""
    path = tmp_path / "xy.csv"
    points, _ = jurs.datasets.example1(120)
    jurs.datasets.save_points(path, points)
    out = tmp_path / "result"
    rc = cli.main(["fit", str(path), "-o", str(out), *PAPER_ARGS, *FIT_ARGS])
    assert rc == 0
    record = json.loads((out / "metrics.json").read_text())
    assert record["normals"] == "estimated"
    assert record["metrics"]["num_components"] == 1
    assert record["metrics"]["num_supplementary"] == 0
    spline = jurs.load_spline(out / "spline.npz")
    assert float(spline(np.array([[0.0, -4.0]]))[0]) < 0  # inside: the normals point out


# --- outputs of another kind of run, and Ctrl-C ----------------------------------------------


def _surface_outputs_from_jurs(out, record=None):
    """A folder as a surface fit leaves it: metrics.json with jurs's record (``mesh``
    included) and the other outputs."""
    out.mkdir()
    record = (
        {"input": "s.ply", "settings": {}, "metrics": {}, "mesh": {}} if record is None else record
    )
    (out / "metrics.json").write_text(json.dumps(record))
    for name in cli.OUTPUTS_3D[1:]:
        (out / name).write_text("old")


def test_curve_fit_removes_a_surface_fits_outputs(example1_csv, tmp_path, capsys):
    """A fit into a folder of another kind of run left its files (mesh.ply, preview.png)
    beside the new ones; jurs's own are removed, files the user put there are kept."""
    out = tmp_path / "out"
    _surface_outputs_from_jurs(out)
    args = ["fit", str(example1_csv), *PAPER_ARGS, *FIT_ARGS]
    assert cli.main([*args, "-o", str(out)]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)
    # Not jurs's metrics.json: mesh.ply and preview.png may be the user's.
    mine = tmp_path / "mine"
    _surface_outputs_from_jurs(mine, record={"mine": True})
    assert cli.main([*args, "-o", str(mine)]) == 0
    assert sorted(os.listdir(mine)) == sorted(set(cli.OUTPUTS) | set(cli.OUTPUTS_3D))
    assert (mine / "mesh.ply").read_text() == "old"


def test_failed_write_puts_back_the_other_kinds_outputs(example1_csv, tmp_path, monkeypatch):
    """The removal of the other kind's files is part of the one atomic write: a failure
    after it puts them back with the old set."""
    out = tmp_path / "out"
    _surface_outputs_from_jurs(out)
    before = {n: (out / n).read_text() for n in os.listdir(out)}
    real_replace = os.replace

    def replace(src, dst):
        if str(src).endswith("preview.png") and ".jurs-" in str(dst):
            raise OSError(28, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(cli.os, "replace", replace)
    assert cli.main(["fit", str(example1_csv), *PAPER_ARGS, *FIT_ARGS, "-o", str(out)]) == 1
    assert {n: (out / n).read_text() for n in os.listdir(out)} == before


def test_ctrl_c_mid_fit_is_one_line_and_exit_130(example1_csv, tmp_path, capsys, monkeypatch):
    """Ctrl-C printed a 70-line traceback; now one line, exit status 130, old outputs
    untouched."""
    out = tmp_path / "out"
    _old_outputs(out)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(jurs, "fit", interrupted)
    rc = cli.main(["fit", str(example1_csv), *PAPER_ARGS, *FIT_ARGS, "-o", str(out)])
    assert rc == cli.EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jurs: interrupted"), err
    assert "previous outputs" in err[0]
    assert all((out / n).read_text() == "old" for n in os.listdir(out))
    assert not [p for p in os.listdir(out) if p.startswith(".jurs-")]


def test_ctrl_c_while_writing_puts_the_old_set_back(example1_csv, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    _old_outputs(out)
    real_replace, pressed = os.replace, []

    def replace(src, dst):  # Ctrl-C once, as the new zero_level.csv is moved in
        if str(dst).endswith("zero_level.csv") and ".jurs-" not in str(dst) and not pressed:
            pressed.append(True)
            raise KeyboardInterrupt
        return real_replace(src, dst)

    monkeypatch.setattr(cli.os, "replace", replace)
    rc = cli.main(["fit", str(example1_csv), *PAPER_ARGS, *FIT_ARGS, "-o", str(out)])
    assert rc == 130
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert sorted(os.listdir(out)) == sorted(set(cli.OUTPUTS) - {"fit.png"})
    assert all((out / n).read_text() == "old" for n in os.listdir(out))


@pytest.mark.slow
def test_ctrl_c_to_the_process(tmp_path):
    """A real SIGINT to ``python -m jurs.cli`` mid-fit (the only test of the signal
    itself, through ``cli.command`` and ``end_process``): one line on stderr after the
    progress bar's, exit status 130, the old outputs kept."""
    import signal
    import time

    path = tmp_path / "cloud.csv"
    jurs.datasets.save_points(path, *jurs.datasets.example1(120))
    out = tmp_path / "out"
    _old_outputs(out)
    proc = subprocess.Popen(
        [sys.executable, "-m", "jurs.cli", "fit", str(path), "-o", str(out), *PAPER_ARGS]
        + ["--steps", "1000000", "--tol", "0", "--no-compilation-cache"],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        # A suite started in the background (`make test &`) ignores SIGINT, and a child
        # inherits that: Python then never turns Ctrl-C into KeyboardInterrupt. The
        # command is tested as a terminal runs it, with SIGINT at its default.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert proc.stderr is not None
    seen = b""
    while b"steps" not in seen:  # the progress bar: the fit is running
        chunk = proc.stderr.read1(4096)  # pyright: ignore[reportAttributeAccessIssue]
        assert chunk, seen
        seen += chunk
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    rest, _ = proc.communicate(timeout=120)[::-1]
    err = (seen + rest).decode()
    assert proc.returncode == 130, err
    # Into a pipe the bar writes plain lines, each naming the steps; then one line.
    lines = [line for line in err.split("\n") if line.strip()]
    assert lines[-1].startswith("jurs: interrupted"), err
    assert all("steps" in line for line in lines[:-1]), err
    assert all((out / n).read_text() == "old" for n in os.listdir(out))


def test_metrics_record_the_doubts_and_extra_components():
    """metrics.json carries the fit's doubts in words and the closed components away from
    the data (numbers and lists, strict JSON); a fit without doubts has empty lists."""
    from typing import Any

    from jurs.cli._results import fit_record

    chosen = jurs.auto_settings(*jurs.datasets.example1(30))
    job: Any = SimpleNamespace(
        path="c.csv",
        points=np.zeros((30, 2)),
        estimated=False,
        grid=(9, 9),
        lam=1e-6,
        chosen=chosen,
        adaptive=False,
    )
    args = SimpleNamespace(solver="exact", tau=None, steps=20, tol=0.0)
    component = {
        "centre": np.array([0.5, -0.25]),
        "lower": np.array([0.25, -0.5]),
        "upper": np.array([0.75, 0.0]),
        "area_share": np.float64(0.125),
        "distance": np.float64(0.5),
    }
    sol = SimpleNamespace(
        metrics={"E_ave": np.float64(1e-6)},
        stats={
            "num_steps": 1,
            "doubts": ("a closed zero-set component",),
            "extra_components": (component,),
        },
        status="doubtful",
        message="doubtful",
        succeeded=False,
    )
    metrics = json.loads(
        json.dumps(fit_record(job, args, sol, 0.5), allow_nan=False, default=float)
    )["metrics"]
    assert metrics["doubts"] == ["a closed zero-set component"]
    assert metrics["extra_components"] == [
        {
            "centre": [0.5, -0.25],
            "lower": [0.25, -0.5],
            "upper": [0.75, 0.0],
            "area_share": 0.125,
            "distance": 0.5,
        }
    ]
    # Settings given: no doubt checks, no entries in stats; the lists are empty.
    sol.stats = {"num_steps": 1}
    metrics = fit_record(job, args, sol, 0.5)["metrics"]
    assert metrics["doubts"] == [] and metrics["extra_components"] == []


def test_fit_help_names_mesh_files(capsys):
    """`jurs fit --help` says that STL and OFF meshes are read (sampled on their faces)."""
    with pytest.raises(SystemExit):
        cli.main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "STL" in text and "OFF" in text and "sampled on its faces" in text


def test_fit_help_gives_the_exit_codes_and_3d_tables(capsys):
    """`jurs fit --help` says what each exit status means (the verdicts that exit 1 named
    as RAISED_RESULTS names them), what a folder of another kind's outputs becomes, and
    that 3 or 6 columns make a 3D cloud; the epilog keeps its lines."""
    from jurs._solution.solution import RAISED_RESULTS

    with pytest.raises(SystemExit):
        cli.main(["fit", "--help"])
    out = capsys.readouterr().out
    lines = out[out.index("exit status:") :].splitlines()
    codes = [line.split()[0] for line in lines if line[:2] == "  " and line.split()[0].isdigit()]
    assert codes == ["0", "1", "2", "130"]
    text = " ".join(out.split())
    assert all(name in text for name in RAISED_RESULTS)
    assert "doubtful" in text and "the exit status is the worst" in text
    assert "output folder:" in out and "zero_level.csv" in text
    assert "x, y, z, nx, ny, nz" in text and "a 3D cloud" in text
