#!/bin/sh
# Rootful podman on a Debian bookworm machine, for building and testing the extension image
# (as root; idempotent). The containers.conf below is what a VM without CAP_SYS_RESOURCE and
# with hybrid cgroups needs (docs/blueos.md): runc instead of crun, and ulimits within the
# hard limits. An existing containers.conf is left alone.
set -eu
apt-get install -y --no-install-recommends podman runc debootstrap qemu-user-static \
    binfmt-support
CONF=/etc/containers/containers.conf
if [ ! -f "$CONF" ]; then
    mkdir -p /etc/containers
    cat > "$CONF" <<'CONFIG'
[containers]
default_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]

[engine]
runtime = "runc"
CONFIG
    echo "wrote $CONF"
fi
podman info --format '{{.Host.OCIRuntime.Name}} {{.Host.CgroupsVersion}}'
