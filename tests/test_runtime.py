"""Process-wide settings the entry points choose once (pipeline.runtime)."""

import warnings

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
    import subprocess
    import sys

    code = ("import warnings; warnings.simplefilter('error'); "
            "from arlight.pipeline.runtime import configure_process; configure_process(); "
            "import numba, numpy as np\n"
            "@numba.njit(parallel=True)\n"
            "def f(a):\n    return a.sum()\n"
            "f(np.ones(8)); print(numba.threading_layer())")
    env = {k: v for k, v in __import__("os").environ.items() if k != "NUMBA_THREADING_LAYER"}
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
