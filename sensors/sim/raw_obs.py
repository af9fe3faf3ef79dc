"""Raw GPS observations of a simulated drive, as a u-blox with raw firmware (M8T, F9P) puts them in UBX-RXM-RAWX.

A survey engineer processes these at the office with RTKLIB (``convbin`` to RINEX, ``rnx2rtkp`` against a base
station), so they must be what real measurements are: functions of the drive's truth that RTKLIB's own models
undo. Everything here follows the documents those tools follow, not RTKLIB's code:

- **Orbits** (IS-GPS-200 20.3.3.4.3). The simulator's GPS satellites (:class:`~sensors.sim.gnss_errors.
  Constellation`, circular orbits of a Walker 24/6/1 constellation in a frame that turns with the earth) are
  exactly Keplerian orbits with e = 0, so each gets broadcast elements (sqrtA, deltaN for the period, i0,
  Omega0, omega = 0, M0, OMEGADOT = the difference between the earth rate in the user algorithm and the one
  the constellation turns with, no harmonic corrections), a new set every two hours as the control segment
  uploads them. :meth:`Ephemeris.position` is the user algorithm; it puts a satellite where the simulator's sky
  has it to well under a millimetre, and it is what the observations are computed from, so a navigation file
  written from the same elements (:func:`write_rinex_nav`, RINEX 3.04) gives a processor the true orbits.
- **Clocks.** Each satellite's clock is a constant offset and rate (af0, af1 of the broadcast, af2 = 0; no
  relativistic term, e being 0; TGD 0). A receiver's clock (:class:`ReceiverClock`) is a free TCXO that the
  firmware keeps within half a millisecond of GPS time by whole-millisecond steps (RXM-RAWX recStat clkReset),
  as u-blox timing receivers do; measurements are taken on whole seconds of that clock.
- **Signal path.** The geometric range is solved for the light time with the earth turning under the signal
  (the Sagnac effect), plus the troposphere of Saastamoinen's model in a standard atmosphere (the model
  RTKLIB's ``tropmodel`` computes, so ``pos1-tropopt=saas`` removes it) and the ionosphere of the Klobuchar
  model (IS-GPS-200 20.3.3.5.2.5) with the coefficients :func:`write_rinex_nav` broadcasts, so
  ``pos1-ionoopt=brdc`` removes it; the ionosphere delays the code and advances the carrier by the same amount.
- **Observables.** Pseudorange = range + c (receiver clock - satellite clock) + troposphere + ionosphere +
  noise; carrier phase (cycles) = (range + the same clocks + troposphere - ionosphere) / lambda_L1 + an integer
  ambiguity, constant while the satellite stays tracked; Doppler = -range rate / lambda with the clock rates.
  Noise is white, larger at low elevation (0.3 m and 3 mm at the zenith over sqrt(sin el)).
- **Tracking** (u-blox interface description, RXM-RAWX). A satellite hidden (below the mask, or behind a
  street canyon's walls as :meth:`~sensors.sim.gnss_errors.SkyGeometry.view` decides for the rover) loses lock;
  when it comes back it gets a new ambiguity, ``locktime`` starts from 0, and the half-cycle ambiguity is
  unresolved (trkStat halfCyc clear) until the receiver has read a subframe preamble, 1 to 6 s later; if the
  tracking loop had locked on the wrong half cycle, the receiver then subtracts it and sets subHalfCyc for the
  rest of the lock, which RTKLIB reads as a slip, as it should. A satellite seen only by reflection off a facade
  (SkyView.reflected) is late by the reflection's extra path on code and carrier alike, and weaker.

:class:`RawObservations` is one receiver (the rover on the drive, or a base station on a fixed point) and makes
an epoch's measurements and its RXM-RAWX frame; :func:`record_raw_drive` writes ``rover.ubx``, ``base.ubx`` and
``nav.rnx`` of a whole drive (``tools/sim_raw.py`` is its command line). Only GPS L1 C/A is modelled: GLONASS
needs its frequency channels and inter-channel biases, Galileo its own navigation message, and RXM-SFRBX
subframes are not generated (the navigation file stands in for them).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TextIO

import numpy as np
from pyubx2 import GET, UBXMessage

from sensors.sim import earth
from sensors.sim.gnss_errors import ELEVATION_MASK_DEG, Constellation, GaussMarkov, SkyGeometry
from sensors.sim.gnss_time import GPS_EPOCH, NS_PER_S, SECONDS_PER_WEEK, GnssTimeline
from sensors.sim.truth import ParkedTrajectory, Trajectory, TruthState
from sensors.sim.ublox_encode import EpochRecord

__all__ = [
    "KLOBUCHAR_ALPHA",
    "KLOBUCHAR_BETA",
    "LAMBDA_L1",
    "Ephemeris",
    "GpsBroadcast",
    "RawDriveFiles",
    "RawEpoch",
    "RawMeasurement",
    "RawObservations",
    "ReceiverClock",
    "klobuchar_m",
    "read_rinex_nav",
    "record_raw_drive",
    "rxm_rawx",
    "saastamoinen_m",
    "write_rinex_nav",
]

# IS-GPS-200 constants of the user algorithm (20.3.3.4.3) and the L1 signal.
CLIGHT = 299_792_458.0
MU_GPS = 3.986005e14  # m^3/s^2
OMEGA_E_GPS = 7.2921151467e-5  # rad/s
F_RELATIVITY = -4.442807633e-10  # s/m^0.5
FREQ_L1 = 1575.42e6
LAMBDA_L1 = CLIGHT / FREQ_L1
TOE_SPACING_S = 7200  # a new ephemeris every two hours; a processor uses one within two hours of its toe
SV_ACCURACY_M = 2.0  # URA of the broadcast: what a processor weights the orbit and clock by
# A broadcast Klobuchar set (alpha s, s/sc, s/sc^2, s/sc^3; beta s, ...), at the four decimals RINEX carries.
KLOBUCHAR_ALPHA = (1.1176e-08, -7.4506e-09, -5.9605e-08, 1.1921e-07)
KLOBUCHAR_BETA = (1.1674e05, -2.2938e05, -1.3107e05, 1.0486e06)
STANDARD_HUMIDITY = 0.7  # relative humidity of the standard atmosphere (RTKLIB's tropmodel takes the same)

# RXM-RAWX (u-blox M8 protocol 18+, F9): class 0x02 id 0x15; header and 32-byte measurement blocks.
RAWX_CLASS, RAWX_ID = 0x02, 0x15
_RAWX_HEADER = struct.Struct("<dHbBBB2x")  # rcvTow, week, leapS, numMeas, recStat, version, reserved1[2]
_RAWX_MEAS = struct.Struct("<ddfBBBBHBBBBBx")  # prMes .. trkStat, reserved2
RAWX_VERSION = 1
LOCKTIME_MAX_MS = 64_500  # u-blox caps locktime here
TRK_PR_VALID, TRK_CP_VALID, TRK_HALF_CYC, TRK_SUB_HALF_CYC = 0x01, 0x02, 0x04, 0x08
REC_LEAP_SEC, REC_CLK_RESET = 0x01, 0x02
GNSS_ID_GPS, SIG_ID_L1CA = 0, 0


# ---- broadcast orbits -------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Ephemeris:
    """One GPS broadcast ephemeris and clock (the fields of a RINEX 'G' record; angles in radians)."""

    prn: int
    week: int  # GPS week of toe and toc (continuous, not modulo 1024)
    toe_s: float  # seconds of week
    toc_s: float
    sqrt_a: float
    e: float
    i0: float
    omega0: float
    omega: float
    m0: float
    delta_n: float
    omega_dot: float
    idot: float = 0.0
    cuc: float = 0.0
    cus: float = 0.0
    crc: float = 0.0
    crs: float = 0.0
    cic: float = 0.0
    cis: float = 0.0
    af0: float = 0.0
    af1: float = 0.0
    af2: float = 0.0
    iode: int = 0
    iodc: int = 0
    tgd_s: float = 0.0
    sv_accuracy_m: float = SV_ACCURACY_M
    health: int = 0
    fit_interval_h: float = 4.0
    transmission_s: float = 0.0  # seconds of week when the subframes were sent

    def position(self, week: int, tow_s: float) -> tuple[np.ndarray, float]:
        """Satellite position (ECEF of the instant, m) and clock offset (s) at GPS time ``week``/``tow_s``.

        The IS-GPS-200 user algorithm (Table 20-IV): mean anomaly from the corrected mean motion, Kepler's
        equation by Newton's method, the second-harmonic corrections, the node at the instant with the earth's
        rotation since the start of the week; the clock polynomial with the relativistic term. ``tk`` counts
        from toe across a week boundary through the week numbers, which is the standard's +-302400 s rule.
        """
        tk = (week - self.week) * SECONDS_PER_WEEK + tow_s - self.toe_s
        a = self.sqrt_a * self.sqrt_a
        m = self.m0 + (math.sqrt(MU_GPS / (a * a * a)) + self.delta_n) * tk
        ecc = self.e
        ek = m
        for _ in range(30):
            step = (ek - ecc * math.sin(ek) - m) / (1.0 - ecc * math.cos(ek))
            ek -= step
            if abs(step) < 1e-15:
                break
        sin_e, cos_e = math.sin(ek), math.cos(ek)
        phi = math.atan2(math.sqrt(1.0 - ecc * ecc) * sin_e, cos_e - ecc) + self.omega
        s2, c2 = math.sin(2.0 * phi), math.cos(2.0 * phi)
        u = phi + self.cus * s2 + self.cuc * c2
        r = a * (1.0 - ecc * cos_e) + self.crs * s2 + self.crc * c2
        inc = self.i0 + self.idot * tk + self.cis * s2 + self.cic * c2
        xp, yp = r * math.cos(u), r * math.sin(u)
        node = self.omega0 + (self.omega_dot - OMEGA_E_GPS) * tk - OMEGA_E_GPS * self.toe_s
        cn, sn, ci = math.cos(node), math.sin(node), math.cos(inc)
        pos = np.array((xp * cn - yp * ci * sn, xp * sn + yp * ci * cn, yp * math.sin(inc)))
        tc = (week - self.week) * SECONDS_PER_WEEK + tow_s - self.toc_s
        dts = self.af0 + self.af1 * tc + self.af2 * tc * tc + F_RELATIVITY * ecc * self.sqrt_a * sin_e
        return pos, dts


def _wrap_pi(angle: float) -> float:
    return math.remainder(angle, 2.0 * math.pi)


class GpsBroadcast:
    """The GPS satellites of a simulated sky as broadcast ephemerides describe them, with their clocks.

    ``constellation`` is the drive's (:attr:`SkyGeometry.constellation`), ``timeline`` maps its drive time to
    GPS time. Satellite clocks are drawn from ``seed``: offsets within +-``clock_offset_s``, rates within
    +-``clock_rate`` (what GPS clocks show before the control segment's corrections).
    """

    def __init__(self, constellation: Constellation, timeline: GnssTimeline, seed: int = 0,
                 clock_offset_s: float = 2e-4, clock_rate: float = 5e-12) -> None:
        self.constellation = constellation
        self.timeline = timeline
        self.index = {int(name[1:]): i for i, name in enumerate(constellation.names) if name.startswith("G")}
        self.prns = tuple(sorted(self.index))
        rng = np.random.default_rng([seed, 17])
        n = len(self.prns)
        self._clock = dict(zip(self.prns, zip(rng.uniform(-clock_offset_s, clock_offset_s, n),
                                              rng.uniform(-clock_rate, clock_rate, n), strict=True), strict=True))
        self._cache: dict[tuple[int, int, int], Ephemeris] = {}

    def ephemeris(self, prn: int, week: int, toe_s: int) -> Ephemeris:
        """The broadcast set of ``prn`` with reference time ``toe_s`` (whole seconds of ``week``)."""
        key = (prn, week, toe_s)
        eph = self._cache.get(key)
        if eph is None:
            eph = self._cache[key] = self._elements(prn, week, toe_s)
        return eph

    def _elements(self, prn: int, week: int, toe_s: int) -> Ephemeris:
        orbit = self.constellation.orbit(self.index[prn])
        # Seconds of the constellation's own time at toe (drive time plus its phasing epoch).
        toe_ns = week * SECONDS_PER_WEEK * NS_PER_S + toe_s * NS_PER_S
        t_toe = self.timeline.drive_ns(toe_ns) / NS_PER_S + self.constellation.epoch_s
        a = orbit.radius_m
        delta_n = orbit.mean_motion_rps - math.sqrt(MU_GPS / (a * a * a))
        # The constellation's node turns at earth.OMEGA_IE; the user algorithm subtracts OMEGA_E_GPS: OMEGADOT
        # carries the difference (1.5e-14 rad/s), so both put the node at the same place at every instant.
        omega_dot = OMEGA_E_GPS - earth.OMEGA_IE
        omega0 = orbit.raan_rad - earth.OMEGA_IE * t_toe + OMEGA_E_GPS * toe_s
        m0 = orbit.arg_lat0_rad + orbit.mean_motion_rps * t_toe
        offset, rate = self._clock[prn]
        af0 = offset + rate * self.timeline.drive_ns(toe_ns) / NS_PER_S
        issue = (toe_s // TOE_SPACING_S) % 256  # IODE/IODC: a new issue with every upload
        return Ephemeris(prn=prn, week=week, toe_s=float(toe_s), toc_s=float(toe_s), sqrt_a=math.sqrt(a), e=0.0,
                         i0=orbit.inclination_rad, omega0=_wrap_pi(omega0), omega=0.0, m0=_wrap_pi(m0),
                         delta_n=delta_n, omega_dot=omega_dot, af0=af0, af1=rate, iode=issue, iodc=issue,
                         transmission_s=float(max(0, toe_s - TOE_SPACING_S // 2)))

    def current(self, prn: int, gps_ns: int) -> Ephemeris:
        """The set a receiver uses at ``gps_ns``: the one whose toe (a whole two hours of the week) is nearest."""
        week, tow_ns = GnssTimeline.week_tow(gps_ns)
        toe = (tow_ns + TOE_SPACING_S * NS_PER_S // 2) // (TOE_SPACING_S * NS_PER_S) * TOE_SPACING_S
        if toe >= SECONDS_PER_WEEK:
            week, toe = week + 1, 0
        return self.ephemeris(prn, week, toe)

    def ephemerides(self, start_gps_ns: int, end_gps_ns: int) -> list[Ephemeris]:
        """Every set a processor needs between two instants (each toe within two hours of some instant)."""
        step = TOE_SPACING_S * NS_PER_S
        first = (start_gps_ns - step) // step + 1
        last = (end_gps_ns + step) // step
        out = []
        for k in range(first, last + 1):
            week, tow_ns = GnssTimeline.week_tow(k * step)
            out.extend(self.ephemeris(prn, week, tow_ns // NS_PER_S) for prn in self.prns)
        return out

    def position(self, prn: int, gps_ns: int, before_s: float = 0.0) -> tuple[np.ndarray, float]:
        """Position and clock of ``prn`` at ``before_s`` seconds before GPS instant ``gps_ns``."""
        week, tow_ns = GnssTimeline.week_tow(gps_ns)
        return self.current(prn, gps_ns).position(week, tow_ns / NS_PER_S - before_s)


# ---- atmosphere -------------------------------------------------------------------------------------------
def klobuchar_m(lat_rad: float, lon_rad: float, az_rad: float, el_rad: float, tow_s: float,
                alpha: tuple[float, ...] = KLOBUCHAR_ALPHA, beta: tuple[float, ...] = KLOBUCHAR_BETA) -> float:
    """L1 ionospheric delay (m) of the broadcast model, IS-GPS-200 20.3.3.5.2.5 (angles in semicircles there)."""
    if el_rad <= 0.0:
        return 0.0
    e_sc = el_rad / math.pi
    psi = 0.0137 / (e_sc + 0.11) - 0.022  # earth-centred angle to the ionospheric pierce point
    phi_i = min(0.416, max(-0.416, lat_rad / math.pi + psi * math.cos(az_rad)))
    lam_i = lon_rad / math.pi + psi * math.sin(az_rad) / math.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * math.cos((lam_i - 1.617) * math.pi)  # geomagnetic latitude
    t = (43_200.0 * lam_i + tow_s) % 86_400.0  # local time at the pierce point
    slant = 1.0 + 16.0 * (0.53 - e_sc) ** 3
    amp = max(0.0, alpha[0] + phi_m * (alpha[1] + phi_m * (alpha[2] + phi_m * alpha[3])))
    per = max(72_000.0, beta[0] + phi_m * (beta[1] + phi_m * (beta[2] + phi_m * beta[3])))
    x = 2.0 * math.pi * (t - 50_400.0) / per
    night = 5e-9
    delay = night + amp * (1.0 - x * x / 2.0 + x**4 / 24.0) if abs(x) < 1.57 else night
    return CLIGHT * slant * delay


def saastamoinen_m(lat_rad: float, height_m: float, el_rad: float, humidity: float = STANDARD_HUMIDITY) -> float:
    """Tropospheric delay (m): Saastamoinen's model with the standard atmosphere at the antenna's height.

    Pressure and temperature follow the standard atmosphere from 1013.25 hPa and 15 degC at the ellipsoid,
    the water vapour pressure a relative ``humidity``; the zenith delays are mapped by 1/cos(z). This is the
    troposphere the simulation has, so a processor with the same model removes it.
    """
    if el_rad <= 0.0 or not -100.0 <= height_m <= 1e4:
        return 0.0
    h = max(0.0, height_m)
    pressure = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp = 15.0 - 6.5e-3 * h + 273.16
    vapour = 6.108 * humidity * math.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    cos_z = math.cos(math.pi / 2.0 - el_rad)
    dry = 0.0022768 * pressure / (1.0 - 0.00266 * math.cos(2.0 * lat_rad) - 0.00028 * h / 1e3) / cos_z
    wet = 0.002277 * (1255.0 / temp + 0.05) * vapour / cos_z
    return dry + wet


# ---- the receiver -----------------------------------------------------------------------------------------
@dataclass
class ReceiverClock:
    """A receiver's clock against GPS time: a TCXO's offset and rate, stepped by whole milliseconds.

    u-blox timing receivers let their clock run free and, when it drifts past half a millisecond from GPS time,
    step it by a whole millisecond (RXM-RAWX recStat clkReset); pseudoranges and carrier phases step with it,
    which a processor estimating the clock every epoch takes in its stride.
    """

    offset_s: float = 1e-4  # at drive time 0
    rate: float = 1e-7  # s/s
    step_s: float = 1e-3
    _steps: int = 0

    def bias(self, drive_s: float) -> tuple[float, bool]:
        """The clock's bias (receiver minus GPS time, s) at ``drive_s`` and whether it stepped just now."""
        free = self.offset_s + self.rate * drive_s
        steps = round(free / self.step_s)
        stepped = steps != self._steps
        self._steps = steps
        return free - steps * self.step_s, stepped


@dataclass(frozen=True, slots=True)
class RawMeasurement:
    """One satellite's measurements in an epoch, as RXM-RAWX carries them."""

    prn: int
    pseudorange_m: float
    carrier_cycles: float
    doppler_hz: float
    locktime_ms: int
    cno_dbhz: int
    pr_std_m: float
    cp_std_cycles: float
    do_std_hz: float
    half_cycle_valid: bool
    half_cycle_subtracted: bool
    elevation_rad: float
    reflected: bool = False


@dataclass(frozen=True, slots=True)
class RawEpoch:
    """The measurements of one epoch at whole second ``rcv_gps_ns`` of the receiver's clock."""

    rcv_gps_ns: int
    leap_s: int
    clock_bias_s: float  # receiver minus GPS time at the measurement
    clock_reset: bool
    measurements: tuple[RawMeasurement, ...]
    receiver_ecef_m: np.ndarray  # where the antenna truly was at the measurement


def _std_index(sigma: float, unit: float, doubling: bool) -> int:
    """A 4-bit standard-deviation field: ``unit`` * 2^n (pr, Doppler) or ``unit`` * n (carrier)."""
    n = math.log2(max(sigma, 1e-12) / unit) if doubling else sigma / unit
    return min(15, max(0 if doubling else 1, math.ceil(n)))


def rxm_rawx(epoch: RawEpoch) -> bytes:
    """UBX-RXM-RAWX of one epoch, framed with its checksum (u-blox M8 protocol 18+ / F9 layout, version 1).

    The standard deviations go in their scaled 4-bit fields (pr 0.01 m * 2^n, carrier 0.004 cycles * n,
    Doppler 0.002 Hz * 2^n); trkStat says which measurements are valid and how the half cycle stands.
    """
    week, tow_ns = GnssTimeline.week_tow(epoch.rcv_gps_ns)
    rec_stat = REC_LEAP_SEC | (REC_CLK_RESET if epoch.clock_reset else 0)
    body = [_RAWX_HEADER.pack(tow_ns / NS_PER_S, week, epoch.leap_s, len(epoch.measurements), rec_stat,
                              RAWX_VERSION)]
    for m in epoch.measurements:
        trk = TRK_PR_VALID | TRK_CP_VALID
        trk |= (TRK_HALF_CYC if m.half_cycle_valid else 0) | (TRK_SUB_HALF_CYC if m.half_cycle_subtracted else 0)
        body.append(_RAWX_MEAS.pack(
            m.pseudorange_m, m.carrier_cycles, m.doppler_hz, GNSS_ID_GPS, m.prn, SIG_ID_L1CA, 0,
            min(m.locktime_ms, LOCKTIME_MAX_MS), m.cno_dbhz, _std_index(m.pr_std_m, 0.01, True),
            _std_index(m.cp_std_cycles, 0.004, False), _std_index(m.do_std_hz, 0.002, True), trk))
    return UBXMessage(RAWX_CLASS, RAWX_ID, GET, payload=b"".join(body)).serialize()


@dataclass
class _Channel:
    """A satellite's tracking since the receiver last locked on to it."""

    ambiguity: int
    lock_ns: int  # receiver time of lock
    half_resolved_ns: int  # when the subframe preamble settles the half cycle
    half_wrong: bool  # locked on the wrong half cycle until then
    nlos: GaussMarkov | None = None


class RawObservations:
    """One receiver's raw GPS measurements: the rover on a drive (``sky`` given) or a station under an open sky.

    ``sky`` decides which satellites the antenna sees at each epoch (the drive's :class:`SkyGeometry`: mask,
    street canyons, tunnels, reflections); without it every GPS satellite above ``mask_deg`` is seen. Measurement
    noise and ambiguities come from ``seed``. :meth:`measure` gives an epoch's measurements, :meth:`frames` its
    RXM-RAWX frame, :meth:`for_epoch` the same for the receiver model's hook (an :class:`EpochRecord`).
    """

    def __init__(self, broadcast: GpsBroadcast, *, sky: SkyGeometry | None = None,
                 mask_deg: float = ELEVATION_MASK_DEG, seed: int = 0, clock: ReceiverClock | None = None,
                 code_sigma_m: float = 0.3, carrier_sigma_m: float = 0.003, doppler_sigma_hz: float = 0.05,
                 nlos_m: float = 15.0, nlos_tau_s: float = 15.0) -> None:
        self.broadcast = broadcast
        self.timeline = broadcast.timeline
        self.sky = sky
        self.mask = math.radians(mask_deg)
        self._rng = np.random.default_rng([seed, 23])
        if clock is None:
            clock = ReceiverClock(float(self._rng.uniform(-4e-4, 4e-4)), float(self._rng.uniform(-3e-7, 3e-7)))
        self.clock = clock
        self.code_sigma_m = code_sigma_m
        self.carrier_sigma_m = carrier_sigma_m
        self.doppler_sigma_hz = doppler_sigma_hz
        self.nlos_m = nlos_m
        self.nlos_tau_s = nlos_tau_s
        self._channels: dict[int, _Channel] = {}
        self._last_ns: int | None = None

    def _visible(self, truth: TruthState, rr: np.ndarray, rcv_gps_ns: int) -> dict[int, bool]:
        """PRN -> seen only by reflection, for every GPS satellite the antenna tracks now."""
        if self.sky is not None:
            view = self.sky.view(truth)
            names = self.sky.constellation.names
            return {int(names[i][1:]): bool(r) for i, r in zip(view.ids, view.reflected, strict=True)
                    if names[i].startswith("G")}
        out = {}
        for prn in self.broadcast.prns:
            pos, _ = self.broadcast.position(prn, rcv_gps_ns)
            if _look(rr, truth.lat_rad, truth.lon_rad, pos)[1] >= self.mask:
                out[prn] = False
        return out

    def measure(self, rcv_gps_ns: int, truth: TruthState) -> RawEpoch:
        """The measurements taken when the receiver's clock reads ``rcv_gps_ns`` (a whole epoch).

        ``truth`` is the vehicle at GPS time ``rcv_gps_ns``; the measurement happens when GPS time is the
        clock's bias earlier, where the antenna was that much earlier along its velocity.
        """
        drive_s = self.timeline.drive_ns(rcv_gps_ns) / NS_PER_S
        dtr, reset = self.clock.bias(drive_s)
        rate = self.clock.rate
        dt_s = 1.0 if self._last_ns is None else (rcv_gps_ns - self._last_ns) / NS_PER_S
        self._last_ns = rcv_gps_ns
        c_ne = earth.dcm_ned_to_ecef(truth.lat_rad, truth.lon_rad)
        vr = c_ne @ truth.vel_ned_mps
        rr = earth.ecef(truth.lat_rad, truth.lon_rad, truth.height_m) - vr * dtr
        t_true_ns = rcv_gps_ns - round(dtr * NS_PER_S)
        frac = dtr * NS_PER_S - round(dtr * NS_PER_S)  # the bias's part below a nanosecond, in ns
        visible = self._visible(truth, rr, rcv_gps_ns)
        for prn in set(self._channels) - set(visible):  # hidden: lock lost
            del self._channels[prn]
        tow_s = GnssTimeline.week_tow(rcv_gps_ns)[1] / NS_PER_S
        out = []
        for prn in sorted(visible):
            rho, rs, dts, sat_rate = self._geometry(prn, t_true_ns, frac * 1e-9, rr)
            h = 0.05
            rho_dot = (self._geometry(prn, t_true_ns, frac * 1e-9 + h, rr + vr * h)[0]
                       - self._geometry(prn, t_true_ns, frac * 1e-9 - h, rr - vr * h)[0]) / (2.0 * h)
            az, el = _look(rr, truth.lat_rad, truth.lon_rad, rs)
            if el <= 0.0:
                continue
            chan = self._channels.get(prn)
            if chan is None:
                chan = self._channels[prn] = self._lock(rcv_gps_ns)
            reflected = visible[prn]
            excess = 0.0
            if reflected:
                if chan.nlos is None:
                    chan.nlos = GaussMarkov(self.nlos_tau_s, self._rng)
                excess = self.nlos_m * (0.3 + abs(float(chan.nlos.step(dt_s)[0])))
            trop = saastamoinen_m(truth.lat_rad, truth.height_m, el)
            iono = klobuchar_m(truth.lat_rad, truth.lon_rad, az, el, tow_s)
            shape = 1.0 / math.sqrt(math.sin(max(el, math.radians(5.0))))
            sig_p, sig_l = self.code_sigma_m * shape, self.carrier_sigma_m * shape
            n_p, n_l, n_d = self._rng.standard_normal(3)
            clocks = CLIGHT * (dtr - dts)
            pr = rho + clocks + trop + iono + excess + sig_p * n_p
            half = rcv_gps_ns >= chan.half_resolved_ns
            carrier = ((rho + clocks + trop - iono + excess + sig_l * n_l) / LAMBDA_L1 + chan.ambiguity
                       + (0.5 if chan.half_wrong and not half else 0.0))
            doppler = -(rho_dot + CLIGHT * (rate - sat_rate)) / LAMBDA_L1 + self.doppler_sigma_hz * n_d
            cno = round(32.0 + 16.0 * math.sin(el)) - (8 if reflected else 0)
            out.append(RawMeasurement(
                prn, pr, carrier, doppler, (rcv_gps_ns - chan.lock_ns) // 1_000_000, cno, sig_p,
                _pll_jitter_cycles(cno), self.doppler_sigma_hz, half, half and chan.half_wrong, el, reflected))
        return RawEpoch(rcv_gps_ns, self.timeline.leap_s, dtr, reset, tuple(out), rr)

    def _lock(self, rcv_gps_ns: int) -> _Channel:
        """A new lock: the phase counter starts near the pseudorange in cycles (as u-blox's does), off by an
        arbitrary integer; the half cycle settles 1 to 6 s later, wrong until then half of the time."""
        rng = self._rng
        ambiguity = int(rng.integers(-500, 500))
        resolved = rcv_gps_ns + round(float(rng.uniform(1.0, 6.0))) * NS_PER_S
        return _Channel(ambiguity, rcv_gps_ns, resolved, bool(rng.integers(2)))

    def _geometry(self, prn: int, t_ns: int, t_frac_s: float, rr: np.ndarray) -> tuple[float, np.ndarray, float,
                                                                                          float]:
        """Range (m) from the satellite's emission to reception at GPS time ``t_ns`` + ``t_frac_s`` at ``rr``.

        The light time is iterated with the satellite taken at emission and turned with the earth for the time
        of flight (the Sagnac effect). Returns the range, the satellite's position at emission (ECEF of that
        instant), its clock offset then and its clock rate.
        """
        eph = self.broadcast.current(prn, t_ns)
        week, tow_ns = GnssTimeline.week_tow(t_ns)
        tow = tow_ns / NS_PER_S + t_frac_s
        tau = 0.075
        for _ in range(4):
            rs, dts = eph.position(week, tow - tau)
            th = OMEGA_E_GPS * tau
            c, s = math.cos(th), math.sin(th)
            rot = np.array((c * rs[0] + s * rs[1], -s * rs[0] + c * rs[1], rs[2]))
            tau = float(np.linalg.norm(rot - rr)) / CLIGHT
        rho = tau * CLIGHT
        return rho, rs, dts, eph.af1 + 2.0 * eph.af2 * ((week - eph.week) * SECONDS_PER_WEEK + tow - eph.toc_s)

    def frames(self, rcv_gps_ns: int, truth: TruthState) -> list[bytes]:
        """The epoch's UBX frames: its RXM-RAWX."""
        return [rxm_rawx(self.measure(rcv_gps_ns, truth))]

    def for_epoch(self, rec: EpochRecord) -> list[bytes]:
        """The receiver model's ``raw_frames`` hook: the frames of the epoch it solved."""
        return self.frames(rec.gps_ns, rec.truth)


def _pll_jitter_cycles(cno_dbhz: float, bandwidth_hz: float = 10.0, integration_s: float = 0.02) -> float:
    """Thermal noise of a carrier tracking loop (cycles): what a receiver reports as cpStdev."""
    cn0 = 10.0 ** (cno_dbhz / 10.0)
    return math.sqrt(bandwidth_hz / cn0 * (1.0 + 1.0 / (2.0 * integration_s * cn0))) / (2.0 * math.pi)


def _look(rr: np.ndarray, lat: float, lon: float, rs: np.ndarray) -> tuple[float, float]:
    """Azimuth and elevation (rad) of ``rs`` from ``rr``."""
    d = earth.dcm_ned_to_ecef(lat, lon).T @ (rs - rr)
    return math.atan2(d[1], d[0]), math.atan2(-d[2], math.hypot(d[0], d[1]))


# ---- RINEX navigation file ---------------------------------------------------------------------------------
def _d19(x: float) -> str:
    return f"{x:19.12E}"


def _header_line(text: str, label: str) -> str:
    return f"{text:<60}{label}\n"


def write_rinex_nav(out: TextIO, ephemerides: Iterable[Ephemeris], leap_s: int,
                    alpha: tuple[float, ...] = KLOBUCHAR_ALPHA, beta: tuple[float, ...] = KLOBUCHAR_BETA,
                    program: str = "vehicle-logger sim") -> None:
    """A RINEX 3.04 GPS navigation file: the Klobuchar coefficients and leap seconds, then one 'G' record
    per ephemeris (epoch of toc in GPS time, then broadcast orbits 1 to 7 in D19.12 fields)."""
    out.write(_header_line(f"{3.04:9.2f}{'':11}N: GNSS NAV DATA    G: GPS", "RINEX VERSION / TYPE"))
    out.write(_header_line(f"{program:<20}{'':20}{'':20}", "PGM / RUN BY / DATE"))
    out.write(_header_line("GPSA " + "".join(f"{x:12.4E}" for x in alpha), "IONOSPHERIC CORR"))
    out.write(_header_line("GPSB " + "".join(f"{x:12.4E}" for x in beta), "IONOSPHERIC CORR"))
    out.write(_header_line(f"{leap_s:6d}", "LEAP SECONDS"))
    out.write(_header_line("", "END OF HEADER"))
    for e in sorted(ephemerides, key=lambda x: (x.week, x.toc_s, x.prn)):
        toc = GPS_EPOCH + timedelta(seconds=e.week * SECONDS_PER_WEEK + e.toc_s)
        out.write(f"G{e.prn:02d} {toc:%Y %m %d %H %M %S}" + "".join(_d19(x) for x in (e.af0, e.af1, e.af2)) + "\n")
        rows = (
            (e.iode, e.crs, e.delta_n, e.m0),
            (e.cuc, e.e, e.cus, e.sqrt_a),
            (e.toe_s, e.cic, e.omega0, e.cis),
            (e.i0, e.crc, e.omega, e.omega_dot),
            (e.idot, 1.0, e.week, 0.0),  # codes on L2: C/A; L2 P data flag
            (e.sv_accuracy_m, e.health, e.tgd_s, e.iodc),
            (e.transmission_s, e.fit_interval_h),
        )
        for row in rows:
            out.write("    " + "".join(_d19(float(x)) for x in row) + "\n")


def read_rinex_nav(path: Path) -> tuple[list[Ephemeris], tuple[float, ...], tuple[float, ...]]:
    """The GPS records of a RINEX 3 navigation file and its Klobuchar alpha and beta (fixed-width fields)."""
    lines = path.read_text().splitlines()
    alpha: tuple[float, ...] = ()
    beta: tuple[float, ...] = ()
    i = 0
    while i < len(lines) and "END OF HEADER" not in lines[i][60:]:
        line = lines[i]
        if line[60:].startswith("IONOSPHERIC CORR"):
            values = tuple(float(line[5 + 12 * k:17 + 12 * k].replace("D", "E")) for k in range(4))
            if line.startswith("GPSA"):
                alpha = values
            elif line.startswith("GPSB"):
                beta = values
        i += 1
    out = []
    i += 1
    while i + 7 < len(lines) + 0 and lines[i].startswith("G"):
        head = lines[i]

        def num(text: str) -> float:
            return float(text.replace("D", "E")) if text.strip() else 0.0

        f = [num(head[23 + 19 * k:42 + 19 * k]) for k in range(3)]
        for row in lines[i + 1:i + 8]:
            f.extend(num(row[4 + 19 * k:23 + 19 * k]) for k in range(4))
        week = int(f[21])
        out.append(Ephemeris(
            prn=int(head[1:3]), week=week, toe_s=f[11], toc_s=_toc_sow(head[4:23], week), sqrt_a=f[10], e=f[8],
            i0=f[15], omega0=f[13], omega=f[17], m0=f[6], delta_n=f[5], omega_dot=f[18], idot=f[19],
            cuc=f[7], cus=f[9], crc=f[16], crs=f[4], cic=f[12], cis=f[14], af0=f[0], af1=f[1], af2=f[2],
            iode=int(f[3]), iodc=int(f[26]), tgd_s=f[25], sv_accuracy_m=f[23], health=int(f[24]),
            fit_interval_h=f[28], transmission_s=f[27]))
        i += 8
    return out, alpha, beta


def _toc_sow(epoch: str, week: int) -> float:
    """Seconds of ``week`` of a record's 'yyyy mm dd hh mm ss' epoch (GPS time)."""
    y, mo, d, hh, mm, ss = (int(x) for x in epoch.split())
    seconds = (datetime(y, mo, d, hh, mm, ss, tzinfo=UTC) - GPS_EPOCH).total_seconds()
    return seconds - week * SECONDS_PER_WEEK


# ---- a whole drive ---------------------------------------------------------------------------------------
@dataclass
class RawDriveFiles:
    """What :func:`record_raw_drive` wrote, and what a check against it needs."""

    rover_ubx: Path
    base_ubx: Path
    nav: Path
    base_ecef_m: np.ndarray
    epochs: int
    rover_epochs_with_measurements: int
    first_gps_ns: int
    rover: list[RawEpoch] = field(default_factory=list)


def base_point(trajectory: Trajectory, distance_m: float = 500.0, bearing_deg: float = 225.0) -> TruthState:
    """A base station's antenna: ``distance_m`` from the drive's start along ``bearing_deg``, at its height."""
    s0 = trajectory.state(0.0)
    rn, re = earth.radii(s0.lat_rad)
    b = math.radians(bearing_deg)
    lat = s0.lat_rad + distance_m * math.cos(b) / (rn + s0.height_m)
    lon = s0.lon_rad + distance_m * math.sin(b) / ((re + s0.height_m) * math.cos(s0.lat_rad))
    return ParkedTrajectory(math.degrees(lat), math.degrees(lon), s0.height_m).state(0.0)


def record_raw_drive(trajectory: Trajectory, sky: SkyGeometry, out_dir: Path, *, duration_s: float | None = None,
                     timeline: GnssTimeline | None = None, seed: int = 0, rate_hz: int = 1,
                     base_distance_m: float = 500.0, keep_epochs: bool = False) -> RawDriveFiles:
    """Write ``rover.ubx`` and ``base.ubx`` (RXM-RAWX of every epoch) and ``nav.rnx`` for a drive.

    Epochs fall on whole ``1/rate_hz`` seconds of each receiver's clock from the first after the drive's start;
    the base stands ``base_distance_m`` from the start under an open sky, with a clock of its own.
    """
    timeline = timeline or GnssTimeline()
    duration_s = trajectory.duration_s if duration_s is None else duration_s
    out_dir.mkdir(parents=True, exist_ok=True)
    broadcast = GpsBroadcast(sky.constellation, timeline, seed)
    rover = RawObservations(broadcast, sky=sky, seed=seed * 2 + 1)
    base = RawObservations(broadcast, seed=seed * 2 + 2)
    base_truth = base_point(trajectory, base_distance_m)
    period_ns = NS_PER_S // rate_hz
    first = -(-timeline.start_gps_ns // period_ns) * period_ns
    n = int((timeline.start_gps_ns + duration_s * NS_PER_S - first) // period_ns) + 1
    paths = (out_dir / "rover.ubx", out_dir / "base.ubx", out_dir / "nav.rnx")
    kept, with_meas = [], 0
    with paths[0].open("wb") as fr, paths[1].open("wb") as fb:
        for k in range(n):
            gps_ns = first + k * period_ns
            truth = trajectory.state(min(timeline.drive_ns(gps_ns) / NS_PER_S, trajectory.duration_s))
            epoch = rover.measure(gps_ns, truth)
            with_meas += bool(epoch.measurements)
            if keep_epochs:
                kept.append(epoch)
            fr.write(rxm_rawx(epoch))
            fb.write(rxm_rawx(base.measure(gps_ns, base_truth)))
    with paths[2].open("w") as f:
        write_rinex_nav(f, broadcast.ephemerides(first, first + n * period_ns), timeline.leap_s)
    base_ecef = earth.ecef(base_truth.lat_rad, base_truth.lon_rad, base_truth.height_m)
    return RawDriveFiles(*paths, base_ecef, n, with_meas, first, kept)
