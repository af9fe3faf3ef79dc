"""A short soak (a few minutes of drive at up to 60x, paced to the host): three daemons in turn on one folder,
ended by SIGTERM, kill -9 and their duration, with faults injected in between; nothing lost, everything recovered,
every fault seen."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Faults whose every occurrence changes what `logger status` shows (garbage on the receiver's line is skipped
# by the framer without a trace there, so the long soak reports it rather than this test asserting it).
FAULTS = "imu_unplugged,elm327_can_error,pps_outage,disk_nearly_full,gnss_restarted"


@pytest.mark.slow_on_board
def test_short_soak(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "soak.py"), "--hours", "0.15", "--time-scale", "60",
                        "--mean-fault-gap-s", "20", "--faults", FAULTS, "--seed", "3", "--sample-real-s", "0.5",
                        "--out", str(out)],
                       capture_output=True, text=True, timeout=900, cwd=ROOT)
    report = json.loads((out / "soak-report.json").read_text())
    assert r.returncode == 0, r.stdout + r.stderr
    assert [s["ended_by"] for s in report["segments"]] == ["sigterm", "kill9", "duration"]
    for seg in report["segments"]:
        assert seg["threads_missing_at_end"] == [] and seg["stale_threads_seen"] == []
        assert seg["records_lost_outside_faults"] == {} and seg["gaps_outside_faults_uncounted"] == {}
        if seg["ended_by"] != "kill9":  # counters read after the samplers ended: every gap, the stop's too, judged
            assert seg["gaps_after_the_last_counters"] == {}, seg
        assert all(n > 0 for n in seg["records"].values()), seg["records"]
        assert seg["stopped_cleanly"] in (True, None)
    assert report["segments"][2]["recovered_lines"], "the file cut by kill -9 was not recovered at the next start"
    assert report["files"]["unfinished"] == [] and report["kill9_files_recovered"]
    whole = [f for f in report["faults"] if not f["cut_short_by_the_stop"]]
    assert whole, "no fault was injected"
    for fault in whole:
        assert fault["status"] and fault["log"], fault
    # 0.15 h of drive never reaches the memory figure's warm-up: said, not passed over.
    assert not report["rss_measured"] and "verdict: OK (memory not judged)" in r.stdout, r.stdout

    # The verdict counts what it measured (it said OK, exit 0, over both of these): the SIGTERM'd worker made to
    # have exited 1, then (exit restored) the first journalled fault made to have shown nowhere.
    def analysed() -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, str(ROOT / "tools" / "soak.py"), "--analyse", str(out)],
                              capture_output=True, text=True, timeout=300, cwd=ROOT)

    segments_file = out / "segments.json"
    segments = json.loads(segments_file.read_text())
    segments["segments"][0]["exit_code"] = 1
    segments_file.write_text(json.dumps(segments))
    again = analysed()
    assert again.returncode == 1 and "verdict: NOT OK" in again.stdout, again.stdout + again.stderr
    segments["segments"][0]["exit_code"] = 0
    segments_file.write_text(json.dumps(segments))
    assert analysed().returncode == 0
    journal = out / "journal-0.jsonl"
    events = [json.loads(line) for line in journal.read_text().splitlines()]
    fault = next(e for e in events if e["ev"] == "fault")
    fault.update(seen_in_status=None, seen_after_s=None, status_excerpt="")
    journal.write_text("".join(json.dumps(e) + "\n" for e in events))
    log = out / "log-0.txt"
    log.write_text("\n".join(line for line in log.read_text().splitlines()
                             if not fault["start_host_ns"] <= int(line.split(" ", 1)[0]) <= fault["end_host_ns"] + 3e9))
    again = analysed()
    assert again.returncode == 1 and "verdict: NOT OK" in again.stdout, again.stdout + again.stderr


def test_a_fault_the_stop_cut_before_it_was_journalled_still_explains_its_losses() -> None:
    """A disk-nearly-full fault still on when SIGTERM came: the daemon's stop ended the process before the
    injector journalled the window (one CI run of the short soak: 86 s of every topic 'lost outside faults').
    Its start was journalled: the fault lasts to the segment's last word, cut short by the stop, and the records
    the recorder did not write meanwhile fall inside it."""
    sys.path.insert(0, str(ROOT / "tools"))
    import soak

    ns = 1_000_000_000
    events = [{"ev": "start", "drive_ns": 0, "host_ns": 0},
              {"ev": "fault", "kind": "elm327_can_error", "start_ns": 10 * ns, "end_ns": 40 * ns,
               "start_host_ns": 1, "end_host_ns": 2, "seen_in_status": "obd: ...", "seen_after_s": 1.0,
               "cut_short": False, "status_excerpt": ""},
              {"ev": "fault_start", "kind": "elm327_can_error", "start_ns": 10 * ns, "start_host_ns": 1},
              {"ev": "fault_start", "kind": "disk_nearly_full", "start_ns": 220 * ns, "start_host_ns": 3 * ns},
              {"ev": "sample", "drive_ns": 300 * ns, "host_ns": 5 * ns}]
    faults = soak.faults_of(events)
    assert [(f["kind"], f["start_ns"] // ns, f["end_ns"] // ns, f["cut_short"]) for f in faults] == [
        ("elm327_can_error", 10, 40, False), ("disk_nearly_full", 220, 300, True)]
    disk = [w for w in soak.windows_for(faults, "/imu") if w[2] == "disk_nearly_full"]
    assert soak.explained(disk, 221 * ns, 299 * ns) == "disk_nearly_full"
    assert soak.explained(soak.windows_for([e for e in events if e["ev"] == "fault"], "/imu"), 221 * ns,
                          299 * ns) is None  # journalled faults only: the losses were outside every window
