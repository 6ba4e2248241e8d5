#!/usr/bin/env bash
# Test-only tools from Debian's packages, installed when missing (best effort: the tests that
# need a tool skip, saying which package to install, when it cannot be installed here):
#   cmgen (libfilament-tools): the Filament cross-check of tests/test_engine_export.py
#   chromium: the browser display's page test (tests/test_web_display.py) drives it headless
#             (ARLIGHT_NO_CHROMIUM=1 leaves it out)
#   libopenni2-0: the OpenNI2 runtime, whose own DummyDevice driver tests/test_cameras.py runs
#             (users of OpenNI2 cameras install it themselves: docs/guides/cameras.md)
set -uo pipefail

need=()
command -v cmgen >/dev/null || need+=(libfilament-tools)
ldconfig -p 2>/dev/null | grep -q libOpenNI2.so.0 || need+=(libopenni2-0)
if [ -z "${ARLIGHT_NO_CHROMIUM:-}" ] && ! command -v chromium >/dev/null \
    && ! command -v chromium-browser >/dev/null; then
  need+=(chromium)
fi
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
  echo "arlight tests: not root, skipping the test tools (${need[*]}); their tests skip" >&2
  exit 0
fi
command -v apt-get >/dev/null || { echo "arlight tests: no apt-get; ${need[*]} not installed" >&2; exit 0; }
echo "arlight tests: installing test tools: ${need[*]}" >&2
{ $SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq \
    "${need[@]}" >/dev/null; } || echo "arlight tests: could not install ${need[*]}; their tests skip" >&2
exit 0
