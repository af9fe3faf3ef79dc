"""PPS driver against the PPS line model, through the real gpiod Python layer with only gpiod._ext replaced."""

from __future__ import annotations

import errno
import threading
from collections.abc import Iterator
from datetime import timedelta

import gpiod
import numpy as np
import pytest
from gpiod.line import Clock, Direction, Edge, Value

from sensors.errors import BusError, DeviceNotFound
from sensors.pps import PpsEdge, PpsLine
from sensors.sim import gpiod_ext
from sensors.sim.clock import ManualClock
from sensors.sim.gpiod_ext import LineEdge, SimGpioChip, sim_gpiochips
from sensors.sim.oscillator import Oscillator, OscillatorClock
from sensors.sim.pps import PpsSignal, pps_chip

CHIP = "/dev/gpiochip-sim"
LINE = 28
NS = 1_000_000_000


def always(_t: float) -> bool:
    return True


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def osc() -> Oscillator:
    return Oscillator(duration_s=4000.0, seed=11)


def make_signal(osc: Oscillator, has_fix=always, **kw) -> PpsSignal:
    return PpsSignal(osc, has_fix, seed=5, gnss_ns_at_start=1_234_567_890_250_000_000, **kw)


@pytest.fixture
def signal(osc: Oscillator) -> PpsSignal:
    return make_signal(osc)


@pytest.fixture
def sim(signal: PpsSignal, clock: ManualClock) -> Iterator[SimGpioChip]:
    chip = pps_chip(signal, clock, path=CHIP, offset=LINE)
    with sim_gpiochips(chip):
        yield chip


def step(clock: ManualClock, line: PpsLine, seconds: float) -> list[PpsEdge]:
    clock.advance(seconds)
    return line.wait(0.0)


def expected_stamp(signal: PpsSignal, k: int) -> int:
    return signal.oscillator.board_ns(signal.pulse_true_ns(k) + signal.latency_ns(k))


# -- the real gpiod layer is in the path --------------------------------------------------------------------
def test_real_gpiod_layer_delivers_edge_events_from_the_model(sim, clock, signal):
    assert gpiod.chip._ext is gpiod_ext.routing_ext
    assert gpiod.Chip.__module__ == "gpiod.chip" and gpiod.LineRequest.__module__ == "gpiod.line_request"
    settings = gpiod.LineSettings(direction=Direction.INPUT, edge_detection=Edge.RISING,
                                  event_clock=Clock.MONOTONIC)
    with gpiod.request_lines(CHIP, consumer="test", config={"P9_12": settings}) as req:
        assert req.offsets == [LINE] and req.chip_name == "gpiochip1"
        assert not req.wait_edge_events(timedelta(0))
        clock.advance(3.0)
        assert req.wait_edge_events(0.0)
        events = req.read_edge_events()
        assert all(type(ev) is gpiod.EdgeEvent for ev in events)
        assert [ev.event_type for ev in events] == [gpiod.EdgeEvent.Type.RISING_EDGE] * 3
        assert [ev.line_seqno for ev in events] == [1, 2, 3] == [ev.global_seqno for ev in events]
        assert {ev.line_offset for ev in events} == {LINE}
        k0 = signal.first_pulse
        assert [ev.timestamp_ns for ev in events] == [expected_stamp(signal, k0 + i) for i in range(3)]
        assert not req.wait_edge_events(0.0)
        with gpiod.Chip(CHIP) as chip:
            info = chip.get_line_info("P9_12")
            assert info.used and info.consumer == "test" and info.edge_detection is Edge.RISING
            assert chip.get_info().num_lines == 32


def test_edges_every_second_with_consecutive_seqnos(sim, clock, signal):
    with PpsLine(CHIP, LINE) as line:
        edges = [e for _ in range(120) for e in step(clock, line, 1.0)]
    assert len(edges) == 120
    assert [e.line_seqno for e in edges] == list(range(1, 121))
    assert all(e.lost == 0 for e in edges)
    k0 = signal.first_pulse
    assert [e.timestamp_ns for e in edges] == [expected_stamp(signal, k0 + i) for i in range(120)]
    # The board second is 1 s * (1 + 30 ppm): the intervals carry the crystal's offset under the jitter.
    intervals = np.diff([e.timestamp_ns for e in edges]) - NS
    assert abs(float(np.mean(intervals)) - signal.oscillator.ppm(60.0) * 1e3) < 1000.0


def test_pulses_sit_on_gnss_seconds(signal):
    k = signal.first_pulse
    assert signal.pulse_true_ns(k) == 750_000_000  # GNSS time at start is ...x.25 s
    assert signal.pulse_gnss_ns(k) % NS == 0
    assert signal.pulse_index(signal.pulse_true_ns(k + 7)) == k + 7


