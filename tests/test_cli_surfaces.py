"""``jurs fit`` on 3D clouds: a surface's outputs, its spline file, bad inputs, the preview."""

import jax

jax.config.update("jax_enable_x64", True)

import io  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jurs  # noqa: E402
from jurs import cli, levelset, plot  # noqa: E402

# A coarse grid keeps each fit about a second once compiled; every fit here has the same
# cloud size and grid, so they share one compilation. (On finer grids the fit of this
# cloud currently grows a bubble inside the sphere, which the checks below would flag.)
FIT_ARGS = ["--grid", "12", "-q"]


@pytest.fixture(autouse=True)
def no_compilation_cache(monkeypatch):
    """cli.main would turn JAX's persistent compilation cache on for the rest of the test
    process, where other tests count compilations."""
    monkeypatch.setenv("JURS_NO_COMPILATION_CACHE", "1")


@pytest.fixture(scope="module")
def sphere():
    return jurs.datasets.sphere3d(1500)


@pytest.fixture(scope="module")
def sphere_files(sphere, tmp_path_factory):
    """The unit sphere's cloud as PLY with normals and as XYZ without."""
    folder = tmp_path_factory.mktemp("clouds")
    jurs.datasets.save_points(folder / "sphere.ply", *sphere)
    jurs.datasets.save_points(folder / "sphere.xyz", sphere[0])
    return folder / "sphere.ply", folder / "sphere.xyz"


def _check_sphere_mesh(out):
    """mesh.ply is one closed genus-0 component on the unit sphere; metrics.json says so."""
    vertices, faces = jurs.datasets.load_mesh(out / "mesh.ply")
    report = levelset.analyze_mesh(vertices, faces)
    assert report.num_components == 1
    assert report.components[0].closed and report.components[0].genus == 0
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 0.05
    record = json.loads((out / "metrics.json").read_text())
    m = record["metrics"]
    assert (m["num_components"], m["num_closed"], m["num_supplementary"]) == (1, 1, 0)
    assert m["genera"] == [0] and m["chamfer"] < 0.05 and m["hausdorff"] < 0.2
    assert record["mesh"]["num_faces"] == len(faces)
    assert record["mesh"]["components"][0]["closed"] is True
    return record


@pytest.mark.slow
def test_surface_from_ply_with_normals(sphere, sphere_files, tmp_path):
    out = tmp_path / "result"
    assert cli.main(["fit", str(sphere_files[0]), "-o", str(out), *FIT_ARGS]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS_3D)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".jurs-")]
    record = _check_sphere_mesh(out)
    assert record["normals"] == "given" and record["num_points"] == len(sphere[0])
    assert record["settings"]["grid"] == [12, 12, 12]
    assert record["metrics"]["converged"] is True
    assert set(record["timings"]) == {"fit_s", "mesh_s", "analysis_s"}
    assert (out / "preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # spline.npz holds the fit jurs.fit gives with the same settings, as a 3D spline (of
    # the cloud as read).
    spline = jurs.load_spline(out / "spline.npz")
    assert isinstance(spline, jurs.ImplicitSpline) and spline.shape == (12, 12, 12)
    direct = jurs.fit(*jurs.datasets.load_points(sphere_files[0]), grid=12).spline
    xyz = np.random.default_rng(1).uniform(-1.2, 1.2, (200, 3))
    np.testing.assert_allclose(np.asarray(spline(xyz)), np.asarray(direct(xyz)), rtol=0, atol=1e-9)
    assert float(spline(np.zeros(3))) < 0  # inside: the normals point out
    jurs.save_spline(tmp_path / "again.npz", spline)
    back = jurs.load_spline(tmp_path / "again.npz")
    np.testing.assert_array_equal(np.asarray(back(xyz)), np.asarray(spline(xyz)))


def test_surface_from_xyz_without_normals(sphere_files, tmp_path):
    out = tmp_path / "result"
    assert (
        cli.main(["fit", str(sphere_files[1]), "-o", str(out), *FIT_ARGS, "--resolution", "40"])
        == 0
    )
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS_3D)
    record = _check_sphere_mesh(out)
    assert record["normals"] == "estimated" and record["mesh"]["resolution"] == 40
    assert float(jurs.load_spline(out / "spline.npz")(np.zeros(3))) < 0


