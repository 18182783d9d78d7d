"""The hierarchy's host solves: the normal product split over threads, the assembled
normal equations made by blocks of rows, and conjugate gradients in NumPy, against their
plain forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import jurs._linalg.sparse as host_sparse
from jurs._linalg.pcg import conjugate_gradients, host_conjugate_gradients
from jurs._linalg.sparse import gram, normal_product, normal_system, rows_in_order
from jurs._problem.adaptive import column_squares
from jurs._threads import row_blocks

jax.config.update("jax_enable_x64", True)


def _matrices(seed=0, rows=900, n=400):
    rng = np.random.default_rng(seed)
    collocation = sp.random(rows, n, density=0.03, format="csr", random_state=seed)
    half = sp.random(n, n, density=0.01, format="csr", random_state=seed + 1)
    regulariser = (half @ half.T + sp.identity(n)).tocsr()
    return collocation, regulariser, rng


def test_row_blocks_are_views_that_cover_the_rows():
    collocation, _, _ = _matrices()
    blocks = row_blocks(collocation, 3)
    assert len(blocks) == 3
    assert all(np.shares_memory(block.data, collocation.data) for _, block in blocks)
    stacked = sp.vstack([block for _, block in blocks]).tocsr()
    assert [first for first, _ in blocks][0] == 0
    assert (stacked != collocation).nnz == 0


@pytest.mark.parametrize("threads", [1, 2, 3, 7])
@pytest.mark.parametrize("weighted", [False, True])
def test_threaded_normal_product_is_the_normal_matrix(threads, weighted):
    collocation, regulariser, rng = _matrices()
    weights = rng.uniform(0.0, 2.0, collocation.shape[0]) if weighted else None
    scale = np.ones(collocation.shape[0]) if weights is None else weights
    matrix = collocation.T @ sp.diags(scale) @ collocation + 0.3 * regulariser
    c = rng.standard_normal(collocation.shape[1])
    with normal_product(collocation, regulariser, 0.3, weights, threads) as product:
        np.testing.assert_allclose(product(c), matrix @ c, rtol=1e-12, atol=1e-12)


def test_rows_in_order_by_last_column_empty_rows_first_ties_kept():
    matrix = sp.csr_matrix(
        np.array([[0, 1, 0, 1], [1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [1, 1, 0, 0]])
    )
    # Last columns 3, 0, none, 2, 1.
    np.testing.assert_array_equal(rows_in_order(matrix), [2, 1, 4, 3, 0])
    collocation, _, _ = _matrices()
    order = rows_in_order(collocation)
    assert sorted(order) == list(range(collocation.shape[0]))
    last = [row.indices.max() for row in collocation[order] if row.nnz]
    assert last == sorted(last)


def test_host_cg_is_the_jax_recurrence():
    """The same steps and solution as ``conjugate_gradients`` on the same system and
    preconditioner, and the solution of the system."""
    collocation, regulariser, rng = _matrices(seed=3)
    matrix = (collocation.T @ collocation + 1e-2 * regulariser).tocsr()
    rhs = rng.standard_normal(matrix.shape[0])
    inverse = 1.0 / matrix.diagonal()
    x, steps, residual = host_conjugate_gradients(
        lambda v: matrix @ v, rhs, precondition=lambda r: inverse * r, rtol=1e-10
    )
    dense = jnp.asarray(matrix.toarray())
    y, jax_steps, _ = conjugate_gradients(
        lambda v: dense @ v, jnp.asarray(rhs), precondition=lambda r: jnp.asarray(inverse) * r
    )
    assert steps == int(jax_steps) and residual <= 1e-10
    np.testing.assert_allclose(x, np.asarray(y), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(x, np.linalg.solve(matrix.toarray(), rhs), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("weighted", [False, True])
def test_gram_by_blocks_is_the_data_term(monkeypatch, weighted):
    """``D^T S D`` made by sorted blocks of rows in threads equals the plain product, with
    the same bits whatever the threads; the normal system adds ``lam R`` and ``D^T S b``,
    and its diagonal is ``column_squares``'s."""
    collocation, regulariser, rng = _matrices(seed=5, rows=3000, n=500)
    collocation.data[collocation.indptr[7] : collocation.indptr[9]] = 0.0  # empty rows too
    collocation.eliminate_zeros()
    weights = rng.uniform(0.0, 2.0, collocation.shape[0]) if weighted else None
    scale = np.ones(collocation.shape[0]) if weights is None else weights
    plain = (collocation.T @ sp.diags(scale) @ collocation).toarray()
    one = gram(collocation, weights)  # below MIN_GRAM_ENTRIES: one product
    np.testing.assert_allclose(one.toarray(), plain, rtol=1e-13, atol=1e-14)
    monkeypatch.setattr(host_sparse, "MIN_GRAM_ENTRIES", 1000)  # several blocks
    assert collocation.nnz // 1000 >= 8
    for count in (8, 5):  # a power of two, and not
        monkeypatch.setattr(host_sparse, "GRAM_BLOCKS", count)
        blocks = [gram(collocation, weights, threads) for threads in (1, 2, 3)]
        np.testing.assert_allclose(blocks[0].toarray(), plain, rtol=1e-13, atol=1e-14)
        for other in blocks[1:]:
            assert np.array_equal(other.toarray(), blocks[0].toarray())
    targets = rng.standard_normal(collocation.shape[0])
    matrix, rhs = normal_system((collocation, regulariser), targets, 0.3, weights)
    np.testing.assert_allclose(
        matrix.toarray(), plain + 0.3 * regulariser.toarray(), rtol=1e-13, atol=1e-14
    )
    np.testing.assert_allclose(rhs, collocation.T @ (scale * targets), rtol=1e-13)
    np.testing.assert_allclose(
        column_squares(collocation, collocation.shape[1], weights), np.diag(plain), rtol=1e-13
    )


def test_assembled_normal_product_is_the_matrix():
    """With no collocation, ``normal_product`` multiplies by the one matrix (an assembled
    normal matrix) over the threads."""
    collocation, regulariser, rng = _matrices(seed=6)
    matrix = (collocation.T @ collocation + 0.3 * regulariser).tocsr()
    c = rng.standard_normal(matrix.shape[0])
    for threads in (1, 3):
        with normal_product(None, matrix, 1.0, threads=threads) as product:
            np.testing.assert_allclose(product(c), matrix @ c, rtol=1e-12, atol=1e-12)