def test_interrupt_latency_statistics(osc, clock):
    signal = make_signal(osc)
    chip = pps_chip(signal, clock, path=CHIP, offset=LINE)
    with sim_gpiochips(chip), PpsLine(CHIP, LINE, event_buffer_size=128) as line:
        edges = [e for _ in range(60) for e in step(clock, line, 60.0)]
    assert len(edges) == 3600 and all(e.lost == 0 for e in edges)
    k0 = signal.first_pulse
    board_top = np.array([osc.board_ns(signal.pulse_true_ns(k0 + i)) for i in range(len(edges))])
    latency_us = (np.array([e.timestamp_ns for e in edges]) - board_top) / 1e3
    assert latency_us.min() > 0.0
    assert abs(latency_us.mean() - 7.0) < 0.2
    assert abs(latency_us.std() - 2.0) < 0.2
    assert np.mean(latency_us > 7.0 + 2 * 2.0) > np.mean(latency_us < 7.0 - 2 * 2.0)  # a late tail


def test_slow_reader_sees_lost_edges_as_seqno_gaps(sim, clock):
    with PpsLine(CHIP, LINE, event_buffer_size=10) as line:  # the kernel rounds the FIFO up to 16
        first = step(clock, line, 1.0)
        assert [(e.line_seqno, e.lost) for e in first] == [(1, 0)]
        late = step(clock, line, 20.0)
        assert [e.line_seqno for e in late] == list(range(6, 22))
        assert [e.lost for e in late] == [4] + [0] * 15
        assert [(e.line_seqno, e.lost) for e in step(clock, line, 1.0)] == [(22, 0)]
        assert line.lost_total == 4 and line.edges_total == 18


def test_no_edges_while_the_receiver_has_no_fix(osc, clock):
    signal = make_signal(osc, has_fix=lambda t: not 100.0 <= t < 160.0)
    chip = pps_chip(signal, clock, path=CHIP, offset=LINE)
    with sim_gpiochips(chip), PpsLine(CHIP, LINE) as line:
        edges = [(clock.now_ns(), e) for _ in range(200) for e in step(clock, line, 1.0)]
    true_tops = [signal.pulse_true_ns(signal.pulse_index(now)) for now, _ in edges]
    assert not [t for t in true_tops if 100 * NS <= t < 160 * NS]
    assert len(edges) == 200 - 60
    seq = [e.line_seqno for _, e in edges]
    assert seq == list(range(1, len(edges) + 1))  # the kernel saw no edge, so there is no gap
    gaps = np.diff([e.timestamp_ns for _, e in edges])
    assert int(np.sum(gaps > 1.5 * NS)) == 1 and 60.9 * NS < gaps.max() < 61.1 * NS


def test_missed_double_and_spurious_edges(sim, clock, signal):
    k0 = signal.first_pulse
    signal.inject_missed(k0 + 3)
    signal.inject_double(k0 + 6)
    signal.inject_spurious(signal.pulse_true_ns(k0 + 8) + 400_000_000)
    with PpsLine(CHIP, LINE) as line:
        edges = step(clock, line, 10.0)
    stamps = np.array([e.timestamp_ns for e in edges])
    assert [e.line_seqno for e in edges] == list(range(1, len(edges) + 1))
    assert all(e.lost == 0 for e in edges)
    assert len(edges) == 10 - 1 + 1 + 1
    gaps = np.diff(stamps) / 1e9
    assert sum(1.9 < g < 2.1 for g in gaps) == 1  # the missed second
    assert sum(0.002 < g < 0.003 for g in gaps) == 1  # the glitch 2.5 ms after the true edge
    assert sum(0.35 < g < 0.45 for g in gaps) == 1  # the spurious edge


def test_random_faults_are_seeded(osc, clock):
    a = make_signal(osc, missed_probability=0.05, double_probability=0.05)
    b = make_signal(osc, missed_probability=0.05, double_probability=0.05)
    ea, eb = a.edges_between(0, 400 * NS), b.edges_between(0, 400 * NS)
    assert ea == eb
    gaps = np.diff([e.true_ns for e in ea if e.rising]) / NS
    missed, doubled = int(np.sum(gaps > 1.5)), int(np.sum(gaps < 0.01))
    assert 8 <= missed <= 35 and 8 <= doubled <= 35  # 5 % of 400 pulses each
    # Asking in pieces gives the same edges as asking at once.
    pieces = [e for i in range(0, 400, 7) for e in a.edges_between(i * NS, min(i + 7, 400) * NS)]
    assert pieces == ea


