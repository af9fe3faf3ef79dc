#!/bin/sh
# Prove the board path on an x86 machine: a Debian 12 armhf root (debootstrap, run by qemu-user-static), the
# logger installed in it by tools/install-board.sh --image from a wheelhouse with no network, then the commands an
# operator runs and the test suite, all on the emulated ARM core. Prints one table: each step, its result and the
# time it took.
#
#   sudo tools/board-check.sh [--root DIR] [--reuse] [--suite full|quick|none] [--bench] [--mirror URL]
#
# --root DIR     where the armhf root is built (default /var/tmp/vehicle-logger-board/root); it is removed first
#                unless --reuse keeps an existing one (then only the tree is copied in again)
# --suite        full: the whole test suite (slow tests skip themselves under emulation, with the reason);
#                quick: a few test files; none: no tests (default full)
# --bench        also the daemon benchmark at 20, 200 and 1000 Hz inside the root (tools/bench_daemon.py):
#                a floor check, not a BeagleBone figure (emulation is not a Cortex-A8; see BENCHMARKS.md)
# --mirror URL   Debian mirror (default http://deb.debian.org/debian)
#
# Needs root (debootstrap, chroot, mounts), a network for debootstrap and apt, and about 1.5 GB in --root's
# filesystem. Not part of the default CI (about 20 minutes or more on two cores); an optional CI job can run it.
set -u

ROOT=/var/tmp/vehicle-logger-board/root
REUSE=0 SUITE=full BENCH=0 MIRROR=http://deb.debian.org/debian
while [ $# -gt 0 ]; do
    case "$1" in
        --root) ROOT="${2:?--root needs a directory}"; shift ;;
        --reuse) REUSE=1 ;;
        --suite) SUITE="${2:?--suite needs full, quick or none}"; shift ;;
        --bench) BENCH=1 ;;
        --mirror) MIRROR="${2:?--mirror needs a URL}"; shift ;;
        -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "board-check.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
case "$SUITE" in full|quick|none) ;; *) echo "board-check.sh: --suite takes full, quick or none" >&2; exit 2 ;; esac
if [ "$(id -u)" != 0 ]; then
    echo "board-check.sh: run as root (debootstrap, chroot and mounts need it)" >&2
    exit 1
fi

SRC=$(cd "$(dirname "$0")/.." && pwd)
LOGS=$(dirname "$ROOT")/logs
WHEELS=/var/cache/vehicle-logger/wheels   # inside the root
TREE=/usr/local/src/vehicle-logger        # inside the root
DRIVES=/root/drives                       # inside the root
mkdir -p "$LOGS"
rm -f "$LOGS"/tests-*.log  # the test line at the end is this run's, or none (an earlier run's was shown)
TABLE=""
FAILURES=0

now() { date +%s; }

check() {
    # check NAME command...: runs one step, its output into $LOGS/NAME.log, and adds a row to the table.
    name=$1
    shift
    echo "== $name"
    start=$(now)
    if "$@" > "$LOGS/$name.log" 2>&1; then
        result=ok
    else
        result="FAILED (exit $?; $LOGS/$name.log)"
        FAILURES=$((FAILURES + 1))
        tail -n 15 "$LOGS/$name.log" | sed 's/^/   | /'
    fi
    took=$(( $(now) - start ))
    echo "-- $name: $result, $took s"
    TABLE="$TABLE$name|$result|$took
"
}

in_root() {
    # A command inside the armhf root, with a clean environment (the host's venv, paths and pip settings stay
    # outside; a proxy, if the host has one, is the root's too).
    chroot "$ROOT" /usr/bin/env -i HOME=/root LANG=C.UTF-8 TERM=dumb \
        PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
        ${http_proxy:+http_proxy=$http_proxy} ${https_proxy:+https_proxy=$https_proxy} \
        ${no_proxy:+no_proxy=$no_proxy} "$@"
}

offline_in_root() {
    # The same with no network at all (a new network namespace holds only a loopback that is down).
    unshare --net chroot "$ROOT" /usr/bin/env -i HOME=/root LANG=C.UTF-8 TERM=dumb \
        PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin "$@"
}

unmount_root() {
    for m in dev/pts dev sys proc; do
        if mountpoint -q "$ROOT/$m" 2>/dev/null; then umount -l "$ROOT/$m"; fi
    done
}
trap unmount_root EXIT

