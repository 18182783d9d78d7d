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
    collocation_transpose,
    rational_residuals,
    weight_gradient,
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
from ._compile import COMPILER_OPTIONS
from ._defaults import Settings, auto_settings
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
    JaxoptGaussNewton,
    JaxoptLBFGS,
    JaxoptLevenbergMarquardt,
    JointLevenbergMarquardt,
    LeastSquares,
    NormalIPIA,
    OptimistixLeastSquares,
    OptimistixMinimiser,
    objective_lam,
    solve,
)

__version__ = "0.1.0"

__all__ = [
    "AbstractSolver", "COMPILER_OPTIONS", "IPIA", "IURS", "ImplicitSpline", "JaxoptGaussNewton",
    "JaxoptLBFGS",
    "JaxoptLevenbergMarquardt", "JointLevenbergMarquardt", "LeastSquares", "LocalBasis",
    "NormalEquations", "NormalIPIA", "OptimistixLeastSquares", "OptimistixMinimiser",
    "Problem", "RESULTS", "Settings", "Solution", "auto_domain", "auto_settings", "bspline_transpose", "bspline_values",
    "bucket_layout", "collocation_column_sums", "collocation_transpose", "cubic_derivatives",
    "cubic_weights", "data_energy", "data_energy_grad_control", "data_energy_grad_weights",
    "datasets", "eta", "fit", "fit_in_chunks", "grid_laplacian", "load_spline", "local_basis",
    "make_problem", "metrics", "normal_equations", "objective", "objective_lam",
    "offset_samples", "rational_residuals", "rational_values", "regulariser",
    "regulariser_grad", "residuals", "save_spline", "solve", "step_size", "transpose_apply",
    "weight_gradient",
]
