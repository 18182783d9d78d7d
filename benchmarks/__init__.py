"""The benchmark scripts, run as ``python benchmarks/<name>.py``; they import their shared
modules (``_common``, ``_baselines``, ...) as top-level modules from this folder.

A package only so that pytest imports ``benchmarks/tests`` under names of its own
(``benchmarks.tests.conftest``) beside the library's ``tests/``, whose modules import their
``conftest`` by that bare name."""
