"""Linear algebra of the exact solve: the normal equations as a banded stencil, their
direct and multigrid solves."""
