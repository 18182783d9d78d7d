"""The host's threads (``jurs._threads``): each helper gives what its plain sequential
form gives, to the bit, with one thread or several, and the kept pools neither deadlock
when nested nor outlive a fork."""

import os
import threading

import numpy as np
import pytest

import jurs._threads as host


@pytest.fixture(params=[1, 2, 3])
def threads(request, monkeypatch):
    monkeypatch.setattr(host, "host_threads", lambda: request.param)
    return request.param


def test_in_threads_and_by_rows_keep_the_order(threads, monkeypatch):
    assert host.in_threads(lambda x: x * x, range(7)) == [x * x for x in range(7)]
    assert host.in_threads(lambda x: x, []) == []
    monkeypatch.setattr(host, "MIN_SPLIT_ROWS", 1)
    rows = np.random.default_rng(0).standard_normal((101, 3))
    np.testing.assert_array_equal(host.by_rows(lambda a: a.sum(axis=1), rows), rows.sum(axis=1))


def test_product_by_rows_is_the_product_to_the_bit(threads):
    """``product_by_rows`` against SciPy's one product: the same entries in the same
    order in each row, the same index type, rows left empty included."""
    from scipy import sparse

    rng = np.random.default_rng(1)
    left = sparse.random(257, 90, density=0.05, format="csr", random_state=rng)
    left = sparse.csr_matrix(left.multiply((np.arange(257) % 7 != 0)[:, None]))  # empty rows
    right = sparse.random(90, 60, density=0.1, format="csr", random_state=rng)
    for a, b in [(left, right), (left, right.tocsc()), (right.T.tocsr(), left.T.tocsr())]:
        expected = sparse.csr_matrix(a @ b)
        got = host.product_by_rows(a, b)
        assert got.shape == expected.shape
        for name in ("data", "indices", "indptr"):
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name))
            assert getattr(got, name).dtype == getattr(expected, name).dtype


def test_ahead_yields_every_result_in_order_and_stops_early(threads):
    made = []

    def work(x):
        made.append(x)
        return 10 * x

    assert list(host.ahead(work, range(6))) == [0, 10, 20, 30, 40, 50]
    made.clear()
    for value in host.ahead(work, [1, 2, 3, 4]):
        if value == 20:
            break
    # At most one item a thread was made ahead of the last one taken.
    assert {1, 2} <= set(made) and len(made) <= 2 + threads
    with pytest.raises(ZeroDivisionError):
        list(host.ahead(lambda x: 1 / x, [1, 0, 2]))


def test_work_nested_in_a_pool_thread_runs_there(monkeypatch):
    monkeypatch.setattr(host, "host_threads", lambda: 2)
    inner = host.in_threads(lambda x: host.in_threads(lambda y: (x, y), range(3)), range(4))
    assert inner == [[(x, y) for y in range(3)] for x in range(4)]
    nested = [list(host.ahead(lambda y: y + x, range(3))) for x in host.ahead(int, range(2))]
    assert nested == [[0, 1, 2], [1, 2, 3]]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_makes_its_own_pools(monkeypatch):
    monkeypatch.setattr(host, "host_threads", lambda: 2)
    assert host.in_threads(lambda x: x + 1, range(3)) == [1, 2, 3]  # the parent's pool
    read, write = os.pipe()
    child = os.fork()
    if child == 0:  # pragma: no cover - the child reports through the pipe
        try:
            ok = host.in_threads(lambda x: x + 1, range(3)) == [1, 2, 3]
            ok = ok and threading.current_thread() is threading.main_thread()
            os.write(write, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(write)
    os.waitpid(child, 0)
    assert os.read(read, 1) == b"1"
    os.close(read)


def test_threaded_work_hands_its_freed_pages_back(threads, monkeypatch):
    """``in_threads`` and ``ahead`` release what their workers freed when threaded work
    ends, and only then (``release_freed_memory``)."""
    calls = []
    monkeypatch.setattr(host, "release_freed_memory", lambda: calls.append(1))
    host.in_threads(lambda x: x, range(4))
    list(host.ahead(lambda x: x, range(4)))
    assert len(calls) == (2 if threads > 1 else 0)
    calls.clear()
    host.in_threads(lambda x: x, [1])
    assert calls == []
