"""The automatic settings of a cloud held by several processes
(``jurs._fit.process_settings``), their reductions checked in one process: with one part
they must make one process's choices exactly. The fit over two real processes is in
tests/test_distributed.py."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jurs
from jurs._fit import settings as settings_module
from jurs._fit.process_settings import settings_across_processes
from jurs._fit.settings import choose_settings


def _one_process(p, n, probes, monkeypatch, smoothing=None):
    """``choose_settings`` of the whole cloud, measured at ``probes`` strided points."""
    import jurs._cloud.cloud as cloud_module

    monkeypatch.setattr(cloud_module, "PROBES", probes)
    monkeypatch.setattr(settings_module, "PROBES", probes)
    return choose_settings(jurs.Cloud(p, n), None, smoothing=smoothing)


@pytest.mark.parametrize("noise, smoothing", [(0.0, None), (0.002, 1e-4)])
def test_combined_reductions_equal_one_process_choice(noise, smoothing, monkeypatch):
    """Measured per part at 250 probes and reduced (gathered per-probe values, medians,
    the weighted agreement, the feature quantile, all-reduced bounds): with one part the
    settings are one process's at the same probes (grid, offset, eps, domain, lambda,
    spacing, noise), to rounding; set_aside is not looked for. The noisy cloud's
    smoothing is given: its held-out choice runs on the gathered probes, not the cloud."""
    p, n = jurs.datasets.example1(1000)
    p = p + noise * np.random.default_rng(0).standard_normal(p.shape)
    args = jnp.asarray(p), jnp.asarray(n)
    got = settings_across_processes(*args, smoothing=smoothing, gather_limit=250)
    ref = _one_process(p, n, 250, monkeypatch, smoothing)
    assert not ref.set_aside  # else the one-process measurements leave points out
    assert got.grid == ref.grid and got.smoothing == ref.smoothing
    for name in ("offset", "eps", "lam", "spacing", "noise", "thin_fraction"):
        assert np.isclose(getattr(got, name), getattr(ref, name), rtol=1e-12, atol=0), name
    np.testing.assert_allclose(got.domain, ref.domain, rtol=1e-12)


def test_small_cloud_gathered_is_one_process_choice():
    """A cloud of at most ``gather_limit`` points is gathered and chosen from as one
    process chooses: the same settings exactly."""
    p, n = jurs.datasets.example1(400)
    got = settings_across_processes(jnp.asarray(p), jnp.asarray(n))
    assert got == jurs.auto_settings(p, n)
