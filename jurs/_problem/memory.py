"""The memory guard: a fit or a lattice too large for the memory available is refused
with a ValueError naming the setting, before anything is allocated."""

from __future__ import annotations

import os

import jax
import numpy as np


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
    exceed the memory available (:func:`available_memory`, on the device or with
    ``device=False`` on the host), before anything is allocated
    (grid=10000 otherwise asked XLA for 248 GB after 20 s, and a level-set resolution of
    30000 ended in a MemoryError traceback)."""
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
#: assemble the 49-point stencil of D^T D and solve with it (LeastSquares measured 0.8 GB,
#: 3.1 KB a coefficient, at 512 x 512, peak resident memory above the process' baseline
#: on this 2-core CPU; XLA asked for 2.5 KB a coefficient at 10000 x 10000); the
#: per-sample iterations hold a few grids (IURS: 0.19 GB at 64 x 64 and at 256 x 256,
#: compilation included). At 2000 x 2000 it held 10 GB (2.5 KB a coefficient) after 8
#: minutes and was still growing: the limit is twice the largest rate measured, so that a
#: fit it lets through does not run the machine out of memory.
BYTES_PER_COEFFICIENT = 8192


BYTES_PER_COEFFICIENT_ITERATIVE = 1024


#: Peak bytes per sample (positions, basis values, residuals).
BYTES_PER_SAMPLE = 256


#: The same for surfaces (3D), from peak resident sets on this 2-core CPU: the 343-point
#: stencil, the per-cell moments it is folded from and the fold's intermediates (a 64^3 fit
#: of 2e4 points peaked at 4.8 GB, 18 KB a coefficient), and each sample's 64 gathered
#: coefficients and basis products (1e6 points at 48^3 peaked at 10 GB: 2.9 KB a sample
#: after the grid's share).
BYTES_PER_COEFFICIENT_3D = 20480


BYTES_PER_SAMPLE_3D = 3072


def fit_memory(shape, num_samples: int, solver) -> float:
    """Estimated peak bytes of a fit on an ``(N, M)`` (or ``(N, M, K)``) grid with
    ``num_samples`` samples (:data:`BYTES_PER_COEFFICIENT`, :data:`BYTES_PER_SAMPLE` and
    their 3D counterparts)."""
    surface = len(shape) == 3
    if getattr(solver, "per_sample_iterations", False):
        per_coefficient = BYTES_PER_COEFFICIENT_ITERATIVE
    else:
        per_coefficient = BYTES_PER_COEFFICIENT_3D if surface else BYTES_PER_COEFFICIENT
    per_sample = BYTES_PER_SAMPLE_3D if surface else BYTES_PER_SAMPLE
    return float(per_coefficient * np.prod(shape) + per_sample * num_samples)
