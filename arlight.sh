#!/usr/bin/env bash
# Run the arlight command, setting everything up first. With no arguments: the demo (a server,
# the built-in synthetic scene streamed to it over loopback, a display client; writes out/).
set -euo pipefail
cd "$(dirname "$0")"
scripts/bootstrap.sh
if [ $# -eq 0 ]; then set -- demo --out out; fi
exec .venv/bin/arlight "$@"
