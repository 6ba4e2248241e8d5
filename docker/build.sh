#!/usr/bin/env bash
# Build arlight's images with podman, from nothing but Debian's packages and PyPI:
#   localhost/arlight-base:bookworm   debootstrap root file system (docker/build-base.sh)
#   localhost/arlight-server          arlight serve, CPU
#   localhost/arlight-server-cuda     the server + numba.cuda's NVVM (run with a GPU: docs/guides/containers.md)
#   localhost/arlight-client          arlight stream / display / record / keys
# Idempotent: the base image is kept once made, and podman's layer cache makes a second run
# quick (seconds) unless pyproject.toml or the sources changed.
#
#   docker/build.sh                    # all images
#   docker/build.sh server client      # only these targets
#   CAMERAS=realsense docker/build.sh client   # a client with a camera library
# Environment: ARLIGHT_BUILD_CA (CA bundle pip trusts during the build; default the host's
# /etc/ssl/certs/ca-certificates.crt), ARLIGHT_REBUILD_BASE=1, MIRROR (Debian mirror).
set -euo pipefail
cd "$(dirname "$0")/.."

missing=()
for tool in podman debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
if [ ${#missing[@]} -gt 0 ]; then
  echo "docker/build.sh: ${missing[*]} not found; on Debian/Ubuntu (as root):" >&2
  echo "  apt-get install podman buildah debootstrap fuse-overlayfs uidmap" >&2
  exit 1
fi
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=(server client server-cuda)
for t in "${targets[@]}"; do
  case $t in server|server-cuda|client) ;;
    *) echo "docker/build.sh: unknown target $t (server, server-cuda, client)" >&2; exit 2 ;;
  esac
done
CA=${ARLIGHT_BUILD_CA:-/etc/ssl/certs/ca-certificates.crt}
if [ ! -r "$CA" ]; then
  echo "docker/build.sh: no CA bundle at $CA (apt-get install ca-certificates, or set" \
       "ARLIGHT_BUILD_CA)" >&2; exit 1
fi

t0=$(date +%s)
docker/build-base.sh
if ! err=$(podman run --rm --entrypoint /bin/true localhost/arlight-base:bookworm 2>&1); then
  echo "docker/build.sh: podman cannot run a container here: $err" >&2
  echo "  (a VM or container without CAP_SYS_RESOURCE or with hybrid cgroups: in" \
       "/etc/containers/containers.conf set [engine] runtime = \"runc\" (apt-get install runc)" \
       "and [containers] default_ulimits = [\"nofile=16384:16384\", \"nproc=32768:32768\"])" >&2
  exit 1
fi

# the build context: the package's sources only (no .venv, .git, tests, benchmarks, data)
ctx=$(mktemp -d /var/tmp/arlight-context.XXXXXX)
trap 'rm -rf "$ctx"' EXIT
tar --exclude=__pycache__ --exclude='*.pyc' -c pyproject.toml README.md arlight server client \
    pipeline protocols sources | tar -x -C "$ctx"
cp docker/Containerfile "$ctx/Containerfile"
# the digest of what goes into the image: the Containerfile rebuilds from the wheel on when
# it changes (podman's cache alone kept stale code)
digest=$(cd "$ctx" && find . -type f ! -name Containerfile -print0 | sort -z \
  | xargs -0 sha256sum | sha256sum | cut -c1-16)

for t in "${targets[@]}"; do
  s=$(date +%s)
  echo "docker/build.sh: building localhost/arlight-$t" >&2
  nice -n 10 podman build --layers --target "$t" --secret "id=ca,src=$CA" \
    --build-arg "CAMERAS=${CAMERAS:-}" --build-arg "SOURCE_DIGEST=$digest" -t "localhost/arlight-$t:latest" -f "$ctx/Containerfile" \
    "$ctx"
  echo "docker/build.sh: arlight-$t built in $(( $(date +%s) - s )) s" >&2
done
echo "docker/build.sh: done in $(( $(date +%s) - t0 )) s" >&2
podman images --filter reference='localhost/arlight-*' \
  --format 'table {{.Repository}}:{{.Tag}} {{.Size}} {{.Created}}' >&2
