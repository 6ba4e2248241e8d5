"""What every test module shares: the process's thread settings, the shared data, helpers.

pytest puts tests/ on sys.path (its default "prepend" import mode: tests/ is not a package),
so test modules import the names below with `from conftest import DATA, SMALL, need_data`,
as they import `streaming_support`; the repository root is on sys.path too (pyproject's
pytest `pythonpath`), so the benchmark scripts import as `benchmarks.<name>`.

Angles between directions: `arlight.evaluation.angular_error_deg`.
"""

import os

# One BLAS thread, as the `arlight` command runs (arlight/cli/__init__.py says why); OpenBLAS
# reads it when numpy loads, which is after this module (a value set by the caller wins)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path

import pytest

# The shared data sets (sequences with ground truth, real recordings, HDR maps) live beside
# the repository; a fresh clone has none, and the tests that read them skip, saying so.
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# a pipeline small enough for tests: a coarse volume and auxiliary buffers
SMALL = {"volume_resolution": 64, "aux_resolution": 32}


def missing_data(path: Path) -> str:
    """The skip message of a test that needs `path` of the shared data."""
    return f"needs the shared test data at {path} (absent: a fresh clone has no ../shared/data)"


def needs_data(path: Path = DATA) -> pytest.MarkDecorator:
    """A skip mark (module, class or test) for tests that read `path` of the shared data."""
    return pytest.mark.skipif(not path.exists(), reason=missing_data(path))


def need_data(path: Path = DATA) -> Path:
    """`path`, or a skip of the running test (or fixture) when it is absent."""
    if not path.exists():
        pytest.skip(missing_data(path))
    return path


@pytest.fixture
def shared_data() -> Path:
    """The shared data folder (../shared/data); the test is skipped without it."""
    return need_data(DATA)


@pytest.fixture
def make_server():
    """make(process=None, **option overrides) -> a started loopback Server; every server made
    is stopped afterwards (streaming_support.server_factory). A module may define its own."""
    from streaming_support import server_factory

    yield from server_factory()


def pytest_configure(config: pytest.Config) -> None:
    """Open3D on one thread, for the whole run: its frame-to-model tracking sums in a
    thread-dependent order, so with several threads the same frames give poses that differ
    by ~1e-5 m from run to run, and the tests compare poses (pipeline/runtime.py)."""
    from arlight.pipeline.runtime import configure_open3d_threads

    configure_open3d_threads(1)
