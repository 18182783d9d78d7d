"""The open-scan benchmark's pieces: visibility by ray casting (facing and occlusion), the
true rim count, Poisson's density trim, the scores, the renderer, and one small run."""

import json
import os

import numpy as np
import pytest

from .._common import RESULTS, optional

pytestmark = pytest.mark.skipif(
    optional("open3d") is None or optional("trimesh") is None,
    reason="the open-scan benchmark needs Open3D and trimesh (pip install -e '.[bench]')",
)

from .. import open_scans  # noqa: E402


def icosphere(subdivisions=3, centre=(0.0, 0.0, 0.0)):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(m.vertices) + np.asarray(centre), np.asarray(m.faces)


def test_a_sphere_seen_from_one_viewpoint_shows_the_cap_its_tangents_bound():
    vertices, faces = icosphere(5)
    scanner = open_scans.Scanner(vertices, faces, [(0.0, 0.0, 1.0)])
    c = scanner.viewpoints[0]
    from jurs.datasets import sample_mesh

    x, n = sample_mesh(vertices, faces, 4000, seed=0)
    seen = scanner.visible(x, n)
    cos_cap = 1.0 / np.linalg.norm(c)  # tangent rays from c touch the sphere there
    height = x @ (c / np.linalg.norm(c))
    clear = np.abs(height - cos_cap) > 0.02  # away from the silhouette's facets
    assert np.array_equal(seen[clear], height[clear] > cos_cap)


def test_a_surface_behind_another_is_hidden():
    """A small sphere in front of a large one: the large one's facing side is hidden where
    the small one covers it, so facing the viewpoint is not enough."""
    v1, f1 = icosphere()
    v1 = 0.4 * v1
    v2, f2 = icosphere(centre=(0.0, 0.0, -3.0))
    vertices, faces = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])
    scanner = open_scans.Scanner(vertices, faces, [(0.0, 0.0, 1.0)])
    from jurs.datasets import sample_mesh

    x, n = sample_mesh(v2, f2, 4000, seed=1)
    facing = np.sum(n * (scanner.viewpoints[0] - x), axis=1) > 0
    seen = scanner.visible(x, n)
    off_axis = np.hypot(x[:, 0], x[:, 1])
    behind = facing & (off_axis < 0.3)  # in the small sphere's shadow
    assert behind.sum() > 50 and not seen[behind].any()
    assert seen[facing & (off_axis > 0.6)].all()  # around it, the large one shows


def test_true_rims_close_holes_too_small_to_see():
    vertices, faces = icosphere(4)
    centroids = vertices[faces].mean(axis=1)
    pole = np.argmin(np.linalg.norm(centroids - [0.0, 0.0, 1.0], axis=1))
    upper = centroids[:, 2] > 0
    upper[pole] = False
    part = faces[upper]
    rims, _ = open_scans.true_rims(vertices, faces, part, 0.02, _support_on(vertices, part))
    assert rims["raw_loops"] == 2  # the cap's rim and a one-face pinhole at the pole
    # The rim of whole faces zigzags about the equator: longer than 2 pi, not much.
    assert rims["rims"] == 1 and 2 * np.pi < rims["rim_lengths"][0] < 1.3 * 2 * np.pi


def _support_on(vertices, faces, m=3000):
    from jurs.datasets import sample_mesh
    from jurs.levelset._trimming import Support

    return Support(sample_mesh(vertices, faces, m, seed=0)[0])


def test_each_rim_is_described_and_followed_or_missed():
    """A cap with a hole at its pole: two rims, the hole's depth measured from the
    samples; a mesh that closes the hole misses its rim, the part itself misses none, and
    a stray piece off the part is an extra loop."""
    from .._open_scan_rims import follow_rims

    vertices, faces = icosphere(4)
    centroids = vertices[faces].mean(axis=1)
    hole = np.linalg.norm(centroids - [0.0, 0.0, 1.0], axis=1) < 0.35
    part = faces[(centroids[:, 2] > 0) & ~hole]
    support = _support_on(vertices, part)
    spacing = float(np.median(support.spacing))
    rims, shown = open_scans.true_rims(vertices, faces, part, spacing, support)
    assert rims["rims"] == 2
    rim, pole = rims["rim_details"]
    assert rim["kind"] == "rim" and pole["kind"] == "hole"
    # The hole is 0.35 across its middle: its centre lies about that far from the data.
    assert 0.25 < pole["depth"] * spacing < 0.45 and pole["beyond"] > 0
    assert 1.0 < pole["gap"] * spacing < 1.25  # from the hole (0.36 rad) to the equator
    same = follow_rims(vertices, shown, vertices, part, support, spacing)
    assert same == {"missed": [], "extra": []}
    closed = faces[centroids[:, 2] > 0]
    assert follow_rims(vertices, shown, vertices, closed, support, spacing)["missed"] == [1]
    stray = faces[centroids[:, 2] < -0.9]  # a cap on the far side: no rim of the part
    mesh = np.vstack([part, stray])
    out = follow_rims(vertices, shown, vertices, mesh, support, spacing)
    assert out["missed"] == [] and len(out["extra"]) == 1 and out["extra"][0]["samples"] == 0


