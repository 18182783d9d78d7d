"""The 3D cases of ``benchmarks/surfaces.py``, shared with the surface fits of
``benchmarks/normals.py``: exact samples of each true surface, point-to-surface distances to
it, and the topology of a reconstructed mesh.

Imports nothing heavier than NumPy at module level (surfaces.py runs each method in a
spawned child that re-imports it); JAX, jurs and Open3D are imported where used.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from ._common import import_open3d, optional

#: Noise of the noisy variant: Gaussian, this fraction of the bounding-box diagonal on each
#: coordinate of the positions.
NOISE = 0.005
#: Dense samples of each reconstruction and of the truth for the distances: the Chamfer
#: mean is a Monte-Carlo estimate whose relative error is about 1 / sqrt(samples).
EVAL_SAMPLES = 400_000
SEEDS = {"cloud": 0, "truth": 1, "noise": 2, "mesh": 3}
#: A folder of pymeshlab's sample meshes (``PYMESHLAB_SAMPLES``); None: pymeshlab's own.
MESHES = os.environ.get("PYMESHLAB_SAMPLES")


# --------------------------------------------------------------------------- the truth


def newton_projection(fn, x, steps: int = 20):
    """Foot points of ``x (n, 3)`` on ``{fn = 0}`` by Newton steps along the gradient and the
    unit normals there; ``fn(x) -> (values, gradients)``.

    For a signed distance (the sphere's and the torus's) one step lands on the closest
    point; the double torus's function is a signed distance up to a smooth blend where the
    tubes meet, where the foot point is the closest point to second order. A foot point is
    on the surface, so ``|x - foot|`` never underestimates the distance. Points with a zero
    gradient (on an axis of symmetry, far from the surface) keep ``|f|`` as distance.
    """
    y = np.array(x, dtype=np.float64)
    for _ in range(steps):
        value, grad = fn(y)
        norm2 = np.sum(grad * grad, axis=1)
        ok = norm2 > 0
        y[ok] -= (value[ok] / norm2[ok])[:, None] * grad[ok]
    value, grad = fn(y)
    length = np.linalg.norm(grad, axis=1)
    distance = np.linalg.norm(y - x, axis=1)
    flat = length == 0
    distance[flat] = np.abs(fn(x[flat])[0])
    return distance, grad / np.where(flat, 1.0, length)[:, None]


def sphere_function(x):
    """Signed distance to the unit sphere and its gradient."""
    r = np.linalg.norm(x, axis=1)
    return r - 1.0, x / np.where(r > 0, r, 1.0)[:, None]


def torus_function(x, major: float = 1.0, minor: float = 0.35):
    """Signed distance to the torus about the z axis and its gradient."""
    ring = np.hypot(x[:, 0], x[:, 1])
    tube = np.stack([ring - major, x[:, 2]], axis=1)
    length = np.linalg.norm(tube, axis=1)
    radial = x[:, :2] / np.where(ring > 0, ring, 1.0)[:, None]
    grad = np.column_stack([tube[:, :1] * radial, tube[:, 1:]])
    return length - minor, grad / np.where(length > 0, length, 1.0)[:, None]


class MeshDistance:
    """Point-to-triangle-mesh distances through Open3D's ``RaycastingScene`` (float32)."""

    def __init__(self, vertices, faces):
        o3d = import_open3d()

        self.o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(np.asarray(vertices, np.float32)),
            o3d.core.Tensor(np.asarray(faces, np.uint32)),
        )
        a, b, c = (np.asarray(vertices)[np.asarray(faces)[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        self.normals = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)

    def closest(self, x):
        """``(distances (n,), unit normals of the closest faces (n, 3))``."""
        found = self.scene.compute_closest_points(self.o3d.core.Tensor(np.asarray(x, np.float32)))
        foot = found["points"].numpy().astype(np.float64)
        return np.linalg.norm(foot - x, axis=1), self.normals[found["primitive_ids"].numpy()]

    def distance(self, x):
        return self.closest(x)[0]


@dataclasses.dataclass
class Truth:
    """A case: exact samples, distance to the true surface, and its topology."""

    name: str
    sample: Callable[..., Any]  # (m, seed) -> (points, normals), exact
    closest: Callable[..., Any]  # (x) -> (distance, true unit normal at the closest point)
    components: int
    genus: int | list[int]
    origin: str


def mesh_path(name: str):
    """Path of a pymeshlab sample mesh, or None (pymeshlab missing, or no such file).
    The same folder and override (``PYMESHLAB_SAMPLES``) as benchmarks/normals.py."""
    pymeshlab = optional("pymeshlab")
    if MESHES is not None:
        folder = MESHES
    elif pymeshlab is None or pymeshlab.__file__ is None:
        return None
    else:
        folder = os.path.join(os.path.dirname(pymeshlab.__file__), "tests", "sample_meshes")
    path = os.path.join(folder, f"{name}.obj")
    return path if os.path.exists(path) else None


def make_truth(name: str) -> Truth | None:
    """The ``Truth`` of a case; None when its mesh is not available."""
    import jurs.datasets as data
    from jurs.levelset import analyze_mesh

    analytic = {
        "sphere": (lambda m, seed: data.sphere3d(m, seed=seed), sphere_function, 0, "unit sphere"),
        "torus": (
            lambda m, seed: data.torus(m, 1.0, 0.35, seed=seed),
            torus_function,
            1,
            "torus R 1, r 0.35",
        ),
        "genus2": (
            lambda m, seed: data.genus2(m, seed=seed),
            data.genus2_function,
            2,
            "jurs.datasets.genus2 (two tori R 1, r 0.35 blended)",
        ),
    }
    if name in analytic:
        sample, fn, genus, origin = analytic[name]
        return Truth(name, sample, lambda x, fn=fn: newton_projection(fn, x), 1, genus, origin)
    path = mesh_path(name)
    if path is None:
        return None
    vertices, faces = data.load_mesh(path)
    report = analyze_mesh(vertices, faces)
    genera = [c.genus for c in report.components]
    return Truth(
        name,
        lambda m, seed: data.sample_mesh(vertices, faces, m, seed=seed),
        MeshDistance(vertices, faces).closest,
        report.num_components,
        genera[0] if len(genera) == 1 else genera,
        f"{os.path.basename(path)} ({len(faces)} faces, "
        f"{report.as_dict()['num_closed']}/{report.num_components} components closed)",
    )


def diagonal(points) -> float:
    return float(np.linalg.norm(np.ptp(points, axis=0)))


# --------------------------------------------------------------------------- measuring


def surface_distances(vertices, faces, truth: Truth, reference, diag: float, samples: int) -> dict:
    """Point-to-surface Chamfer and Hausdorff (absolute and / ``diag``) and normal
    consistency between a mesh and the true surface; ``reference`` are exact samples."""
    from jurs.datasets import sample_mesh
    from jurs.levelset import face_areas

    if len(faces) == 0 or not face_areas(vertices, faces).sum() > 0:
        return {
            "chamfer": float("inf"),
            "hausdorff": float("inf"),
            "chamfer_rel": float("inf"),
            "hausdorff_rel": float("inf"),
            "normal_consistency": float("nan"),
        }
    z, z_normals = sample_mesh(vertices, faces, samples, seed=SEEDS["mesh"])
    to_truth, true_normals = truth.closest(z)
    to_mesh = MeshDistance(vertices, faces).distance(reference)
    chamfer = 0.5 * (to_truth.mean() + to_mesh.mean())
    hausdorff = max(to_truth.max(), to_mesh.max())
    return {
        "chamfer": float(chamfer),
        "hausdorff": float(hausdorff),
        "chamfer_rel": float(chamfer / diag),
        "hausdorff_rel": float(hausdorff / diag),
        "normal_consistency": float(np.mean(np.abs(np.sum(z_normals * true_normals, axis=1)))),
        "to_truth_mean": float(to_truth.mean()),
        "to_mesh_mean": float(to_mesh.mean()),
    }


def topology(vertices, faces, points) -> tuple[dict, np.ndarray]:
    """``analyze_mesh`` against the input cloud: its summary, and the supplementary faces."""
    from jurs.levelset import analyze_mesh

    report = analyze_mesh(vertices, faces, points)
    bubbles = [c.faces for c in report.supplementary]
    return report.as_dict(), (np.concatenate(bubbles) if bubbles else np.empty(0, int))
