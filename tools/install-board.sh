#!/bin/sh
# Install the vehicle logger on a Debian 12 board (BeagleBone, armhf) as a systemd service.
#
#   sudo tools/install-board.sh [--operator USER] [--image] [--wheels DIR] [--prefix DIR]
#                               [--no-apt] [--no-start] [--no-link] [--dry-run]
#   sudo tools/install-board.sh --fetch-wheels DIR [--no-apt]
#
# The steps, in order (each reports done, skipped or failed with the reason; a step whose prerequisite failed is
# skipped, the others still run; the summary at the end lists them all and the exit status is 1 if any failed):
#   1. apt: Debian's builds of the compiled dependencies, so nothing heavy is compiled on the board
#   2. a virtual environment in /opt/vehicle-logger/venv that sees those packages (--system-site-packages);
#      pip adds only what Debian lacks (mcap, pyubx2, pyrtcm, pynmeagps, gpiod 2.x, which compiles with gcc;
#      from the index it also fetches setuptools for the builds, from a wheelhouse nothing)
#   3. the system user vehicle-logger with the groups dialout, i2c, gpio (systemd-sysusers)
#   4. udev rules: /dev/vehicle-logger/gnss and /dev/vehicle-logger/elm327, group access to I2C and GPIO
#   5. /etc/vehicle-logger/logger.toml from the commented example, if there is none yet, then checked
#   6. the unit, enabled at boot and started (unless --no-start)
#   7. /usr/local/bin/logger -> the venv's logger, so `logger status` works from any shell; anything else
#      given to `logger` still reaches util-linux's /usr/bin/logger unchanged
# Re-running it is safe: an existing venv and configuration are kept, files are replaced by the tree's.
#
# --operator USER  adds USER to the vehicle-logger group, which may read the status socket and the drives.
# --image          prepares a chroot or an image instead of a running system: neither udev nor systemd is
#                  contacted (the rules take effect at first boot, the unit is enabled offline, nothing started).
# --wheels DIR     installs offline from a wheelhouse (pip never touches the network); make DIR with
#                  --fetch-wheels DIR on a machine of the same architecture and Debian release that has a network.
# --fetch-wheels DIR  runs step 1, then puts into DIR a wheel of everything step 2 would fetch, and stops.
# --prefix DIR     installs the venv under DIR instead of /opt/vehicle-logger; a drop-in then points the unit's
#                  ExecStart at it (not under /home, /root, /run/user, /tmp or /var/tmp, which the unit hides: refused).
# --dry-run        shows every step's commands without doing anything, the same whatever is already installed.
set -u

UNIT_PREFIX=/opt/vehicle-logger  # where systemd/vehicle-logger.service starts the logger from
PREFIX=$UNIT_PREFIX
SRC=$(cd "$(dirname "$0")/.." && pwd)
APT_PACKAGES="python3-numpy python3-serial python3-smbus2 python3-can python3-zstandard python3-lz4 python3-ujson \
python3-venv python3-dev python3-setuptools python3-wheel gcc"
CONFIG=/etc/vehicle-logger/logger.toml

