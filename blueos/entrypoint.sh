#!/bin/sh
# The extension's start: the daemon on /data/netpose.toml (first start: a copy of
# config/blueos.toml). Arguments replace that: `docker run IMAGE run --config ...`.
set -eu
DATA="${NETPOSE_DATA:-/data}"
if [ "$#" -gt 0 ]; then
    exec netpose "$@"
fi
mkdir -p "$DATA"
if [ ! -f "$DATA/netpose.toml" ]; then
    cp /opt/netpose/config/blueos.toml "$DATA/netpose.toml"
    echo "netpose: first start: wrote $DATA/netpose.toml from config/blueos.toml"
fi
exec netpose run --config "$DATA/netpose.toml"
