"""The benchmark scripts (each run as `.venv/bin/python benchmarks/NAME.py`, see
docs/developer/benchmarking.md), outside the test suite. A package, so that the tests that
check a benchmark's functions import them as `benchmarks.NAME`."""
