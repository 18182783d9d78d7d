"""A cloud read in parts (``jurs.datasets.load_rows``, ``global_arrays``) and the helpers of
``jurs.distributed``, checked in one process: the row and file splits, the exchange of
rows to the even split (every process simulated here), and the errors. Two real processes
run in tests/test_distributed.py."""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest

import jurs
import jurs.distributed
from jurs.datasets import global_arrays, load_rows, part_files, part_rows
from jurs.datasets._parts import _assemble, _outgoing


@pytest.mark.parametrize("total, count", [(10, 1), (10, 3), (12, 4), (7, 7), (1003, 8)])
def test_part_rows_cover_every_row_once_in_order(total, count):
    """The parts are contiguous, in process order, every row once, sizes within one."""
    parts = [part_rows(total, i, count) for i in range(count)]
    rows = np.concatenate([np.arange(total)[s] for s in parts])
    np.testing.assert_array_equal(rows, np.arange(total))
    sizes = [s.stop - s.start for s in parts]
    assert max(sizes) - min(sizes) <= 1


def test_part_files_split_and_fewer_files_than_processes():
    names = [f"scan_{i:03d}.ply" for i in range(16)]
    parts = [part_files(names, i, 3) for i in range(3)]
    assert sum(parts, []) == names
    assert [len(p) for p in parts] == [5, 5, 6]
    with pytest.raises(ValueError, match="2 file\\(s\\) for 3 processes"):
        part_files(names[:2], 0, 3)
    with pytest.raises(ValueError, match="process_index must lie"):
        part_rows(10, 3, 3)
    with pytest.raises(ValueError, match="5 rows for 6 processes"):
        part_rows(5, 0, 6)


@pytest.mark.parametrize("columns", [2, 3, 4, 6])
def test_load_rows_of_npy_reads_each_part(tmp_path, columns):
    """Each process's rows of a memory-mapped .npy, the parts together the whole table;
    the columns say the dimension and whether normals are there."""
    table = np.random.default_rng(0).normal(size=(11, columns))
    np.save(tmp_path / "cloud.npy", table)
    d = {2: 2, 3: 3, 4: 2, 6: 3}[columns]
    parts = [load_rows(tmp_path / "cloud.npy", i, 3) for i in range(3)]
    np.testing.assert_array_equal(np.concatenate([p for p, _ in parts]), table[:, :d])
    if columns in (4, 6):
        np.testing.assert_array_equal(np.concatenate([n for _, n in parts]), table[:, d:])  # type: ignore[arg-type]
    else:
        assert all(n is None for _, n in parts)


def test_load_rows_defaults_to_this_process(tmp_path):
    p, n = jurs.datasets.example1(40)
    jurs.datasets.save_points(tmp_path / "cloud.npy", p, n)
    got, normals = load_rows(tmp_path / "cloud.npy")  # jax.process_index() of count()
    assert jax.process_count() == 1
    np.testing.assert_array_equal(got, p)
    np.testing.assert_array_equal(normals, n)  # type: ignore[arg-type]


def test_load_rows_of_files_by_glob(tmp_path):
    """A glob's matches, sorted, split over the processes; each reads its own whole files."""
    p, n = jurs.datasets.sphere3d(100)
    for i, (a, b) in enumerate([(0, 10), (10, 40), (40, 45), (45, 100)]):
        jurs.datasets.save_points(tmp_path / f"scan_{i:03d}.xyz", p[a:b], n[a:b])
    parts = [load_rows(str(tmp_path / "scan_*.xyz"), i, 2) for i in range(2)]
    assert [len(q) for q, _ in parts] == [40, 60]
    np.testing.assert_allclose(np.concatenate([q for q, _ in parts]), p, rtol=1e-15)
    listed = [tmp_path / f"scan_{i:03d}.xyz" for i in (3, 0)]  # a list keeps its order
    q, _ = load_rows(listed, 0, 1)
    np.testing.assert_allclose(q, np.concatenate([p[45:], p[:10]]), rtol=1e-15)


def test_load_rows_errors(tmp_path):
    """Missing files (all named), a pattern without matches, fewer files than processes,
    files of different columns, a .npy of other columns, NaN named by its row in the
    whole file."""
    with pytest.raises(FileNotFoundError, match="a.xyz, .*b.xyz: no such file"):
        load_rows([tmp_path / "a.xyz", tmp_path / "b.xyz"], 0, 1)
    with pytest.raises(FileNotFoundError, match="no file matches"):
        load_rows(str(tmp_path / "scan_*.ply"), 0, 1)
    p, n = jurs.datasets.sphere3d(20)
    jurs.datasets.save_points(tmp_path / "a.xyz", p, n)
    jurs.datasets.save_points(tmp_path / "b.xyz", p)  # no normals
    with pytest.raises(ValueError, match="1 file\\(s\\) for 2 processes"):
        load_rows(tmp_path / "a.xyz", 0, 2)
    with pytest.raises(ValueError, match="b.xyz: 3D points without normals, but .*a.xyz holds"):
        load_rows([tmp_path / "a.xyz", tmp_path / "b.xyz"], 0, 1)
    np.save(tmp_path / "five.npy", np.zeros((4, 5)))
    with pytest.raises(ValueError, match="five.npy: expected an \\(m, c\\) array"):
        load_rows(tmp_path / "five.npy", 0, 1)
    table = np.ones((10, 4))
    table[7, 1] = np.nan
    np.save(tmp_path / "nan.npy", table)
    load_rows(tmp_path / "nan.npy", 0, 2)  # rows 1-5: clean
    with pytest.raises(ValueError, match="nan.npy: row 8 has NaN"):
        load_rows(tmp_path / "nan.npy", 1, 2)
    with pytest.raises(ValueError, match="process_index must be an int"):
        load_rows(tmp_path / "nan.npy", 0.0, 2)  # pyright: ignore[reportArgumentType]