def test_a_part_seen_whole_has_one_rim_and_no_hole():
    """A heightfield seen whole: its own border is its one rim, and nothing is unseen."""
    vertices, faces = icosphere(3)
    part = faces[vertices[faces].mean(axis=1)[:, 2] > 0]
    used = np.unique(part)
    index = np.full(len(vertices), -1)
    index[used] = np.arange(len(used))
    vertices, part = vertices[used], index[part]  # the cap alone: every face seen
    support = _support_on(vertices, part)
    spacing = float(np.median(support.spacing))
    rims, shown = open_scans.true_rims(vertices, part, part, spacing, support)
    assert rims["rims"] == 1 and len(shown) == len(part)
    assert rims["rim_details"][0]["kind"] == "rim"


def test_the_density_trim_drops_faces_at_low_density_vertices():
    vertices = np.zeros((5, 3))
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    densities = np.array([5.0, 4.0, 3.0, 2.0, 1.0])
    _, kept = open_scans.density_trim(vertices, faces, densities, 0.2)  # cuts below 1.8
    assert kept.tolist() == [[0, 1, 2], [1, 2, 3]]


def test_the_scanned_part_scores_itself_perfectly():
    from jurs.datasets import sample_mesh
    from jurs.levelset._trimming import Support

    vertices, faces = icosphere(4)
    part = faces[vertices[faces].mean(axis=1)[:, 2] > 0]
    points, _ = sample_mesh(vertices, part, 3000, seed=0)
    truth = open_scans.part_truth("cap", vertices, part, "")
    reference, _ = truth.sample(5000, 1)
    s = open_scans.score(vertices, part, truth, reference, 2.0, Support(points), 5000)
    assert s["chamfer"] < 1e-5 and s["loops"] == 1 and s["components"] == 1
    # Random samples leave gaps: even the true surface reads over one spacing in places.
    assert 1.0 < s["stray_max"] < 3.0


@pytest.mark.skipif(
    not os.path.exists(os.path.join(RESULTS, "open_scans.json")), reason="no committed run"
)
def test_the_committed_run_rerenders_beside_its_json(tmp_path):
    with open(os.path.join(RESULTS, "open_scans.json")) as fh:
        data = json.load(fh)
    copy = tmp_path / "copy.json"
    copy.write_text(json.dumps(data))
    open_scans.main(["--from-json", str(copy)])
    text = (tmp_path / "copy.md").read_text()
    assert text.startswith("# Open scans")
    for r in data["runs"]:
        assert f"| {r['case']} | jurs | " in text


@pytest.mark.slow  # fits with JAX's compilation: tens of seconds on a loaded 2-core machine
def test_a_small_run_writes_its_results(tmp_path):
    """A run end to end on the smallest case: the files, the rows and a sane score."""
    open_scans.main(
        ["--cases", "sphere/one view", "--points", "1500", "--max-grid", "8"]
        + ["--eval-samples", "5000", "--out", str(tmp_path), "--name", "small"]
    )
    data = json.loads((tmp_path / "small.json").read_text())
    (run,) = data["runs"]
    assert set(open_scans.ROW_ORDER) <= set(run["rows"])
    assert run["rims"] == 1
    # Untrimmed, both close the sphere: far more stray surface than jurs's trimmed mesh.
    rows = run["rows"]
    assert rows["Poisson"]["stray_share"] > 3 * rows["jurs"]["stray_share"]
    assert rows["jurs untrimmed"]["stray_share"] > 3 * rows["jurs"]["stray_share"]
    assert (tmp_path / "small.md").read_text().startswith("# Open scans")
