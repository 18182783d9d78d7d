"""Fits over several processes (``jax.distributed``): joining them, writing a result once,
and a launcher for N processes on one machine (docs/sharding.md, "Reading and writing in
parts").

    python -m jurs.distributed --processes 4 fit_parts.py [script arguments ...]

starts ``fit_parts.py`` 4 times on this machine, each with the environment
[`initialize`][jurs.distributed.initialize] reads (``JAX_COORDINATOR_ADDRESS``,
``JURS_NUM_PROCESSES``, ``JURS_PROCESS_ID``); the script calls
``jurs.distributed.initialize()`` before any other JAX call. On several machines run the
launcher on each with ``--total``, ``--first`` and the coordinator's ``--coordinator
host:port``, or set those three variables (or ``jax.distributed.initialize``'s
arguments) by hand. Not imported by ``import jurs``: ``import jurs.distributed``.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable

#: Environment variables the launcher sets and ``initialize`` reads (JAX itself reads the
#: coordinator's address from ``JAX_COORDINATOR_ADDRESS``).
ENV_ADDRESS, ENV_COUNT, ENV_ID = "JAX_COORDINATOR_ADDRESS", "JURS_NUM_PROCESSES", "JURS_PROCESS_ID"


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    **kwargs,
) -> bool:
    """Join this process to the others (``jax.distributed.initialize``), before any other
    JAX call; True where it joined, False where there is nothing to join.

    Arguments not given come from the environment the launcher
    (``python -m jurs.distributed``) sets: ``JAX_COORDINATOR_ADDRESS`` (``host:port`` of
    process 0), ``JURS_NUM_PROCESSES`` and ``JURS_PROCESS_ID``. With neither arguments nor
    those variables (a script run alone), or one process in all, nothing is joined and
    the script runs as one process. CPU processes exchange their sums through gloo
    (``jax_cpu_collectives_implementation``); GPUs and TPUs bring their own collectives.
    ``kwargs`` go to ``jax.distributed.initialize`` (e.g. ``initialization_timeout``).
    Calling it again in a process already joined does nothing (returns True).
    """
    import jax

    if jax.distributed.is_initialized():
        return True
    env = os.environ
    address = coordinator_address or env.get(ENV_ADDRESS)
    count = num_processes if num_processes is not None else _env_int(ENV_COUNT)
    index = process_id if process_id is not None else _env_int(ENV_ID)
    if count is None and index is None and address is None:
        return False
    if count is None or index is None or address is None:
        raise ValueError(
            f"coordinator_address, num_processes and process_id (or {ENV_ADDRESS}, {ENV_COUNT} "
            f"and {ENV_ID}) go together: got {address!r}, {count!r}, {index!r}"
        )
    if count == 1:
        return False
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=address, num_processes=count, process_id=index, **kwargs
    )
    return True


def _env_int(name: str) -> int | None:
    value = os.environ.get(name)
    if value is None or value == "":
        return None
    try:
        return int(value)
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {value!r}") from None


def write_once(path: str | os.PathLike[str], write: Callable[[str], object]) -> str:
    """Write a file of the whole result once, by process 0: ``write(name)`` runs in process
    0 only, into a temporary file beside ``path`` (``.<name>.partial-<pid><suffix>``, the
    suffix kept for writers that choose the format by it), which then replaces ``path``
    in one rename; a reader never sees half a file, and a failed write leaves no file.
    Every process calls it and returns once the file is there (one all-gather of a flag,
    which waits for process 0): an error in process 0's write is raised there, and a
    RuntimeError naming it in the others. Returns ``path`` as a string.

    The spline a fit returns is the same in every process, so its mesh and its file are
    made where they are written::

        jurs.distributed.write_once("fit.npz", lambda f: jurs.save_spline(f, sol.spline))
        jurs.distributed.write_once(
            "surface.ply", lambda f: jurs.datasets.save_mesh(f, *jurs.levelset.mesh(sol.spline))
        )

    The other processes see the file where the folder is shared (one machine, or a
    shared file system). In one process it is a plain atomic write.
    """
    import jax

    from ._cloud.parts import agree

    path = os.fspath(path)
    failure = None
    if jax.process_index() == 0:
        folder, name = os.path.split(path)
        stem, suffix = os.path.splitext(name)
        partial = os.path.join(folder, f".{stem}.partial-{os.getpid()}{suffix}")
        try:
            write(partial)
            os.replace(partial, path)
        except Exception as error:  # re-raised below, once the others know
            failure = error
            if os.path.exists(partial):
                os.remove(partial)
    agree(failure, f"writing {path}")
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m jurs.distributed",
        description="Run a script as N processes on this machine, joined by "
        "jax.distributed (the script calls jurs.distributed.initialize() first).",
    )
    parser.add_argument("--processes", type=int, required=True, help="processes to start here")
    parser.add_argument(
        "--coordinator",
        default=None,
        help="host:port of process 0 (default localhost and a free port; on several "
        "machines the same on every one)",
    )
    parser.add_argument(
        "--total", type=int, default=None, help="processes on all machines (default --processes)"
    )
    parser.add_argument(
        "--first", type=int, default=0, help="the id of the first process started here"
    )
    parser.add_argument(
        "--cpu-devices",
        type=int,
        default=None,
        help="CPU devices in each process (XLA_FLAGS=--xla_force_host_platform_device_count)",
    )
    parser.add_argument("script", help="the Python script every process runs")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="the script's arguments")
    return parser


def launch(argv: list[str] | None = None) -> int:
    """``python -m jurs.distributed``: start the processes, wait for them all, and return
    the first non-zero exit status (0 where all succeeded). One that fails has the others
    stopped (they would wait for it in their next collective); so does Ctrl-C. Their
    output goes to this terminal as they write it."""
    parser = _parser()
    a = parser.parse_args(argv)
    total = a.processes if a.total is None else a.total
    if a.processes < 1 or not 0 <= a.first <= total - a.processes:
        parser.error(
            f"--processes {a.processes} from --first {a.first} must lie within --total {total}"
        )
    if not os.path.exists(a.script):
        parser.error(f"{a.script}: no such file")
    if a.coordinator is None and total > a.processes:
        parser.error("--coordinator host:port is needed where processes run on several machines")
    env = dict(os.environ, **{ENV_COUNT: str(total)})
    env[ENV_ADDRESS] = a.coordinator or f"localhost:{_free_port()}"
    if a.cpu_devices is not None:
        flag = f"--xla_force_host_platform_device_count={a.cpu_devices}"
        env["XLA_FLAGS"] = " ".join(filter(None, [env.get("XLA_FLAGS"), flag]))
    children = [
        subprocess.Popen(
            [sys.executable, a.script, *a.args], env=dict(env, **{ENV_ID: str(a.first + i)})
        )
        for i in range(a.processes)
    ]
    status = 0
    try:
        while None in (states := [c.poll() for c in children]):  # every one polled
            failed = [code for code in states if code not in (None, 0)]
            if failed:
                status = failed[0]
                break
            time.sleep(0.1)
    except KeyboardInterrupt:
        status = 128 + signal.SIGINT
    finally:
        for child in children:
            if child.poll() is None:
                child.terminate()
        for child in children:
            try:
                child.wait(timeout=10)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
    return status or next((c.returncode for c in children if c.returncode), 0)


if __name__ == "__main__":
    sys.exit(launch())
