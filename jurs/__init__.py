"""jurs: implicit curve reconstruction with uniform rational B-splines, in JAX.

Implements "Implicit Uniform Rational Spline Reconstruction Method With Regularization
Term": the rational implicit function (eq. 14), the offset-sample energy (eq. 16), the
control-difference regulariser (eq. 31), and the paper's I-PIA and IURS iterations, on one
solver interface beside exact and general-purpose solvers.
"""

from . import datasets
from ._basis import cubic_derivatives, cubic_weights
from ._energy import (
    collocation_column_sums,
    data_energy,
    data_energy_grad_control,
    data_energy_grad_weights,
    eta,
    grid_laplacian,
    metrics,
    objective,
    regulariser,
    regulariser_grad,
    residuals,
    step_size,
    transpose_apply,
)
from ._fit import fit
from ._problem import Problem, auto_domain, make_problem, offset_samples
from ._solution import RESULTS, Solution
from ._spline import ImplicitSpline, LocalBasis, local_basis
from .solvers import IPIA, IURS, AbstractSolver, objective_lam, solve

__version__ = "0.1.0"

__all__ = [
    "AbstractSolver", "IPIA", "IURS", "ImplicitSpline", "LocalBasis", "Problem", "RESULTS",
    "Solution", "auto_domain", "collocation_column_sums", "cubic_derivatives", "cubic_weights",
    "data_energy", "data_energy_grad_control", "data_energy_grad_weights", "datasets", "eta",
    "fit", "grid_laplacian", "local_basis", "make_problem", "metrics", "objective",
    "objective_lam", "offset_samples", "regulariser", "regulariser_grad", "residuals", "solve",
    "step_size", "transpose_apply",
]
