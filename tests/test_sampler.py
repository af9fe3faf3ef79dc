"""Sampler scheduling and recovery, in virtual time so nothing depends on the machine's load.

The source here is a scripted stand-in for a driver adapter: these tests are about the thread's deadlines and
back-off, which no device model can make deterministic. Drivers are tested against device models elsewhere.
"""

from __future__ import annotations

import itertools
import threading

import pytest

from logger.runtime.sampler import Reading, Sampler, Source, wait_until
from logger.runtime.timebase import TimeBase
from sensors.errors import BusError, DeviceNotFound
from sensors.sim.clock import ManualClock


class VirtualTime(TimeBase):
    """Waiting advances a manual clock at once: the thread runs as fast as it can in drive time."""

    def __init__(self) -> None:
        self.clock = ManualClock(start_ns=1_000_000_000)
        super().__init__(self.clock.now_ns, 1.0)

    def wait(self, event: threading.Event, seconds: float) -> bool:
        if seconds > 0:
            self.clock.advance(seconds)
        return event.is_set()

    def sleep(self, seconds: float) -> None:
        self.clock.advance(max(0.0, seconds))


class Scripted(Source):
    name = "imu"

    def __init__(self, tb: VirtualTime, work_s: list[float] | None = None, fail_at: set[int] | None = None,
                 absent_opens: int = 0, limit: int = 100) -> None:
        self.tb, self.work_s, self.fail_at = tb, work_s or [], fail_at or set()
        self.absent_opens, self.limit = absent_opens, limit
        self.n = 0
        self.opens = 0
        self.done = threading.Event()

    def open(self) -> None:
        self.opens += 1
        if self.opens <= self.absent_opens:
            raise DeviceNotFound("/dev/i2c-2: no such device")

    def read(self) -> list[Reading]:
        i = self.n
        self.n += 1
        if i >= self.limit:
            self.done.set()
            return []
        t = self.tb.monotonic_ns()
        if i in self.fail_at:
            raise BusError("I2C transfer failed (EIO)")
        if i < len(self.work_s):
            self.tb.clock.advance(self.work_s[i])
        return [Reading("/imu", {"i": i}, t)]

    def close(self) -> None:
        pass


def _run(src: Scripted, rate: float) -> tuple[Sampler, list[Reading]]:
    out: list[Reading] = []
    stop = threading.Event()
    s = Sampler(src, out.append, src.tb, rate, stop)
    s.start()
    assert wait_until(src.done.is_set, 10)
    stop.set()
    s.join(5)
    assert not s.is_alive()
    return s, out


def test_deadlines_do_not_drift() -> None:
    tb = VirtualTime()
    # Each read takes 30 % of the period: sleeping a full period after it would drift by 30 %.
    src = Scripted(tb, work_s=[0.015] * 100, limit=100)
    s, out = _run(src, 20.0)
    t = [r.t_mono_ns for r in out]
    assert len(t) == 100
    assert all(b - a == 50_000_000 for a, b in itertools.pairwise(t))
    assert s.health.late == 0 and s.health.missed == 0 and s.health.gaps == 0


def test_a_slow_sample_is_counted_late_and_missed_periods_are_counted() -> None:
    tb = VirtualTime()
    work = [0.0] * 100
    work[10] = 0.175  # ends 3.5 periods later: three deadlines passed unsampled
    src = Scripted(tb, work_s=work, limit=50)
    s, out = _run(src, 20.0)
    assert s.health.late == 1
    assert s.health.missed == 3
    t = [r.t_mono_ns for r in out]
    # After the slow one the sampler is back on the original grid, not shifted.
    assert (t[11] - t[0]) % 50_000_000 == 0 and t[11] - t[10] == 200_000_000
    assert s.health.gaps == 1


def test_failure_backs_off_reconnects_and_counts(caplog: pytest.LogCaptureFixture) -> None:
    tb = VirtualTime()
    src = Scripted(tb, fail_at={5}, absent_opens=2, limit=30)
    s, out = _run(src, 20.0)
    h = s.health
    assert h.errors == 3  # two opens while absent, one bus error
    assert h.reconnects == 1  # the first successful open is not a reconnect
    assert h.state == "stopped"
    # Recovered: the error is no present one (the status would show it as stale), the log keeps what it was.
    assert h.last_error == ""
    assert "imu: back after: I2C transfer failed (EIO)" in caplog.text
    assert len(out) == 29  # every read but the failed one delivered


