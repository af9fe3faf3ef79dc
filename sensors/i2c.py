"""I2C transfers whose failures a sampler thread and a person in the field can act on.

smbus2 reports every failed transfer as a bare ``OSError`` from the kernel's i2c-dev ioctl. Drivers must
raise :mod:`sensors.errors` instead, so that the thread can tell an absent chip from a flaky bus. The
kernel's adapters report a chip that does not acknowledge its address as ENXIO or EREMOTEIO (which one
depends on the adapter driver): that is :class:`~sensors.errors.DeviceNotFound` (wiring, power, address).
Any other errno (EIO, ETIMEDOUT, EAGAIN on arbitration loss, ...) is a transfer that went wrong on a bus
with a chip on it: :class:`~sensors.errors.BusError`. Both messages are one line naming the chip, its
address, the bus and what the driver was doing.

A chip that has answered since it was opened and then does not acknowledge is no wiring fault: some adapters
(the BeagleBone's i2c-omap) return EREMOTEIO for a NACK of any byte, not only of the address, so one such NACK on
a working chip is a bus error (the sampler retries at once) rather than a missing chip (check the wiring and the
address strap). EBUSY means no transfer happened at all: a kernel driver (a device-tree overlay's
``inv-mpu6050-i2c`` or ``bmp280``) holds the address, for I2C_SLAVE the likeliest reason, which the message
names with its remedy.
"""

from __future__ import annotations

import errno
import re
from collections.abc import Callable
from typing import Any, TypeVar

from sensors.errors import BusError, DeviceNotFound

NO_ACK_ERRNOS = (errno.ENXIO, errno.EREMOTEIO)  # the address was not acknowledged: no chip answers there

_T = TypeVar("_T")


def i2c_transfer(chip: str, address: int, bus_name: str, doing: str, fn: Callable[..., _T], *args: Any,
                 no_ack_hint: str = "check wiring and power", answered: bool = False) -> _T:
    """``fn(address, *args)`` (an ``smbus2.SMBus`` method), with OSError mapped as the module says.

    ``doing`` names the action for the message ("reading the chip id"); ``no_ack_hint`` is what to check
    when the chip does not answer; ``answered``: the chip has answered since it was opened (a NACK is then a
    bus error, not a missing chip).
    """
    try:
        return fn(address, *args)
    except OSError as exc:
        where = f"{chip} at 0x{address:02x} on {bus_name}"
        if exc.errno in NO_ACK_ERRNOS:
            if answered:
                raise BusError(f"{where}: no ACK while {doing}, after it had answered (a glitch on the bus, or "
                               "its supply dipped)") from exc
            raise DeviceNotFound(f"{where}: no answer while {doing} (no ACK): {no_ack_hint}") from exc
        if exc.errno == errno.EBUSY:
            number = re.search(r"(\d+)$", bus_name)
            dev = f"{number.group(1) if number else 'N'}-00{address:02x}"  # the kernel's name for the device
            raise BusError(f"{where}: address busy while {doing} (a kernel driver bound to it by a device-tree "
                           f"overlay? remove the overlay, or: echo {dev} > /sys/bus/i2c/devices/{dev}/driver/unbind)"
                           ) from exc
        raise BusError(f"{where}: I2C transfer failed while {doing}: {exc.strerror or exc}") from exc
