#!/usr/bin/env bash
# Smoke test of the images: builds them (or reuses them: docker/build.sh is idempotent), then
# runs the demo across containers twice and checks that the display received every Result:
#   1. plain podman: keys made in a volume, the server, a display and a capture client, each
#      its own container on one podman network, talking over TCP with CURVE keys;
#   2. docker/compose.yaml with podman-compose (skipped, and said so, when it is missing).
# It also checks that the server ran as a non-root user and compiled no Numba kernel (the
# image's cache served them all: nothing was added to NUMBA_CACHE_DIR).
# Exit 0 when every check passed, 1 otherwise.
#
#   docker/smoke-test.sh               # build if needed, then both runs
#   ARLIGHT_SKIP_BUILD=1 docker/smoke-test.sh
#   ARLIGHT_SMOKE_FRAMES=48 docker/smoke-test.sh
set -euo pipefail
cd "$(dirname "$0")/.."

FRAMES=${ARLIGHT_SMOKE_FRAMES:-24}
SERVER=localhost/arlight-server:latest
CLIENT=localhost/arlight-client:latest
P=arlight-smoke
failed=0
check() {  # check NAME CONDITION-RESULT(0/1) DETAIL
  if [ "$2" = 0 ]; then echo "smoke-test: ok    $1: $3"; else echo "smoke-test: FAIL  $1: $3"; failed=1; fi
}
since() { echo $(( $(date +%s) - $1 )); }

if [ "${ARLIGHT_SKIP_BUILD:-0}" != 1 ]; then
  t=$(date +%s)
  docker/build.sh server client
  echo "smoke-test: images ready in $(since "$t") s"
fi
for image in "$SERVER" "$CLIENT"; do
  podman image exists "$image" || { echo "smoke-test: no $image (run docker/build.sh)" >&2; exit 1; }
done

cleanup() {
  podman rm -f -t 2 "$P-server" "$P-display" "$P-stream" >/dev/null 2>&1 || true
  podman volume rm -f "$P-keys" "$P-results" >/dev/null 2>&1 || true
  podman network rm -f "$P" >/dev/null 2>&1 || true
}
wait_log() {  # wait_log CONTAINER TEXT SECONDS
  local end=$(( $(date +%s) + $3 ))
  until podman logs "$1" 2>&1 | grep -q "$2"; do
    if [ "$(date +%s)" -ge "$end" ] || [ "$(podman inspect -f '{{.State.Running}}' "$1")" != true ]; then
      echo "smoke-test: $1 did not print '$2' within $3 s:" >&2; podman logs "$1" 2>&1 | tail -20 >&2
      return 1
    fi
    sleep 0.5
  done
}
in_volume() {  # in_volume COMMAND: run a shell command with the results volume at /out
  podman run --rm -v "$P-results:/out:ro" --entrypoint /bin/sh "$CLIENT" -c "$1"
}

# ------------------------------------------------------------------ 1. plain podman
trap cleanup EXIT
cleanup
t_run=$(date +%s)
podman network create "$P" >/dev/null
podman volume create "$P-keys" >/dev/null  # one volume for all here, for brevity; compose.yaml
# keeps the server's secret key out of the clients' volume
podman volume create "$P-results" >/dev/null
podman run --rm --user 0 -v "$P-keys:/keys" --entrypoint /bin/sh "$CLIENT" -ec '
  arlight keys generate /keys 2>/dev/null
  python -c "from arlight.protocols import new_token; print(new_token())" > /keys/session.token
  chmod 0600 /keys/session.token; chown -R 10001:0 /keys'
K="--server-key /keys/server.key --client-key /keys/client.key_secret --token-file /keys/session.token"
podman run -d --name "$P-server" --network "$P" --network-alias server -v "$P-keys:/keys:ro" \
  "$SERVER" >/dev/null   # the image's own command: serve on 0.0.0.0:5555 with /keys
wait_log "$P-server" "listening on" 60
podman run -d --name "$P-display" --network "$P" -v "$P-keys:/keys:ro" -v "$P-results:/out" \
  "$CLIENT" display --server tcp://server:5555 --session smoke $K --out /out --idle-exit 120 \
  >/dev/null
