"""Solvers: one interface ([`AbstractSolver`][jurs.AbstractSolver]), one driver
([`solve`][jurs.solve]).

The paper's iterations (I-PIA, IURS), the exact solve for fixed weights and its
outlier-robust reweighting, a sparse joint Levenberg-Marquardt, and optimistix and jaxopt
wrappers (jaxopt itself is imported only when one of its solvers runs). The two wrapper
modules load on first access to one of their names (module ``__getattr__``, PEP 562):
optimistix alone is a noticeable share of ``import jurs`` (docs/performance.md).
"""

import importlib
from typing import TYPE_CHECKING

from ._base import AbstractSolver
from ._driver import solve
from ._held_out import HeldOutLeastSquares, HeldOutLeastSquaresState
from ._ipia import IPIA, IPIAState, NormalIPIA, NormalIPIAState
from ._iurs import IURS, IURSState, objective_lam
from ._least_squares import LeastSquares, LeastSquaresState
from ._robust import RobustLeastSquares, RobustLeastSquaresState
from ._sparse_lm import JointLevenbergMarquardt, JointLMState

if TYPE_CHECKING:  # loaded on first access at run time (``__getattr__`` below)
    from ._jaxopt import JaxoptGaussNewton, JaxoptLBFGS, JaxoptLevenbergMarquardt, JaxoptState
    from ._optimistix import OptimistixLeastSquares, OptimistixMinimiser, OptimistixState

#: Names of the lazily loaded wrapper modules.
_LAZY = {
    **dict.fromkeys(
        ("JaxoptGaussNewton", "JaxoptLBFGS", "JaxoptLevenbergMarquardt", "JaxoptState"), "._jaxopt"
    ),
    **dict.fromkeys(
        ("OptimistixLeastSquares", "OptimistixMinimiser", "OptimistixState"), "._optimistix"
    ),
}


def __getattr__(name):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "AbstractSolver",
    "HeldOutLeastSquares",
    "HeldOutLeastSquaresState",
    "IPIA",
    "IPIAState",
    "IURS",
    "IURSState",
    "JaxoptGaussNewton",
    "JaxoptLBFGS",
    "JaxoptLevenbergMarquardt",
    "JaxoptState",
    "JointLMState",
    "JointLevenbergMarquardt",
    "LeastSquares",
    "LeastSquaresState",
    "NormalIPIA",
    "NormalIPIAState",
    "OptimistixLeastSquares",
    "OptimistixMinimiser",
    "OptimistixState",
    "RobustLeastSquares",
    "RobustLeastSquaresState",
    "objective_lam",
    "solve",
]
