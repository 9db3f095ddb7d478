#!/bin/sh
# A Debian bookworm base image built from Debian packages (debootstrap), for machines that
# cannot pull debian:bookworm-slim from a registry. Then build the extension on it:
#
#   blueos/build-base.sh arm64          # -> localhost/bookworm-base:arm64
#   podman build --platform linux/arm64 --build-arg BASE=localhost/bookworm-base:arm64 \
#       -f blueos/Dockerfile -t localhost/netpose:arm64 .
#
# ARCH: amd64 (tag latest), arm64, armhf (linux/arm/v7). Foreign architectures need
# qemu-user-static and binfmt-support (blueos/podman-setup.sh). Takes 1-3 minutes.
set -eu
ARCH="${1:-$(dpkg --print-architecture)}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"
case "$ARCH" in
    amd64) TAG=latest; PLATFORM="--arch amd64" ;;
    arm64) TAG=arm64; PLATFORM="--arch arm64" ;;
    armhf) TAG=armhf; PLATFORM="--arch arm --variant v7" ;;
    *) echo "usage: $0 [amd64|arm64|armhf]" >&2; exit 2 ;;
esac
ROOT="$(mktemp -d)"
trap 'rm -rf "$ROOT"' EXIT
debootstrap --variant=minbase --arch="$ARCH" bookworm "$ROOT" "$MIRROR"
cat > "$ROOT/etc/apt/sources.list" <<SOURCES
deb $MIRROR bookworm main
deb $MIRROR bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
SOURCES
rm -rf "$ROOT"/var/cache/apt/archives/*.deb "$ROOT"/var/lib/apt/lists/*
# shellcheck disable=SC2086  # PLATFORM is several words on purpose
tar -C "$ROOT" --numeric-owner -c . | podman import $PLATFORM \
    --change 'CMD ["/bin/bash"]' \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    - "localhost/bookworm-base:$TAG"
echo "built localhost/bookworm-base:$TAG"