DRY_RUN=0 APT=1 START=1 LINK=1 IMAGE=0 OPERATOR="" WHEELS="" FETCH="" RUN_HINT=""
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) DRY_RUN=1 ;;
        --no-apt) APT=0 ;;
        --no-start) START=0 ;;
        --no-link) LINK=0 ;;
        --image) IMAGE=1 ;;
        --operator) OPERATOR="${2:?--operator needs a user name}"; shift ;;
        --wheels) WHEELS="${2:?--wheels needs a directory}"; shift ;;
        --fetch-wheels) FETCH="${2:?--fetch-wheels needs a directory}"; shift ;;
        --prefix) PREFIX="${2:?--prefix needs a directory}"; shift
                  case "$PREFIX" in
                      *" "* | *"	"*)
                         echo "install-board.sh: --prefix '$PREFIX' holds a space, which the unit's ExecStart cannot" >&2
                         exit 2 ;;
                      /*) ;;
                      *) echo "install-board.sh: --prefix $PREFIX must be an absolute path (the unit runs from it)" >&2
                         exit 2 ;;
                  esac
                  # What the unit hides from the service (ProtectHome=, PrivateTmp=): it could not start from there.
                  for hidden in /home /root /run/user /tmp /var/tmp; do
                      case "$PREFIX" in
                          "$hidden" | "$hidden"/*)
                             echo "install-board.sh: --prefix $PREFIX: the unit hides $hidden from the service" \
                                  "(ProtectHome=, PrivateTmp=), which could not start from there; try /srv or /opt" >&2
                             exit 2 ;;
                      esac
                  done ;;
        -h|--help) sed -n '2,30p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "install-board.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
VENV="$PREFIX/venv"

if [ "$DRY_RUN" = 0 ] && [ "$(id -u)" != 0 ]; then
    echo "install-board.sh: run as root (sudo), or with --dry-run to see the steps" >&2
    exit 1
fi
# A mistyped operator would fail step 3 after apt and pip had run, and with it the configuration and the service:
# refused before anything is done.
if [ -n "$OPERATOR" ] && [ "$DRY_RUN" = 0 ] && ! id -u "$OPERATOR" >/dev/null 2>&1; then
    echo "install-board.sh: --operator $OPERATOR: no such user (give the operator's own login, e.g. debian)" >&2
    exit 2
fi
if [ -n "$WHEELS" ] && [ "$DRY_RUN" = 0 ] && [ ! -d "$WHEELS" ]; then
    echo "install-board.sh: --wheels $WHEELS is not a directory (make one with --fetch-wheels DIR)" >&2
    exit 2
fi

REASON=$(mktemp)
trap 'rm -f "$REASON"' EXIT
SUMMARY=""   # one "N|title|outcome" line per step
FAILED=" "   # numbers of the steps that failed or were skipped for a failure, space-separated

run() {
    # Every change goes through here: --dry-run shows the whole installation without touching the system, and a
    # failing command ends its step (steps run in a subshell with -e) with the command named as the reason.
    echo "+ $*"
    [ "$DRY_RUN" = 1 ] && return 0
    "$@" && return 0
    rc=$?
    if [ "$rc" = 127 ]; then
        echo "\`$1\` was not found (not installed, or not on PATH: $PATH)" > "$REASON"
    else
        echo "\`$*\` exited $rc${RUN_HINT:+ ($RUN_HINT)}" > "$REASON"
    fi
    exit "$rc"
}

unless_present() {
    # unless_present PATH WHAT command...: run the command only where PATH does not exist yet. The dry run lists
    # it in any case (so it shows the same steps before and after an installation) and says when it applies.
    path=$1 what=$2
    shift 2
    if [ "$DRY_RUN" = 1 ]; then
        run "$@"
        echo "  (only where $path does not exist yet)"
    elif [ -e "$path" ]; then
        echo "keeping the existing $what $path"
    else
        run "$@"
    fi
}

skip() {
    # Ends a step as skipped, with why.
    echo "$*" > "$REASON"
    exit 99
}

step() {
    # step N "title" "prerequisite step numbers" function: runs the function in a subshell with -e, records the
    # outcome, and skips it when a prerequisite failed.
    n=$1 title=$2 needs=$3 body=$4
    echo "== $n. $title"
    : > "$REASON"
    for need in $needs; do
        case "$FAILED" in
            *" $need "*)
                outcome="skipped: step $need did not complete"
                echo "-- $n. $outcome"
                SUMMARY="$SUMMARY$n|$title|$outcome
"
                FAILED="$FAILED$n "
                return 0 ;;
        esac
    done
    (set -e; "$body")
    rc=$?
    if [ "$rc" = 0 ] && [ "$DRY_RUN" = 1 ]; then
        outcome="shown (dry run)"
    elif [ "$rc" = 0 ]; then
        outcome=done
    elif [ "$rc" = 99 ]; then
        outcome="skipped: $(cat "$REASON")"
    else
        reason=$(cat "$REASON")
        outcome="FAILED: ${reason:-exit status $rc}"
        FAILED="$FAILED$n "
    fi
    echo "-- $n. $outcome"
    SUMMARY="$SUMMARY$n|$title|$outcome
"
}

pip_source() {
    # Where pip takes what Debian lacks: the package index (building gpiod and this tree in isolated environments
    # with a setuptools it fetches: gpiod's metadata needs a newer one than Debian's 66), or only the wheelhouse
    # (gpiod already built there; this tree built with Debian's setuptools, so nothing is fetched).
    if [ -n "$WHEELS" ]; then
        echo "--no-index --find-links $WHEELS --no-build-isolation"
    fi
}

apt_packages() {
    [ "$APT" = 1 ] || skip "--no-apt"
    run apt-get update
    # shellcheck disable=SC2086 # the list is meant to split into words
    run env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $APT_PACKAGES
}

copy_tree() {
    # copy_tree DIR: what the package is built from, copied into DIR for pip. pip prepares a source tree in place,
    # as root (build/, vehicle_logger.egg-info/), even for a report of what it would install: the operator's own
    # checkout then refused their `pip install -e .`, and a module deleted from the tree was installed again from
    # the old build/.
    run install -d -m 0755 "$1"
    run tar -C "$SRC" --exclude=__pycache__ -cf "$1/tree.tar" pyproject.toml README.md logger sensors sync
    run tar -C "$1" -xf "$1/tree.tar"
}

venv() {
    run install -d -m 0755 "$PREFIX"
    unless_present "$VENV/bin/python" "virtual environment" python3 -m venv --system-site-packages "$VENV"
    if [ "$DRY_RUN" = 1 ]; then
        stage=/tmp/vehicle-logger-build.XXXXXX
    else
        stage=$(mktemp -d /tmp/vehicle-logger-build.XXXXXX)
        trap 'rm -rf "$stage"' EXIT
    fi
    copy_tree "$stage"
    # Offline, pip's own reason ("No matching distribution found for setuptools>=61") is far above its exit.
    [ -n "$WHEELS" ] || RUN_HINT="no network? pip needs the package index; offline, install from a wheelhouse: \
--wheels DIR, see README"
    # shellcheck disable=SC2046 # pip_source is meant to split into words
    run "$VENV/bin/pip" install --no-cache-dir $(pip_source) "$stage"
    RUN_HINT=""
}

users() {
    run install -D -m 0644 "$SRC/systemd/vehicle-logger.sysusers" /etc/sysusers.d/vehicle-logger.conf
    run systemd-sysusers /etc/sysusers.d/vehicle-logger.conf
    if [ -n "$OPERATOR" ]; then
        run usermod -a -G vehicle-logger "$OPERATOR"
    fi
}

udev_rules() {
    run install -D -m 0644 "$SRC/systemd/70-vehicle-logger.rules" /etc/udev/rules.d/70-vehicle-logger.rules
    if [ "$IMAGE" = 1 ]; then
        echo "image: udev is not contacted, the rules take effect at first boot"
        return 0
    fi
    if [ "$DRY_RUN" = 0 ] && ! udevadm control --ping >/dev/null 2>&1; then
        echo "\`udevadm control --ping\`: udevd is not running (a chroot? --image prepares one without it)" > "$REASON"
        exit 1
    fi
    run udevadm control --reload
    run udevadm trigger --action=add --subsystem-match=tty --subsystem-match=i2c-dev --subsystem-match=gpio
}

configuration() {
    run install -d -m 0755 /etc/vehicle-logger
    unless_present "$CONFIG" configuration \
        install -m 0640 -o root -g vehicle-logger "$SRC/systemd/logger.toml" "$CONFIG"
    # Checked as the service reads it: a configuration kept from before that the service's user may not read (root's
    # 0600) passed a check run as root, then the service failed at every start.
    run runuser -u vehicle-logger -- "$VENV/bin/logger" config check "$CONFIG"
}

service() {
    run install -D -m 0644 "$SRC/systemd/vehicle-logger.service" /etc/systemd/system/vehicle-logger.service
    # Another --prefix: the unit's own ExecStart with that venv, as a drop-in (the unit stays as shipped); one left
    # by an earlier installation elsewhere goes when the default is installed again.
    dropin=/etc/systemd/system/vehicle-logger.service.d/prefix.conf
    if [ "$PREFIX" != "$UNIT_PREFIX" ]; then
        shipped=$(grep '^ExecStart=' "$SRC/systemd/vehicle-logger.service")
        exec_start="ExecStart=$PREFIX/${shipped#"ExecStart=$UNIT_PREFIX/"}"
        if [ "$shipped" = "${shipped#"ExecStart=$UNIT_PREFIX/"}" ]; then
            echo "systemd/vehicle-logger.service has no ExecStart under $UNIT_PREFIX to point at $PREFIX" > "$REASON"
            exit 1
        fi
        if [ "$DRY_RUN" = 1 ]; then
            echo "  ($PREFIX/prefix.conf: [Service], ExecStart= to clear the unit's, then $exec_start)"
        else
            printf '# tools/install-board.sh --prefix %s\n[Service]\nExecStart=\n%s\n' "$PREFIX" "$exec_start" \
                > "$PREFIX/prefix.conf"
        fi
        run install -D -m 0644 "$PREFIX/prefix.conf" "$dropin"
    elif [ "$DRY_RUN" = 1 ]; then
        run rm -f "$dropin"
        echo "  (only where $dropin exists)"
    elif [ -e "$dropin" ]; then
        run rm -f "$dropin"
    fi
    # chronyd's SOCK refclock socket given to the logger's group (read only where chrony runs)
    run install -D -m 0644 "$SRC/systemd/chrony.service.d/vehicle-logger.conf" \
        /etc/systemd/system/chrony.service.d/vehicle-logger.conf
    if [ "$IMAGE" = 1 ]; then
        # Offline: systemctl --root edits the enablement links only, never the running manager.
        run systemctl --root=/ enable vehicle-logger.service
        echo "image: not started (it starts at first boot)"
        return 0
    fi
    run systemctl daemon-reload
    run systemctl enable vehicle-logger.service
    if [ "$START" = 1 ]; then
        run systemctl restart vehicle-logger.service
    fi
}

command_link() {
    [ "$LINK" = 1 ] || skip "--no-link"
    run ln -sfn "$VENV/bin/logger" /usr/local/bin/logger
}

fetch_wheels() {
    # What pip would fetch into the venv beside Debian's packages, as wheels built here: pip's own report of an
    # installation it does not make names them, so Debian's numpy & co. are never fetched or compiled.
    if [ "$DRY_RUN" = 1 ]; then
        build=/tmp/wheelhouse.XXXXXX
    else
        build=$(mktemp -d /tmp/wheelhouse.XXXXXX)
        trap 'rm -rf "$build"' EXIT
    fi
    copy_tree "$build/tree"
    run python3 -m venv --system-site-packages "$build/venv"
    run "$build/venv/bin/pip" install --dry-run --quiet --report "$build/report.json" "$build/tree"
    run install -d "$FETCH"
    if [ "$DRY_RUN" = 1 ]; then
        echo "+ $build/venv/bin/pip wheel --no-deps --wheel-dir $FETCH <each package in the report>"
        return 0
    fi
    wanted=$("$build/venv/bin/python" -c '
import json, sys
report = json.load(open(sys.argv[1]))
print(" ".join(i["metadata"]["name"] + "==" + i["metadata"]["version"] for i in report["install"]
               if i["metadata"]["name"] != "vehicle-logger"))' "$build/report.json")
    echo "pip would fetch: $wanted"
    # shellcheck disable=SC2086 # one requirement a word
    run "$build/venv/bin/pip" wheel --no-deps --wheel-dir "$FETCH" $wanted
    rm -rf "$build"
}

if [ -n "$FETCH" ]; then
    step 1 "Debian packages" "" apt_packages
    step W "wheelhouse" "1" fetch_wheels
else
    step 1 "Debian packages" "" apt_packages
    step 2 "virtual environment" "1" venv
    step 3 "user and groups" "" users
    step 4 "udev rules" "" udev_rules
    step 5 "configuration" "2 3" configuration
    step 6 "service" "2 3 5" service
    step 7 "the logger command" "2" command_link
fi

echo
echo "summary:"
printf '%s' "$SUMMARY" | while IFS='|' read -r n title outcome; do
    printf '  %-3s %-20s %s\n' "$n." "$title" "$outcome"
done
failed=$(printf '%s' "$SUMMARY" | grep -c '|FAILED\||skipped: step')
if [ "$failed" != 0 ]; then
    echo "install-board.sh: $failed step(s) did not complete; the output above each FAILED line says why" >&2
    exit 1
fi
if [ "$DRY_RUN" = 1 ]; then
    echo "dry run: nothing was done; run it again without --dry-run, as root, to install"
elif [ -n "$FETCH" ]; then
    echo "done: copy $FETCH to the board, then: sudo tools/install-board.sh --wheels DIR"
elif [ "$IMAGE" = 1 ]; then
    echo "done: the image starts vehicle-logger at first boot"
else
    echo "done: systemctl status vehicle-logger; logger status; journalctl -u vehicle-logger -f"
fi
