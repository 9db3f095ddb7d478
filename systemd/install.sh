#!/bin/sh
# Install netpose as a systemd service on a Raspberry Pi / Debian bookworm (run as root from a
# checkout: `sudo systemd/install.sh`). Idempotent: re-running upgrades the code and keeps the
# configuration in $CONF_DIR.
#
#   - system user `netpose` (no login), in the video and dialout groups;
#   - $PREFIX/src: a copy of this checkout; $PREFIX/venv: a venv made with
#     --system-site-packages, so Debian's python3-opencv/numpy/scipy/lxml are reused (no wheels
#     to build on a 32-bit Pi);
#   - $CONF_DIR/netpose.toml from a vehicle profile unless one exists: PROFILE=raspberrypi (the
#     default: V4L2 camera, serial autopilot) or PROFILE=blueos (a BlueOS vehicle; the BlueOS
#     extension is the usual way there, docs/blueos.md). The profile leaves the net's mesh size
#     for you to fill: the service refuses to start until it is set;
#   - $UNIT_DIR/netpose.service with these paths, daemon-reload, enable (start with START=1).
#
#   - with the web page on in that file (PROFILE=blueos), $CONF_DIR writable by the service
#     (a drop-in: ReadWritePaths, group-writable), so the page can save settings and recordings;
#   - an upgrade (re-running it) restarts a running service on the new code. When the new code
#     rejects the configuration in $CONF_DIR, nothing is started or restarted (a running service
#     keeps the previous version), the script says what runs and exits with the check's status
#     (78 for a configuration error, as the service would).
#
# Variables: PREFIX (/opt/netpose), CONF_DIR (/etc/netpose), UNIT_DIR (/etc/systemd/system),
# BIN_DIR (/usr/local/bin: the `netpose` command, a link into the venv),
# PROFILE (raspberrypi), CONFIG (a file to install instead of the profile: relative to this
# checkout, or absolute), PYTHON (python3), START (0).
#
# What needs the network, installing offline, and removing all of this: docs/daemon.md.
set -eu

SRC_DIR=$(CDPATH= cd -- "$(dirname -- "$0")/.." && pwd)
PREFIX=${PREFIX:-/opt/netpose}
CONF_DIR=${CONF_DIR:-/etc/netpose}
UNIT_DIR=${UNIT_DIR:-/etc/systemd/system}
BIN_DIR=${BIN_DIR:-/usr/local/bin}
PROFILE=${PROFILE:-raspberrypi}
CONFIG=${CONFIG:-config/$PROFILE.toml}
PYTHON=${PYTHON:-python3}
START=${START:-0}
SERVICE_USER=netpose

if [ "$(id -u)" -ne 0 ]; then
    echo "install.sh: run as root (sudo $0)" >&2
    exit 1
