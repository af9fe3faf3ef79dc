#!/bin/sh
# Regenerates the .pos fixtures of this folder with Debian's rtklib (apt-get install rtklib): see README.md.
# make.sh [OUT_DIR]: into OUT_DIR instead (tests/test_nav_solution.py compares the two).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
out=$(mkdir -p "${1:-$here}" && cd "${1:-$here}" && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"${PYTHON:-python3}" "$here/../../../tools/rinex_synth.py" "$work" --epochs 20 --seed 1 >/dev/null
cp "$work/truth.csv" "$out/truth.csv"
base="-2387136.5236 -3923067.1859 4413006.5382"  # printed by rinex_synth.py
cd "$work"
printf 'out-timeform =tow\n' | cat "$here/rtklib.conf" - > tow.conf
printf 'out-timesys =jst\n' | cat "$here/rtklib.conf" - > jst.conf
run() { f=$1; shift; rnx2rtkp "$@" -o "$out/$f" >/dev/null 2>&1; }
k="$here/rtklib.conf"
run single-llh-gpst.pos -k "$k" -p 0 rover.obs gps.nav
run single-xyz-utc.pos -k "$k" -p 0 -e -u rover.obs gps.nav
run dgps-llh-gpst.pos -k "$k" -p 1 -r $base rover.obs base.obs gps.nav
run float-llh-gpst.pos -k "$k" -p 2 -f 1 -v 0 -r $base rover.obs base.obs gps.nav
run kinematic-llh-gpst.pos -k "$k" -p 2 -f 1 -r $base rover.obs base.obs gps.nav
run kinematic-llh-utc-d1.pos -k "$k" -p 2 -f 1 -u -d 1 -r $base rover.obs base.obs gps.nav
run kinematic-xyz-gpst.pos -k "$k" -p 2 -f 1 -e -r $base rover.obs base.obs gps.nav
run kinematic-enu-gpst.pos -k "$k" -p 2 -f 1 -a -r $base rover.obs base.obs gps.nav
run kinematic-dms-gpst.pos -k "$k" -p 2 -f 1 -g -r $base rover.obs base.obs gps.nav
run kinematic-llh-tow.pos -k tow.conf -p 2 -f 1 -r $base rover.obs base.obs gps.nav
run kinematic-llh-jst.pos -k jst.conf -p 2 -f 1 -r $base rover.obs base.obs gps.nav
sed -i 's/^\(% inp file  : \).*\//\1/' "$out"/*.pos  # the temporary folder's name out of the headers
