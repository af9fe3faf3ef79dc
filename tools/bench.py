"""Run every benchmark, each in its own process, and write the figures as tables into BENCHMARKS.md.

    python tools/bench.py                      # everything, about 35 minutes; writes BENCHMARKS.md
    python tools/bench.py --quick              # a short smoke run of everything; prints, writes nothing
    python tools/bench.py --only recorder,nav  # a subset; the other sections keep their last figures
    python tools/bench.py --only daemon --board-python .venv-floors/bin/python  # also with Debian 12's libraries

Benchmarks (``--only`` names): ``daemon`` (CPU per thread and memory of the daemon on the simulated vehicle
at the default rates and with the IMU at 200, 500 and 1000 Hz, each long enough to tell whether the rate is
sustained, plus a profiled run; ``tools/bench_daemon.py``), ``recorder`` (throughput against the bare mcap
writer; ``tools/bench_recorder.py``), ``nav`` (filter cost per IMU sample and ``logger replay`` speed;
``tools/bench_nav.py``), ``sync`` (stamp error against the truth, locked and in holdover;
``tools/bench_sync.py``), ``startup`` (time to the first recorded sample; ``tools/bench_startup.py``). The
recorder and filter benchmarks share one simulated drive, recorded first by ``tools/nav_eval.py``'s recorder.

The raw figures of each benchmark go to BENCHMARKS.json beside the report, with when and under what load they
were taken, so that a subset run keeps the other sections. Other jobs may share the machine: the load average
and how busy the machine was while each benchmark ran are in the report. No test asserts on these figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(TOOLS))

import bench_board  # noqa: E402
import bench_daemon  # noqa: E402
import bench_nav  # noqa: E402
import bench_recorder  # noqa: E402
import bench_startup  # noqa: E402
import bench_sync  # noqa: E402

BENCHMARKS = ("daemon", "recorder", "nav", "sync", "startup")

# (full, quick) settings of each benchmark
DAEMON_RATES = ((20.0, 300.0), (200.0, 300.0), (500.0, 300.0), (1000.0, 300.0))
QUICK_DAEMON_RATES = ((20.0, 30.0), (200.0, 30.0), (500.0, 30.0), (1000.0, 30.0))
PROFILE_S = (60.0, 20.0)
BOARD_LIBRARY_RATES = (20.0, 1000.0)  # the daemon's rates run again with Debian 12's libraries (--board-python)
DRIVE_S = (600.0, 180.0)
DRIVE_TIME_SCALE = 4.0  # faster starves the simulated sensors on a loaded 2-core host (docs/nav.md)
RECORDER = (("--messages", "200000", "--repeat", "3"), ("--messages", "20000", "--repeat", "1"))
SYNC = (("--duration", "900", "--pps-outage", "300", "400", "--time-scale", "5"),
        ("--duration", "180", "--pps-outage", "60", "60", "--time-scale", "6"))
STARTUP_RUNS = ("5", "2")


# ---- the machine ---------------------------------------------------------------------------------------------
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text(encoding="ascii").split()[:3])
    except OSError:
        return "?"


def machine_busy() -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs since boot, from /proc/stat."""
    fields = [int(x) for x in Path("/proc/stat").read_text(encoding="ascii").splitlines()[0].split()[1:]]
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return sum(fields) - idle, sum(fields)


def versions() -> dict[str, str]:
    return {"python": platform.python_version(), **bench_daemon.library_versions()}


