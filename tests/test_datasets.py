"""Built-in curves, noise, and reading points from files."""

import pathlib

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
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


def test_thin_plate_has_two_faces_and_a_rim():
    points, normals = datasets.thin_plate(step=0.25, thickness=0.1)
    side = np.sign(normals[:, 2])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    np.testing.assert_allclose(points[side > 0, 2], 0.05)
    np.testing.assert_allclose(points[side < 0, 2], -0.05)
    assert (side > 0).sum() == (side < 0).sum() == 81  # a 9 x 9 grid a face
    rim = points[side == 0]
    assert len(rim) == 4 * 7 and np.allclose(rim[:, 2], 0.0)
    # Each rim point faces out of the side it lies on.
    on = np.abs(rim[:, :2]) == 1.0
    np.testing.assert_allclose(normals[side == 0][:, :2][on], rim[:, :2][on])
    for bad in (dict(step=0.0), dict(step=2.0), dict(step=0.3), dict(thickness=-1.0)):
        with pytest.raises(ValueError):
            datasets.thin_plate(**bad)


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
        ("a,b,c,d\n0,0,1,0\n", r"row 1: header a, b, c, d is not one of x,y \| x,y,z"),
        ("0,0,1,0,1\n", r"row 1: expected 2 \(x y\), 3 \(x y z\), 4 .* columns, got 5"),
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
    np.save(path, np.ones((5, 5)))
    with pytest.raises(ValueError, match=r"expected an \(m, c\) table .* got shape \(5, 5\)"):
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


def _table_text(columns, header):
    """A table of the unit sphere's 40 points (3D) or the unit circle's (2D) with
    ``columns`` columns, and the header naming them where ``header``."""
    names = datasets.TABLE_COLUMNS[columns]
    if "z" in names:
        points, normals = datasets.sphere3d(40)
    else:
        t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
        points = normals = np.stack([np.cos(t), np.sin(t)], axis=1)
    table = np.concatenate([points, normals], axis=1)[:, :columns]
    rows = "\n".join(",".join(f"{v:.17g}" for v in row) for row in table)
    return ((",".join(names) + "\n") if header else "") + rows + "\n", points, normals


@pytest.mark.parametrize("header", [True, False])
@pytest.mark.parametrize("columns", [2, 3, 4, 6])
def test_table_columns_decide_the_dimension(tmp_path, columns, header):
    """A CSV of x, y, z was refused ("expected 4 columns x, y, nx, ny, got 3"): 2 and 4
    columns are 2D points (without and with normals), 3 and 6 3D ones, read from a header
    naming them or, without one, from their number. The same for .npy and for text
    separated by spaces."""
    text, points, normals = _table_text(columns, header)
    with_normals = columns in (4, 6)
    csv = tmp_path / "cloud.csv"
    csv.write_text(text)
    txt = tmp_path / "cloud.txt"
    txt.write_text(text.replace(",", " "))
    npy = tmp_path / "cloud.npy"
    np.save(npy, np.loadtxt(csv, delimiter=",", skiprows=int(header), ndmin=2))
    for path in (csv, txt, npy):
        p, n = datasets.load_points(path)
        np.testing.assert_array_equal(p, points)
        if with_normals:
            assert n is not None
            np.testing.assert_array_equal(n, normals)
        else:
            assert n is None


@pytest.mark.parametrize(
    "text, needles",
    [
        # A header that contradicts the rows: the header's reading and the row's.
        ("x,y,z\n0,0,1,0\n", ["row 2: expected 3 columns x, y, z (3D points)", "x, y, nx, ny"]),
        ("x,y,nx,ny\n0,0,1\n", ["row 2: expected 4 columns x, y, nx, ny", "x, y, z (3D"]),
        # Names of neither set: what the names suggest and what the count reads as.
        (
            "x,y,nx\n0,0,1\n",
            ["header x, y, nx is not one of", "2D points with normals", "x, y, z (3D points)"],
        ),
        ("x,y,z,nz\n0,0,1,1\n", ["names read as 3D points", "x, y, nx, ny (2D points with"]),
    ],
)
def test_ambiguous_tables_name_both_readings(tmp_path, text, needles):
    path = tmp_path / "cloud.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        datasets.load_points(path)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle in message, message


