#!/usr/bin/env bash
# Run the arlight command, setting everything up first. With no arguments: estimate the
# lighting of the built-in synthetic scene (the default main job).
set -euo pipefail
cd "$(dirname "$0")"
scripts/bootstrap.sh
if [ $# -eq 0 ]; then set -- estimate synthetic --poses groundtruth --out out/results.jsonl; mkdir -p out; fi
exec .venv/bin/arlight "$@"
