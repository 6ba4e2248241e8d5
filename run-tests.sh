#!/usr/bin/env bash
# Set everything up, then run the linter and the test suite (extra arguments go to pytest).
set -euo pipefail
cd "$(dirname "$0")"
scripts/bootstrap.sh
scripts/test-tools.sh  # test-only tools (cmgen, headless Chromium) where apt and root allow
.venv/bin/ruff check .
exec .venv/bin/python -m pytest "$@"
