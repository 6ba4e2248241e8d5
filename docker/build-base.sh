#!/usr/bin/env bash
# The base image of every arlight image, made from Debian's own packages: no image registry
# is needed. debootstrap writes a minimal Debian bookworm root file system (Python 3.11, the
# libraries Open3D loads at import, CA certificates), apt brings it up to date with
# bookworm-updates and the security archive, and `podman import` turns it into the image
# localhost/arlight-base:bookworm. Idempotent: an existing image is kept (ARLIGHT_REBUILD_BASE=1
# makes it again). Needs root (debootstrap, chroot).
#
#   docker/build-base.sh            # or through docker/build.sh, which calls it
#   MIRROR=http://ftp.de.debian.org/debian docker/build-base.sh
set -euo pipefail

IMAGE=${ARLIGHT_BASE_IMAGE:-localhost/arlight-base:bookworm}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
SECURITY_MIRROR=${SECURITY_MIRROR:-http://deb.debian.org/debian-security}
SUITE=bookworm
# python3-venv: the images' virtual environment (ensurepip's wheels); libgomp1 libgl1 libegl1
# libusb-1.0-0: what Open3D's wheel loads at import (scripts/bootstrap.sh checks the same)
PACKAGES=ca-certificates,python3,python3-venv,libgomp1,libgl1,libegl1,libusb-1.0-0

missing=()
for tool in podman debootstrap; do command -v "$tool" >/dev/null || missing+=("$tool"); done
if [ ${#missing[@]} -gt 0 ]; then
  echo "build-base: missing ${missing[*]}; on Debian/Ubuntu: apt-get install podman buildah" \
       "debootstrap fuse-overlayfs uidmap" >&2
  exit 1
fi
if [ "$(id -u)" != 0 ]; then
  echo "build-base: debootstrap and chroot need root (sudo $0)" >&2; exit 1
fi
if [ "${ARLIGHT_REBUILD_BASE:-0}" != 1 ] && podman image exists "$IMAGE"; then
  echo "build-base: $IMAGE exists (ARLIGHT_REBUILD_BASE=1 makes it again)" >&2; exit 0
fi

work=$(mktemp -d /var/tmp/arlight-rootfs.XXXXXX)
cleanup() {
  for m in "$work/rootfs/proc" "$work/rootfs/dev/pts" "$work/rootfs/dev"; do
    mountpoint -q "$m" 2>/dev/null && umount -l "$m"
  done
  rm -rf "$work"
}
trap cleanup EXIT

echo "build-base: debootstrap $SUITE ($MIRROR) into $work/rootfs" >&2
nice -n 10 debootstrap --variant=minbase --include="$PACKAGES" "$SUITE" "$work/rootfs" "$MIRROR" \
  > "$work/debootstrap.log" 2>&1 || { tail -30 "$work/debootstrap.log" >&2; exit 1; }

root=$work/rootfs
rm -f "$root/etc/apt/sources.list"
cat > "$root/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $MIRROR
Suites: $SUITE $SUITE-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $SECURITY_MIRROR
Suites: $SUITE-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
# no documentation, manual pages or translations in the image (dpkg honours this from now on)
cat > "$root/etc/dpkg/dpkg.cfg.d/01-arlight-nodoc" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
EOF
cat > "$root/etc/apt/apt.conf.d/01-arlight-slim" <<'EOF'
APT::Install-Recommends "false";
APT::Install-Suggests "false";
EOF

echo "build-base: updates from $SUITE-updates and $SUITE-security" >&2
cp /etc/resolv.conf "$root/etc/resolv.conf"
mount -t proc proc "$root/proc"
chroot "$root" /bin/sh -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
  apt-get -y -qq -o Dpkg::Options::=--force-confold upgrade >/dev/null && apt-get clean'
umount "$root/proc"

# what the image does not need: apt's lists and caches, the docs debootstrap put there
# before the dpkg filter existed, byte-code caches, logs
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/cache/debconf/*-old \
       "$root"/usr/share/man/* "$root"/usr/share/info/* "$root"/usr/share/locale/* \
       "$root"/var/log/*.log "$root"/var/log/apt/* "$root"/tmp/* "$root"/etc/resolv.conf
find "$root/usr/share/doc" -mindepth 2 ! -name copyright -delete 2>/dev/null || true
find "$root/usr/lib/python3" -name __pycache__ -type d -prune -exec rm -rf {} + 2>/dev/null || true
: > "$root/etc/resolv.conf"  # the container runtime provides its own

echo "build-base: importing into $IMAGE" >&2
created=$(date -u +%Y-%m-%dT%H:%M:%SZ)
tar --numeric-owner --xattrs -C "$root" -c . | podman import \
  --change 'ENV LANG=C.UTF-8' --change 'CMD ["/bin/bash"]' \
  --message "debootstrap --variant=minbase $SUITE ($created) + $PACKAGES" - "$IMAGE" >/dev/null
podman image inspect --format "build-base: {{.Id}} {{.Size}} bytes" "$IMAGE" >&2
