"""Solvers: one interface (:class:`AbstractSolver`), one driver (:func:`solve`)."""

from ._base import AbstractSolver
from ._driver import solve
from ._ipia import IPIA, IPIAState
from ._iurs import IURS, IURSState, objective_lam

__all__ = ["AbstractSolver", "solve", "IPIA", "IPIAState", "IURS", "IURSState", "objective_lam"]