def test_3d_tables_are_checked_as_3d_clouds(tmp_path):
    """A 3D table's rows get the 3D cloud's checks, named by the file's row."""
    path = tmp_path / "cloud.csv"
    path.write_text("x,y,z,nx,ny,nz\n0,0,1,0,0,1\n1,0,0,0,0,0\n")
    with pytest.raises(ValueError, match="row 3 has a zero-length normal"):
        datasets.load_points(path)
    path.write_text("0 0 1\n# a comment\n1 nan 0\n")
    with pytest.raises(ValueError, match="row 3 has NaN or Inf"):
        datasets.load_points(path)


def test_two_column_csv_checks_every_row(tmp_path):
    path = tmp_path / "xy.csv"
    path.write_text("x,y\n0,0\n1,1,0\n")
    with pytest.raises(ValueError, match=r"row 3: expected 2 columns x, y .*, got 3"):
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


# --- 3D files: meshes read as meshes ------------------------------------------------------

trimesh = pytest.importorskip("trimesh")


def _box(inward=False):
    """A closed box from trimesh (outward winding), or wound inward."""
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    faces = box.faces[:, ::-1] if inward else box.faces
    return np.asarray(box.vertices, float), np.asarray(faces)


def _on_faces(points, vertices, faces, tol):
    """Whether each point lies on one of the triangles (within ``tol``): in its plane
    and inside its edges (barycentric coordinates >= -tol)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):  # faces without area: never inside
        return _on_faces_of(points, a, b, c, tol)


def _on_faces_of(points, a, b, c, tol):
    e1, e2, d = b - a, c - a, points[:, None, :] - a[None]
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    height = np.abs(np.einsum("pfk,fk->pf", d, n)) / area2
    # Barycentric coordinates from the Gram system of the two edges.
    g11, g12, g22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    r1, r2 = np.einsum("pfk,fk->pf", d, e1), np.einsum("pfk,fk->pf", d, e2)
    det = g11 * g22 - g12**2
    s, t = (g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det
    scale = np.sqrt(area2)
    inside = (s >= -tol / scale) & (t >= -tol / scale) & (s + t <= 1 + tol / scale)
    return ((height <= tol) & inside).any(axis=1)


@pytest.mark.parametrize("kind", ["ply", "ply_ascii", "obj", "stl", "stl_ascii", "off"])
def test_mesh_files_are_read_as_meshes(tmp_path, kind):
    """A mesh file's points are drawn on its faces (not its 8 vertices: a box read as its
    corners fits no box), with the faces' outward normals, seeded, and a note says so."""
    vertices, faces = _box()
    path = tmp_path / f"box.{kind.split('_')[0]}"
    encoding = {"encoding": "ascii"} if kind == "ply_ascii" else {}
    file_type = "stl_ascii" if kind == "stl_ascii" else kind.split("_")[0]
    trimesh.Trimesh(vertices, faces, process=False).export(path, file_type=file_type, **encoding)
    with pytest.warns(UserWarning, match=r"8 vertices, 12 faces.*500 points drawn") as notes:
        points, normals = datasets.load_points(path, mesh_samples=500)
    assert str(path) in str(notes[0].message)
    assert points.shape == normals.shape == (500, 3)
    assert _on_faces(points, vertices, faces, 1e-6).all()
    # Every face gets points (by area: the box's largest faces the most).
    assert np.unique(np.round(normals, 6), axis=0).shape == (6, 3)
    # Outward: each normal points away from the box's centre along its own axis.
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()
    with pytest.warns(UserWarning):
        again, _ = datasets.load_points(path, mesh_samples=500)
    np.testing.assert_array_equal(again, points)


def test_mesh_sample_count(tmp_path):
    """By default a mesh gets MESH_SAMPLES points, or one per vertex where it has more."""
    path = tmp_path / "box.obj"
    datasets.save_mesh(path, *_box())
    with pytest.warns(UserWarning, match=f"{datasets.MESH_SAMPLES} points"):
        points, _ = datasets.load_points(path)
    assert len(points) == datasets.MESH_SAMPLES
    fine = trimesh.creation.icosphere(subdivisions=6)  # 40962 vertices
    datasets.save_mesh(path, fine.vertices, fine.faces)
    with pytest.warns(UserWarning, match="40962 vertices"):
        points, _ = datasets.load_points(path)
    assert len(points) == len(fine.vertices) > datasets.MESH_SAMPLES
    with pytest.raises(ValueError, match="mesh_samples must be a positive int"):
        datasets.load_points(path, mesh_samples=0)


