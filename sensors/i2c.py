"""I2C transfers whose failures a sampler thread and a person in the field can act on.

smbus2 reports every failed transfer as a bare ``OSError`` from the kernel's i2c-dev ioctl. Drivers must
raise :mod:`sensors.errors` instead, so that the thread can tell an absent chip from a flaky bus. The
kernel's adapters report a chip that does not acknowledge its address as ENXIO or EREMOTEIO (which one
depends on the adapter driver): that is :class:`~sensors.errors.DeviceNotFound` (wiring, power, address).
Any other errno (EIO, ETIMEDOUT, EAGAIN on arbitration loss, ...) is a transfer that went wrong on a bus
with a chip on it: :class:`~sensors.errors.BusError`. Both messages are one line naming the chip, its
address, the bus and what the driver was doing.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from typing import Any, TypeVar

from sensors.errors import BusError, DeviceNotFound

NO_ACK_ERRNOS = (errno.ENXIO, errno.EREMOTEIO)  # the address was not acknowledged: no chip answers there

_T = TypeVar("_T")


def i2c_transfer(chip: str, address: int, bus_name: str, doing: str, fn: Callable[..., _T], *args: Any,
                 no_ack_hint: str = "check wiring and power") -> _T:
    """``fn(address, *args)`` (an ``smbus2.SMBus`` method), with OSError mapped as the module says.

    ``doing`` names the action for the message ("reading the chip id"); ``no_ack_hint`` is what to check
    when the chip does not answer.
    """
    try:
        return fn(address, *args)
    except OSError as exc:
        where = f"{chip} at 0x{address:02x} on {bus_name}"
        if exc.errno in NO_ACK_ERRNOS:
            raise DeviceNotFound(f"{where}: no answer while {doing} (no ACK): {no_ack_hint}") from exc
        raise BusError(f"{where}: I2C transfer failed while {doing}: {exc.strerror or exc}") from exc
