#!/bin/sh
# The extension's start: the daemon on /data/netpose.toml (first start: a copy of
# config/blueos.toml). Arguments replace that: `docker run IMAGE run --config ...`.
set -eu
DATA="${NETPOSE_DATA:-/data}"
if [ "$#" -gt 0 ]; then
    exec netpose "$@"
fi
mkdir -p "$DATA"
# /data must be the vehicle's folder (the permissions' bind): a container volume (an install
# with empty Custom settings) is thrown away by the next update, configuration and all.
root="$(awk -v d="$DATA" '$5 == d { print $4 }' /proc/self/mountinfo 2>/dev/null | tail -n 1)"
case "$root" in
    "" | */volumes/*)
        echo "netpose: WARNING: $DATA is not a folder of the vehicle (${root:-not a mount}):" \
             "the configuration, calibration and recordings will be lost at the next update." \
             "Install with the permissions of docs/blueos.md (Custom settings)." >&2 ;;
esac
if [ ! -f "$DATA/netpose.toml" ]; then
    cp "${NETPOSE_CONFIG_DIR:-/opt/netpose/config}/blueos.toml" "$DATA/netpose.toml"
    echo "netpose: first start: wrote $DATA/netpose.toml from config/blueos.toml"
    # BlueOS gives every extension the vehicle's MAVLink id: netpose speaks as that vehicle.
    case "${MAV_SYSTEM_ID:-}" in
        "" | *[!0-9]*) ;;
        *)
            if [ "$MAV_SYSTEM_ID" -ge 1 ] && [ "$MAV_SYSTEM_ID" -le 255 ]; then
                sed -i "s/^source_system = 1$/source_system = $MAV_SYSTEM_ID/" "$DATA/netpose.toml"
                echo "netpose: mavlink.source_system = $MAV_SYSTEM_ID (MAV_SYSTEM_ID)"
            fi ;;
    esac
fi
exec netpose run --config "$DATA/netpose.toml"
