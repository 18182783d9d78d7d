"""Solvers: one interface (:class:`AbstractSolver`), one driver (:func:`solve`)."""

from ._base import AbstractSolver
from ._driver import solve
from ._ipia import IPIA, IPIAState
from ._iurs import IURS, IURSState, objective_lam

__all__ = ["AbstractSolver", "solve", "IPIA", "IPIAState", "IURS", "IURSState", "objective_lam"]

# Issue 3: exact solve, a sparse joint Levenberg-Marquardt, optimistix and jaxopt wrappers
# (jaxopt itself is imported only when one of its solvers runs).
from ._jaxopt import JaxoptGaussNewton, JaxoptLBFGS, JaxoptLevenbergMarquardt, JaxoptState
from ._least_squares import LeastSquares, LeastSquaresState
from ._optimistix import OptimistixLeastSquares, OptimistixMinimiser, OptimistixState
from ._sparse_lm import JointLevenbergMarquardt, JointLMState

__all__ += [
    "JaxoptGaussNewton", "JaxoptLBFGS", "JaxoptLevenbergMarquardt", "JaxoptState",
    "JointLMState", "JointLevenbergMarquardt", "LeastSquares", "LeastSquaresState",
    "OptimistixLeastSquares", "OptimistixMinimiser", "OptimistixState",
]