fi
case "$CONFIG" in
    /*) CONFIG_FILE=$CONFIG ;;
    *) CONFIG_FILE=$SRC_DIR/$CONFIG ;;
esac
if [ ! -f "$CONFIG_FILE" ]; then
    echo "install.sh: no such configuration: $CONFIG_FILE (PROFILE=raspberrypi|blueos)" >&2
    exit 1
fi

echo "netpose: Debian packages (skipped when present)"
if command -v apt-get >/dev/null 2>&1; then
    missing=""
    # python3-lxml: pymavlink's XML parser, prebuilt (pip would compile it on a Pi).
    # python3-matplotlib: filterpy depends on it; from pip it would come in a version that
    # needs a newer numpy than Debian's, and pip would replace python3-numpy (or build it).
    # python3-wheel: with the setuptools 66 python3-venv puts in the venv, the venv builds
    # netpose itself, so a later upgrade needs no network (below).
    for pkg in python3-venv python3-numpy python3-scipy python3-opencv python3-yaml \
               python3-serial python3-lxml python3-matplotlib python3-wheel; do
        dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"
    done
    if [ -n "$missing" ]; then
        apt-get update
        apt-get install -y --no-install-recommends $missing
    fi
fi

echo "netpose: user and groups"
if ! id "$SERVICE_USER" >/dev/null 2>&1; then
    useradd --system --home-dir /var/lib/netpose --no-create-home \
        --shell /usr/sbin/nologin --user-group "$SERVICE_USER"
fi
for group in video dialout; do
    getent group "$group" >/dev/null && usermod -a -G "$group" "$SERVICE_USER"
done

work_dir=$(mktemp -d)
trap 'rm -rf "$work_dir"' EXIT

echo "netpose: code in $PREFIX"
# A fresh copy: modules removed upstream must not linger from an earlier install.
rm -rf "$PREFIX/src"
install -d -m 0755 "$PREFIX" "$PREFIX/src"
# Copy the tracked sources only (no .venv, no caches).
(cd "$SRC_DIR" && tar --exclude=.venv --exclude=.git --exclude='*.egg-info' \
    --exclude=__pycache__ --exclude=.mypy_cache --exclude=.pytest_cache \
    -cf - pyproject.toml README.md service drivers config systemd docs) \
    | (cd "$PREFIX/src" && tar -xf -)
if [ ! -x "$PREFIX/venv/bin/python" ]; then
    "$PYTHON" -m venv --system-site-packages "$PREFIX/venv"
fi
# pip builds netpose with pyproject.toml's backend (setuptools>=66), by default in an isolated
# environment it downloads that backend into, even when the venv has it: an offline companion
# could not install or upgrade. A trial build with no index, checked against those requirements
# (pip's --check-build-dependencies), says whether the venv can build it itself: on a Pi it can
# with Debian's python3-setuptools (66) and python3-wheel. Otherwise the usual, isolated build.
build_isolation=--no-build-isolation
if ! "$PREFIX/venv/bin/python" -m pip wheel --quiet --no-index --no-deps $build_isolation \
        --check-build-dependencies --wheel-dir "$work_dir/wheel" "$PREFIX/src" >/dev/null 2>&1
then
    build_isolation=
    echo "netpose: this venv cannot build netpose itself (setuptools>=66 and wheel): pip fetches"
    echo "         them for the build (offline: a wheelhouse, docs/daemon.md)"
fi
# opencv-python is an extra, not a dependency: Debian's python3-opencv provides cv2.
# Wheels where pip has a choice (pure-Python packages that exist only as sources are fine).
"$PREFIX/venv/bin/python" -m pip install --quiet --prefer-binary --upgrade $build_isolation \
    "$PREFIX/src"
if ! "$PREFIX/venv/bin/python" -c "import cv2" 2>/dev/null; then
    "$PREFIX/venv/bin/python" -m pip install --quiet "opencv-python-headless>=4.6"
fi
# `sudo netpose mavlink-check ...` as the docs write it: the command on PATH, a link that an
# upgrade keeps pointing at the venv.
install -d -m 0755 "$BIN_DIR"
ln -sfn "$PREFIX/venv/bin/netpose" "$BIN_DIR/netpose"

echo "netpose: configuration in $CONF_DIR"
install -d -m 0750 -o root -g "$SERVICE_USER" "$CONF_DIR"
if [ ! -e "$CONF_DIR/netpose.toml" ]; then
    install -m 0640 -o root -g "$SERVICE_USER" "$CONFIG_FILE" "$CONF_DIR/netpose.toml"
    echo "netpose: wrote $CONF_DIR/netpose.toml from $CONFIG: set the mesh size, the camera"
    echo "         calibration and the MAVLink endpoint (see the comments in the file)"
else
    echo "netpose: keeping existing $CONF_DIR/netpose.toml"
fi

echo "netpose: systemd unit"
# The unit names the paths of this installation (PREFIX, CONF_DIR may differ from the defaults).
# Checked under its own name: systemd-analyze refuses a file without the .service suffix.
unit_tmp=$work_dir/netpose.service
sed -e "s#/opt/netpose#$PREFIX#g" -e "s#/etc/netpose/netpose.toml#$CONF_DIR/netpose.toml#g" \
    "$SRC_DIR/systemd/netpose.service" > "$unit_tmp"
if command -v systemd-analyze >/dev/null 2>&1 && ! systemd-analyze verify "$unit_tmp"; then
    # Not fatal: a warning about this system must not leave a half-installed service behind.
    echo "netpose: systemd-analyze verify reported problems (above); installing anyway" >&2
fi
install -m 0644 "$unit_tmp" "$UNIT_DIR/netpose.service"
# The web page saves the configuration (and, with a relative recordings_dir, its recordings)
# next to it: the hardened unit must let the service write there, and the files must let it.
dropin=$UNIT_DIR/netpose.service.d/web-page.conf
if "$PREFIX/venv/bin/python" -c "
import sys, tomllib
with open(sys.argv[1], 'rb') as fh:
    sys.exit(0 if tomllib.load(fh).get('web', {}).get('enabled', False) else 1)
" "$CONF_DIR/netpose.toml" 2>/dev/null; then
    install -d -m 0755 "$UNIT_DIR/netpose.service.d"
    printf '# Written by install.sh: the web page is on in %s.\n[Service]\nReadWritePaths=%s\nConfigurationDirectoryMode=0770\n' \
        "$CONF_DIR/netpose.toml" "$CONF_DIR" > "$dropin"
    chmod 0770 "$CONF_DIR"
    chmod 0660 "$CONF_DIR/netpose.toml"
    echo "netpose: the web page is on: $CONF_DIR is writable by the service ($dropin)"
else
    rm -f "$dropin"
fi
systemctl daemon-reload
systemctl enable netpose.service

# Validate as the service user, so files it cannot read fail here and not at start; no device
# is opened. Exit 78 names the key to fix.
if command -v runuser >/dev/null 2>&1; then
    as_service="runuser -u $SERVICE_USER --"
else
    as_service="setpriv --reuid=$SERVICE_USER --regid=$SERVICE_USER --init-groups"
fi
check_status=0
$as_service "$PREFIX/venv/bin/netpose" run --config "$CONF_DIR/netpose.toml" --check \
    || check_status=$?
if [ "$check_status" -eq 0 ]; then
    if [ "$START" = "1" ]; then
        systemctl restart netpose.service
        systemctl --no-pager status netpose.service || true
    elif systemctl is-active --quiet netpose.service; then
        systemctl restart netpose.service  # an upgrade: the running service takes the new code
        echo "netpose: upgraded and restarted"
    else
        echo "netpose: installed and enabled; start with: systemctl start netpose"
    fi
elif [ "$check_status" -ne 78 ]; then
    # Not a verdict on the configuration: the new code itself does not run (a numpy/OpenCV
    # that does not import, a venv left half-written by a power cut). The service would not
    # exit 78 but crash and be restarted every few seconds, so the fix is the installation.
    echo "netpose: installed and enabled, but the new version does not run (exit $check_status," >&2
    echo "         the lines above); $CONF_DIR/netpose.toml was not judged. A running service" >&2
    echo "         still runs what it loaded; restarted (or at the next boot) it would crash and" >&2
    echo "         be restarted every few seconds. Repair the venv before that, e.g." >&2
    echo "         rm -rf $PREFIX/venv and run this script again." >&2
    exit "$check_status"
else
    # The new code is on disk and enabled, but it will not start on this configuration. A
    # running unit is still the previous version: `systemctl start` does nothing to it, and at
    # the next boot it exits 78 and stays down. So that is said, and the check's exit status
    # (78 for a configuration error) tells automation that the install did not take.
    if systemctl is-active --quiet netpose.service; then
        echo "netpose: installed and enabled, but the new version rejects $CONF_DIR/netpose.toml" >&2
        echo "         (the line above). The running service keeps the previous version until" >&2
        echo "         the configuration is fixed, mixed with new files it reads while it runs" >&2
        echo "         (the web page's): restart it soon. As it is, the service will not start" >&2
        echo "         again (at the next boot either). Fix the file, check again with:" >&2
        then_do="systemctl restart netpose"
    else
        echo "netpose: installed and enabled, but not running: it rejects $CONF_DIR/netpose.toml" >&2
        echo "         (the line above). Fix the file, check again with:" >&2
        then_do="systemctl start netpose"
    fi
    echo "         $as_service $PREFIX/venv/bin/netpose run --config $CONF_DIR/netpose.toml --check" >&2
    echo "         then: $then_do" >&2
    exit "$check_status"
fi
