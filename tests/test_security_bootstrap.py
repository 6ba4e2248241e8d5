"""scripts/bootstrap.sh decides which system libraries are missing from `ldconfig -p`
(issue 39, item 9): under `set -o pipefail`, `ldconfig -p | grep -q LIB` failed with 141 when
grep stopped at its first match while ldconfig still wrote (SIGPIPE), and set-up took a
present library for a missing one (as root it ran apt-get, as another user it refused to
start). The script runs here in a copy of the repository's layout with stand-ins for
ldconfig, id, sudo and Python, so nothing is installed."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LIBS = ("libusb-1.0.so.0", "libGL.so.1", "libEGL.so.1", "libgomp.so.1")


def _executable(path: Path, text: str) -> None:
    path.write_text("#!/usr/bin/env bash\n" + text)
    path.chmod(0o755)


@pytest.fixture
def layout(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A copy of the script in a folder whose .venv is already installed (its stamp
    matches pyproject.toml), and an environment whose ldconfig lists every library first,
    then 200 000 more lines (far past a pipe's buffer), as a real cache may."""
    root = tmp_path / "repo"
    (root / "scripts").mkdir(parents=True)
    shutil.copy(REPO / "scripts" / "bootstrap.sh", root / "scripts" / "bootstrap.sh")
    (root / "pyproject.toml").write_text("[project]\nname = 'stand-in'\n")
    venv_bin = root / ".venv" / "bin"
    venv_bin.mkdir(parents=True)
    _executable(venv_bin / "python", "cat >/dev/null; exit 0\n")
    digest = hashlib.sha1((root / "pyproject.toml").read_bytes()).hexdigest()
    (root / ".venv" / ".arlight-installed").write_text(digest + "\n")
    fake = tmp_path / "bin"
    fake.mkdir()
    listed = "".join(f'echo "\t{lib} (libc6,x86-64) => /usr/lib/{lib}"\n' for lib in LIBS)
    filler = "yes '\tlibfiller.so.0 => /usr/lib/x' | head -n 200000\n"
    _executable(fake / "ldconfig", listed + filler)
    _executable(fake / "id", "echo 1000\n")  # not root
    _executable(fake / "sudo", "exit 1\n")  # and no sudo: a 'missing' library stops set-up
    _executable(fake / "python3", "exit 0\n")
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}", "PYTHON": str(fake / "python3")}
    return root, env


def test_present_libraries_are_found_whatever_the_cache_size(layout):
    root, env = layout
    for _ in range(3):  # the failure depended on a race; each run must pass
        run = subprocess.run(
            ["bash", str(root / "scripts" / "bootstrap.sh")],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        assert "missing system libraries" not in run.stderr


def test_a_missing_library_is_still_reported(layout):
    root, env = layout
    fake_ldconfig = Path(env["PATH"].split(":")[0]) / "ldconfig"
    _executable(fake_ldconfig, "echo '\tlibusb-1.0.so.0 => /usr/lib/libusb-1.0.so.0'\n")
    run = subprocess.run(
        ["bash", str(root / "scripts" / "bootstrap.sh")],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 1
    assert "missing system libraries (libGL.so.1 libEGL.so.1 libgomp.so.1)" in run.stderr