host_tools() {
    # debootstrap and qemu-user-static from Debian, and the kernel's binfmt_misc handing ARM binaries to qemu.
    if ! command -v debootstrap >/dev/null || [ ! -e /usr/libexec/qemu-binfmt/arm-binfmt-P ]; then
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends debootstrap \
            qemu-user-static binfmt-support
    fi
    if [ ! -e /proc/sys/fs/binfmt_misc/status ]; then
        mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
    fi
    if [ ! -e /proc/sys/fs/binfmt_misc/qemu-arm ]; then
        update-binfmts --enable qemu-arm
    fi
    grep -q enabled /proc/sys/fs/binfmt_misc/qemu-arm
}

build_root() {
    unmount_root
    rm -rf "$ROOT"
    mkdir -p "$ROOT"
    # systemd and udev as on a board's image (sysusers, offline enable); a user 'debian' as BeagleBone images have.
    # Each command's failure ends the step with its status (a function's status is its last command's: a failed
    # debootstrap followed by a useradd that worked said "ok").
    debootstrap --arch=armhf --variant=minbase --include=systemd,udev,ca-certificates,passwd \
        bookworm "$ROOT" "$MIRROR" || return
    in_root useradd -m -s /bin/bash debian
}

prepare_root() {
    mountpoint -q "$ROOT/proc" || mount -t proc proc "$ROOT/proc" || return
    mountpoint -q "$ROOT/sys" || mount -t sysfs sys "$ROOT/sys" || return
    mountpoint -q "$ROOT/dev" || mount --bind /dev "$ROOT/dev" || return
    mountpoint -q "$ROOT/dev/pts" || mount --bind /dev/pts "$ROOT/dev/pts" || return
    cp /etc/resolv.conf "$ROOT/etc/resolv.conf" || return
    # A site's own certificate authorities (a proxy that inspects TLS) are trusted in the root as on the host,
    # as they would be on a board behind the same proxy.
    if ls /usr/local/share/ca-certificates/*.crt >/dev/null 2>&1; then
        mkdir -p "$ROOT/usr/local/share/ca-certificates"
        cp /usr/local/share/ca-certificates/*.crt "$ROOT/usr/local/share/ca-certificates/"
        in_root update-ca-certificates || return
    fi
    # Packages installed into a chroot must not start services.
    printf '#!/bin/sh\nexit 101\n' > "$ROOT/usr/sbin/policy-rc.d"
    chmod 0755 "$ROOT/usr/sbin/policy-rc.d"
    # The tree as committed plus what is changed in the work tree (git's list; no venvs, caches or drives).
    rm -rf "$ROOT$TREE"
    mkdir -p "$ROOT$TREE" || return
    (cd "$SRC" && git ls-files -z --cached --others --exclude-standard | xargs -0 tar -cf - 2>/dev/null) \
        | tar -xf - -C "$ROOT$TREE" || return
    # The tests' own Debian packages (pytest and what the suite imports); no network needed later. Not matplotlib
    # (its three tests skip, saying so), and not RTKLIB, an office tool: Debian's armhf rtklib 2.4.3 b34 under
    # qemu-user reads none of the observations its x86 build reads from the same files (rnx2rtkp "no obs data",
    # convbin no epochs; RTKLIB has a history of ARM portability bugs, tomojitakasu/RTKLIB#118), so its tests
    # skip here as "not installed" and run in the x86 CI.
    in_root apt-get install -y -qq --no-install-recommends python3-pytest python3-hypothesis python3-jsonschema
}

install_image() {
    offline_in_root sh "$TREE/tools/install-board.sh" --image --no-apt --wheels "$WHEELS" --operator debian
}

same_dry_run() {
    # The dry run after a full installation lists the steps it listed before.
    in_root sh "$TREE/tools/install-board.sh" --dry-run --image --operator debian > "$LOGS/dry-run-after.txt"
    diff -u "$LOGS/dry-run-before.txt" "$LOGS/dry-run-after.txt"
}

sim_drive() {
    rm -rf "$ROOT$DRIVES"
    in_root /usr/local/bin/logger run --sim --duration 60 --out "$DRIVES"
    ls "$ROOT$DRIVES"/*.mcap
}

info() {
    in_root sh -c "/usr/local/bin/logger info $DRIVES/*.mcap"
}

replay() {
    in_root sh -c "/usr/local/bin/logger replay --out $DRIVES/replay $DRIVES/*.mcap"
    test -s "$ROOT$DRIVES/replay/trajectory.csv"
}

suite() {
    if [ "$SUITE" = quick ]; then
        files="tests/test_config.py tests/test_systemd.py tests/test_install_board.py tests/test_ublox_reader.py tests/test_mpu6050.py"
    else
        files=""
    fi
    # The installed venv (Debian's numpy & co. and the wheelhouse's packages), the tree's tests; a test that
    # cannot hold on a slow core skips itself and says so.
    in_root sh -c "cd $TREE && LOGGER_BOARD=1 /opt/vehicle-logger/venv/bin/python -m pytest -p no:cacheprovider -rs $files"
}

bench() {
    # The daemon benchmark at each IMU rate, here and inside the root, alternated so that both see the same load;
    # the figures go to $LOGS/emulated.json for tools/bench_board.py (--show-emulated, --record-emulated).
    host_python="$SRC/.venv/bin/python"
    [ -x "$host_python" ] || echo "no $host_python: the runs on this machine are left out (python3 -m venv .venv ...)"
    for rate in 20 200 1000; do
        if [ -x "$host_python" ]; then
            (cd "$SRC" && "$host_python" tools/bench_daemon.py --imu-rate "$rate" --seconds 60 \
                --json "$LOGS/bench-host-$rate.json") || return 1
        fi
        in_root sh -c "cd $TREE && /opt/vehicle-logger/venv/bin/python tools/bench_daemon.py --imu-rate $rate \
            --seconds 60 --json /root/bench-emulated-$rate.json" || return 1
        cp "$ROOT/root/bench-emulated-$rate.json" "$LOGS/"
    done
    python3 - "$LOGS" "$(date -u '+%Y-%m-%d %H:%M UTC')" <<'PY'
import json, pathlib, sys
logs = pathlib.Path(sys.argv[1])
def load(name):
    p = logs / name
    return json.loads(p.read_text()) if p.exists() else None
runs = [{"host": load(f"bench-host-{r}.json"), "emulated": load(f"bench-emulated-{r}.json")} for r in (20, 200, 1000)]
(logs / "emulated.json").write_text(json.dumps({"measured": sys.argv[2], "command": "tools/board-check.sh --bench",
                                                "runs": runs}, indent=1))
PY
    (cd "$SRC" && python3 tools/bench_board.py --show-emulated "$LOGS/emulated.json")
}

check host-tools host_tools
if [ "$REUSE" = 1 ] && [ -x "$ROOT/usr/bin/python3" ]; then
    echo "== reusing the root in $ROOT"
else
    check debootstrap build_root
fi
[ "$FAILURES" -gt 0 ] || check prepare prepare_root
if [ "$FAILURES" -gt 0 ]; then
    # Every later step runs in the root: without one, each would fail for that reason alone.
    echo "the armhf root could not be made or prepared (see above and $LOGS): the steps that need it are not run"
else
    check wheelhouse in_root sh "$TREE/tools/install-board.sh" --fetch-wheels "$WHEELS"
    in_root sh "$TREE/tools/install-board.sh" --dry-run --image --operator debian > "$LOGS/dry-run-before.txt" 2>&1
    check install-offline install_image
    check install-again install_image
    check dry-run-same same_dry_run
    check config-check in_root /usr/local/bin/logger config check /etc/vehicle-logger/logger.toml
    check sim-drive-60s sim_drive
    check info info
    check replay replay
    if [ "$SUITE" != none ]; then
        check "tests-$SUITE" suite
    fi
    if [ "$BENCH" = 1 ]; then
        check bench-daemon bench
    fi
fi

echo
echo "board check: Debian 12 armhf under qemu-user-static, root $ROOT, logs $LOGS"
printf '  %-16s %-8s %s\n' step seconds result
printf '%s' "$TABLE" | while IFS='|' read -r name result took; do
    printf '  %-16s %7s  %s\n' "$name" "$took" "$result"
done
grep -h -E '^[0-9]+ (passed|failed)|passed|failed' "$LOGS"/tests-*.log 2>/dev/null | tail -n 1 | sed 's/^/  tests: /'
if [ "$BENCH" = 1 ] && [ -e "$LOGS/emulated.json" ]; then
    echo
    (cd "$SRC" && python3 tools/bench_board.py --show-emulated "$LOGS/emulated.json")
    echo "into BENCHMARKS.md: python3 tools/bench_board.py --record-emulated $LOGS/emulated.json"
fi
exit $((FAILURES > 0))
