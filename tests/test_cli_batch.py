"""``jurs fit`` on several clouds in one process: one sub-folder each, written whole or not
at all, a bad file reported while the others go on."""

import jax

jax.config.update("jax_enable_x64", True)

import json  # noqa: E402
import os  # noqa: E402

import pytest  # noqa: E402

import jurs  # noqa: E402
from jurs import cli  # noqa: E402
from jurs.cli._batch import expand_inputs, folder_names  # noqa: E402

FIT_ARGS = ["--steps", "20", "--tol", "0", "-q", "--resolution", "100"]
PAPER_ARGS = ["--solver", "lstsq", "--lam", "1e-4", "--grid", "8x8", "-d", "0.1", "--eps", "0.01"]


@pytest.fixture(autouse=True)
def no_compilation_cache(monkeypatch):
    monkeypatch.setenv("JURS_NO_COMPILATION_CACHE", "1")


def test_folder_names_follow_the_stems_and_resolve_clashes_in_order():
    paths = ["a/scan.csv", "b/scan.csv", "scan-2.npy", "c/scan.txt", "x.y.csv"]
    assert folder_names(paths) == ["scan", "scan-3", "scan-2", "scan-4", "x.y"]
    assert folder_names(paths) == folder_names(list(paths))  # the same run, the same folders


def test_folders_and_patterns_expand_to_their_cloud_files(tmp_path):
    for name in ("b.csv", "a.npy", "notes.md", "c.xyz", "d.STL", "e.off"):
        (tmp_path / name).write_text("")
    (tmp_path / "sub.csv").mkdir()  # a folder, not a cloud
    found = expand_inputs([str(tmp_path)])
    # Triangle meshes (STL, OFF) are read as the surfaces they describe.
    assert [os.path.basename(p) for p in found] == ["a.npy", "b.csv", "c.xyz", "d.STL", "e.off"]
    pattern = expand_inputs([str(tmp_path / "*.csv"), str(tmp_path / "b.csv")])
    assert [os.path.basename(p) for p in pattern] == ["b.csv"]  # named twice, fitted once


@pytest.mark.slow  # two whole command-line fits with figures: the batch form end to end
def test_a_bad_file_among_good_ones(tmp_path, capsys):
    """Two good clouds and a malformed one (a NaN in row 4): the good ones get their whole
    set of outputs each, the bad one nothing (no folder, no temporary folder), the error
    names it, and the exit status says a file failed."""
    data = tmp_path / "data"
    (data / "more").mkdir(parents=True)
    jurs.datasets.save_points(data / "ring.csv", *jurs.datasets.example1(120))
    jurs.datasets.save_points(data / "more" / "ring.csv", *jurs.datasets.example1(110))
    bad = data / "bad.csv"
    bad.write_text("x,y,nx,ny\n1,0,1,0\n0,1,0,1\n-1,nan,-1,0\n0,-1,0,-1\n")
    out = tmp_path / "out"
    files = [str(data / "ring.csv"), str(bad), str(data / "more" / "ring.csv")]
    rc = cli.main(["fit", *files, "-o", str(out), *PAPER_ARGS, *FIT_ARGS])
    err = capsys.readouterr().err
    assert rc == 2
    assert sorted(os.listdir(out)) == ["ring", "ring-2"]
    for name, path, m in (("ring", files[0], 120), ("ring-2", files[2], 110)):
        assert sorted(os.listdir(out / name)) == sorted(cli.OUTPUTS)
        record = json.loads((out / name / "metrics.json").read_text())
        assert record["input"] == os.path.abspath(path) and record["num_points"] == m
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and str(bad) in errors[0] and "row 4" in errors[0]
    assert "fitted 2 of 3" in err and str(bad) in err.splitlines()[-1]
    assert not [p for d, _, names in os.walk(out) for p in names + [d] if ".jurs-" in p]


def test_a_folder_without_clouds_fails(tmp_path, capsys):
    out = tmp_path / "out"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["fit", str(empty), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(empty) in err and "no cloud files" in err
    assert not out.exists()


def test_progress_lines_on_a_terminal_and_the_worst_status(tmp_path, capsys, monkeypatch):
    """Each file gets a progress line on a terminal (none with --quiet); a fit that
    raises goes on to the next file; the exit status is the worst of the files'."""
    from jurs.cli import _batch

    for name in ("a.csv", "b.csv", "c.csv"):
        (tmp_path / name).write_text("")
    codes = {"a.csv": 0, "b.csv": 1, "c.csv": "raise"}
    seen = []

    def run_one(args):
        name = os.path.basename(args.file)
        seen.append((name, os.path.basename(args.output), args.files))
        if codes[name] == "raise":
            raise cli.InputError(f"{args.file}: malformed")
        return codes[name]

    monkeypatch.setattr(_batch.sys.stderr, "isatty", lambda: True, raising=False)
    args = cli.build_parser().parse_args(["fit", str(tmp_path), "-o", str(tmp_path / "out")])
    assert _batch.run_batch(args, run_one) == 2
    assert [s[:2] for s in seen] == [("a.csv", "a"), ("b.csv", "b"), ("c.csv", "c")]
    assert all(len(files) == 1 for _, _, files in seen)  # each run sees a single file
    err = capsys.readouterr().err
    assert [line.split("] ")[0] for line in err.splitlines() if "] " in line] == [
        "jurs: [1/3",
        "jurs: [2/3",
        "jurs: [3/3",
    ]
    assert "malformed" in err and "fitted 1 of 3" in err
    quiet = cli.build_parser().parse_args(["fit", str(tmp_path), "-o", "o", "-q"])
    codes["c.csv"] = 0
    assert _batch.run_batch(quiet, run_one) == 1
    assert "[1/3]" not in capsys.readouterr().err


def test_a_fit_that_is_not_a_reconstruction_among_good_ones(tmp_path, capsys):
    """A cloud whose fit's verdict is inconsistent_normals (half its normals flipped)
    among good ones: no sub-folder for it, the others written, exit status 1 (a failed
    fit), its one line and the summary naming it."""
    good = tmp_path / "good.csv"
    jurs.datasets.save_points(good, *jurs.datasets.example1(120))
    points, normals = jurs.datasets.example1(120)
    normals = normals.copy()
    normals[:60] *= -1
    flipped = tmp_path / "flipped.csv"
    jurs.datasets.save_points(flipped, points, normals)
    out = tmp_path / "out"
    rc = cli.main(["fit", str(flipped), str(good), "-o", str(out), *PAPER_ARGS, *FIT_ARGS])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert os.listdir(out) == ["good"]
    assert sorted(os.listdir(out / "good")) == sorted(cli.OUTPUTS)
    errors = [line for line in err.splitlines() if line.startswith("jurs: error:")]
    assert len(errors) == 1 and "inconsistent_normals" in errors[0], err
    assert "fitted 1 of 2" in err and str(flipped) in err.splitlines()[-1]