def test_surface_from_3d_tables_into_a_curve_fits_folder(sphere, tmp_path, capsys):
    """A CSV of columns x, y, z was refused ("expected 4 columns x, y, nx, ny, got 3"): it
    is a 3D cloud, fitted as a surface, as a 6-column .npy of points and normals is. And
    fitted into a folder that holds a curve fit's outputs, it leaves only its own."""
    out = tmp_path / "out"
    curve = tmp_path / "ring.csv"
    jurs.datasets.save_points(curve, *jurs.datasets.example1(120))
    curve_args = ["--solver", "lstsq", "--lam", "1e-4", "--grid", "8", "--resolution", "64"]
    assert cli.main(["fit", str(curve), "-o", str(out), *curve_args, "-q"]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS)

    path = tmp_path / "sphere.csv"
    np.savetxt(path, sphere[0], delimiter=",", header="x,y,z", comments="", fmt="%.17g")
    assert cli.main(["fit", str(path), "-o", str(out), *FIT_ARGS, "--resolution", "40"]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS_3D)  # fit.png, zero_level.csv gone
    record = _check_sphere_mesh(out)
    assert record["normals"] == "estimated" and record["num_points"] == len(sphere[0])

    npy = tmp_path / "sphere.npy"
    np.save(npy, np.concatenate(sphere, axis=1))
    out = tmp_path / "npy"
    assert cli.main(["fit", str(npy), "-o", str(out), *FIT_ARGS, "--resolution", "40"]) == 0
    assert _check_sphere_mesh(out)["normals"] == "given"
    assert capsys.readouterr().err == ""


BAD_XYZ = {
    "extra_column": ("1 0 0\n0 1 0\n0 0 1 5\n-1 0 0\n", "row 3"),
    "not_a_number": ("1 0 0\n0 x 0\n0 0 1\n-1 0 0\n", "row 2"),
    "two_columns": ("1 0\n0 1\n-1 0\n", "expected 3 columns"),
    "zero_normal": ("1 0 0 1 0 0\n0 1 0 0 0 0\n0 0 1 0 0 1\n", "zero-length normal"),
    "nan": ("# a comment\n1 0 0\n0 nan 0\n0 0 1\n", "row 3"),
}


def _refused(capsys, args, out, needle):
    """Exit code 2, one line on stderr naming the file and ``needle``, nothing written."""
    assert cli.main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and args[1] in lines[0] and needle in lines[0], lines
    assert not out.exists()
    assert not [p for p in os.listdir(out.parent) if p.startswith(".jurs-")]


@pytest.mark.parametrize("kind", sorted(BAD_XYZ))
def test_malformed_xyz_files(kind, tmp_path, capsys):
    text, needle = BAD_XYZ[kind]
    path = tmp_path / f"{kind}.xyz"
    path.write_text(text)
    out = tmp_path / "out"
    _refused(capsys, ["fit", str(path), "-o", str(out), *FIT_ARGS], out, needle)


def test_malformed_ply_file(tmp_path, capsys):
    path = tmp_path / "broken.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nend_header\n")
    out = tmp_path / "out"
    _refused(capsys, ["fit", str(path), "-o", str(out)], out, "not a readable PLY file")


def test_options_of_the_other_dimension(sphere_files, tmp_path, capsys):
    """A 2D grid on a 3D cloud, and a 3D grid on a 2D one, are refused before the fit."""
    out = tmp_path / "out"
    _refused(
        capsys,
        ["fit", str(sphere_files[0]), "-o", str(out), "--grid", "12x12"],
        out,
        "--grid 12x12 is for a 2D cloud; this cloud is 3D",
    )
    curve = tmp_path / "curve.csv"
    jurs.datasets.save_points(curve, *jurs.datasets.example1(60))
    _refused(
        capsys,
        ["fit", str(curve), "-o", str(out), "--grid", "9x9x9"],
        out,
        "--grid 9x9x9 is for a 3D cloud; this cloud is 2D",
    )
    with pytest.raises(SystemExit):  # argparse: more than three numbers
        cli.main(["fit", str(sphere_files[0]), "-o", str(out), "--grid", "8x8x8x8"])
    assert not out.exists()
    capsys.readouterr()  # argparse's usage
    _refused(
        capsys,
        ["fit", str(curve), "-o", str(out), "--faces", "500"],
        out,
        "--faces sets the face budget of a surface's mesh; this cloud is 2D",
    )
    for bad in ("3", "1e3", "many"):  # argparse: an integer >= 4
        with pytest.raises(SystemExit):
            cli.main(["fit", str(sphere_files[0]), "-o", str(out), "--faces", bad])
    assert not out.exists()


