"""Solvers: one interface (:class:`AbstractSolver`), one driver (:func:`solve`).

The paper's iterations (I-PIA, IURS), the exact solve for fixed weights, a sparse joint
Levenberg-Marquardt, and optimistix and jaxopt wrappers (jaxopt itself is imported only
when one of its solvers runs).
"""

from ._base import AbstractSolver
from ._driver import solve
from ._ipia import IPIA, IPIAState, NormalIPIA, NormalIPIAState
from ._iurs import IURS, IURSState, objective_lam
from ._jaxopt import JaxoptGaussNewton, JaxoptLBFGS, JaxoptLevenbergMarquardt, JaxoptState
from ._least_squares import LeastSquares, LeastSquaresState
from ._optimistix import OptimistixLeastSquares, OptimistixMinimiser, OptimistixState
from ._sparse_lm import JointLevenbergMarquardt, JointLMState

__all__ = [
    "AbstractSolver", "IPIA", "IPIAState", "IURS", "IURSState", "JaxoptGaussNewton",
    "JaxoptLBFGS", "JaxoptLevenbergMarquardt", "JaxoptState", "JointLMState",
    "JointLevenbergMarquardt", "LeastSquares", "LeastSquaresState", "NormalIPIA",
    "NormalIPIAState", "OptimistixLeastSquares", "OptimistixMinimiser", "OptimistixState",
    "objective_lam", "solve",
]