def test_receiver_pulse_offset_moves_the_edges(osc, clock):
    plain = make_signal(osc)
    sawtooth = make_signal(osc, pulse_offset_ns=lambda second: float(second % 7) - 3.0)
    k0 = plain.first_pulse
    a = [e for e in plain.edges_between(0, 10 * NS) if e.rising]
    b = [e for e in sawtooth.edges_between(0, 10 * NS) if e.rising]
    seconds = [sawtooth.pulse_gnss_ns(k0 + i) // NS for i in range(10)]
    assert [y.true_ns - x.true_ns for x, y in zip(a, b, strict=True)] == [s % 7 - 3 for s in seconds]


def test_falling_edge_configuration(sim, clock, signal):
    with PpsLine(CHIP, LINE, edge="falling") as line:
        edges = step(clock, line, 5.0)
    k0 = signal.first_pulse
    falls = [signal.oscillator.board_ns(signal.pulse_true_ns(k0 + i) + signal.pulse_width_ns) for i in range(5)]
    assert len(edges) == 5
    assert all(0 < e.timestamp_ns - f < 30_000 for e, f in zip(edges, falls, strict=True))


# -- errors a field engineer sees -------------------------------------------------------------------------
def test_missing_chip_is_device_not_found_with_and_without_sim():
    with pytest.raises(DeviceNotFound, match=r"/dev/gpiochip-missing.*line 17"):
        PpsLine("/dev/gpiochip-missing", 17).open()
    with sim_gpiochips(), pytest.raises(DeviceNotFound, match="/dev/gpiochip-missing"):
        PpsLine("/dev/gpiochip-missing", 17).open()


def test_not_a_chip_is_device_not_found(tmp_path):
    path = tmp_path / "plain-file"
    path.write_text("")
    with pytest.raises(DeviceNotFound, match="not a GPIO chip"):
        PpsLine(str(path), 3).open()


def test_unknown_line_and_offset_out_of_range(sim):
    with pytest.raises(DeviceNotFound, match="no line named 'GNSS_PPS'"):
        PpsLine(CHIP, "GNSS_PPS").open()
    with pytest.raises(DeviceNotFound, match=r"has no line 40 \(it has 32 lines\)"):
        PpsLine(CHIP, 40).open()
    with PpsLine(CHIP, "P9_12") as line:
        assert line.is_open


def test_busy_line_is_bus_error_naming_chip_and_line(sim):
    with PpsLine(CHIP, LINE) as first:
        with pytest.raises(BusError, match=rf"line {LINE} of {CHIP} is busy"):
            PpsLine(CHIP, LINE).open()
        assert first.is_open
    with PpsLine(CHIP, LINE):  # released again
        pass


def test_permission_denied_is_bus_error(signal, clock):
    chip = pps_chip(signal, clock, path=CHIP)
    chip.accessible = False
    with sim_gpiochips(chip), pytest.raises(BusError, match="permission denied opening /dev/gpiochip-sim"):
        PpsLine(CHIP, LINE).open()


def test_vanished_chip_gives_bus_error_then_reopens(sim, clock):
    line = PpsLine(CHIP, LINE)
    line.open()
    kept = step(clock, line, 3.0)
    sim.vanish()
    clock.advance(2.0)
    with pytest.raises(BusError, match="reading line 28 of /dev/gpiochip-sim failed"):
        line.wait(0.0)
    assert not line.is_open and [e.line_seqno for e in kept] == [1, 2, 3]
    with pytest.raises(DeviceNotFound):
        line.open()
    sim.reappear()
    line.open()
    assert [(e.line_seqno, e.lost) for e in step(clock, line, 1.0)] == [(1, 0)]
    line.close()


def test_wait_on_closed_line_is_bus_error():
    with pytest.raises(BusError, match="not open"):
        PpsLine(CHIP, LINE).wait(0.0)


def test_bad_configuration_is_value_error():
    with pytest.raises(ValueError, match="edge"):
        PpsLine(CHIP, LINE, edge="both")
    with pytest.raises(ValueError, match="bias"):
        PpsLine(CHIP, LINE, bias="strong")


# -- the fake extension behaves like the kernel ---------------------------------------------------------------
def test_realtime_clock_active_low_and_values(sim, clock, signal):
    settings = gpiod.LineSettings(direction=Direction.INPUT, edge_detection=Edge.RISING,
                                  event_clock=Clock.REALTIME, active_low=True)
    with gpiod.request_lines(CHIP, config={LINE: settings}) as req:
        clock.advance(2.0)
        events = req.read_edge_events()
        k0 = signal.first_pulse
        fall = signal.oscillator.board_ns(signal.pulse_true_ns(k0) + signal.pulse_width_ns)
        # Active low: the physical falling edge is the logical rising one; realtime = monotonic + offset.
        assert 0 < events[0].timestamp_ns - sim.realtime_offset_ns - fall < 30_000
        clock.advance((signal.pulse_true_ns(k0 + 2) + 50_000_000 - clock.now_ns()) / NS)  # inside a pulse
        assert req.get_value(LINE) is Value.INACTIVE
        clock.advance(0.2)
        assert req.get_value(LINE) is Value.ACTIVE


def test_hte_clock_and_edges_on_outputs_are_refused(sim):
    with pytest.raises(OSError) as exc:
        gpiod.request_lines(CHIP, config={LINE: gpiod.LineSettings(direction=Direction.INPUT,
                                                                      edge_detection=Edge.RISING,
                                                                      event_clock=Clock.HTE)})
    assert exc.value.errno == errno.EOPNOTSUPP
    with pytest.raises(OSError) as exc:
        gpiod.request_lines(CHIP, config={LINE: gpiod.LineSettings(direction=Direction.OUTPUT,
                                                                      edge_detection=Edge.RISING)})
    assert exc.value.errno == errno.EINVAL


def test_software_debounce_swallows_a_glitch(sim, clock, signal):
    k0 = signal.first_pulse
    signal.inject_double(k0 + 1)
    settings = gpiod.LineSettings(direction=Direction.INPUT, edge_detection=Edge.RISING,
                                  debounce_period=timedelta(milliseconds=5))
    with gpiod.request_lines(CHIP, config={LINE: settings}) as req:
        clock.advance(4.0)
        events = req.read_edge_events()
    assert len(events) == 4  # the 0.5 ms dip 2 ms after pulse k0+1 is shorter than the debounce period
    top = signal.oscillator.board_ns(signal.pulse_true_ns(k0))
    assert 5_000_000 < events[0].timestamp_ns - top < 5_030_000  # reported when the level has held 5 ms


def test_line_info_watch_events(sim, clock):
    with gpiod.Chip(CHIP) as chip:
        assert not chip.watch_line_info(LINE).used
        with PpsLine(CHIP, LINE, consumer="ppsd"):
            assert chip.wait_info_event(0.0)
            ev = chip.read_info_event()
            assert ev.event_type is gpiod.InfoEvent.Type.LINE_REQUESTED and ev.line_info.consumer == "ppsd"
        ev = chip.read_info_event()
        assert ev.event_type is gpiod.InfoEvent.Type.LINE_RELEASED and not ev.line_info.used
        assert not chip.wait_info_event(0.0)


def test_patching_is_reversible_nested_and_thread_safe(signal, clock):
    real = gpiod.chip._ext
    assert real is not gpiod_ext.routing_ext
    chip = pps_chip(signal, clock, path=CHIP)

    def churn() -> None:
        for _ in range(200):
            with sim_gpiochips():
                assert gpiod.chip._ext is gpiod_ext.routing_ext

    with sim_gpiochips(chip):
        threads = [threading.Thread(target=churn) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert gpiod.line_settings._ext is gpiod_ext.routing_ext  # still installed by the outer block
        assert gpiod.is_gpiochip_device(CHIP) and not gpiod.is_gpiochip_device("/dev/null")
    for mod in (gpiod, gpiod.chip, gpiod.line_request, gpiod.line_settings):
        assert mod._ext is real
    with pytest.raises(DeviceNotFound):
        PpsLine(CHIP, LINE).open()  # the simulated path is gone with the block


def test_paced_chip_wakes_a_blocked_reader_on_the_board_clock():
    host = [0]
    osc = Oscillator(duration_s=100.0, seed=3, board_start_ns=0)
    # A host clock that moves only when slept on: the pacer's sleeps drive the simulated time.
    lock = threading.Lock()

    def host_ns() -> int:
        with lock:
            return host[0]

    def host_sleep(s: float) -> None:
        with lock:
            host[0] += max(1, round(s * NS))
        threading.Event().wait(0.0005)

    board = OscillatorClock(osc, time_scale=1.0, host_monotonic_ns=host_ns, host_sleep=host_sleep)
    signal = PpsSignal(osc, always, seed=8)
    chip = pps_chip(signal, board, path=CHIP, paced=True)
    with sim_gpiochips(chip), PpsLine(CHIP, LINE) as line:
        edges: list[PpsEdge] = []
        while len(edges) < 3:
            edges += line.wait(30.0)  # blocks in select until the pacer posts the edge
        for e in edges:
            assert e.timestamp_ns <= board.monotonic_ns()
    assert [e.line_seqno for e in edges[:3]] == [1, 2, 3]
    assert [e.timestamp_ns for e in edges[:3]] == [osc.board_ns(signal.pulse_true_ns(k) + signal.latency_ns(k))
                                                   for k in range(3)]


def test_line_edge_model_is_an_edge_source(signal):
    edges = signal.edges_between(0, 3 * NS)
    assert all(isinstance(e, LineEdge) for e in edges)
    assert [e.rising for e in edges] == [True, False, True, False, True, False]
    assert signal.next_edge_after(0, 2 * NS) == edges[0].true_ns
    assert signal.next_edge_after(edges[0].true_ns, 10) is None
