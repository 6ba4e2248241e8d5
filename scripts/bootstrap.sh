#!/usr/bin/env bash
# Set up everything arlight needs on a fresh Debian/Ubuntu machine (idempotent, quick when done):
# the system libraries Open3D loads, a virtual environment in .venv, and arlight installed
# into it in editable mode with its test and docs tools, and the Numba kernels compiled into
# their cache.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if ! command -v "$PYTHON" >/dev/null; then
  echo "arlight: python3 (>= 3.10) is required: apt-get install python3 python3-venv" >&2; exit 1
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
  echo "arlight: Python >= 3.10 is required, found $("$PYTHON" --version)" >&2; exit 1
fi

# Open3D's wheel loads libusb-1.0, libGL/libEGL and libgomp at import time. The cache is read
# once into a variable: `ldconfig -p | grep -q` under pipefail fails with 141 when grep exits
# at its first match while ldconfig still writes (SIGPIPE), and a present library looked missing.
need=()
cache=$(ldconfig -p 2>/dev/null || true)
for lib in libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libgomp.so.1; do
  grep -qF "$lib" <<<"$cache" || need+=("$lib")
done
if [ ${#need[@]} -gt 0 ] || ! "$PYTHON" -c 'import venv, ensurepip' 2>/dev/null; then
  pkgs="libusb-1.0-0 libgl1 libegl1 libgomp1 python3-venv"
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
    echo "arlight: missing system libraries (${need[*]}); run: sudo apt-get install $pkgs" >&2
    exit 1
  fi
  echo "arlight: installing system packages: $pkgs" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $pkgs >/dev/null
fi

stamp=.venv/.arlight-installed
want=$(cat pyproject.toml | sha1sum | cut -d' ' -f1)
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "arlight: creating .venv and installing dependencies (first run takes a few minutes)" >&2
  "$PYTHON" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  # PYTHONWARNINGS: setuptools' notes about editable installs are not for our users
  # [docs]: ./run-tests.sh builds the docs site (mkdocs) before the tests
  PYTHONWARNINGS=ignore .venv/bin/python -m pip install -q -e ".[test,docs]"
  # compile the Numba kernels now (a minute or two, once), not on a user's first frames
  .venv/bin/python -m arlight.warmup
  echo "$want" > "$stamp"
fi

# The type checker's view of the package (pyproject's [tool.mypy] mypy_path): pipeline/,
# server/, client/, protocols/ and sources/ are arlight.* subpackages through setuptools'
# package-dir, which the editable install maps with an import hook that mypy cannot follow.
# build/typecheck/arlight/<sub> links to each such folder (not to its files: a module added
# later is seen without linking again), read from pyproject so the two cannot disagree.
.venv/bin/python - <<'EOF_PY'
from pathlib import Path

try:
    import tomllib
except ImportError:  # Python 3.10: pip's own copy of the same parser
    from pip._vendor import tomli as tomllib

package_dir = tomllib.loads(Path("pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
for name, folder in package_dir.items():
    link = Path("build/typecheck", *name.split("."))
    if Path(*name.split(".")) != Path(folder):
        link.parent.mkdir(parents=True, exist_ok=True)
        target = Path(*[".."] * (len(link.parts) - 1), folder)
        if not link.is_symlink() or Path(link.readlink()) != target:
            link.unlink(missing_ok=True)
            link.symlink_to(target, target_is_directory=True)
EOF_PY