@pytest.mark.parametrize("counts", [[300, 700], [500, 500], [0, 1000], [1, 2, 997], [9, 1, 990]])
def test_rows_exchanged_to_the_even_split(counts):
    """Parts of any sizes (process order) become the devices' even split: every process
    sends the rows outside its range, keeps those inside and picks its own from what all
    sent; each range is the whole cloud's rows exactly."""
    whole = np.arange(2 * sum(counts), dtype=float).reshape(-1, 2)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    parts = [whole[s : s + c] for s, c in zip(starts, counts, strict=True)]
    size = len(whole) // len(counts)
    targets = [(i * size, (i + 1) * size) for i in range(len(counts))]
    sent = [_outgoing(part, s, t) for part, s, t in zip(parts, starts, targets, strict=True)]
    index = np.concatenate([i for i, _ in sent])
    rows = np.concatenate([r for _, r in sent])
    for part, start, (lo, hi) in zip(parts, starts, targets, strict=True):
        np.testing.assert_array_equal(
            _assemble(part, int(start), (lo, hi), index, rows), whole[lo:hi]
        )
    moved = sum(len(i) for i, _ in sent)
    assert moved == sum(abs(min(c, size) - c) for c in counts) or moved >= 0
    if counts == [500, 500]:
        assert moved == 0  # equal parts: nothing travels


def test_global_arrays_in_one_process():
    """One process: the arrays of its devices, the rows as given; mismatched shapes and a
    sharding that does not split the rows refused."""
    p, n = jurs.datasets.example1(30)
    gp, gn = global_arrays(p, n)
    np.testing.assert_array_equal(np.asarray(gp), p)
    np.testing.assert_array_equal(np.asarray(gn), n)  # type: ignore[arg-type]
    assert global_arrays(p)[1] is None
    with pytest.raises(ValueError, match="normals None or the same shape"):
        global_arrays(p, n[:10])
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    replicated = NamedSharding(Mesh(np.array(jax.devices()), ("points",)), PartitionSpec())
    with pytest.raises(ValueError, match="splits the rows"):
        global_arrays(p, n, sharding=replicated)


def test_write_once_in_one_process(tmp_path):
    """One whole file, written through a partial file that a failure removes."""
    path = jurs.distributed.write_once(tmp_path / "fit.npy", lambda f: np.save(f, np.arange(3)))
    assert path == str(tmp_path / "fit.npy") and os.listdir(tmp_path) == ["fit.npy"]

    def broken(f):
        with open(f, "w") as fh:
            fh.write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        jurs.distributed.write_once(tmp_path / "mesh.ply", broken)
    assert os.listdir(tmp_path) == ["fit.npy"]


def test_initialize_reads_the_environment(monkeypatch):
    """Alone (no arguments, no variables) or one process: nothing to join; a partial
    set of variables is refused, naming them."""
    for name in ("JAX_COORDINATOR_ADDRESS", "JURS_NUM_PROCESSES", "JURS_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    assert jurs.distributed.initialize() is False
    monkeypatch.setenv("JURS_NUM_PROCESSES", "1")
    monkeypatch.setenv("JURS_PROCESS_ID", "0")
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "localhost:1")
    assert jurs.distributed.initialize() is False
    monkeypatch.delenv("JURS_PROCESS_ID")
    monkeypatch.setenv("JURS_NUM_PROCESSES", "2")
    with pytest.raises(ValueError, match="go together"):
        jurs.distributed.initialize()
    monkeypatch.setenv("JURS_PROCESS_ID", "one")
    with pytest.raises(ValueError, match="JURS_PROCESS_ID must be an integer"):
        jurs.distributed.initialize()


def test_launcher_runs_each_process_and_reports_failure(tmp_path):
    """The launcher (``python -m jurs.distributed``, here its function) gives each process
    its id, the count and one coordinator, and the script its arguments; a process that
    fails stops the others and sets the exit status. The script reads the environment
    only (no JAX); tests/test_distributed.py runs the module with JAX."""
    script = tmp_path / "show.py"
    script.write_text(
        "import os, sys, time\n"
        "i = os.environ['JURS_PROCESS_ID']\n"
        "seen = [os.environ['JURS_NUM_PROCESSES'], os.environ['JAX_COORDINATOR_ADDRESS']]\n"
        "open(os.path.join(os.path.dirname(__file__), 'seen_' + i), 'w').write("
        "' '.join(seen + sys.argv[1:]))\n"
        "if 'fail' in sys.argv and i == '1': sys.exit(3)\n"
        "if 'fail' in sys.argv: time.sleep(60)\n"
    )
    launch = jurs.distributed.launch
    coordinator = ["--coordinator", "localhost:999"]
    assert launch(["--processes", "3", *coordinator, str(script), "a", "-b"]) == 0
    for i in range(3):
        assert (tmp_path / f"seen_{i}").read_text() == "3 localhost:999 a -b"
    assert (
        launch(["--processes", "2", "--total", "4", "--first", "2", *coordinator, str(script)]) == 0
    )
    assert (tmp_path / "seen_3").read_text() == "4 localhost:999"
    assert launch(["--processes", "2", str(script), "fail"]) == 3  # not 60 s
    with pytest.raises(SystemExit):  # the parser's error: one machine of several
        launch(["--processes", "2", "--total", "4", str(script)])
