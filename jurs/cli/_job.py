"""One fit of the command line: what ``jurs fit`` has read and checked before it
(``FitJob``), the bytes its outputs take, and the exit statuses of a run."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

from ._inputs import printable
from ._outputs import (
    MAX_ADAPTIVE_RESOLUTION,
    MESH_VERTICES_PER_PLANE_NODE,
    OUTPUT_OVERHEAD,
    PLY_BYTES_PER_VERTEX,
    outputs_for,
)

if TYPE_CHECKING:  # the command line imports NumPy and jurs's modules when it runs them
    import numpy as np

    from .. import AbstractSolver, Cloud, Settings

EXIT_BAD_INPUT = 2
EXIT_FIT_FAILED = 1


def lattice_resolution(resolution: int | None, dim: int, adaptive: bool) -> int | None:
    """``--resolution``, or where not given a uniform curve fit's default lattice; None
    for an adaptive curve (its lattice follows its finest level, known after the fit) and
    for a surface (its mesh chooses)."""
    from .. import levelset as ls

    if dim == 2 and resolution is None and not adaptive:
        return ls.DEFAULT_RESOLUTION
    return resolution


@dataclasses.dataclass(frozen=True)
class FitJob:
    """What ``jurs fit`` has read and checked before the fit: the cloud (``(m, 2)`` or
    ``(m, 3)``, normals given or estimated), the absolute output folder, the settings
    (``jurs.Settings``, with the options given), the solver and the level-set or
    marching-cubes resolution (None: the 3D default)."""

    path: str
    points: np.ndarray
    normals: np.ndarray
    estimated: bool
    out: str
    chosen: Settings
    solver: AbstractSolver | None  # None: jurs.fit's own, from ``chosen``
    resolution: int | None
    cloud: Cloud
    adaptive: bool = False  # jurs.fit_adaptive instead of jurs.fit
    finest: int | None = None  # its finest level's cells along the longest side
    # jurs.fit chooses: the capped uniform grid where its fit follows the data, else the
    # adaptive basis (``adaptive`` True until the fit says which; ``settled``).
    chooses: bool = False

    def settled(self, sol) -> FitJob:
        """The job as ``sol`` was fitted: where ``jurs.fit`` chose (``chooses``) and kept
        the uniform grid, a uniform job (a curve's lattice at its default resolution)."""
        import jurs

        if not self.chooses or isinstance(sol.spline, jurs.AdaptiveSpline):
            return self
        resolution = lattice_resolution(self.resolution, self.dim, adaptive=False)
        return dataclasses.replace(
            self, adaptive=False, finest=None, chooses=False, resolution=resolution
        )

    @property
    def dim(self) -> int:
        return int(self.points.shape[1])

    @property
    def shown(self) -> str:
        return printable(self.path)

    @property
    def grid(self) -> tuple:
        return tuple(self.chosen.grid)

    @property
    def basis(self) -> str:
        """The basis in words: ``grid 96x96`` or ``adaptive``."""
        if self.adaptive:
            return "adaptive"
        return f"grid {'x'.join(map(str, self.grid))}"

    @property
    def lam(self) -> float:
        if self.solver is None:
            return float(self.chosen.lam)
        return float(getattr(self.solver, "lam", 0.0))

    @property
    def outputs(self) -> tuple:
        return outputs_for(self.dim)


def output_bytes(job: FitJob) -> int:
    """Bytes the outputs take: the spline (two grids of float64 in the .npz), the figure
    and the metrics, and in 2D the polylines (at most about resolution^2 / 2 vertices of
    ~40 bytes as text), in 3D the mesh (``MESH_VERTICES_PER_PLANE_NODE``)."""
    from ..levelset._meshing import MAX_RESOLUTION

    # An adaptive spline's active functions are known after the fit; about 10 a point on
    # traced outlines, 64 bounds them.
    spline = 16 * (64 * len(job.points) if job.adaptive else math.prod(job.grid))
    if job.dim == 2:
        # prepare_fit gives a uniform 2D job the level-set default; an adaptive one's is
        # at most MAX_ADAPTIVE_RESOLUTION.
        r = job.resolution or MAX_ADAPTIVE_RESOLUTION
        return OUTPUT_OVERHEAD + spline + 20 * min(r**2, 10 * r * len(job.points))
    r = job.resolution or MAX_RESOLUTION
    return OUTPUT_OVERHEAD + spline + PLY_BYTES_PER_VERTEX * MESH_VERTICES_PER_PLANE_NODE * r**2