def test_closed_mesh_wound_inward_gets_outward_normals(tmp_path):
    path = tmp_path / "inward.ply"
    datasets.save_mesh(path, *_box(inward=True))
    with pytest.warns(UserWarning, match="outward"):
        points, normals = datasets.load_points(path, mesh_samples=200)
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()


@pytest.mark.parametrize("first_inward", [False, True])
def test_closed_mesh_wound_both_ways_is_rewound(tmp_path, first_inward):
    """A closed box whose faces are wound half one way, half the other, was read as an
    open mesh with its faces' normals pointing both ways, and its fit refused. Its
    windings are made consistent, then outward."""
    vertices, faces = _box(inward=first_inward)
    faces = faces.copy()
    faces[1::2] = faces[1::2, ::-1]
    path = tmp_path / "mixed.ply"
    datasets.save_mesh(path, vertices, faces)
    with pytest.warns(UserWarning, match="outward .*re-wound"):
        points, normals = datasets.load_points(path, mesh_samples=300)
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()


def test_open_mesh_says_its_normals_follow_the_winding(tmp_path):
    vertices, faces = _box()
    path = tmp_path / "open.obj"
    datasets.save_mesh(path, vertices, faces[2:])
    with pytest.warns(UserWarning, match="not closed"):
        datasets.load_points(path, mesh_samples=50)


def _ascii_ply(vertices, faces=None):
    header = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}"]
    header += [f"property float {a}" for a in "xyz"]
    body = [" ".join(map(str, v)) for v in vertices]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        body += ["3 " + " ".join(map(str, f)) for f in faces]
    return "\n".join(header + ["end_header"] + body) + "\n"


@pytest.mark.parametrize("mesh", [False, True])
@pytest.mark.parametrize("drop, said", [(2, "cut short"), (-1, "longer than its header")])
def test_ascii_ply_body_must_match_its_header(tmp_path, mesh, drop, said):
    """An ASCII PLY with fewer rows than its header declares was read without a word
    (trimesh reads what is there)."""
    vertices, faces = _box()
    text = _ascii_ply(vertices, faces if mesh else None)
    lines = text.splitlines()
    lines = lines[:-drop] if drop > 0 else lines + lines[-1:]
    path = tmp_path / "cut.ply"
    path.write_text("\n".join(lines) + "\n")
    declared = 20 if mesh else 8
    rows = declared - drop
    with pytest.raises(ValueError, match=f"declares {declared} rows .*the body has {rows}.*{said}"):
        datasets.load_points(path)


def test_binary_stl_and_binary_text_files(tmp_path):
    """A binary STL was read as CSV text and died on a UTF-8 decode error; a binary file
    under a text suffix is refused naming the file."""
    path = tmp_path / "part.stl"
    trimesh.Trimesh(*_box(), process=False).export(path)
    with pytest.raises(UnicodeDecodeError):  # what the text reader met before
        path.read_text(encoding="utf-8")
    with pytest.warns(UserWarning, match="triangle mesh"):
        points, normals = datasets.load_points(path, mesh_samples=100)
    assert points.shape == normals.shape == (100, 3)
    for name in ("part.csv", "part.xyz"):
        (tmp_path / name).write_bytes(b"\x80\x81binary\xff" * 10)
        with pytest.raises(ValueError, match="not a text file") as info:
            datasets.load_points(tmp_path / name)
        assert name in str(info.value)


