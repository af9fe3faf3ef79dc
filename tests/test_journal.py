"""The journal's rate limiter, shared by the problem journal and the sensor threads' warnings."""

from __future__ import annotations

from logger.runtime.journal import RateLimiter, problem_key


def test_a_problem_is_the_same_problem_whatever_its_numbers() -> None:
    assert problem_key("no sample for 4.2 s") == problem_key("no sample for 17 s")
    assert problem_key("imu: no sample") != problem_key("baro: no sample")


def test_held_back_lines_are_counted_per_key() -> None:
    lim = RateLimiter(burst=1, refill_s=60.0)
    assert lim.allow("a", 0.0) == (True, 0)
    assert lim.allow("a", 1.0) == (False, 0)
    assert lim.allow("a", 2.0) == (False, 0)
    assert lim.allow("b", 3.0) == (True, 0)  # b's first line carries none of a's repeats
    assert lim.allow("a", 61.0) == (True, 2)  # a's next line says how many of a were held back
    assert lim.allow("b", 64.0) == (True, 0)


def test_burst_then_one_per_refill() -> None:
    lim = RateLimiter(burst=3, refill_s=10.0)
    assert [lim.allow("k", 0.0)[0] for _ in range(4)] == [True, True, True, False]
    assert lim.allow("k", 5.0)[0] is False  # half a token back
    assert lim.allow("k", 10.0) == (True, 2)  # a whole token back: the two refused lines are reported


def test_prune_forgets_refilled_buckets_first_then_all_but_the_kept() -> None:
    lim = RateLimiter(burst=1, refill_s=10.0, max_keys=2)
    lim.allow("old", 0.0)
    lim.allow("recent", 95.0)
    lim.allow("flapping", 99.0)
    lim.allow("flapping", 99.5)  # held back
    lim.prune(100.0)  # "old" has refilled (a line of it would go out anyway): only it is forgotten
    assert lim.allow("flapping", 100.0) == (False, 0)  # still limited: its bucket was kept
    assert lim.allow("old", 100.0) == (True, 0)
    lim.allow("third", 100.0)
    lim.prune(100.0, keep={"third"})  # nothing has refilled: everything but the kept goes
    assert lim.allow("third", 100.0) == (False, 0)
    assert lim.allow("flapping", 100.0) == (True, 0)  # forgotten, with its held-back count


def test_a_problem_that_lasts_is_never_said_to_be_resolved() -> None:
    """The review's disk-full spell: the recorder's line named a file that changed at every retry (boot name, then
    dated name) and its free space changed unit; the journal said "resolved" while the disk was still full. And a
    write failure followed by open failures with another cause is one problem changing its wording."""
    from logger.runtime.journal import ProblemJournal

    assert problem_key("recorder: disk full (984 KiB free, 256 MiB minimum)") == problem_key(
        "recorder: disk full (1.2 MiB free, 256 MiB minimum)")
    assert problem_key("cannot open drive_boot-3a79384f_0001.mcap: No space") == problem_key(
        "cannot open drive_20261206T051912Z_0002.mcap: No space")
    j = ProblemJournal()
    lines = j.update(["recorder: not recording: disk full (984 KiB free)", "imu: silent"], 0.0)
    assert [t for _, t in lines] == ["problem: recorder: not recording: disk full (984 KiB free)",
                                     "problem: imu: silent"]
    assert j.update(["recorder: not recording: disk full (2.1 MiB free)", "imu: silent"], 1.0) == []
    lines = j.update(["recorder: not recording: Read-only file system", "imu: silent"], 5.0)
    assert [t for _, t in lines] == ["changed: recorder: not recording: Read-only file system (was: recorder: not "
                                     "recording: disk full (2.1 MiB free); for 5 s)"]
    lines = j.update(["imu: silent"], 9.0)
    assert [t for _, t in lines] == ["resolved: recorder: not recording: Read-only file system (lasted 9 s)"]


def test_two_components_changing_their_problem_in_one_second_are_two_changes() -> None:
    """An I2C bus dropped (the IMU's and the barometer's problems turning into others in the same second): the
    second component's old key was looked up after the first's carry had popped it, and the KeyError ended the
    service thread that logs problems and answers the watchdog, while `logger status` said OK."""
    from logger.runtime.journal import ProblemJournal

    j = ProblemJournal()
    j.update(["imu: no sample for 2 s", "baro: no sample for 2 s"], 0.0)
    lines = j.update(["imu: stalled in a bus read", "baro: stalled in a bus read"], 1.0)
    assert sorted(t for _, t in lines) == [
        "changed: baro: stalled in a bus read (was: baro: no sample for 2 s; for 1 s)",
        "changed: imu: stalled in a bus read (was: imu: no sample for 2 s; for 1 s)"]
    assert [t for _, t in j.update([], 3.0)] == ["resolved: imu: stalled in a bus read (lasted 3 s)",
                                                  "resolved: baro: stalled in a bus read (lasted 3 s)"]
