"""The hierarchy fit's one flow: jurs.fit_adaptive takes jurs.fit's cloud and settings,
and the verdict of a hierarchy solve is made in one place for one process and several
(``jurs._fit.adaptive.hierarchy_solution``)."""

import numpy as np

import jurs
from jurs._fit.adaptive import DIRECT_RTOL, hierarchy_solution


def test_hierarchy_verdict_follows_the_solve():
    points, normals = jurs.datasets.example1(200)
    sol = jurs.fit_adaptive(points, normals)
    hierarchy, control = sol.spline.hierarchy, np.asarray(sol.spline.control)

    def verdict(method="cg", residual=0.0, rtol=1e-10, values=control, settled=True):
        made = hierarchy_solution(
            hierarchy, values, sol.metrics, sol.settings, method=method, steps=3,
            residual=residual, rtol=rtol, dtype=control.dtype, settled=settled, devices=2,
        )  # fmt: skip
        return made.status, made.stats

    status, stats = verdict()
    assert status == "successful"
    head = ["method", "num_steps", "residual", "levels", "active", "finest"]
    assert list(stats) == head + ["devices"]  # the caller's entries last
    assert stats["finest"] == sol.stats["finest"] and stats["active"] == sol.stats["active"]
    assert verdict(residual=1e-8)[0] == "max_steps_reached"  # CG stopped short
    assert verdict(settled=False)[0] == "max_steps_reached"  # the solver's own rule
    # A direct solve is exact up to rounding: only a residual past DIRECT_RTOL fails it.
    assert verdict("direct", residual=1e-8)[0] == "successful"
    assert verdict("direct", residual=10 * DIRECT_RTOL)[0] == "max_steps_reached"
    assert verdict(values=np.full_like(control, np.nan))[0] == "nonfinite"


def test_fit_adaptive_takes_the_cloud_and_settings_of_fit():
    """Without normals both estimate them and say so; the same settings give the same
    spline on the hierarchy."""
    points, _ = jurs.datasets.example1(200)
    by_fit = jurs.fit(points, basis="adaptive")
    direct = jurs.fit_adaptive(points)
    assert direct.stats["estimated_normals"] == by_fit.stats["estimated_normals"]
    assert direct.settings == by_fit.settings
    np.testing.assert_array_equal(direct.spline.control, by_fit.spline.control)
