"""Linear algebra of the exact solve, one job a module: ``operator`` (the lineax operator
type of the systems), ``stencil`` (banded stencils and ``StencilOperator``),
``normal`` (the normal equations assembled from a problem), ``cholesky`` (direct
factorisations), ``coarsen`` (coarser grids and the maps between grids), ``patches`` (the
multigrid's Schwarz smoother), ``multigrid`` (the multigrid-preconditioned solver),
``sparse`` (host-assembled sparse matrices applied in JAX), ``thb_multigrid`` (the
hierarchy's V-cycle) and ``pcg`` (conjugate gradients).
Nothing here imports from ``jurs.solvers`` or ``jurs._fit``."""
