"""Building blocks under the public API: the model's kernels, energies and gradients.

What [`jurs.fit`][] and the solvers are made of, for tests, benchmarks and users who
build their own solvers or losses (the optimistix pattern): the cubic B-spline basis and
its sample layouts, the rational function and its transposes (eq. 14, 22-23), the energies
and their hand-derived gradients (eq. 16-19, 31-33; docs/design.md section 2), the metrics
(eq. 35-37), the normal equations of the exact solve (docs/design.md section 3), and the
hierarchy's differentiable solve with its multilevel preconditioner.

These names may change between versions without notice; ``jurs.__all__`` is the stable
surface. Importing this module costs nothing beyond ``import jurs``.
"""

from ._fit.adaptive import multilevel_preconditioner, solve_adaptive
from ._linalg.normal import NormalEquations, normal_equations
from ._model.basis import cubic_derivatives, cubic_weights
from ._model.groups import with_groups
from ._model.hierarchy import (
    Hierarchy,
    build_hierarchy,
    cascade,
    cascade_matrix,
    hierarchy_regulariser,
    refine_near,
)
from ._model.leaves import hierarchy_gradient, hierarchy_values, leaf_terms, locate_leaves
from ._model.local import LocalBasis
from ._model.spline import (
    bspline_transpose,
    bspline_values,
    local_basis,
    rational_values,
)
from ._problem.adaptive import (
    AdaptiveProblem,
    adaptive_objective,
    adaptive_values,
    make_adaptive_problem,
)
from ._problem.energy import (
    collocation_column_sums,
    collocation_transpose,
    data_energy,
    data_energy_grad_control,
    data_energy_grad_weights,
    eta,
    grid_laplacian,
    metrics,
    rational_residuals,
    regulariser,
    regulariser_grad,
    residuals,
    step_size,
    transpose_apply,
    weight_gradient,
)
from ._problem.layout import bucket_layout, cell_groups
from ._problem.problem import auto_domain, offset_samples

__all__ = [
    "AdaptiveProblem",
    "Hierarchy",
    "adaptive_objective",
    "adaptive_values",
    "build_hierarchy",
    "cascade",
    "cascade_matrix",
    "hierarchy_gradient",
    "hierarchy_regulariser",
    "hierarchy_values",
    "leaf_terms",
    "locate_leaves",
    "make_adaptive_problem",
    "multilevel_preconditioner",
    "refine_near",
    "LocalBasis",
    "NormalEquations",
    "auto_domain",
    "bspline_transpose",
    "bspline_values",
    "bucket_layout",
    "cell_groups",
    "collocation_column_sums",
    "collocation_transpose",
    "cubic_derivatives",
    "cubic_weights",
    "data_energy",
    "data_energy_grad_control",
    "data_energy_grad_weights",
    "eta",
    "grid_laplacian",
    "local_basis",
    "metrics",
    "normal_equations",
    "offset_samples",
    "rational_residuals",
    "rational_values",
    "regulariser",
    "regulariser_grad",
    "residuals",
    "solve_adaptive",
    "step_size",
    "transpose_apply",
    "weight_gradient",
    "with_groups",
]