@pytest.mark.parametrize(("fail_at", "reopened_within_s"), [(5, None), (200, 0.0)])
def test_a_device_that_worked_for_a_while_is_opened_again_at_once_the_first_time(fail_at: int,
                                                                                 reopened_within_s: float | None
                                                                                 ) -> None:
    """One bus error on a device that delivered for QUICK_RETRY_AFTER_S (10 s at 20 Hz here) reopens it at once:
    one NACK cost the IMU the back-off's half second of samples as well. A device failing sooner backs off."""
    tb = VirtualTime()
    src = Scripted(tb, fail_at={fail_at}, limit=fail_at + 10)
    _, out = _run(src, 20.0)
    t = {r.payload["i"]: r.t_mono_ns for r in out}
    waited_s = (t[fail_at + 1] - t[fail_at - 1]) / 1e9 - 2 * 0.05  # beyond the two periods the failed read spans
    if reopened_within_s is None:
        assert waited_s >= Sampler.BACKOFF_START_S - 0.05
    else:
        assert waited_s <= reopened_within_s + 1e-9


class OpensButNeverDelivers(Scripted):
    """An ELM327 with the ignition off (its set-up succeeds, every request fails), a CAN interface on a bus that is
    off: each open succeeds, each read fails."""

    def read(self) -> list[Reading]:
        self.n += 1
        if self.opens >= 6:
            self.done.set()
        raise BusError("ELM327 unable to connect to the vehicle: ignition off or protocol not supported")


def test_a_device_that_opens_but_never_delivers_is_not_back_and_backs_off_further(
        caplog: pytest.LogCaptureFixture) -> None:
    """Each successful open counted a reconnection, logged "back after", set the state ok and started the back-off
    over: 7 reconnections in 20 s of a parked car, the adapter reset and searching every few seconds all day."""
    tb = VirtualTime()
    src = OpensButNeverDelivers(tb)
    opened_at: list[int] = []
    open_ = src.open
    src.open = lambda: (opened_at.append(tb.monotonic_ns()), open_())[1]  # type: ignore[method-assign]
    s, out = _run(src, 2.0)
    assert out == [] and s.health.reconnects == 0
    assert "back after" not in caplog.text
    waits = [(b - a) / 1e9 for a, b in itertools.pairwise(opened_at)]
    assert waits == sorted(waits) and waits[-1] >= 4 * waits[0], waits


class QuietAfterReopening(Scripted):
    """A PPS line: pulses, one read error, then opened again with the receiver without a fix: no pulses."""

    def read(self) -> list[Reading]:
        if self.opens == 1:
            return super().read()
        self.n += 1
        if self.n >= 60:
            self.done.set()
        return []


def test_a_device_opened_again_that_is_quiet_shows_no_old_error() -> None:
    """Opened again, it is not back until it delivers (no reconnection counted), but the error it was opened again
    after is past: a PPS line without a fix kept showing its read error as present for as long as it was quiet."""
    tb = VirtualTime()
    src = QuietAfterReopening(tb, fail_at={5}, limit=1000)
    s, out = _run(src, 20.0)
    assert len(out) == 5 and s.health.reconnects == 0
    assert s.health.last_error == ""


class Silent(Scripted):
    """Answers NO DATA for a while, like an ELM327 with the engine off."""

    def __init__(self, tb: VirtualTime, quiet: range, limit: int) -> None:
        super().__init__(tb, limit=limit)
        self.quiet = quiet

    def read(self) -> list[Reading]:
        if self.n in self.quiet:
            self.n += 1
            from sensors.errors import NoData

            raise NoData("NO DATA (engine off?)")
        return super().read()


def test_no_data_keeps_the_device_open_and_the_schedule() -> None:
    tb = VirtualTime()
    src = Silent(tb, quiet=range(5, 15), limit=40)
    s, out = _run(src, 2.0)
    assert src.opens == 1  # no reset and protocol search for an engine that is off
    assert s.health.errors == 10 and s.health.reconnects == 0
    assert len(out) == 30 and s.health.gaps == 1
    t = [r.t_mono_ns for r in out]
    assert all((b - t[0]) % 500_000_000 == 0 for b in t)  # still on the 2 Hz grid


