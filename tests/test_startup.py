"""Start-up: ``import jurs`` loads only the core, and compiled fits are kept across
processes (the command line by default, library users through
``jurs.enable_compilation_cache``). Each check runs in a fresh process."""

import json
import os
import subprocess
import sys

import pytest

import jurs

HEAVY = (
    "matplotlib",
    "scipy.spatial",
    "optimistix",
    "optax",
    "jaxopt",
    "contourpy",
    "skimage",
    "jurs.levelset",
    "jurs.plot",
    "jurs.shapes",
    "jurs.datasets",
)

LAZY_IMPORTS = """
import json, sys
import jurs
loaded = [name for name in {heavy!r} if name in sys.modules]
missing = [name for name in jurs.__all__ if name not in dir(jurs)]
levelset = jurs.levelset.analyze.__module__  # a submodule on first attribute access
wrapper = jurs.OptimistixMinimiser.__name__
unreachable = [name for name in jurs.__all__ if not hasattr(jurs, name)]
print(json.dumps([loaded, missing, levelset, wrapper, unreachable,
                  "optimistix" in sys.modules]))
"""


def _run_python(code, env=None, timeout=300):
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, env=env
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_import_loads_only_the_core_and_every_name_on_first_use():
    loaded, missing, levelset, wrapper, unreachable, optimistix = json.loads(
        _run_python(LAZY_IMPORTS.format(heavy=HEAVY)).splitlines()[-1]
    )
    assert loaded == [] and missing == [] and unreachable == []
    assert levelset == "jurs.levelset" and wrapper == "OptimistixMinimiser" and optimistix


def test_unknown_attribute_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        jurs.no_such_name  # noqa: B018


def _cli(args, tmp_path, **env):
    environ = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "xdg"), JAX_PLATFORMS="cpu")
    environ.pop("JAX_COMPILATION_CACHE_DIR", None)
    environ.pop("JURS_NO_COMPILATION_CACHE", None)
    environ.update(env)
    return subprocess.run(
        [sys.executable, "-m", "jurs.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env=environ,
        cwd=tmp_path,
    )


@pytest.mark.slow
def test_command_line_cache_folder_and_its_switches(tmp_path):
    """The cache folder is $XDG_CACHE_HOME/jurs unless the flag or the variable turns it
    off (checked on a bad input file: the folder is set up before the input is read)."""
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,nx,ny\n1,2,3\n")
    folder = tmp_path / "xdg" / "jurs"
    for args, env in ((["--no-compilation-cache"], {}), ([], {"JURS_NO_COMPILATION_CACHE": "1"})):
        proc = _cli(["fit", str(bad), *args], tmp_path, **env)
        assert proc.returncode == 2 and not folder.exists(), proc.stderr
    proc = _cli(["fit", str(bad)], tmp_path, JURS_NO_COMPILATION_CACHE="0")
    assert proc.returncode == 2 and (folder / "jurs-exported-fits").is_dir(), proc.stderr


FIT_WITH_THE_STORE = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import functools
import jurs, jurs.solvers._parts as parts
folder = jurs.enable_compilation_cache(sys.argv[1])
traced = []
def counting(fn):
    @functools.wraps(fn)
    def run(*args):
        traced.append(fn.__name__)
        return fn(*args)
    return run
for name in ("_assembled_part", "_solved", "_measured_part", "_concluded"):
    setattr(parts, name, counting(getattr(parts, name)))
points, normals = jurs.datasets.example1(90)
sol = jurs.fit(points, normals, grid=9, offset=0.1, eps=0.01, solver=jurs.LeastSquares(lam=1e-4))
again = jurs.fit(points[:85], normals[:85], grid=9, offset=0.1, eps=0.01,
                 solver=jurs.LeastSquares(lam=1e-3))
print(json.dumps([folder, len(traced), float(sol.metrics["E_ave"]), sol.message,
                  type(sol.spline).__name__, float(again.metrics["E_ave"])]))
"""


@pytest.mark.slow
def test_a_new_process_loads_the_exported_fit_without_tracing(tmp_path):
    """The first process traces each of the fit's four steps once (the second fit, 85
    points and another lambda, reuses them), in the one program of a cloud that is one
    small part; the next process traces none of them and gets the same result."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    code = FIT_WITH_THE_STORE.replace("sys.argv[1]", repr(str(tmp_path / "cache")))
    first = json.loads(_run_python(code, env).splitlines()[-1])
    second = json.loads(_run_python(code, env).splitlines()[-1])
    assert first[0] == second[0] == str(tmp_path / "cache")
    assert first[1] == 4 and second[1] == 0, (first, second)
    assert first[2:] == second[2:] and first[4] == "ImplicitSpline"
    assert len(os.listdir(tmp_path / "cache" / "jurs-exported-fits")) == 1
