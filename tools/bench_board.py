"""What the figures measured on this machine mean on a BeagleBone-class board (AM335x: one Cortex-A8, 1 GHz).

The translation: CPU times measured on this machine's core are multiplied by a range of factors, the ratio of
this core's speed to a Cortex-A8's for the same Python code, taken from published measurements. The factors, their
sources and the assumptions that join them are stated in :data:`METHOD` and printed with every report, so that a
measurement on a real board (``tools/bench.py --only daemon`` runs there unchanged: the per-thread split leaves the
simulator out) can replace them.

The floor check: ``tools/board-check.sh --bench`` runs the same daemon benchmark inside a Debian 12 armhf root
under qemu-user, alternated with runs on this machine, and ``python tools/bench_board.py --record-emulated FILE``
puts those figures beside the translation (:func:`render_emulated` says what they do and do not tell).

    python tools/bench_board.py --record-emulated /var/tmp/vehicle-logger-board/logs/emulated.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import resident  # noqa: E402
from bench_daemon import daemon_alone_mb  # noqa: E402

FACTOR_LOW = 9.0
FACTOR_HIGH = 28.0
FACTOR_MID = 16.0  # geometric middle of the range
BUDGET_PCT = 25.0  # of one board core, for the default setup
# The core H (below) was judged for: CPU seconds measured on another core need H judged again.
FACTOR_JUDGED_FOR = "Intel(R) Xeon(R) Processor"
I2C_KERNEL_US = (20.0, 50.0)  # assumed kernel CPU per I2C transfer on the board (i2c-omap, interrupt driven)

METHOD = f"""\
**Method.** CPU seconds measured here on one x86 core are multiplied by a factor F, the ratio of this core's
speed to a Cortex-A8 at 1 GHz's for CPython code, given as a range **F = {FACTOR_LOW:g} to {FACTOR_HIGH:g}**. It rests
on published ratios between x86 desktop cores and ~1 GHz in-order ARM cores, and on stated assumptions:

1. J. Whitham, *Relative speed of Raspberry Pi, Pi 2, and desktop PC (x86 and AMD64)*, 26 April 2015
   (jwhitham.org/2015/04/relative-speed-of-raspberry-pi-pi-2-and.html): the same C programs ran 11.3x (Doom,
   integer) and 10.5x (Quake 2, integer and floating point) faster on a Core i3-3220 (x86-64, 3.3 GHz) than on a
   Raspberry Pi 2 (Cortex-A7, 900 MHz).
2. SABnzbd maintainers, *Improve pystone measurement*, github.com/sabnzbd/sabnzbd/issues/1162 (2018): typical
   CPython pystone figures of 170,000 for a 2018 Core i3 and 15,000 for a NanoPi NEO2 (Cortex-A53): 11.3x for
   interpreted Python, the same ratio as for compiled code in 1.
3. ARM rates the Cortex-A8 at 2.0 DMIPS/MHz, so 2,000 DMIPS at 1 GHz, about 1.2x one Cortex-A7 core of the
   Raspberry Pi 2 (6,840 DMIPS for four cores at 900 MHz, raspberry-pi-geek.com, *Raspberry Pi 1 and 2
   compared*, 2015); the AM335x has 256 KB of L2 cache (TI, *Cortex-A8 Features*), and the Cortex-A8's VFP
   unit (VFPLite) is not pipelined (ARM, Cortex-A8 Technical Reference Manual).