class Resetting(Scripted):
    """An adapter that resets itself now and then and is set up again inside the read: every read succeeds."""

    def __init__(self, tb: VirtualTime, resets_at: dict[int, int], **kw: object) -> None:
        super().__init__(tb, **kw)  # type: ignore[arg-type]
        self.resets_at = resets_at
        self.resets = 0

    def open(self) -> None:
        super().open()
        self.resets = 2  # counted while the device was being opened: start-up, not a fault

    def read(self) -> list[Reading]:
        self.resets += self.resets_at.get(self.n, 0)
        return super().read()

    def incidents(self) -> dict[str, int]:
        return {"adapter resets": self.resets}


def test_incidents_inside_successful_reads_are_counted_and_shown_while_fresh() -> None:
    tb = VirtualTime()
    src = Resetting(tb, resets_at={10: 1, 30: 2}, fail_at={20}, limit=50)
    s, _ = _run(src, 2.0)
    h = s.health
    # 1 at read 10, 2 at read 30; the counts present at each (re)open are not faults.
    assert h.incidents == {"adapter resets": 3}
    assert h.last_incident == "adapter resets: 2 more (3 since start)"
    assert h.recent_incident(h.last_incident_mono_ns) == h.last_incident
    later = h.last_incident_mono_ns + int(31e9)
    assert h.recent_incident(later) is None
    assert h.snapshot(later)["incidents"] == {"adapter resets": 3}


class BrokenOpen(Scripted):
    """A driver whose open fails with something other than a SensorError (a library's own exception)."""

    def open(self) -> None:
        super().open()
        if self.opens <= 2:
            raise ValueError("unexpected reply 0xFF")


def test_an_unexpected_error_while_opening_is_retried_not_fatal(caplog: pytest.LogCaptureFixture) -> None:
    tb = VirtualTime()
    src = BrokenOpen(tb, limit=5)
    s, out = _run(src, 2.0)
    assert src.opens == 3 and len(out) == 5
    assert s.health.errors == 2 and "imu: cannot open: ValueError: unexpected reply 0xFF" in caplog.text
    assert s.health.last_error == ""  # opened in the end: no present error


def test_a_sample_finished_over_half_a_period_late_is_counted_delayed_not_late() -> None:
    tb = VirtualTime()
    work = [0.0] * 100
    work[10] = 0.030  # 30 ms of a 50 ms period: the next deadline still ahead, but the stamps' spacing is off
    work[20] = 0.020  # 20 ms: ordinary jitter
    src = Scripted(tb, work_s=work, limit=50)
    s, _ = _run(src, 20.0)
    assert s.health.delayed == 1 and s.health.late == 0 and s.health.missed == 0


def test_the_measured_rate_counts_the_window_s_samples_only() -> None:
    """The rate over the last 10 s of the kept times (found by bisection): samples before the window do not count,
    a window without samples reads 0, one with one sample has no rate (None: "-" in the status, not 0.0), and a
    sensor slower than a sample in 3.3 s is measured over three of its intervals."""
    from logger.runtime.sampler import SensorHealth

    h = SensorHealth("imu", 1000.0)
    ns = 1_000_000_000
    h._recent.extend(range(0, 30 * ns, 4 * ns))  # 0.25 Hz for 30 s: only its last three within the window
    h._recent.extend(range(30 * ns, 31 * ns, ns // 100))  # then 100 Hz for a second
    now = 31 * ns
    kept = [t for t in h._recent if t >= now - 10 * ns]
    assert h.measured_rate_hz(now) == pytest.approx((len(kept) - 1) / ((kept[-1] - kept[0]) / 1e9))
    assert h.measured_rate_hz(now, window_s=1.0) == pytest.approx(100.0)
    assert h.measured_rate_hz(100 * ns) == 0.0  # nothing in the last 10 s
    assert SensorHealth("baro", 1.0).measured_rate_hz(now) == 0.0
    one = SensorHealth("baro", 1.0)
    one._recent.append(now - ns)  # the first sample after an open
    assert one.measured_rate_hz(now) is None and one.snapshot(now)["measured_rate_hz"] is None
    slow = SensorHealth("baro", 0.1)  # the configuration allows a barometer every 10 s
    slow._recent.extend([now - 25 * ns, now - 15 * ns, now - 5 * ns])
    assert slow.measured_rate_hz(now) == pytest.approx(0.1)
