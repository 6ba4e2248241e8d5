#!/usr/bin/env bash
# The npm packages of the optional node tests (tests/test_gltf_asset.py: Babylon.js's glTF
# loader reads arlight's .glb; tests/test_gltf_render.py: Babylon's browser build renders it
# in headless Chromium; tests/test_engine_export_node.py: three.js evaluates the webxr and
# main_light layouts), installed outside the repository (about 350 MB), in
# ${ARLIGHT_NODE_PREFIX:-$HOME/.cache/arlight-node}/node_modules, where the tests look
# (or set ARLIGHT_NODE_MODULES). Without node/npm, or offline, the tests skip and say so.
set -euo pipefail
prefix="${ARLIGHT_NODE_PREFIX:-$HOME/.cache/arlight-node}"
if ! command -v npm >/dev/null; then
  echo "node_test_deps: npm not installed (apt-get install nodejs npm); the node tests skip" >&2
  exit 0
fi
mkdir -p "$prefix"
npm install --prefix "$prefix" --no-audit --no-fund @babylonjs/core@9 @babylonjs/loaders@9 \
  babylonjs@9 babylonjs-loaders@9 three@0.187