Assumptions joining them: F = R x H x A, with R = 11 the published ratio (1 and 2 agree), H = 1.0 to 1.7 how
much faster the measuring machine's core runs Python than those 2012-2018 desktop cores (judged for the machine
these figures were first taken on, a virtualised Xeon reporting AVX-512 and AMX, a Sapphire Rapids-class core;
another machine needs H judged again), and A = 1/1.2 to 1.5 how much slower a Cortex-A8 at 1 GHz runs
CPython than the small ARM cores in 1 and 2: 1.2x faster by Dhrystone (3), up to 1.5x slower where its small L2,
DDR3 latency and slow floating point tell (the filter and the JSON encoding use floats). Hence F from
11 x 1.0 / 1.2 = {FACTOR_LOW:g} to 11 x 1.7 x 1.5 = {FACTOR_HIGH:g}; the geometric middle, about {FACTOR_MID:g}, is the
likeliest. Not included: the board's kernel work for the same
I/O (I2C transfers through i2c-omap, UART and GPIO interrupts), estimated below from the measured transfer
rate at an assumed {I2C_KERNEL_US[0]:g} to {I2C_KERNEL_US[1]:g} us of kernel CPU per I2C transfer; the simulator's own
CPU, which the measurement already leaves out. Memory: the tables above measure it on x86-64, whose pointers
are twice armhf's; the board's own, with Debian's armhf libraries, is measured in the emulated root below (the
guest's pages, not qemu's), where the instructions' speed does not matter.
"""


def machine_caveat(cpu: str) -> str | None:
    """A line for the report when the figures were measured on a core other than the one F was judged for."""
    if cpu == FACTOR_JUDGED_FOR:
        return None
    return (f"- The board's range uses F, judged for a {FACTOR_JUDGED_FOR} core (H in the BeagleBone section's "
            f"method); these figures were measured on {cpu}, for which H was not judged again: where this core runs "
            "Python faster than that one, the range understates the board by as much, and where slower, overstates "
            "it (no host reference was taken on that core to tell which: the load table's reference compares only "
            "the hosts measured since).")


def board_range(pct_here: float) -> tuple[float, float]:
    return pct_here * FACTOR_LOW, pct_here * FACTOR_HIGH


def verdict(low: float, high: float) -> str:
    if high < BUDGET_PCT:
        return f"within the {BUDGET_PCT:g} % budget even at the slow end"
    if low < BUDGET_PCT:
        return f"within the {BUDGET_PCT:g} % budget at the fast end, **over it at the slow end**"
    return f"**over the {BUDGET_PCT:g} % budget** across the whole range"


def render(results: dict[str, Any]) -> list[str]:
    """The board section: the method, then each measured figure translated."""
    lines = [*METHOD.splitlines(), ""]
    daemon = [r for r in (results.get("daemon") or {}).get("runs", []) if not r["profile"]]
    rows = ["| figure | measured here | on the board (F = "
            f"{FACTOR_LOW:g} to {FACTOR_HIGH:g}) |", "| --- | --- | --- |"]
    default = next((r for r in daemon if r["imu_rate_hz"] == 20.0), None)
    for r in daemon:
        low, high = board_range(r["daemon_pct"])
        kern = (r["i2c_transfers_per_s"] * I2C_KERNEL_US[0] / 1e4, r["i2c_transfers_per_s"] * I2C_KERNEL_US[1] / 1e4)
        rows.append(f"| daemon threads, IMU at {r['imu_rate_hz']:g} Hz | {r['daemon_pct']:.2f} % of a core "
                    f"| **{low:.0f} to {high:.0f} %** of the core, plus {kern[0]:.2f} to {kern[1]:.2f} % kernel I2C |")
    rec = (results.get("recorder") or {}).get("streams", {}).get("drive mix")
    if rec:
        us = rec["writers"]["recorder"]["cpu_us_per_msg"]
        rows.append(f"| recorder, CPU per record at full throughput | {us:.1f} us | {us * FACTOR_LOW:.0f} to "
                    f"{us * FACTOR_HIGH:.0f} us |")
    if default is not None:
        import bench_daemon

        us = bench_daemon.live_costs(default)["recorder_us_per_record"]
        rows.append(f"| recorder thread per record, live at the default rates | {us:.0f} us | "
                    f"{us * FACTOR_LOW / 1000:.1f} to {us * FACTOR_HIGH / 1000:.1f} ms |")
    nav = results.get("nav")
    if nav:
        us = next(r["cpu_us_per_sample"] for r in nav["replays"] if r["mode"] == "17" and not r["smooth"])
        for rate in (20, 200, 1000):
            rows.append(f"| 17-state filter at {rate} Hz (per sample x rate) | {us * rate / 1e4:.2f} % of a core "
                        f"| {us * rate * FACTOR_LOW / 1e4:.0f} to {us * rate * FACTOR_HIGH / 1e4:.0f} % of the core |")
    start = results.get("startup")
    if start:
        import bench_startup

        s = bench_startup.summary(start)
        cpu = (s["cpu_at_first_imu_s"] or 0.0) - (s["vehicle_cpu_s"] or 0.0)
        rows.append(f"| CPU from process start to the first IMU record (without the simulated vehicle) "
                    f"| {cpu:.2f} s | {cpu * FACTOR_LOW:.1f} to {cpu * FACTOR_HIGH:.1f} s, plus reading the files "
                    "from the SD card |")
    lines += rows
    if results.get("emulated"):
        lines += ["", *render_emulated(results["emulated"])]
    if default is not None:
        low, high = board_range(default["daemon_pct"])
        lines += ["", f"**Default setup** (IMU 20 Hz, baro 1 Hz, OBD 2 Hz, GNSS and PPS 1 Hz, live filter): "
                  f"{default['daemon_pct']:.2f} % of a core here, so **{low:.0f} to {high:.0f} % of the board's core**"
                  f" (likeliest about {default['daemon_pct'] * FACTOR_MID:.0f} %): {verdict(low, high)}."]
        if high >= BUDGET_PCT:
            lines += ["", *costliest(default, results)]
    return lines


def costliest(default: dict[str, Any], results: dict[str, Any]) -> list[str]:
    """What the default setup's CPU goes to: the daemon threads by their own share, and the profile's modules."""
    threads = sorted(((n, t["pct"] - t["sim_inside_pct"]) for n, t in default["threads"].items()
                      if t["class"] == "daemon"), key=lambda kv: kv[1], reverse=True)
    out = ["**What costs most** at the default rates, to act on: by thread (own CPU, % of a core here) "
           + ", ".join(f"{n} {pct:.2f} %" for n, pct in threads if pct >= 0.01) + "."]
    profiled = next((r for r in (results.get("daemon") or {}).get("runs", []) if r["profile"]), None)
    if profiled and profiled["profile_top"].get("modules"):
        mods = [m for m in profiled["profile_top"]["modules"] if not m["sim"]][:8]
        out.append("By module in the profile (share of the daemon threads' own CPU): "
                   + ", ".join(f"{m['module']} {m['share'] * 100:.1f} %" for m in mods) + ".")
    return out


EMULATION_CAVEATS = """\
What this tells: the daemon installs and runs on armhf with Debian's own numpy, pyserial, smbus2, python-can,
zstandard and lz4, and whether the rates are held when every instruction is translated; the ratio of its CPU to
this machine's in the same run is a floor check on the translation above. What it does not: qemu-user translates
ARM instructions to x86 ones on this machine's core, so the emulated CPU is neither a Cortex-A8's speed (no
in-order pipeline, no 256 KB L2, no VFPLite, none of the board's memory latency) nor a bound on it; the kernel's
work (system calls, the simulated devices' pty and ioctl) runs natively at x86 speed; the simulated vehicle runs
emulated too, in the same process, competing for the same core."""


def render_emulated(section: dict[str, Any]) -> list[str]:
    """The daemon benchmark run inside the emulated armhf root beside the same run here, rate by rate."""
    lines = [f"**Measured under emulation** ({section.get('measured', '?')}; `{section.get('command', '')}`): "
             "the daemon benchmark inside a Debian 12 armhf root under qemu-user-static, alternated with the same "
             "run on this machine, 60 s windows.", "",
             "| IMU rate | daemon threads here | under emulation | emulated / here | sustained here / emulated "
             "| IMU samples kept under emulation | resident set under emulation, peak "
             "| of which the daemon alone at the end, estimated |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for run in section["runs"]:
        here, emu = run.get("host"), run["emulated"]
        ratio = f"{emu['daemon_pct'] / here['daemon_pct']:.1f}x" if here and here["daemon_pct"] > 0 else "-"
        held = (("yes" if here["sustained"] else "no") if here else "-") + " / " + \
            ("yes" if emu["sustained"] else "no")
        here_pct = f"{here['daemon_pct']:.2f} %" if here else "-"
        kept = emu["counters"]["sensors"].get("imu", {}).get("samples", 0)
        guest = guest_pages(emu) and daemon_alone_mb(emu) is not None
        peak = f"{emu['hwm_mb']:.1f} MB" + ("" if guest else " (qemu's)")
        alone = f"{daemon_alone_mb(emu):.1f} MB" if guest else "-"
        due = emu["imu_rate_hz"] * emu["window_s"]
        lines.append(f"| {emu['imu_rate_hz']:g} Hz | {here_pct} | {emu['daemon_pct']:.2f} % | {ratio} | {held} "
                     f"| {kept} of {due:.0f} ({emu['file']['fifo_lost']} lost to FIFO overflow) "
                     f"| {peak} | {alone} |")
    lines += ["", "A rate not sustained under emulation is the emulated core's limit with the simulated vehicle (its "
              "share beside the daemon's: " + ", ".join(f"{r['emulated']['sim_pct']:.0f} %" for r in section["runs"])
              + " of the core) in the same process: the daemon's own CPU at that rate is then under-counted, since "
              "it handled only the samples that came."]
    if any(guest_pages(r["emulated"]) for r in section["runs"]):
        lines += ["", "The resident set under emulation is the guest's own pages (`tools/resident.py`: qemu keeps the "
                  "guest's memory as one window of its own address space, and the Rss of that window's mappings is "
                  "the 32-bit program's, without the translator and its code cache): the board's binaries, Debian's "
                  "armhf numpy and 4-byte pointers, measured as on the board. Its peak is the largest of the run's "
                  "samples (every 5 s). Runs saved before 2026-12-05 give qemu's whole process instead."]
        idx = [(r["emulated"]["imu_rate_hz"], r["emulated"].get("writer_index") or {}) for r in section["runs"]]
        idx = [(hz, x) for hz, x in idx if "beyond_window_mb" in x]
        if idx:
            lines[-1] += (" By the end of each hour's file the recorder's MCAP writer holds its index besides, "
                          "measured in the same runs: " + ", ".join(
                              f"{hz:g} Hz {x['bytes_per_chunk']:.0f} B a chunk, {x['beyond_window_mb']:.1f} MB more "
                              "than at the window's end" for hz, x in idx) + ".")
    lines += ["", *EMULATION_CAVEATS.splitlines()]
    return lines


def guest_pages(run: dict[str, Any]) -> bool:
    """Whether an emulated run's resident set is the guest's own (tools/resident.py), not qemu's whole process."""
    return run.get("rss_source", resident.NATIVE) != resident.NATIVE


def record_emulated(path: Path, report: Path) -> None:
    """Put the emulated runs into the saved figures and write the report again from them."""
    raw = report.with_suffix(".json")
    saved = json.loads(raw.read_text())
    saved["results"]["emulated"] = json.loads(path.read_text())
    raw.write_text(json.dumps(saved, indent=1))
    subprocess.run([sys.executable, str(ROOT / "tools" / "bench.py"), "--render-only", "--out", str(report)],
                   check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--record-emulated", type=Path, metavar="FILE",
                    help="emulated.json from tools/board-check.sh --bench: add it to BENCHMARKS.md")
    ap.add_argument("--show-emulated", type=Path, metavar="FILE", help="print that file's table only")
    ap.add_argument("--out", type=Path, default=ROOT / "BENCHMARKS.md", help="report (default BENCHMARKS.md)")
    args = ap.parse_args(argv)
    for given in (args.record_emulated, args.show_emulated):
        if given is not None and not given.is_file():
            ap.error(f"{given}: no such file (tools/board-check.sh --bench writes it)")
    if args.show_emulated:
        print("\n".join(render_emulated(json.loads(args.show_emulated.read_text()))))
    elif args.record_emulated:
        record_emulated(args.record_emulated, args.out)
    else:
        ap.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
