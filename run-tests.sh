#!/usr/bin/env bash
# Set everything up, then run the linter, the format check and the type checker, build the docs and run the test
# suite (extra arguments go to pytest).
set -euo pipefail
cd "$(dirname "$0")"
scripts/bootstrap.sh
scripts/test-tools.sh  # test-only tools (cmgen, headless Chromium) where apt and root allow
.venv/bin/ruff check .
.venv/bin/ruff format --check .  # formatted once (.git-blame-ignore-revs); run `ruff format .`
# the type checker ([tool.mypy] in pyproject.toml): the arlight package but the Numba kernels
.venv/bin/mypy
# the docs site, warnings as errors: a broken link or a reference page the code can no longer
# generate fails the run (NO_MKDOCS_2_WARNING: the Material theme's banner, not our warning)
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --quiet
exec .venv/bin/python -m pytest "$@"