def test_surface_with_a_face_budget(sphere_files, tmp_path):
    """--faces N: mesh.ply decimated to N faces, still the closed sphere; metrics.json
    records the budget."""
    out = tmp_path / "result"
    args = ["fit", str(sphere_files[0]), "-o", str(out), *FIT_ARGS, "--faces", "1000"]
    assert cli.main(args) == 0
    record = _check_sphere_mesh(out)
    assert 999 <= record["mesh"]["num_faces"] <= 1000
    assert record["mesh"]["face_budget"] == 1000


def test_spline_files_3d(tmp_path):
    """3D spline files load as 3D splines; bad ones name the file and the problem."""
    good = dict(
        control=np.zeros((5, 6, 7)),
        weights=np.ones((5, 6, 7)),
        lower=np.zeros(3),
        upper=np.array([1.0, 2.0, 3.0]),
    )
    np.savez(tmp_path / "good.npz", **good)
    spline = jurs.load_spline(tmp_path / "good.npz")
    assert spline.ndim == 3 and spline.shape == (5, 6, 7)
    for change, needle in (
        (dict(lower=np.zeros(2)), "shape (3,) for a 3D grid"),
        (dict(weights=np.ones((5, 6, 6))), "matching 2D or 3D grids"),
        (dict(control=np.zeros((3, 6, 7)), weights=np.ones((3, 6, 7))), "at least 4 x 4 x 4"),
        (dict(upper=np.array([1.0, 0.0, 3.0])), "every axis"),
        (dict(weights=-np.ones((5, 6, 7))), "weights must all be positive"),
        (dict(control=np.full((5, 6, 7), np.inf)), "control contain NaN"),
    ):
        path = tmp_path / "bad.npz"
        np.savez(path, **{**good, **change})
        with pytest.raises(ValueError) as info:
            jurs.load_spline(path)
        assert str(path) in str(info.value) and needle in str(info.value), str(info.value)


def test_plot_mesh_decimates_and_highlights():
    trimesh = pytest.importorskip("trimesh")
    ball = trimesh.creation.icosphere(subdivisions=4)  # 5120 faces
    vertices, faces = np.asarray(ball.vertices), np.asarray(ball.faces)
    v, f, flags, normals = plot.decimate_mesh(vertices, faces, 1000, np.arange(len(faces)) < 100)
    assert 0 < len(f) <= 1000 and flags.dtype == bool and len(flags) == len(f)
    assert np.abs(np.linalg.norm(v, axis=1) - 1).max() < 0.05  # still the sphere
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    assert np.mean(np.sum(normals * v[f].mean(axis=1), axis=1) > 0.9) > 0.99  # outward
    fig = plot.plot_mesh(vertices, faces, highlight=np.arange(10), max_faces=2000, title="t")
    assert len(fig.axes) == 3 and len(fig.legends) == 1
    fig.savefig(io.BytesIO(), format="png", dpi=40)  # mplot3d draws only when saving
    plt.close(fig)
    fig = plot.plot_mesh(np.empty((0, 3)), np.empty((0, 3), dtype=np.int64), views=[(0, 0)])
    assert len(fig.axes) == 1
    plt.close(fig)
    with pytest.raises(ValueError, match="3D Axes"):
        plot.plot_mesh(vertices, faces, ax=plt.figure().add_subplot())
    plt.close("all")


def test_surface_far_from_the_origin_into_a_curve_fits_folder(sphere, tmp_path, capsys):
    """A sphere 1e7 from the origin: mesh.ply was float32, off by the float32 spacing
    there (about 1, half the sphere) while metrics.json said the fit was close. And a
    surface fit into a folder that held a curve fit left fit.png and zero_level.csv."""
    centre = np.array([1e7, -2e7, 3e7])
    path = tmp_path / "far.xyz"
    jurs.datasets.save_points(path, sphere[0] + centre, sphere[1])
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text(json.dumps({"input": "c.csv", "settings": {}, "metrics": {}}))
    for name in ("spline.npz", "fit.png", "zero_level.csv"):
        (out / name).write_text("old")
    assert cli.main(["fit", str(path), "-o", str(out), *FIT_ARGS]) == 0
    assert sorted(os.listdir(out)) == sorted(cli.OUTPUTS_3D)
    record = json.loads((out / "metrics.json").read_text())
    vertices, _ = jurs.datasets.load_mesh(out / "mesh.ply")
    off = np.abs(np.linalg.norm(vertices - centre, axis=1) - 1.0)
    # The mesh file is as close to the data as metrics.json says the mesh is.
    assert off.max() < max(2 * record["metrics"]["hausdorff"], 0.05)


