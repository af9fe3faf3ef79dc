#!/bin/sh
# Install the vehicle logger on a Debian 12 board (BeagleBone, armhf) as a systemd service.
#
#   sudo tools/install-board.sh [--operator USER] [--no-apt] [--no-start] [--no-link] [--dry-run]
#
# What it does, in order (each step can be repeated safely; an existing configuration is never overwritten):
#   1. apt: Debian's builds of the compiled dependencies, so nothing heavy is compiled on the board
#   2. a virtual environment in /opt/vehicle-logger/venv that sees those packages (--system-site-packages);
#      pip adds only what Debian lacks (mcap, pyubx2, pynmeagps, gpiod 2.x, which compiles with gcc)
#   3. the system user vehicle-logger with the groups dialout, i2c, gpio (systemd-sysusers)
#   4. udev rules: /dev/vehicle-logger/gnss and /dev/vehicle-logger/elm327, group access to I2C and GPIO
#   5. /etc/vehicle-logger/logger.toml from the commented example, if there is none yet, then checked
#   6. the unit, enabled at boot and started (unless --no-start)
#   7. /usr/local/bin/logger -> the venv's logger, so `logger status` works from any shell; anything else
#      given to `logger` still reaches util-linux's /usr/bin/logger unchanged
# --operator USER adds USER to the vehicle-logger group, which may read the status socket and the drives.
set -eu

PREFIX=/opt/vehicle-logger
VENV="$PREFIX/venv"
SRC=$(cd "$(dirname "$0")/.." && pwd)
APT_PACKAGES="python3-numpy python3-serial python3-smbus2 python3-can python3-zstandard python3-lz4 python3-venv python3-dev gcc"

DRY_RUN=0 APT=1 START=1 LINK=1 OPERATOR=""
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --no-apt) APT=0 ;;
        --no-start) START=0 ;;
        --no-link) LINK=0 ;;
        --operator) OPERATOR="${2:?--operator needs a user name}"; shift ;;
        -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "install-board.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done

run() {
    # Every change goes through here: --dry-run shows the whole installation without touching the system.
    echo "+ $*"
    if [ "$DRY_RUN" = 0 ]; then
        "$@"
    fi
}

if [ "$DRY_RUN" = 0 ] && [ "$(id -u)" != 0 ]; then
    echo "install-board.sh: run as root (sudo), or with --dry-run to see the steps" >&2
    exit 1
fi

echo "== 1. Debian packages"
if [ "$APT" = 1 ]; then
    run apt-get update
    # shellcheck disable=SC2086 # the list is meant to split into words
    run apt-get install -y --no-install-recommends $APT_PACKAGES
fi

echo "== 2. virtual environment in $VENV"
run install -d -m 0755 "$PREFIX"
if [ ! -x "$VENV/bin/python" ]; then
    run python3 -m venv --system-site-packages "$VENV"
fi
run "$VENV/bin/pip" install --no-cache-dir "$SRC"

echo "== 3. user and groups"
run install -D -m 0644 "$SRC/systemd/vehicle-logger.sysusers" /etc/sysusers.d/vehicle-logger.conf
run systemd-sysusers /etc/sysusers.d/vehicle-logger.conf
if [ -n "$OPERATOR" ]; then
    run usermod -a -G vehicle-logger "$OPERATOR"
fi

echo "== 4. udev rules"
run install -D -m 0644 "$SRC/systemd/70-vehicle-logger.rules" /etc/udev/rules.d/70-vehicle-logger.rules
run udevadm control --reload
run udevadm trigger --action=add --subsystem-match=tty --subsystem-match=i2c-dev --subsystem-match=gpio

echo "== 5. configuration"
run install -d -m 0755 /etc/vehicle-logger
if [ -e /etc/vehicle-logger/logger.toml ]; then
    echo "keeping the existing /etc/vehicle-logger/logger.toml"
else
    run install -m 0640 -o root -g vehicle-logger "$SRC/systemd/logger.toml" /etc/vehicle-logger/logger.toml
fi
run "$VENV/bin/logger" config check /etc/vehicle-logger/logger.toml

echo "== 6. service"
run install -D -m 0644 "$SRC/systemd/vehicle-logger.service" /etc/systemd/system/vehicle-logger.service
run systemctl daemon-reload
run systemctl enable vehicle-logger.service
if [ "$START" = 1 ]; then
    run systemctl restart vehicle-logger.service
fi

echo "== 7. the logger command"
if [ "$LINK" = 1 ]; then
    run ln -sfn "$VENV/bin/logger" /usr/local/bin/logger
fi

echo "done: systemctl status vehicle-logger; logger status; journalctl -u vehicle-logger -f"
