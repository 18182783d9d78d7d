"""The memory guard: a fit or a lattice too large for the memory available is refused
with a ValueError naming the setting, before anything is allocated. And the return of
freed heap memory to the system between the large steps of a fit."""

from __future__ import annotations

import math
import os

import jax


def available_memory(device: bool = True) -> int | None:
    """Bytes a new allocation can take: with ``device`` on an accelerator its free memory,
    else the host's available memory (``MemAvailable`` of /proc/meminfo, else the physical
    memory); None where neither is known."""
    stats = {}
    if device:
        try:
            stats = jax.devices()[0].memory_stats() or {}
        except Exception:  # backends without memory statistics
            stats = {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


#: Estimates below this are never refused: every machine jurs runs on has this much.
NEVER_REFUSED_BYTES = 64 << 20


def check_memory(
    setting: str, estimate: float, available: int | None = None, device: bool = True
) -> None:
    """MemoryError-free refusal: ValueError naming ``setting`` when ``estimate`` bytes
    exceed the memory available (``available_memory``, on the device or with
    ``device=False`` on the host), before anything is allocated
    (without it an oversized grid failed inside XLA after many seconds, and an oversized
    level-set resolution in a MemoryError traceback: docs/robustness.md, "Memory";
    docs/performance.md, "Measurements behind the defaults")."""
    if estimate < NEVER_REFUSED_BYTES and available is None:
        return  # nothing to ask the system (reading its memory costs more than a small fit)
    available = available_memory(device) if available is None else available
    if available is not None and estimate > available:
        raise ValueError(
            f"{setting} needs about {estimate / 2**30:.3g} GiB of memory, more "
            f"than the {available / 2**30:.3g} GiB available; choose a smaller "
            f"{setting.split(' ')[0].split('=')[0]}"
        )


#: Peak bytes a fit holds per coefficient: the exact solve and the normal-equation form
#: assemble the 49-point stencil of D^T D and solve with it; the per-sample iterations
#: hold a few grids (``BYTES_PER_COEFFICIENT_ITERATIVE``). The limit is twice the
#: largest rate measured, so that a fit it lets through does not run the machine out of
#: memory (docs/robustness.md, "Memory").
BYTES_PER_COEFFICIENT = 8192


BYTES_PER_COEFFICIENT_ITERATIVE = 1024


#: Peak bytes per sample (positions, basis values, residuals).
BYTES_PER_SAMPLE = 256


#: The same for surfaces (3D), from peak resident sets: the 343-point stencil, the
#: per-cell moments it is folded from and the fold's intermediates, and each sample's 64
#: gathered coefficients and basis products, each above the largest rate measured
#: (docs/performance.md, "Measurements behind the defaults").
BYTES_PER_COEFFICIENT_3D = 20480


BYTES_PER_SAMPLE_3D = 3072


def fit_memory(shape, num_samples: int, solver) -> float:
    """Estimated peak bytes of a fit on an ``(N, M)`` (or ``(N, M, K)``) grid with
    ``num_samples`` samples (``BYTES_PER_COEFFICIENT``, ``BYTES_PER_SAMPLE`` and
    their 3D counterparts)."""
    surface = len(shape) == 3
    if getattr(solver, "per_sample_iterations", False):
        per_coefficient = BYTES_PER_COEFFICIENT_ITERATIVE
    else:
        per_coefficient = BYTES_PER_COEFFICIENT_3D if surface else BYTES_PER_COEFFICIENT
    per_sample = BYTES_PER_SAMPLE_3D if surface else BYTES_PER_SAMPLE
    return float(per_coefficient * math.prod(shape) + per_sample * num_samples)


def check_fit_memory(shape, num_points: int, solver) -> None:
    """``check_memory`` of a fit of ``num_points`` points (3 samples each) on the grid
    ``shape`` by ``solver`` (None: the default exact solve), naming the grid."""
    check_memory("grid=" + "x".join(map(str, shape)), fit_memory(shape, 3 * num_points, solver))
