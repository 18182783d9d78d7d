"""Built-in curves, noise, and reading points from files."""

import pathlib

import numpy as np
import pytest
from matplotlib.path import Path

from jurs import datasets


@pytest.mark.parametrize("make", [datasets.example1, datasets.ellipse])
def test_curves_have_unit_outward_normals(make):
    points, normals = make(200)
    assert points.shape == normals.shape == (200, 2)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    outline = Path(points)
    assert not outline.contains_points(points + 0.05 * normals).any()
    assert outline.contains_points(points - 0.05 * normals).all()


def test_example1_is_the_papers_curve():
    points, _ = datasets.example1(120)
    t = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    np.testing.assert_allclose(points[:, 0], 4 * np.cos(t))
    np.testing.assert_allclose(points[:, 1], np.sin(t) * (3 - 5 * np.sin(t)))


def test_noise_is_seeded():
    a = datasets.example10(seed=1)
    b = datasets.example10(seed=1)
    c = datasets.example10(seed=2)
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.allclose(a[0], c[0])
    assert a[0].shape == (500, 2) and datasets.example9()[0].shape == (400, 2)
    clean = datasets.ellipse(500)[0]
    assert 0.02 < np.std(a[0] - clean) < 0.08  # sigma = 0.05
    np.testing.assert_allclose(np.linalg.norm(a[1], axis=1), 1.0)
    with pytest.raises(ValueError):
        datasets.add_noise(*datasets.ellipse(10), sigma=-1.0)


@pytest.mark.parametrize("suffix", [".csv", ".npy", ".txt"])
def test_round_trip(tmp_path, suffix):
    points, normals = datasets.example1(25)
    path = tmp_path / f"cloud{suffix}"
    datasets.save_points(path, points, normals)
    p2, n2 = datasets.load_points(path)
    np.testing.assert_allclose(p2, points, rtol=1e-15)
    np.testing.assert_allclose(n2, normals, rtol=1e-15)


def test_whitespace_without_header(tmp_path):
    path = tmp_path / "cloud.txt"
    path.write_text("0 0 0 1\n1 0 1 0\n# a comment\n0 1 -1 0\n")
    points, normals = datasets.load_points(path)
    assert points.shape == (3, 2)


@pytest.mark.parametrize(
    "text, message",
    [
        ("x,y,nx,ny\n0,0,1,0\n1,1,0\n", r"row 3: expected 4 columns"),
        ("x,y,nx,ny\n0,0,1,0\n1,abc,0,1\n", r"row 3: y = 'abc' is not a number"),
        ("x,y,nx,ny\n0,0,1,0\n1,nan,0,1\n", r"row 3 has NaN or Inf"),
        ("x,y,nx,ny\n0,0,0,0\n", r"row 2 has a zero-length normal"),
        ("x,y,nx,ny\n", r"no data rows"),
        ("", r"no data rows"),
        ("a,b,c,d\n0,0,1,0\n", r"row 1: header must be x, y, nx, ny"),
    ],
)
def test_bad_csv(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        datasets.load_points(path)
    assert str(path) in str(info.value)


def test_bad_npy(tmp_path):
    path = tmp_path / "bad.npy"
    np.save(path, np.ones((5, 3)))
    with pytest.raises(ValueError, match=r"expected an \(m, 4\) table .* got shape \(5, 3\)"):
        datasets.load_points(path)
    np.save(path, np.ones(8))
    with pytest.raises(ValueError, match=r"got shape \(8,\)"):
        datasets.load_points(path)
    np.save(path, np.array(["a", "b"]))
    with pytest.raises(ValueError, match="not numeric"):
        datasets.load_points(path)
    with pytest.raises(FileNotFoundError):
        datasets.load_points(tmp_path / "missing.csv")


@pytest.mark.parametrize("suffix", [".csv", ".npy"])
def test_points_without_normals_round_trip(tmp_path, suffix):
    """Two columns (x, y) are points without normals: load_points gives None for them."""
    points, _ = datasets.example1(20)
    path = tmp_path / f"points{suffix}"
    datasets.save_points(path, points)
    loaded, normals = datasets.load_points(path)
    assert normals is None
    np.testing.assert_array_equal(loaded, points)


def test_two_column_csv_checks_every_row(tmp_path):
    path = tmp_path / "xy.csv"
    path.write_text("x,y\n0,0\n1,1,0\n")
    with pytest.raises(ValueError, match=r"row 3: expected 2 columns x, y, got 3"):
        datasets.load_points(path)
    path.write_text("0 0\n1 nan\n2 2\n")
    with pytest.raises(ValueError, match=r"row 2 has NaN or Inf"):
        datasets.load_points(path)


# --- spline files: a format version -------------------------------------------------------

DATA = pathlib.Path(__file__).resolve().parent / "data"


def test_spline_files_carry_a_version(tmp_path):
    """save_spline writes ``format_version``; load_spline reads it back."""
    import jurs
    from jurs._model.io import FORMAT_VERSION, VERSION_KEY

    spline = jurs.load_spline(DATA / "spline_unversioned.npz")
    jurs.save_spline(tmp_path / "s.npz", spline)
    with np.load(tmp_path / "s.npz") as data:
        assert int(data[VERSION_KEY]) == FORMAT_VERSION
    back = jurs.load_spline(tmp_path / "s.npz")
    np.testing.assert_array_equal(np.asarray(back.control), np.asarray(spline.control))


def test_unversioned_spline_files_still_load():
    """A file written by save_spline before the format had a version (tests/data, made by
    that code: the four arrays alone) loads as it did."""
    import jurs

    with np.load(DATA / "spline_unversioned.npz") as data:
        assert sorted(data.files) == ["control", "lower", "upper", "weights"]
        control = data["control"]
    spline = jurs.load_spline(DATA / "spline_unversioned.npz")
    np.testing.assert_array_equal(np.asarray(spline.control), control)
    assert np.isfinite(float(spline(np.zeros(2))))


@pytest.mark.parametrize(
    "extra, needle",
    [
        ({"format_version": np.int64(99)}, r"format version 99; this jurs reads versions 0, 1"),
        ({"format_version": np.float64(1.0)}, "format_version must be one integer"),
        ({"format_version": np.arange(2)}, "format_version must be one integer"),
        ({"format_version": np.int64(1), "offsets": np.ones(3)}, "unexpected arrays"),
        ({"mask": np.ones((6, 6))}, r"unexpected arrays \['mask'\]"),
    ],
)
def test_spline_files_of_other_versions_or_layouts_are_refused(tmp_path, extra, needle):
    """A file of a newer format, or with arrays the format does not have, is refused
    naming the file (it was read as a spline when its four arrays happened to fit)."""
    import jurs

    with np.load(DATA / "spline_unversioned.npz") as data:
        arrays = {k: data[k] for k in data.files}
    path = tmp_path / "other.npz"
    np.savez(path, **arrays, **extra)
    with pytest.raises(ValueError, match=needle) as info:
        jurs.load_spline(path)
    assert str(path) in str(info.value)