wait_log "$P-display" "arlight display: session" 60
sleep 2  # the subscription's round trip, before the first Result can exist
t_stream=$(date +%s)
podman run --name "$P-stream" --network "$P" -v "$P-keys:/keys:ro" "$CLIENT" \
  stream synthetic --server tcp://server:5555 --session smoke $K --mode lossless --rate max \
  --size 320x240 --max-frames "$FRAMES" --preset fast --composite --scene demo 2>&1 | tail -3
stream_rc=$(podman inspect -f '{{.State.ExitCode}}' "$P-stream")
display_rc=$(podman wait "$P-display")
echo "smoke-test: stream $(since "$t_stream") s; display said:"
podman logs "$P-display" 2>&1 | tail -3 | sed 's/^/  /'
results=$(in_volume 'wc -l < /out/results.jsonl')
frames=$(in_volume 'ls /out/frames | wc -l')
first_ms=$(in_volume "python -c 'import json; r = [json.loads(l) for l in open(\"/out/results.jsonl\")]; print(round(r[0][\"pipeline_ms\"]), round(sorted(x[\"pipeline_ms\"] for x in r)[len(r) // 2]))'")
check "podman: stream exit" "$([ "$stream_rc" = 0 ]; echo $?)" "$stream_rc"
check "podman: display exit" "$([ "$display_rc" = 0 ]; echo $?)" "$display_rc"
check "podman: results received" "$([ "$results" = "$FRAMES" ]; echo $?)" "$results of $FRAMES"
check "podman: composites received" "$([ "$frames" = "$FRAMES" ]; echo $?)" "$frames of $FRAMES"
uid=$(podman exec "$P-server" id -u 2>/dev/null || echo "?")
check "podman: server user" "$([ "$uid" != 0 ] && [ "$uid" != "?" ]; echo $?)" "uid $uid"
compiled=$(podman diff "$P-server" | grep -c '/var/cache/arlight/numba/.' || true)
check "podman: no Numba compilation in the server" "$([ "$compiled" = 0 ]; echo $?)" \
  "$compiled cache entries added; first frame's pipeline ${first_ms% *} ms, median ${first_ms#* } ms"
podman stop -t 15 "$P-server" >/dev/null
echo "smoke-test: plain podman run took $(since "$t_run") s"
cleanup

# ------------------------------------------------------------------ 2. compose
if ! command -v podman-compose >/dev/null; then
  echo "smoke-test: skipped docker/compose.yaml: no podman-compose (apt-get install podman-compose)"
else
  C=(podman-compose -p "$P" -f docker/compose.yaml)
  compose_down() {  # podman-compose 1.0.3's down leaves the project's network behind
    "${C[@]}" down -v >/dev/null 2>&1 || true
    podman network rm -f "${P}_default" >/dev/null 2>&1 || true
  }
  trap 'compose_down; cleanup' EXIT
  compose_down
  t_compose=$(date +%s)
  "${C[@]}" up -d >/dev/null 2>&1
  display_rc=$(timeout 300 podman wait "${P}_display_1" || echo timeout)
  stream_rc=$(podman inspect -f '{{.State.ExitCode}}' "${P}_stream_1")
  echo "smoke-test: compose display said:"
  podman logs "${P}_display_1" 2>&1 | tail -2 | sed 's/^/  /'
  results=$(podman run --rm -v "${P}_results:/out:ro" --entrypoint /bin/sh "$CLIENT" \
            -c 'wc -l < /out/results.jsonl')
  check "compose: stream exit" "$([ "$stream_rc" = 0 ]; echo $?)" "$stream_rc"
  check "compose: display exit" "$([ "$display_rc" = 0 ]; echo $?)" "$display_rc"
  check "compose: results received" "$([ "$results" = 24 ]; echo $?)" "$results of 24"
  echo "smoke-test: compose run took $(since "$t_compose") s"
  if [ "$failed" != 0 ]; then "${C[@]}" logs 2>&1 | tail -40; fi
fi

if [ "$failed" = 0 ]; then echo "smoke-test: PASSED"; else echo "smoke-test: FAILED"; fi
exit "$failed"