def tree_state() -> str:
    """The commit measured, and whether the work tree differed from it (read-only git commands)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return head + (" with uncommitted changes" if dirty else "")


def reference_ms(repeat: int = 5) -> float:
    """CPU time of a fixed piece of work, best of ``repeat``, in ms: how fast this host runs this Python now.

    Figures measured on different hosts (a virtual machine moved to another one keeps its CPU's name) or on one
    host on a busier day are not comparable by themselves; the same work timed beside them says by how much the
    host changed. The work is the kind the daemon does: interpreted arithmetic, dict and list operations, and
    small numpy matrices (the filter's)."""
    import math

    import numpy as np

    best = math.inf
    for _ in range(repeat):
        c0 = time.process_time()
        table: dict[int, float] = {}
        x = 0.0
        for i in range(100_000):
            x += math.sin(i) * 1.0001
            table[i & 1023] = x
        rows = [[float(i + j) for j in range(8)] for i in range(8)]
        a = np.array(rows)
        for _ in range(2_000):
            a = a @ a.T * 1e-3 + 1.0
        best = min(best, time.process_time() - c0)
    return round(best * 1e3, 1)


def machine() -> dict[str, Any]:
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "kernel": platform.release(), "arch": platform.machine(),
            "versions": versions(), "commit": tree_state()}


# ---- running one benchmark in its own process ----------------------------------------------------------------
def run_step(name: str, args: list[str], work: Path, python: str = sys.executable) -> Any:
    """Run ``tools/<script> args --json F`` as a child (by ``python``); returns its JSON and notes the load while it
    ran."""
    out = work / f"{name}.json"
    log = work / f"{name}.log"
    started = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    reference = reference_ms()
    busy0, total0 = machine_busy()
    child0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0, t0 = loadavg(), time.monotonic()
    print(f"[bench] {name}: {' '.join(args)}", flush=True)
    with open(log, "w", encoding="utf-8") as f:
        code = subprocess.run([python, *args, "--json", str(out)], cwd=ROOT, stdout=f, stderr=f).returncode
    wall = time.monotonic() - t0
    busy1, total1 = machine_busy()
    child1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if code != 0 or not out.exists():
        tail = log.read_text(encoding="utf-8", errors="replace")[-3000:]
        raise SystemExit(f"bench: {name} failed (exit {code}); its log ends:\n{tail}")
    ours = (child1.ru_utime - child0.ru_utime) + (child1.ru_stime - child0.ru_stime)
    ticks = os.sysconf("SC_CLK_TCK")
    cores = os.cpu_count() or 1
    busy_pct = (busy1 - busy0) / max(total1 - total0, 1) * 100
    return {"result": json.loads(out.read_text()),
            "load": {"started": started, "wall_s": round(wall), "loadavg_before": load0, "loadavg_after": loadavg(),
                     "kernel": platform.release(), "reference_ms": reference,
                     "machine_busy_pct": round(busy_pct, 1),
                     "others_pct_of_machine": round(max(0.0, busy_pct - ours * 100 / (wall * cores)), 1),
                     "jiffy_hz": ticks}}


def run_daemon(quick: bool, work: Path, nice: int, board_python: str | None = None) -> dict[str, Any]:
    runs, loads, board_runs = [], [], []
    for rate, seconds in QUICK_DAEMON_RATES if quick else DAEMON_RATES:
        step = run_step(f"daemon-{rate:g}", ["tools/bench_daemon.py", "--imu-rate", f"{rate:g}", "--seconds",
                                             f"{seconds:g}", "--nice", str(nice)], work)
        runs.append(step["result"])
        loads.append({"step": f"daemon {rate:g} Hz", **step["load"]})
    step = run_step("daemon-profile", ["tools/bench_daemon.py", "--imu-rate", "20", "--seconds",
                                       f"{PROFILE_S[quick]:g}", "--profile", "--nice", str(nice)], work)
    runs.append(step["result"])
    loads.append({"step": "daemon 20 Hz, profiled", **step["load"]})
    # The board installs Debian 12's libraries (numpy 1.24.2, whose ``import numpy`` loads more): the memory the
    # daemon takes with them, at the default rate and the highest.
    board_rates = [(rate, s) for rate, s in (QUICK_DAEMON_RATES if quick else DAEMON_RATES)
                   if board_python and rate in BOARD_LIBRARY_RATES]
    for rate, seconds in board_rates:
        step = run_step(f"daemon-{rate:g}-board-libraries", ["tools/bench_daemon.py", "--imu-rate", f"{rate:g}",
                                                             "--seconds", f"{seconds:g}", "--nice", str(nice)],
                        work, python=board_python)
        board_runs.append(step["result"])
        loads.append({"step": f"daemon {rate:g} Hz, Debian 12's libraries", **step["load"]})
    return {"runs": runs, "loads": loads, "board_runs": board_runs}


def record_drive(quick: bool, work: Path) -> list[Path]:
    import nav_eval

    files = nav_eval.record(work / "drives", "urban", 1, DRIVE_S[quick], DRIVE_TIME_SCALE)
    if not files:
        raise SystemExit("bench: recording the simulated drive gave no file")
    return files


def run_all(selected: list[str], quick: bool, work: Path, nice: int, board_python: str | None = None
            ) -> dict[str, Any]:
    done: dict[str, Any] = {}
    drive: list[Path] = []
    for name in selected:
        started = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
        if name == "daemon":
            section = run_daemon(quick, work, nice, board_python)
        else:
            if name in ("recorder", "nav") and not drive:
                drive = record_drive(quick, work)
            args = {"recorder": ["tools/bench_recorder.py", *map(str, drive), *RECORDER[quick]],
                    "nav": ["tools/bench_nav.py", *map(str, drive)],
                    "sync": ["tools/bench_sync.py", *SYNC[quick]],
                    "startup": ["tools/bench_startup.py", "--runs", STARTUP_RUNS[quick]]}[name]
            step = run_step(name, args, work)
            section = {**step["result"], "loads": [{"step": name, **step["load"]}]}
        section["measured"] = started
        section["quick"] = quick
        done[name] = section
    return done


# ---- the report ----------------------------------------------------------------------------------------------
HEADINGS = {
    "daemon": ("Daemon CPU and memory on the simulated vehicle", bench_daemon),
    "recorder": ("Recorder throughput against the bare mcap writer", bench_recorder),
    "nav": ("Navigation filter and `logger replay`", bench_nav),
    "sync": ("Time sync: stamp error against the truth", bench_sync),
    "startup": ("Start-up to the first recorded sample", bench_startup),
}


def _doc(module: Any) -> list[str]:
    """The module's description after its usage line, for the method under each table (lists kept as lists)."""
    parts = (module.__doc__ or "").strip().split("\n\n")[2:]
    out: list[str] = []
    for part in parts:
        items: list[str] = []
        for line in part.splitlines():
            if line.startswith("- ") or not items:
                items.append(line.strip())
            else:
                items[-1] += " " + line.strip()
        out += [*items, ""]
    return out


def report(results: dict[str, Any], info: dict[str, Any], command: str) -> str:
    v = info["versions"]
    lines = ["# Benchmarks", "",
             f"Written by `{command}`; each section says when it was measured. Every figure below was measured; "
             "the BeagleBone section translates them with the stated factors. Tools: `tools/bench*.py`; raw "
             "figures in `BENCHMARKS.json`.", "",
             "## Machine", "",
             "| CPU | cores | kernel | Python | " + " | ".join(bench_daemon.LIBRARIES) + " | commit |",
             "| --- | --- | --- | --- | " + " | ".join("---" for _ in bench_daemon.LIBRARIES) + " | --- |",
             f"| {info['cpu']} ({info['arch']}) | {info['cores']} | {info['kernel']} | {v['python']} | "
             + " | ".join(v.get(n, "?") for n in bench_daemon.LIBRARIES) + f" | {info['commit']} |", ""]
    caveat = bench_board.machine_caveat(info["cpu"])
    summary = summary_lines(results, f_judged_here=caveat is None)
    if summary and caveat:
        summary.append(caveat)
    if summary:
        lines += ["## Summary", "", *summary, ""]
    for name in BENCHMARKS:
        section = results.get(name)
        if not section:
            continue
        title, module = HEADINGS[name]
        lines += [f"## {title}", "", f"Measured {section['measured']}" + (" (quick run)" if section.get("quick")
                                                                           else "") + ".", ""]
        lines += _doc(module)
        lines += [*(module.render(section["runs"], section.get("board_runs", [])) if name == "daemon"
                    else module.render(section)), ""]
    kf = results.get("kfgins")
    if kf:
        import bench_kfgins  # here, not at the top: it takes its machine readings from this module

        lines += ["## Side by side with KF-GINS", "", *_doc(bench_kfgins),
                  *bench_kfgins.render(kf["drives"], kf["machine"]["repeat"], kf["machine"]["stat"]), "",
                  f"Measured {kf['machine']['load']['started']} on {kf['machine']['cpu']} ({kf['machine']['cores']} "
                  f"cores), commit {kf['machine']['commit']}: load average {kf['machine']['load']['loadavg_before']} "
                  f"-> {kf['machine']['load']['loadavg_after']}, machine busy "
                  f"{kf['machine']['load']['machine_busy_pct']:.0f} %, of which other jobs "
                  f"{kf['machine']['load']['others_pct_of_machine']:.0f} %. Recorded with `python tools/bench.py "
                  "--record-kfgins FILE` from `tools/bench_kfgins.py --json FILE`.", ""]
    lines += ["## On a BeagleBone-class board", "", *bench_board.render(results), ""]
    lines += ["## Load on this machine while measuring", "",
              "Other jobs shared the machine. *Busy* is the share of all cores in use while the step ran, *others* "
              "that share less this benchmark's own processes. *Host reference*: the CPU time of a fixed piece of "
              "Python and numpy work (`tools/bench.py` reference_ms) just before the step, with the kernel it ran "
              "on: figures of steps whose reference differs were measured on a faster or slower host (a virtual "
              "machine keeps its CPU's name on another one), by about that ratio.", "",
              "| step | started | wall | load average before -> after | machine busy | others | host reference |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for name in BENCHMARKS:
        for ld in (results.get(name) or {}).get("loads", []):
            when = ld.get("started") or f"in the section from {results[name]['measured']}"
            lines.append(f"| {ld['step']} | {when} | {ld['wall_s']} s "
                         f"| {ld['loadavg_before']} -> {ld['loadavg_after']} | {ld['machine_busy_pct']:.0f} % "
                         f"| {ld['others_pct_of_machine']:.0f} % | {host_reference(ld)} |")
    return "\n".join(lines) + "\n"


HOST_SPREAD = 1.15  # steps whose references differ by more ran on hosts (or host loads) that differ


def host_reference(load: dict[str, Any]) -> str:
    """A step's host reference for the load table: "12.3 ms (kernel)", or "-" for steps measured before it was."""
    if "reference_ms" not in load:
        return "-"
    return f"{load['reference_ms']:.1f} ms ({load.get('kernel', '?')})"


def alone(r: dict[str, Any]) -> str:
    """", the daemon alone about N MB" where the run measured the simulator's share, else nothing."""
    mb = bench_daemon.daemon_alone_mb(r)
    return "" if mb is None else f", the daemon alone about {mb:.0f} MB"


def summary_lines(results: dict[str, Any], f_judged_here: bool = True) -> list[str]:
    """The summary's lines; ``f_judged_here`` False: the board's factor F was judged for another core, and the
    verdict says so (the caveat line that :func:`report` adds tells which way that can go)."""
    out: list[str] = []
    daemon = [r for r in (results.get("daemon") or {}).get("runs", []) if not r["profile"]]
    default = next((r for r in daemon if r["imu_rate_hz"] == 20.0), None)
    if default:
        low, high = bench_board.board_range(default["daemon_pct"])
        out.append(f"- Daemon threads at the default rates: **{default['daemon_pct']:.2f} % of one core** here "
                   f"(the whole process with the simulator: {default['process_pct']:.2f} %); RSS "
                   f"{default['rss_end_mb']:.0f} MB{alone(default)}; on a BeagleBone-class core {low:.0f} to "
                   f"{high:.0f} %: "
                   f"{bench_board.verdict(low, high)}"
                   + ("" if f_judged_here else " by F as judged for another core (see the last line here)") + ".")
        for r in daemon:
            if r is not default:
                out.append(f"  - IMU at {r['imu_rate_hz']:g} Hz: {r['daemon_pct']:.2f} % here, RSS "
                           f"{r['rss_end_mb']:.0f} MB{alone(r)}.")
        index = [r["writer_index"] for r in daemon if r.get("writer_index")]
        if index:
            more = [x.get("beyond_window_mb", x["at_rotation_mb"]) for x in index]
            out.append(f"  - By the end of each file ({index[0]['rotate_s'] / 3600:g} h) the MCAP writer's index "
                       f"holds about {bench_daemon.mb_span(more)} more than these (freed as the file rotates).")
        for r in (results.get("daemon") or {}).get("board_runs", []):
            out.append(f"  - With Debian 12's libraries (numpy {bench_daemon.numpy_version(r)}), IMU at "
                       f"{r['imu_rate_hz']:g} Hz: {r['daemon_pct']:.2f} % here, RSS {r['rss_end_mb']:.0f} MB"
                       f"{alone(r)}.")
        emulated = [run["emulated"] for run in (results.get("emulated") or {}).get("runs", [])
                    if bench_board.guest_pages(run["emulated"])]
        if emulated:
            out.append("  - On the board's own architecture (Debian 12 armhf with its numpy, in the emulated root, "
                       f"{results['emulated'].get('measured', '?')}; the BeagleBone section): the daemon alone "
                       "about " + ", ".join(f"{bench_daemon.daemon_alone_mb(r):.0f} MB at {r['imu_rate_hz']:g} Hz"
                                            + ("" if r["sustained"] else ", a rate not sustained there")
                                            for r in emulated) + ".")
        ok = [r["imu_rate_hz"] for r in daemon if r["sustained"]]
        failed = [f"{r['imu_rate_hz']:g} Hz ({bench_daemon.why_not(r)})" for r in daemon if not r["sustained"]]
        out.append(f"- Highest IMU rate sustained over {default['window_s']:.0f} s without a late, missed, lost or "
                   f"dropped sample: **{max(ok):g} Hz**" if ok else
                   "- No IMU rate tried was sustained without a late, missed, lost or dropped sample")
        out[-1] += (f"; not sustained: {', '.join(failed)}." if failed else ".")
    rec = (results.get("recorder") or {}).get("streams", {}).get("drive mix")
    if rec:
        w = rec["writers"]
        out.append(f"- Recorder: {w['recorder']['msgs_per_s']:,.0f} records/s, {w['recorder']['mb_per_s']:.1f} MB/s "
                   f"of JSON; {w['recorder']['cpu_vs_bare']:.2f}x the bare mcap writer's CPU per record "
                   f"({w['recorder']['cpu_us_per_msg']:.1f} against {w['bare']['cpu_us_per_msg']:.1f} us).")
    nav = results.get("nav")
    if nav:
        r17 = next(r for r in nav["replays"] if r["mode"] == "17" and not r["smooth"])
        out.append(f"- Filter: {r17['cpu_us_per_sample']:.1f} us of CPU per IMU sample (17-state); `logger replay` "
                   f"runs at {nav['cli']['x_real_time_wall']:.0f}x real time.")
    sync = results.get("sync")
    if sync:
        err = sync["report"].get("stamp_error", {})
        parts = [f"{state} RMSE {err[k]['rmse_us']:.2f} us, largest {err[k]['max_us']:.2f} us"
                 for state in ("locked", "holdover") for k in [f"/imu {state}"] if k in err]
        if parts:
            out.append("- IMU stamp error against the truth: " + "; ".join(parts) + ".")
    start = results.get("startup")
    if start:
        s = bench_startup.summary(start)
        out.append(f"- Start-up: first IMU sample recorded {s['first_s']['/imu']:.2f} s after the process started "
                   f"(median of {len(start['runs'])}).")
    hosts = hosts_line(results)
    if hosts:
        out.append(hosts)
    return out


def hosts_line(results: dict[str, Any]) -> str:
    """A warning when the sections were not all measured on one host (their steps' kernels, or a reference more
    than HOST_SPREAD apart): their figures then differ by the host as well as by the code."""
    steps = [(name, ld) for name in BENCHMARKS for ld in (results.get(name) or {}).get("loads", [])]
    kernels = sorted({ld["kernel"] for _, ld in steps if "kernel" in ld})
    refs = [ld["reference_ms"] for _, ld in steps if "reference_ms" in ld]
    unknown = sorted({name for name, ld in steps if "reference_ms" not in ld})
    spread = max(refs) / min(refs) if refs else 1.0
    if len(kernels) <= 1 and spread <= HOST_SPREAD and not (unknown and refs):
        return ""
    parts = []
    if len(kernels) > 1:
        parts.append(f"kernels {', '.join(kernels)}")
    if refs:
        parts.append(f"host reference {min(refs):.1f} to {max(refs):.1f} ms")
    if unknown and refs:
        parts.append(f"{', '.join(unknown)} measured before the reference was taken")
    return ("- Not every section was measured on the same host (" + "; ".join(parts) + ": the load table at the "
            "end): compare figures within a section, or scaled by the reference.")


def board_interpreter(python: str, selected: list[str], ap: argparse.ArgumentParser) -> str:
    """--board-python resolved (the benchmark runs it from the repository's root) and checked before half an hour of
    measuring: it must run the daemon's modules."""
    if "daemon" not in selected:
        ap.error("--board-python runs the daemon benchmark again: give it with the daemon benchmark")
    path = shutil.which(python) if os.sep not in python else os.path.abspath(python)  # a venv's link kept
    if path is None or not os.access(path, os.X_OK):
        ap.error(f"--board-python: no interpreter {python!r}")
    probe = subprocess.run([path, "-c", "import numpy, mcap, ujson, logger.compose"], cwd=ROOT, capture_output=True,
                           text=True)
    if probe.returncode != 0:
        last = (probe.stderr.strip().splitlines() or ["(no message)"])[-1]
        ap.error(f"--board-python {path}: cannot run the daemon's modules: {last}")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("--quick", action="store_true", help="short runs (30 s per IMU rate): a smoke test, not figures")
    ap.add_argument("--only", help=f"comma-separated subset of: {','.join(BENCHMARKS)}")
    ap.add_argument("--out", type=Path, help="report file (default BENCHMARKS.md; --quick prints unless given)")
    ap.add_argument("--work", type=Path, help="keep the benchmarks' files and logs in this folder")
    ap.add_argument("--render-only", action="store_true",
                    help="write the report again from the saved figures (BENCHMARKS.json), measuring nothing")
    ap.add_argument("--daemon-nice", type=int, default=-10,
                    help="niceness of the daemon benchmark (default -10, as root): other jobs on a shared machine "
                    "then delay its sampler threads less, as nothing would on the board; CPU times are unaffected")
    ap.add_argument("--board-python", metavar="PYTHON",
                    help="an interpreter with Debian 12's library versions (.ci/floors.txt, as CI's .venv-floors "
                    "has them): the daemon benchmark runs again with it at 20 Hz and 1 kHz, for the memory the board's "
                    "libraries take")
    ap.add_argument("--record-kfgins", type=Path, metavar="FILE",
                    help="put tools/bench_kfgins.py's --json FILE into the saved figures and write the report again")
    args = ap.parse_args(argv)
    if args.record_kfgins is not None:
        raw_path = (args.out or ROOT / "BENCHMARKS.md").with_suffix(".json")
        if not args.record_kfgins.is_file() or not raw_path.is_file():
            ap.error(f"--record-kfgins: need {args.record_kfgins} and the saved figures {raw_path}")
        saved_all = json.loads(raw_path.read_text())
        saved_all["results"]["kfgins"] = json.loads(args.record_kfgins.read_text())
        raw_path.write_text(json.dumps(saved_all, indent=1))
        (args.out or ROOT / "BENCHMARKS.md").write_text(report(saved_all["results"], saved_all["machine"],
                                                                saved_all["command"]))
        print(f"[bench] added the KF-GINS figures to {raw_path} and wrote the report again")
        return 0
    selected = list(BENCHMARKS)
    if args.only:
        selected = [s.strip() for s in args.only.split(",") if s.strip()]
        unknown = [s for s in selected if s not in BENCHMARKS]
        if unknown or not selected:
            ap.error(f"--only: unknown benchmark {', '.join(unknown) or '(none)'}; choose from {', '.join(BENCHMARKS)}")
    if args.board_python is not None:
        args.board_python = board_interpreter(args.board_python, selected, ap)
    out = args.out or (None if args.quick else ROOT / "BENCHMARKS.md")
    command = "python tools/bench.py" + ("" if argv is None and len(sys.argv) == 1 else " " + " ".join(
        sys.argv[1:] if argv is None else argv))
    raw = out.with_suffix(".json") if out is not None else None
    saved: dict[str, Any] = {}
    if raw is not None and raw.exists() and (args.only or args.render_only):
        saved = json.loads(raw.read_text())
    if args.render_only:
        if not saved:
            ap.error(f"--render-only: no saved figures in {raw}")
        assert out is not None and raw is not None
        out.write_text(report(saved["results"], saved["machine"], saved["command"]))
        print(f"[bench] wrote {out} from {raw}")
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        fresh = run_all(selected, args.quick, work, args.daemon_nice, args.board_python)
    results: dict[str, Any] = dict(saved.get("results", {}))  # the sections not run now keep their figures
    results.update(fresh)
    info = machine()
    if raw is not None:  # the figures first: a report that fails to render loses no measurement (--render-only)
        raw.write_text(json.dumps({"machine": info, "command": command, "results": results}, indent=1))
    text = report(results, info, command)
    if out is None or raw is None:
        print(text)
        return 0
    out.write_text(text)
    print(f"[bench] wrote {out} and {raw}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
