"""jurs: implicit curve reconstruction with uniform rational B-splines, in JAX.

Implements "Implicit Uniform Rational Spline Reconstruction Method With Regularization
Term": the rational implicit function (eq. 14), the offset-sample energy (eq. 16), the
control-difference regulariser (eq. 31), and the paper's I-PIA and IURS iterations, on one
solver interface beside exact and general-purpose solvers.

``import jurs`` loads the core (JAX, equinox, lineax) only. The submodules ``datasets``,
``levelset``, ``plot`` and ``shapes`` (matplotlib, contourpy, SciPy's KD-tree) and the
optimistix and jaxopt wrappers load on first use (``jurs.levelset.analyze(...)``,
``jurs.OptimistixMinimiser(...)``), through the module ``__getattr__`` below (PEP 562).
"""

import importlib

from ._basis import cubic_derivatives, cubic_weights
from ._compile import COMPILER_OPTIONS, enable_compilation_cache
from ._defaults import Settings, auto_settings
from ._energy import (
    collocation_column_sums,
    collocation_transpose,
    data_energy,
    data_energy_grad_control,
    data_energy_grad_weights,
    eta,
    grid_laplacian,
    metrics,
    objective,
    rational_residuals,
    regulariser,
    regulariser_grad,
    residuals,
    step_size,
    transpose_apply,
    weight_gradient,
)
from ._fit import fit
from ._io import load_spline, save_spline
from ._normal import NormalEquations, normal_equations
from ._problem import Problem, auto_domain, bucket_layout, make_problem, offset_samples
from ._progress import fit_in_chunks
from ._solution import RESULTS, Solution
from ._spline import (
    ImplicitSpline,
    LocalBasis,
    bspline_transpose,
    bspline_values,
    local_basis,
    rational_values,
)
from .solvers import (
    IPIA,
    IURS,
    AbstractSolver,
    JointLevenbergMarquardt,
    LeastSquares,
    NormalIPIA,
    objective_lam,
    solve,
)

__version__ = "0.1.0"

__all__ = [
    "AbstractSolver",
    "COMPILER_OPTIONS",
    "IPIA",
    "IURS",
    "ImplicitSpline",
    "JaxoptGaussNewton",
    "JaxoptLBFGS",
    "JaxoptLevenbergMarquardt",
    "JointLevenbergMarquardt",
    "LeastSquares",
    "LocalBasis",
    "NormalEquations",
    "NormalIPIA",
    "OptimistixLeastSquares",
    "OptimistixMinimiser",
    "Problem",
    "RESULTS",
    "Settings",
    "Solution",
    "auto_domain",
    "auto_settings",
    "bspline_transpose",
    "bspline_values",
    "bucket_layout",
    "collocation_column_sums",
    "collocation_transpose",
    "cubic_derivatives",
    "cubic_weights",
    "data_energy",
    "data_energy_grad_control",
    "data_energy_grad_weights",
    "datasets",
    "enable_compilation_cache",
    "estimate_normals",
    "eta",
    "fit",
    "fit_in_chunks",
    "grid_laplacian",
    "load_spline",
    "local_basis",
    "make_problem",
    "metrics",
    "normal_equations",
    "objective",
    "objective_lam",
    "offset_samples",
    "rational_residuals",
    "rational_values",
    "regulariser",
    "regulariser_grad",
    "residuals",
    "save_spline",
    "solve",
    "step_size",
    "transpose_apply",
    "weight_gradient",
]

#: Submodules loaded on first attribute access (``jurs.plot``): matplotlib, contourpy and
#: SciPy's KD-tree cost more to import than the core.
_LAZY_SUBMODULES = ("datasets", "levelset", "plot", "shapes")
#: Names loaded from their module on first access: the solver wrappers of optional or
#: heavy libraries (optimistix alone takes about 0.1 s to import) and the normal estimation
#: (SciPy's sparse graphs and KD-tree).
_LAZY_NAMES = {
    **{
        name: "solvers"
        for name in (
            "JaxoptGaussNewton",
            "JaxoptLBFGS",
            "JaxoptLevenbergMarquardt",
            "OptimistixLeastSquares",
            "OptimistixMinimiser",
        )
    },
    "estimate_normals": "_orientation",
}


def __getattr__(name):
    """PEP 562: load lazy submodules and names when first asked for."""
    if name in _LAZY_SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _LAZY_NAMES:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY_NAMES[name]}"), name)
        globals()[name] = value  # later lookups skip __getattr__
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__) | set(_LAZY_SUBMODULES) | set(_LAZY_NAMES))