@pytest.mark.parametrize("mesh", [False, True])
def test_float32_far_from_the_origin_is_refused_naming_the_precision(tmp_path, mesh):
    """Float32 coordinates 1e7 from the origin collapse a unit sphere onto a few points;
    the error blamed coincident points (later, in the fit), not the file's precision."""
    points, normals = datasets.sphere3d(300)
    far = points + 1e7
    path = tmp_path / "far.ply"
    if mesh:
        sphere = trimesh.creation.icosphere(2)
        data = trimesh.exchange.ply.export_ply(
            trimesh.Trimesh(sphere.vertices + 1e7, sphere.faces, process=False)
        )
    else:
        data = trimesh.exchange.ply.export_ply(
            trimesh.Trimesh(far, np.empty((0, 3), int), vertex_normals=normals, process=False),
            vertex_normal=True,
        )
    path.write_bytes(data)  # trimesh writes float32
    with pytest.raises(ValueError, match="float32") as info:
        datasets.load_points(path)
    assert str(path) in str(info.value) and "distinct" in str(info.value)
    # The same cloud near the origin, and far off in float64, are read as given.
    datasets.save_points(path, far, normals)
    np.testing.assert_array_equal(datasets.load_points(path)[0], far)


def test_a_file_that_is_neither_cloud_nor_mesh(tmp_path):
    path = tmp_path / "empty.ply"
    path.write_text(_ascii_ply(np.empty((0, 3))))
    with pytest.raises(ValueError, match="neither a point cloud nor a triangle mesh") as info:
        datasets.load_points(path)
    assert str(path) in str(info.value)
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="faces have no area"):
        datasets.load_points(path)


def test_meshes_and_clouds_far_from_the_origin_keep_float64(tmp_path):
    """mesh.ply and cloud PLY files were float32: a sphere 1e7 from the origin came back
    off by the float32 spacing there (about 1)."""
    sphere = trimesh.creation.icosphere(2)
    vertices = np.asarray(sphere.vertices) + [1e7, -3e7, 0.5]
    datasets.save_mesh(tmp_path / "far.ply", vertices, sphere.faces)
    back, faces = datasets.load_mesh(tmp_path / "far.ply")
    np.testing.assert_array_equal(back, vertices)
    np.testing.assert_array_equal(faces, sphere.faces)
    for suffix in (".ply", ".obj", ".off"):
        datasets.save_mesh(tmp_path / f"far{suffix}", vertices, sphere.faces)
        back = datasets.load_mesh(tmp_path / f"far{suffix}")[0]
        np.testing.assert_allclose(back, vertices, rtol=1e-15, atol=1e-12)


# --- property-based: any small mesh file reads as points on its faces ---------------------


@st.composite
def small_meshes(draw):
    """1-6 triangles on 3-8 vertices in [-1, 1]^3, with some area (degenerate faces
    allowed beside others)."""
    count = draw(st.integers(3, 8))
    coordinate = st.floats(-1.0, 1.0, allow_nan=False, width=32)
    vertices = draw(arrays(np.float64, (count, 3), elements=coordinate))
    corners = st.lists(st.integers(0, count - 1), min_size=3, max_size=3, unique=True)
    faces = np.array(draw(st.lists(corners, min_size=1, max_size=6)))
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2
    assume(area > 0.05)
    return vertices, faces


@settings(
    max_examples=25,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(mesh=small_meshes(), kind=st.sampled_from(["ply", "ply_ascii", "obj", "stl", "off"]))
def test_any_small_mesh_file_reads_as_points_on_its_faces(tmp_path_factory, mesh, kind):
    """Written by trimesh in any of its formats, read back: every point lies on a face of
    the mesh, with a unit normal perpendicular to that face."""
    vertices, faces = mesh
    path = tmp_path_factory.mktemp("meshes") / f"mesh.{kind.split('_')[0]}"
    options = {"encoding": "ascii"} if kind == "ply_ascii" else {}
    trimesh.Trimesh(vertices, faces, process=False).export(
        path, file_type=kind.split("_")[0], **options
    )
    with pytest.warns(UserWarning, match="drawn uniformly by area"):
        points, normals = datasets.load_points(path, mesh_samples=40)
    assert points.shape == normals.shape == (40, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-12)
    assert _on_faces(points, vertices, faces, 1e-5).all()
    # Each normal is perpendicular to a face the point lies on.
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    plane = np.cross(b - a, c - a)
    plane /= np.maximum(np.linalg.norm(plane, axis=1, keepdims=True), 1e-300)
    parallel = np.abs(normals @ plane.T) > 1 - 1e-5
    assert parallel.any(axis=1).all()
