#!/usr/bin/env bash
# Set everything up, then run the linter and the test suite (extra arguments go to pytest).
set -euo pipefail
cd "$(dirname "$0")"
scripts/bootstrap.sh --chromium  # + headless Chromium for the browser display's page test
.venv/bin/ruff check .
exec .venv/bin/python -m pytest "$@"
