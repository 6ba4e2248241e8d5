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

import functools
import importlib.util
import math
from pathlib import Path

import msgpack
import numpy as np
import pytest

from arlight.protocols import (
    PROTOCOL_VERSION,
    CameraCalibration,
    Frame,
    ProtocolError,
    Result,
    read_container,
)

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


# --------------------------------------------------------------------------- protocol helpers
# The protocol's golden vectors and helpers of its tests (test_protocols*.py, test_spec_rules*.py)

TESTS = Path(__file__).resolve().parent
GOLDEN = TESTS / "golden" / f"protocol_v{PROTOCOL_VERSION}"


def load_vector_script(name: str = "make_protocol_vectors"):
    """tests/golden/make_protocol_vectors.py as a module named `name`: VEC.vectors() etc."""
    spec = importlib.util.spec_from_file_location(
        name, TESTS / "golden" / "make_protocol_vectors.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def smooth_rgb(h: int = 48, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack(
        [x * 255 // max(w - 1, 1), y * 255 // max(h - 1, 1), (x + y) * 127 // (w + h)], axis=-1
    ).astype(np.uint8)


def noisy_depth(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(400, 8000, (h, w)).astype(np.uint16)
    d[rng.random((h, w)) < 0.3] = 0
    d[0, 0] = 65535
    return d


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def as_bytes(parts) -> list[bytes]:
    return [bytes(memoryview(p).cast("B")) for p in parts]


def calibration(w: int = 64, h: int = 48) -> CameraCalibration:
    return CameraCalibration(w, h, 50.0, 50.0, w / 2, h / 2)


def frame(**kw) -> Frame:
    args = dict(seq=3, timestamp=12.5, color=smooth_rgb(), depth=noisy_depth(), pose=np.eye(4))
    args.update(kw)
    return Frame(**args)


def result(**kw) -> Result:
    args = dict(
        seq=3,
        timestamp=12.5,
        sh=[0.1] * 9,
        sh_rgb=None,
        dominant_direction_camera=[0.0, 0.0, 1.0],
        dominant_direction_world=[0.0, 1.0, 0.0],
        intensity=1.5,
        confidence={"samples": 10, "condition": math.inf},
        pose=np.eye(4),
        timings_ms={"render": 1.25},
        frames_received=4,
        frames_processed=3,
        frames_dropped=1,
        server_receive_time=1.0,
        server_finish_time=1.5,
    )
    args.update(kw)
    return Result(**args)


def tamper(parts, fn) -> list[bytes]:
    """Re-pack the header after fn(header) edited it in place; buffers unchanged."""
    parts = as_bytes(parts)
    header = msgpack.unpackb(parts[0], raw=False)
    fn(header)
    return [msgpack.packb(header, use_bin_type=True), *parts[1:]]


def expect(code: str, fn, *args, field: str | None = None, **kw) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        fn(*args, **kw)
    assert info.value.code == code, info.value
    if field is not None:
        assert info.value.field == field, info.value
    return info.value


# --------------------------------------------------------------------------- SPEC.md
# protocols/SPEC.md read as an outside implementer reads it (test_spec_rules*.py)


@functools.cache
def spec_text() -> str:
    return (TESTS.parent / "protocols" / "SPEC.md").read_text(encoding="utf-8")


def spec_section(heading: str) -> str:
    """The text under the first heading that starts with `heading` (any level), up to the
    next heading; fenced code is kept."""
    lines = spec_text().splitlines()
    fenced = False
    starts = []
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            starts.append(i)
    for k, i in enumerate(starts):
        if lines[i].lstrip("#").strip().startswith(heading):
            end = starts[k + 1] if k + 1 < len(starts) else len(lines)
            return "\n".join(lines[i + 1 : end])
    raise AssertionError(f"SPEC.md has no heading {heading!r}")


def golden_bytes(name: str) -> list[bytes]:
    """The parts of golden vector `name`, as bytes."""
    messages = read_container((GOLDEN / f"{name}.bin").read_bytes())
    assert len(messages) == 1
    return [bytes(p) for p in messages[0]]


def refused_parts(name: str) -> list[bytes]:
    messages = read_container((GOLDEN / "refused" / f"{name}.bin").read_bytes())
    assert len(messages) == 1
    return [bytes(p) for p in messages[0]]


def expect_refusal(code: str, field: str | None, fn, *args):
    """fn(*args) raises ProtocolError with exactly (code, field)."""
    with pytest.raises(ProtocolError) as info:
        fn(*args)
    assert (info.value.code, info.value.field) == (code, field), str(info.value)
    return info.value


def run_cli(argv: list[str], capsys) -> tuple[int, str]:
    """(exit code, stdout + stderr) of `arlight ARGV`, run in this process (argparse's
    usage errors included)."""
    from arlight.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out + captured.err


def pytest_configure(config: pytest.Config) -> None:
    """Open3D on one thread, for the whole run: its frame-to-model tracking sums in a
    thread-dependent order, so with several threads the same frames give poses that differ
    by ~1e-5 m from run to run, and the tests compare poses (pipeline/runtime.py)."""
    from arlight.pipeline.runtime import configure_open3d_threads

    configure_open3d_threads(1)
