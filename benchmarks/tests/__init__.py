"""Tests of the benchmark scripts and their results files (run with the library's tests)."""
