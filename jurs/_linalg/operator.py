"""The lineax operator type of the exact solve's systems, whatever their storage.

The exact solve's matrix ``D^T D + 2 lam L`` is symmetric positive semi-definite and acts
on one coefficient grid. ``AbstractGridOperator`` states that contract once, with the
lineax tags it implies, so that each storage of the matrix is an operator type of its own
(``jurs._linalg.stencil.StencilOperator``: the banded stencil of a uniform grid) and
solvers that need a storage recognise it by type (``jurs._linalg.multigrid.Multigrid``,
``jurs._linalg.cholesky.BlockCholesky``), the pattern of lineax's own operators. Any
other lineax solver reaches the matrix through ``mv`` (CG and the other iterative ones) or
``as_matrix`` (the dense factorisations).

lineax answers its structural queries (``is_symmetric``, ``diagonal``, ``linearise``, ...)
by single dispatch on the operator's type; they are registered here for the abstract type,
so a subclass inherits them.
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import jax
import jax.numpy as jnp
import lineax as lx
from jax import Array


class AbstractGridOperator(lx.AbstractLinearOperator):
    """A symmetric positive semi-definite linear operator on one real coefficient grid (a
    ``grid_shape`` array in, one out): a normal-equation matrix in some storage.

    Subclasses implement ``mv``, ``as_matrix`` (the ``n x n`` matrix of the row-major
    flattened grid), ``in_structure``, ``grid_diagonal`` and
    ``with_grid_diagonal``. The transpose is the operator itself; lineax sees it tagged
    symmetric and positive semi-definite.
    """

    @abc.abstractmethod
    def in_structure(self) -> jax.ShapeDtypeStruct:
        """The coefficient grid's shape and dtype."""

    def out_structure(self) -> jax.ShapeDtypeStruct:
        return self.in_structure()

    def transpose(self) -> AbstractGridOperator:
        return self  # symmetric

    @abc.abstractmethod
    def grid_diagonal(self) -> Array:
        """The matrix's diagonal, shaped like the grid."""

    @abc.abstractmethod
    def with_grid_diagonal(self, diagonal: Array) -> AbstractGridOperator:
        """The same operator with its diagonal replaced by ``diagonal`` (grid-shaped)."""

    def preconditioner(self) -> Callable[[Array], Array]:
        """CG's preconditioner for this operator: a symmetric positive definite
        approximation of its inverse, as a function of a grid. The inverse of the diagonal
        (Jacobi), which must be positive; a storage that knows more of its matrix
        overrides it (``jurs._linalg.stencil.StencilOperator``: blocks of neighbouring
        coefficients in 3D)."""
        inverse = 1.0 / self.grid_diagonal()
        return lambda r: inverse * r


@lx.linearise.register(AbstractGridOperator)
@lx.materialise.register(AbstractGridOperator)  # already stored, not a function
@lx.conj.register(AbstractGridOperator)  # real
def _(operator):
    return operator


@lx.diagonal.register(AbstractGridOperator)
def _(operator):
    return operator.grid_diagonal().ravel()


@lx.tridiagonal.register(AbstractGridOperator)
def _(operator):
    matrix = operator.as_matrix()
    return jnp.diagonal(matrix), jnp.diagonal(matrix, -1), jnp.diagonal(matrix, 1)


@lx.is_symmetric.register(AbstractGridOperator)
@lx.is_positive_semidefinite.register(AbstractGridOperator)
def _(operator):
    return True


@lx.is_diagonal.register(AbstractGridOperator)
@lx.is_tridiagonal.register(AbstractGridOperator)
@lx.has_unit_diagonal.register(AbstractGridOperator)
@lx.is_lower_triangular.register(AbstractGridOperator)
@lx.is_upper_triangular.register(AbstractGridOperator)
@lx.is_negative_semidefinite.register(AbstractGridOperator)
def _(operator):
    return False
