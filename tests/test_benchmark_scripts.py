"""Every benchmark script imports: a module moved in the package must not leave a script
importing it from its old place (no test runs most of these scripts end to end)."""

import importlib
from pathlib import Path

import pytest

SCRIPTS = sorted(
    p.stem for p in (Path(__file__).resolve().parent.parent / "benchmarks").glob("*.py")
)


@pytest.mark.parametrize("name", [s for s in SCRIPTS if s != "__init__"])
def test_benchmark_script_imports(name):
    module = importlib.import_module(f"benchmarks.{name}")
    assert module.__name__ == f"benchmarks.{name}"
