"""Shared test setup: the maths runs in float64 (E_ave sits at 1e-6..1e-8)."""

import os

import equinox as eqx
import jax
import matplotlib
import numpy as np
import pytest
from scipy.interpolate import BSpline

jax.config.update("jax_enable_x64", True)
# jurs.cli.main turns JAX's persistent compilation cache on (in the user's cache folder) for
# the rest of its process: in-process CLI calls in tests would then write there and change
# what later tests in the same worker compile. Tests of the cache itself run subprocesses
# with their own environment (tests/test_startup.py).
os.environ["JURS_NO_COMPILATION_CACHE"] = "1"
matplotlib.use("Agg")


#: The paper's Example 1 settings (fit's defaults are chosen from the data instead).
PAPER = dict(grid=(9, 9), offset=0.1, eps=0.01)


def dense_basis(xy, lower, upper, shape):
    """All N*M tensor-product B-spline values at ``xy`` as a dense (n, N*M) matrix, built
    independently of jurs with scipy (knots: uniform, extended 3 cells past the box)."""
    columns = []
    for axis in range(2):
        n = shape[axis]
        h = (upper[axis] - lower[axis]) / (n - 3)
        knots = lower[axis] + (np.arange(n + 4) - 3.0) * h
        columns.append(BSpline.design_matrix(np.asarray(xy)[:, axis], knots, 3).toarray())
    bx, by = columns
    return (bx[:, :, None] * by[:, None, :]).reshape(len(xy), -1)


def dense_collocation(problem, weights):
    """D of eq. 23 (rows w_ij B_ij / W), dense, in the problem's slot order (test sizes only)."""
    basis = dense_basis(
        np.asarray(problem.samples),
        np.asarray(problem.lower),
        np.asarray(problem.upper),
        problem.shape,
    )
    wb = basis * np.asarray(weights).ravel()[None, :]
    return wb / wb.sum(axis=1, keepdims=True)


TABLE_FIELDS = ("terms", "terms_t", "index", "corner", "order", "position", "filled")


def without_table(problem):
    """The same problem with its basis in the power form only (as a traced build has it)."""
    return eqx.tree_at(
        lambda p: tuple(getattr(p.local, f) for f in TABLE_FIELDS),
        problem,
        (None,) * len(TABLE_FIELDS),
        is_leaf=lambda x: x is None,
    )


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def example1_cloud():
    """The paper's Example 1 at 120 points: ``(points, normals)``."""
    import jurs

    return jurs.datasets.example1(120)


#: Tests of one file that take no module-scoped fixture go to a worker in runs of this
#: many neighbours (pytest_xdist_make_scheduler).
XDIST_CHUNK = 8


def _module_fixture_users(path):
    """Names of the test functions in the file at ``path`` that take, directly or through
    another fixture of the file, a fixture of module scope defined there."""
    import ast

    fixtures, module_scoped, tests = {}, set(), {}
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if not isinstance(node, ast.FunctionDef):
            continue
        args = {a.arg for a in node.args.args}
        for dec in node.decorator_list:
            call = dec if isinstance(dec, ast.Call) else None
            target = call.func if call else dec
            if ast.unparse(target) in ("pytest.fixture", "fixture"):
                fixtures[node.name] = args
                scope = [k.value for k in call.keywords if k.arg == "scope"] if call else []
                if scope and isinstance(scope[0], ast.Constant) and scope[0].value == "module":
                    module_scoped.add(node.name)
                break
        else:
            if node.name.startswith("test"):
                tests[node.name] = args
    bound = set(module_scoped)
    while True:  # fixtures that use a module-scoped one wait for it too
        more = {name for name, args in fixtures.items() if args & bound} - bound
        if not more:
            break
        bound |= more
    return {name for name, args in tests.items() if args & bound}


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    """With several workers (make test: -n 2), xdist's default "load" splits the tests
    without regard to fixtures: the tests of one module-scoped fixture landed on both
    workers and each built it (the ten solver fits of test_solvers_extra: 128 s and 101 s
    of setup in one run), and a worker that ran another module in between built it again.
    Here the tests that take such a fixture go to one worker together, in their order;
    the others go in runs of ``XDIST_CHUNK`` neighbours of one file (they often compile
    the same fits). xdist sends the larger units first. (xdist's own ``--dist loadgroup``
    marks groups by renaming test ids, which this pytest's nodes no longer allow.)"""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    users, scopes, counts = {}, {}, {}

    class ModuleFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            if nodeid in scopes:
                return scopes[nodeid]
            module, _, rest = nodeid.partition("::")
            if module.endswith(".py") and module not in users:
                path = config.rootpath / module
                users[module] = _module_fixture_users(path) if path.is_file() else set()
            name = rest.split("::")[0].split("[")[0]
            if name in users.get(module, ()):
                scope = module
            else:
                i = counts.get(module, 0)
                counts[module] = i + 1
                scope = f"{module}#{i // XDIST_CHUNK}"
            scopes[nodeid] = scope
            return scope

    return ModuleFixtureScheduling(config, log)


@pytest.fixture(autouse=True)
def _fresh_kept_clouds():
    """Each test starts with no cloud kept by ``jurs.fit`` from an earlier one (the clouds
    it keeps by content for repeated fits): tests that count checks or problem builds see
    their own fit's."""
    from jurs._fit import fit as fit_module

    fit_module._kept_clouds.clear()
    yield
