"""The benchmark scripts, a package: run each from the repository root as a module,
``python -m benchmarks.<name>`` (``python -m benchmarks.speed --quick``). The scripts import
their shared modules (``_common``, ``_baselines``, ...) and each other relatively
(``from ._common import ...``); a script that measures in fresh processes starts them as
``python -m benchmarks.<worker>`` from the repository root.

Being a package also lets pytest import ``benchmarks/tests`` under names of its own
(``benchmarks.tests.conftest``) beside the library's ``tests/``, whose modules import their
``conftest`` by that bare name."""