def test_mesh_file_input_notes_the_sampling(tmp_path, capsys):
    """A mesh file given to ``jurs fit`` is read as points drawn on its faces, said in a
    ``jurs: note:`` line; a binary STL died on a UTF-8 decode error."""
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "ball.stl"
    trimesh.creation.icosphere(2).export(path)
    points, normals = cli.read_input(str(path))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jurs: note: {path}: a triangle mesh"), err
    assert len(points) == jurs.datasets.MESH_SAMPLES and normals is not None
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=0.05)
    bad = tmp_path / "bad.ply"
    bad.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    out = tmp_path / "o"
    _refused(capsys, ["fit", str(bad), "-o", str(out)], out, "declares 4 rows")


def test_open_scan_trimmed_on_the_command_line(sphere, tmp_path, capsys):
    """The upper half of a sphere, an open scan: --trim writes an open mesh.ply with one
    boundary loop near the rim, and metrics.json records the trim and the loop. (As many
    points as ``sphere``: the fits share one compilation.)"""
    points, normals = jurs.datasets.sphere3d(3400, seed=2)
    upper = np.flatnonzero(points[:, 2] > 0)[: len(sphere[0])]
    assert len(upper) == len(sphere[0])
    path = tmp_path / "half.ply"
    jurs.datasets.save_points(path, points[upper], normals[upper])
    out = tmp_path / "result"
    assert cli.main(["fit", str(path), "-o", str(out), "--grid", "12", "--trim"]) == 0
    said = capsys.readouterr()
    said_trim = "trimmed to 2.5 point spacings amid the data, 1 past its rim: 1 boundary loop(s)"
    assert said_trim in said.out
    assert "unsupported" not in said.err
    vertices, faces = jurs.datasets.load_mesh(out / "mesh.ply")
    report = levelset.analyze_mesh(vertices, faces, points[upper])
    assert report.num_boundary_loops == 1 and not report.components[0].closed
    assert -0.4 < vertices[:, 2].min() < 0  # stops a few spacings past the rim at z = 0
    m = json.loads((out / "metrics.json").read_text())["metrics"]
    assert m["trim"] == levelset.DEFAULT_TRIM and m["rim"] == levelset.DEFAULT_RIM
    # --rim as large as the trim: the distance alone, which runs on farther past the rim.
    wide = tmp_path / "wide"
    args = ["fit", str(path), "-o", str(wide), "--grid", "12", "--trim", "--rim", "2.5", "-q"]
    assert cli.main(args) == 0
    assert json.loads((wide / "metrics.json").read_text())["metrics"]["rim"] == 2.5
    further, _ = jurs.datasets.load_mesh(wide / "mesh.ply")
    assert further[:, 2].min() < vertices[:, 2].min()
    capsys.readouterr()
    assert cli.main(["fit", str(path), "-o", str(tmp_path / "x"), "--rim", "1"]) == 2
    assert "add --trim" in capsys.readouterr().err and not (tmp_path / "x").exists()
    assert m["num_boundary_loops"] == 1 and m["boundary_loops"] == [1]
    assert m["boundary_length"] == pytest.approx(report.boundary_length)
    assert m["num_closed"] == 0 and m["genera"] == [None]


@pytest.mark.slow  # a surface fit by CG and its band mesh: about 10 s
def test_adaptive_surface_fit_is_band_meshed(sphere_files, tmp_path):
    """``jurs fit --adaptive`` on a 3D cloud: the band mesh chooses its resolution
    (recorded as None) and the sphere comes back closed, of genus 0, near the unit
    sphere."""
    out = tmp_path / "out"
    assert cli.main(["fit", str(sphere_files[0]), "-o", str(out), "--adaptive", "-q"]) == 0
    record = json.loads((out / "metrics.json").read_text())
    assert record["settings"]["basis"] == "adaptive" and record["mesh"]["resolution"] is None
    assert record["metrics"]["num_components"] == 1
    assert record["mesh"]["components"][0]["genus"] == 0
    vertices, _ = jurs.datasets.load_mesh(out / "mesh.ply")
    assert np.abs(np.linalg.norm(vertices, axis=1) - 1.0).max() < 0.05
    assert isinstance(jurs.load_spline(out / "spline.npz"), jurs.AdaptiveSpline)
