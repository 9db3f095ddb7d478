#!/bin/sh
# Install netpose as a systemd service on a Raspberry Pi / Debian bookworm (run as root from a
# checkout: `sudo systemd/install.sh`). Idempotent: re-running upgrades the code and keeps the
# configuration in /etc/netpose.
#
#   - system user `netpose` (no login), in the video and dialout groups;
#   - /opt/netpose/src: a copy of this checkout; /opt/netpose/venv: a venv made with
#     --system-site-packages, so Debian's python3-opencv/numpy/scipy are reused (no wheels to
#     build on a 32-bit Pi);
#   - /etc/netpose/netpose.toml from config/netpose.toml unless one exists (CONFIG=... picks
#     another example, e.g. CONFIG=config/blueos.toml);
#   - /etc/systemd/system/netpose.service, daemon-reload, enable (start with START=1).
set -eu

SRC_DIR=$(CDPATH= cd -- "$(dirname -- "$0")/.." && pwd)
PREFIX=${PREFIX:-/opt/netpose}
CONF_DIR=${CONF_DIR:-/etc/netpose}
UNIT_DIR=${UNIT_DIR:-/etc/systemd/system}
CONFIG=${CONFIG:-config/netpose.toml}
PYTHON=${PYTHON:-python3}
START=${START:-0}

if [ "$(id -u)" -ne 0 ]; then
    echo "install.sh: run as root (sudo $0)" >&2
    exit 1
fi

echo "netpose: Debian packages (skipped when present)"
if command -v apt-get >/dev/null 2>&1; then
    missing=""
    for pkg in python3-venv python3-numpy python3-scipy python3-opencv python3-yaml \
               python3-serial; do
        dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"
    done
    if [ -n "$missing" ]; then
        apt-get install -y --no-install-recommends $missing
    fi
fi

echo "netpose: user and groups"
if ! id netpose >/dev/null 2>&1; then
    useradd --system --home-dir /var/lib/netpose --no-create-home \
        --shell /usr/sbin/nologin --user-group netpose
fi
for group in video dialout; do
    getent group "$group" >/dev/null && usermod -a -G "$group" netpose
done

echo "netpose: code in $PREFIX"
install -d -m 0755 "$PREFIX" "$PREFIX/src"
# Copy the tracked sources only (no .venv, no caches).
(cd "$SRC_DIR" && tar --exclude=.venv --exclude=.git --exclude='*.egg-info' \
    --exclude=__pycache__ --exclude=.mypy_cache --exclude=.pytest_cache \
    -cf - pyproject.toml README.md service drivers config systemd docs) \
    | (cd "$PREFIX/src" && tar -xf -)
if [ ! -x "$PREFIX/venv/bin/python" ]; then
    "$PYTHON" -m venv --system-site-packages "$PREFIX/venv"
fi
# opencv-python is an extra, not a dependency: Debian's python3-opencv provides cv2.
"$PREFIX/venv/bin/python" -m pip install --quiet --upgrade "$PREFIX/src"
if ! "$PREFIX/venv/bin/python" -c "import cv2" 2>/dev/null; then
    "$PREFIX/venv/bin/python" -m pip install --quiet "opencv-python-headless>=4.6"
fi

echo "netpose: configuration in $CONF_DIR"
install -d -m 0750 -o root -g netpose "$CONF_DIR"
if [ ! -e "$CONF_DIR/netpose.toml" ]; then
    install -m 0640 -o root -g netpose "$SRC_DIR/$CONFIG" "$CONF_DIR/netpose.toml"
    echo "netpose: wrote $CONF_DIR/netpose.toml from $CONFIG: edit it (mesh, camera, MAVLink)"
else
    echo "netpose: keeping existing $CONF_DIR/netpose.toml"
fi

# Validate without opening any device (exit 78 names the key to fix); not fatal here, the
# service would refuse to start with the same message.
if ! "$PREFIX/venv/bin/netpose" run --config "$CONF_DIR/netpose.toml" --check; then
    echo "netpose: fix $CONF_DIR/netpose.toml before starting the service" >&2
fi

echo "netpose: systemd unit"
install -m 0644 "$SRC_DIR/systemd/netpose.service" "$UNIT_DIR/netpose.service"
if command -v systemd-analyze >/dev/null 2>&1; then
    systemd-analyze verify "$UNIT_DIR/netpose.service"
fi
systemctl daemon-reload
systemctl enable netpose.service
if [ "$START" = "1" ]; then
    systemctl restart netpose.service
    systemctl --no-pager status netpose.service || true
else
    echo "netpose: installed and enabled; start with: systemctl start netpose"
fi
