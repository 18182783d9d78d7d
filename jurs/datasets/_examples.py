"""The built-in point clouds: the paper's analytic curves (2D), noise, and 3D surfaces.

Every generator returns ``(points, normals)`` as float64 NumPy arrays of shape ``(m, 2)``
(the 3D ones [`sphere3d`][jurs.datasets.sphere3d], [`torus`][jurs.datasets.torus],
[`genus2`][jurs.datasets.genus2] and [`sample_mesh`][jurs.datasets.sample_mesh]:
``(m, 3)``), normals unit length and pointing out of the enclosed region. Public through
[`jurs.datasets`][]; reading and writing files is in ``jurs/datasets/_files.py``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int


def _outward(points: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Unit normals from tangents of a closed curve, oriented outward by the signed area."""
    x, y = points[:, 0], points[:, 1]
    signed_area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    normals = np.stack([tangents[:, 1], -tangents[:, 0]], axis=1)  # outward if CCW
    if signed_area < 0:
        normals = -normals
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def parametric_curve(
    curve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    derivative: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    num_points: int,
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Sample a closed curve at ``num_points`` uniform parameters t in [0, 2 pi)."""
    if num_points < 3:
        raise ValueError(f"num_points must be >= 3, got {num_points}")
    t = np.linspace(0.0, 2.0 * np.pi, num_points, endpoint=False)
    points = np.stack(curve(t), axis=1)
    return points, _outward(points, np.stack(derivative(t), axis=1))


def example1(num_points: int = 120) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """The paper's Example 1: x = 4 cos t, y = sin t (3 - 5 sin t), 120 points by default.

    A simple closed curve with a concave dent at the top (upper branch minus lower branch
    at the same x is 6 sin t > 0).
    """
    return parametric_curve(
        lambda t: (4.0 * np.cos(t), np.sin(t) * (3.0 - 5.0 * np.sin(t))),
        lambda t: (-4.0 * np.sin(t), 3.0 * np.cos(t) - 10.0 * np.sin(t) * np.cos(t)),
        num_points,
    )


def ellipse(
    num_points: int = 500, a: float = 4.0, b: float = 5.0
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """The ellipse x = a cos t, y = b sin t (Example 10's clean curve: a = 4, b = 5)."""
    return parametric_curve(
        lambda t: (a * np.cos(t), b * np.sin(t)),
        lambda t: (-a * np.sin(t), b * np.cos(t)),
        num_points,
    )


def add_noise(
    points: Float[np.ndarray, "m d"],
    normals: Float[np.ndarray, "m d"],
    *,
    sigma: float,
    normal_sigma: float | None = None,
    seed: int = 0,
) -> tuple[Float[np.ndarray, "m d"], Float[np.ndarray, "m d"]]:
    """Gaussian noise: ``sigma`` on point coordinates, ``normal_sigma`` (default ``sigma``
    relative to unit length) on normals, which are then re-normalised. Reproducible by seed."""
    if sigma < 0 or (normal_sigma is not None and normal_sigma < 0):
        raise ValueError("noise levels must be non-negative")
    rng = np.random.default_rng(seed)
    normal_sigma = sigma if normal_sigma is None else normal_sigma
    noisy_points = points + sigma * rng.standard_normal(points.shape)
    noisy_normals = normals + normal_sigma * rng.standard_normal(normals.shape)
    return noisy_points, noisy_normals / np.linalg.norm(noisy_normals, axis=1, keepdims=True)


def example9(
    seed: int = 0, sigma: float = 0.05
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Example 9: Example 1's curve with 400 noisy points. The paper gives no noise level;
    ``sigma = 0.05`` (0.5 % of the bounding-box diagonal) is this library's choice."""
    return add_noise(*example1(400), sigma=sigma, seed=seed)


def example10(
    seed: int = 0, sigma: float = 0.05
) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
    """Example 10: the ellipse 4 cos t, 5 sin t with 500 noisy points (``sigma`` as in
    [`example9`][jurs.datasets.example9]; the paper gives none)."""
    return add_noise(*ellipse(500), sigma=sigma, seed=seed)


def _count(m) -> int:
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
        raise ValueError(f"the number of points must be a positive int, got {m!r}")
    return int(m)


def sphere3d(
    m: int, radius: float = 1.0, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly (by area) on the sphere of ``radius`` about the origin,
    with their outward unit normals; ``(points (m, 3), normals (m, 3))``."""
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    # Normalised Gaussian vectors are uniform on the sphere (rotation invariance).
    normals = np.random.default_rng(seed).standard_normal((_count(m), 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return radius * normals, normals


def torus(
    m: int, major: float = 1.0, minor: float = 0.35, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly (by area) on the torus about the z axis with tube
    centre radius ``major`` and tube radius ``minor`` (``0 < minor < major``), with outward
    unit normals.

    The torus ``((R + r cos v) cos u, (R + r cos v) sin u, r sin v)`` has area element
    ``r (R + r cos v) du dv``: ``u`` is uniform, ``v`` is drawn by rejection against that
    density.
    """
    if not 0 < minor < major:
        raise ValueError(f"need 0 < minor < major, got minor={minor}, major={major}")
    m = _count(m)
    rng = np.random.default_rng(seed)
    v = np.empty(0)
    while len(v) < m:
        candidate = rng.uniform(0.0, 2.0 * np.pi, 2 * m)
        keep = rng.uniform(0.0, major + minor, 2 * m) < major + minor * np.cos(candidate)
        v = np.concatenate([v, candidate[keep]])
    v = v[:m]
    u = rng.uniform(0.0, 2.0 * np.pi, m)
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    centres = major * np.stack([np.cos(u), np.sin(u), np.zeros(m)], axis=1)
    return centres + minor * normals, normals


def thin_plate(
    step: float = 0.1, thickness: float = 0.15
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """A thin square plate over ``[-1, 1]^2``: its two faces at ``z = +-thickness / 2``
    sampled on a grid of ``step`` (normals ``+-e_z``) and its rim at mid-height (the four
    sides without the corners, normals facing out). A planted case of two sheets nearer
    than a cell: the sign of a normal's z says which face a point is on (0 on the rim).
    ``step`` divides 2 (the grid ends on the rim); ValueError otherwise.
    """
    count = round(2.0 / step) if np.isfinite(step) and 0 < step <= 1 else 0
    if count == 0 or abs(count * step - 2.0) > 1e-9:
        raise ValueError(f"step must divide 2 and lie in (0, 1], got {step}")
    if not (np.isfinite(thickness) and thickness > 0):
        raise ValueError(f"thickness must be positive, got {thickness}")
    axis = np.linspace(-1.0, 1.0, count + 1)
    x, y = (a.ravel() for a in np.meshgrid(axis, axis, indexing="ij"))
    half = thickness / 2
    faces = [np.stack([x, y, np.full_like(x, z)], 1) for z in (half, -half)]
    inner, zero, one = axis[1:-1], np.zeros(len(axis) - 2), np.ones(len(axis) - 2)
    rim_points, rim_normals = [], []
    for sign in (-1.0, 1.0):  # the sides y = +-1 and x = +-1, facing out
        rim_points += [
            np.stack([inner, sign * one, zero], 1),
            np.stack([sign * one, inner, zero], 1),
        ]
        rim_normals += [
            np.stack([zero, sign * one, zero], 1),
            np.stack([sign * one, zero, zero], 1),
        ]
    up = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    return np.concatenate([*faces, *rim_points]), np.concatenate([up, -up, *rim_normals])


#: The double torus of [`genus2`][jurs.datasets.genus2]: two tori about parallel axes
#: through (+-GENUS2_SHIFT, 0), of radii GENUS2_MAJOR, GENUS2_MINOR, joined by a smooth
#: minimum of blend width GENUS2_BLEND.
GENUS2_SHIFT, GENUS2_MAJOR, GENUS2_MINOR, GENUS2_BLEND = 1.0, 1.0, 0.35, 0.1


def genus2_function(
    points: Float[npt.ArrayLike, "n 3"],
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, "n 3"]]:
    """The implicit double torus sampled by [`genus2`][jurs.datasets.genus2] and its
    gradient at ``points (n, 3)``: ``(values (n,), gradients (n, 3))``, negative inside.

    The smooth minimum ``-k log(exp(-a / k) + exp(-b / k))`` of the signed distances ``a``,
    ``b`` to two tori whose tube centre circles touch at the origin: the tubes merge there,
    so the union is one closed surface with two holes, and the smooth minimum rounds the
    crease where the tubes meet (width ``k``). Near the surface the value is close to the
    signed distance.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    values, gradients = [], []
    for shift in (-GENUS2_SHIFT, GENUS2_SHIFT):
        q = p - [shift, 0.0, 0.0]
        ring = np.hypot(q[:, 0], q[:, 1])
        tube = np.stack([ring - GENUS2_MAJOR, q[:, 2]], axis=1)  # (radial, z) in the tube
        length = np.linalg.norm(tube, axis=1)
        values.append(length - GENUS2_MINOR)
        # On a torus's axis and its tube's centre circle the distance has no gradient
        # (far inside or outside the surface): 0 there instead of NaN.
        radial = q[:, :2] / np.where(ring > 0, ring, 1.0)[:, None]
        gradients.append(
            np.column_stack([tube[:, :1] * radial, tube[:, 1:]])
            / np.where(length > 0, length, 1.0)[:, None]
        )
    a, b = values
    k = GENUS2_BLEND
    value = -k * np.logaddexp(-a / k, -b / k)
    share = 1.0 / (1.0 + np.exp((a - b) / k))  # weight of a's gradient: softmax of -a/k, -b/k
    return value, share[:, None] * gradients[0] + (1.0 - share[:, None]) * gradients[1]


def genus2(m: int, seed: int = 0) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points on a smooth double torus (genus 2;
    [`genus2_function`][jurs.datasets.genus2_function]), uniform by area, with outward unit
    normals (the normalised gradient).

    Points are drawn uniformly in a shell of half-width 0.01 about the surface (first-order
    distance ``|f| / |grad f|``) and moved onto it by Newton steps. A thin shell's volume
    is area times width, so the landing points are uniform by area, up to a relative
    error of the order of (width x curvature)^2, 1e-3 here.
    """
    m = _count(m)
    rng = np.random.default_rng(seed)
    half = (
        np.array(
            [GENUS2_SHIFT + GENUS2_MAJOR + GENUS2_MINOR, GENUS2_MAJOR + GENUS2_MINOR, GENUS2_MINOR]
        )
        + 0.1
    )
    width = 0.01
    accepted = []
    total = 0
    while total < m:
        candidate = rng.uniform(-half, half, (1 << 16, 3))
        value, gradient = genus2_function(candidate)
        keep = np.abs(value) < width * np.linalg.norm(gradient, axis=1)
        accepted.append(candidate[keep])
        total += int(keep.sum())
    points = np.concatenate(accepted)[:m]
    for _ in range(8):  # from 0.01 off, quadratic convergence: far below 1e-12 after 4
        value, gradient = genus2_function(points)
        points = points - (value / np.sum(gradient * gradient, axis=1))[:, None] * gradient
    gradient = genus2_function(points)[1]
    return points, gradient / np.linalg.norm(gradient, axis=1, keepdims=True)


def sample_mesh(
    vertices: Float[npt.ArrayLike, "V 3"], faces: Int[npt.ArrayLike, "F 3"], m: int, seed: int = 0
) -> tuple[Float[np.ndarray, "m 3"], Float[np.ndarray, "m 3"]]:
    """``m`` points drawn uniformly by area on a triangle mesh, with the unit normal of the
    face each lies on (right-hand rule); ``(points (m, 3), normals (m, 3))``. Faces without
    area are never drawn; ValueError for a mesh without area."""
    vertices, faces = mesh_arrays(vertices, faces)
    m = _count(m)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no area to sample")
    rng = np.random.default_rng(seed)
    face = rng.choice(len(faces), size=m, p=area / area.sum())
    # Uniform in a triangle: reflect the unit square's upper half onto the lower.
    s, t = rng.uniform(size=(2, m))
    flip = s + t > 1.0
    s[flip], t[flip] = 1.0 - s[flip], 1.0 - t[flip]
    points = a[face] + s[:, None] * (b - a)[face] + t[:, None] * (c - a)[face]
    return points, cross[face] / area[face, None]


def mesh_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3))`` as arrays; ValueError for other shapes."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(
            f"vertices and faces must have shapes (V, 3) and (F, 3), got "
            f"{vertices.shape} and {faces.shape}"
        )
    return vertices, faces
