"""jurs: implicit curves and surfaces from point clouds with uniform rational B-splines, in JAX.

Implements "Implicit Uniform Rational Spline Reconstruction Method With Regularization
Term": the rational implicit function (eq. 14), the offset-sample energy (eq. 16), the
control-difference regulariser (eq. 31), and the paper's I-PIA and IURS iterations, on one
solver interface beside exact and general-purpose solvers.

``import jurs`` loads the core (JAX, equinox, lineax) only. The submodules ``datasets``,
``levelset``, ``plot`` and ``shapes`` (matplotlib, contourpy, SciPy's KD-tree) and the
optimistix and jaxopt wrappers load on first use (``jurs.levelset.analyze(...)``,
``jurs.OptimistixMinimiser(...)``), through the module ``__getattr__`` below (PEP 562).
The kernels, energies and gradients under the solvers are in [`jurs.internal`][].
"""

import importlib
from typing import TYPE_CHECKING

from ._cloud.cloud import Cloud
from ._fit.attributes import AttributeField, fit_attributes
from ._fit.compile import COMPILER_OPTIONS, enable_compilation_cache
from ._fit.fit import fit, fit_in_chunks
from ._fit.fit_adaptive import fit_adaptive
from ._fit.settings import Settings, auto_settings
from ._model.adaptive import AdaptiveSpline
from ._model.function import AbstractSpline
from ._model.io import load_spline, save_spline
from ._model.spline import ImplicitSpline
from ._problem.energy import objective
from ._problem.problem import Problem, make_problem
from ._solution.solution import RESULTS, Solution
from .solvers import (
    IPIA,
    IURS,
    AbstractSolver,
    HeldOutLeastSquares,
    JointLevenbergMarquardt,
    LeastSquares,
    NormalIPIA,
    RobustLeastSquares,
    objective_lam,
    solve,
)

if TYPE_CHECKING:  # loaded on first access at run time (``__getattr__`` below)
    from . import datasets, levelset, plot, shapes
    from ._cloud.normals import estimate_normals
    from .solvers import (
        JaxoptGaussNewton,
        JaxoptLBFGS,
        JaxoptLevenbergMarquardt,
        OptimistixLeastSquares,
        OptimistixMinimiser,
    )

__version__ = "0.1.0"

# Entry points and types first; the kernels under them live in ``jurs.internal``.
__all__ = [
    # fitting
    "fit",
    "fit_adaptive",
    "Cloud",
    "fit_in_chunks",
    "estimate_normals",
    "auto_settings",
    "Settings",
    "Solution",
    "RESULTS",
    "AbstractSpline",
    "ImplicitSpline",
    "AdaptiveSpline",
    "save_spline",
    "load_spline",
    # per-point values (colour, intensity, labels) carried onto the zero set
    "fit_attributes",
    "AttributeField",
    # solvers, one interface and one driver
    "AbstractSolver",
    "solve",
    "LeastSquares",
    "RobustLeastSquares",
    "HeldOutLeastSquares",
    "IURS",
    "IPIA",
    "NormalIPIA",
    "JointLevenbergMarquardt",
    "OptimistixLeastSquares",
    "OptimistixMinimiser",
    "JaxoptGaussNewton",
    "JaxoptLBFGS",
    "JaxoptLevenbergMarquardt",
    # the problem and its objective, for custom losses
    "make_problem",
    "Problem",
    "objective",
    "objective_lam",
    # compilation
    "COMPILER_OPTIONS",
    "enable_compilation_cache",
    # submodules (loaded on first access)
    "datasets",
    "levelset",
    "plot",
    "shapes",
]

#: Submodules loaded on first attribute access (``jurs.plot``): matplotlib, contourpy and
#: SciPy's KD-tree cost more to import than the core.
_LAZY_SUBMODULES = ("datasets", "internal", "levelset", "plot", "shapes")
#: Names loaded from their module on first access: the solver wrappers of optional or
#: heavy libraries (optimistix alone is a noticeable share of the import) and the normal estimation
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
    "estimate_normals": "_cloud.normals",
}


def __getattr__(name):
    """PEP 562: load lazy submodules and names when first asked for."""
    if name in _LAZY_SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _LAZY_NAMES:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY_NAMES[name]}"), name)
        globals()[name] = value  # later lookups skip __getattr__
        return value
    internal = importlib.import_module(f"{__name__}.internal")
    if name in internal.__all__:
        raise AttributeError(
            f"jurs.{name} is a kernel helper, not part of the public API: use jurs.internal.{name}"
        )
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__) | set(_LAZY_SUBMODULES) | set(_LAZY_NAMES))
