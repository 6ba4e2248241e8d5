"""Process-wide settings the entry points choose once (pipeline.runtime, the `arlight`
command), none made by importing the library, and the version written in one place."""

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import open3d as o3d
import pytest

from arlight.pipeline import runtime
from arlight.pipeline.volume import _check_open3d_version


def test_configure_open3d_threads():
    runtime.configure_open3d_threads(1)
    assert o3d.utility.get_max_threads() == 1
    with pytest.raises(ValueError, match="--open3d-threads"):
        runtime.configure_open3d_threads(0)
    runtime.configure_open3d_threads(None)  # leaves it as it is
    assert o3d.utility.get_max_threads() == 1


def test_numba_uses_openmp_without_probing_tbb():
    code = (
        "import warnings; warnings.simplefilter('error'); "
        "from arlight.pipeline.runtime import configure_process; configure_process(); "
        "import numba, numpy as np\n"
        "@numba.njit(parallel=True)\n"
        "def f(a):\n    return a.sum()\n"
        "f(np.ones(8)); print(numba.threading_layer())"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() in ("omp", "tbb", "workqueue")
    assert "TBB" not in run.stderr


def test_importing_the_pipeline_leaves_the_warnings_filter_alone():
    import importlib

    import arlight.pipeline

    before = list(warnings.filters)
    importlib.reload(arlight.pipeline)
    assert warnings.filters == before


def test_open3d_version_outside_the_supported_range_is_refused():
    _check_open3d_version("0.20.0")
    for version in ("0.19.0", "0.21.0"):
        with pytest.raises(ImportError, match=r"open3d >=0\.20,<0\.21"):
            _check_open3d_version(version)


def _python(code: str, env: dict | None = None) -> str:
    """stdout of `python -c code` in a fresh interpreter (imports not yet done here)."""
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert run.returncode == 0, run.stderr
    return run.stdout


class TestNoSideEffectsOnImport:
    def test_importing_arlight_and_the_pipeline_changes_no_environment_variable(self):
        out = _python(
            "import os\nbefore = dict(os.environ)\n"
            "import arlight, arlight.pipeline\n"
            "print(sorted(set(os.environ.items()) ^ set(before.items())))"
        )
        assert out.strip() == "[]"

    # what OpenBLAS reads is the environment when numpy is imported: watched by a finder
    WATCH = (
        "import os, sys\n"
        "class Watch:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'numpy':\n"
        "            print('at numpy:', os.environ.get('OPENBLAS_NUM_THREADS'), flush=True)\n"
        "sys.meta_path.insert(0, Watch())\n"
        "import arlight.cli\n"
    )

    def test_the_command_sets_one_blas_thread_before_numpy_loads(self):
        env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
        assert _python(self.WATCH, env).splitlines()[0] == "at numpy: 1"

    def test_a_users_blas_threads_win(self):
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "3"}
        assert _python(self.WATCH, env).splitlines()[0] == "at numpy: 3"


def test_the_version_is_pyprojects():
    """Written once, in pyproject.toml; arlight.__version__ reads the installed metadata."""
    import arlight

    text = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    project = text.split("[project]", 1)[1]
    assert arlight.__version__ == re.search(r'^version = "([^"]+)"', project, re.M).group(1)
