"""The public surface: a small ``jurs.__all__`` with docstrings, the kernels under
``jurs.internal``, and a clear error for a name that moved there."""

import inspect

import pytest

import jurs
import jurs.internal


def test_public_names_resolve_and_are_documented():
    # Kept small on purpose: a new top-level name must earn its place (the adaptive fit
    # and its spline did; so did the attribute fit, fit_attributes and AttributeField, and
    # AbstractSpline, the interface both bases' splines share).
    assert len(jurs.__all__) <= 40
    for name in jurs.__all__:
        value = getattr(jurs, name)
        if name == "COMPILER_OPTIONS":  # a dict, documented by its #: comment
            assert isinstance(value, dict)
            continue
        assert inspect.getdoc(value), name


def test_internal_names_resolve_and_are_not_public():
    for name in jurs.internal.__all__:
        assert inspect.getdoc(getattr(jurs.internal, name)), name
        assert name not in jurs.__all__


def test_a_moved_name_says_where_it_went():
    with pytest.raises(AttributeError, match=r"jurs\.internal\.bspline_values"):
        jurs.bspline_values
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        jurs.no_such_name


def test_every_verdict_has_a_short_name():
    from jurs._solution.solution import RAISED_RESULTS, RESULT_NAMES

    items = [getattr(jurs.RESULTS, name) for name in RESULT_NAMES]
    for i, a in enumerate(items):  # distinct items, so Solution.status names each one
        for j, b in enumerate(items):
            assert bool(a == b) == (i == j)
    assert set(RAISED_RESULTS) < set(RESULT_NAMES) and "max_steps_reached" not in RAISED_RESULTS
