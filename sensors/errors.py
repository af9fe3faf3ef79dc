"""Exceptions every driver raises, so a sampler thread can tell 'retry later' from 'my own bug'.

Anything derived from :class:`SensorError` is a condition of the device or its bus (absent, silent,
garbled) that the caller may retry; its message is one line a person in the field understands.
"""

from __future__ import annotations


class SensorError(Exception):
    """A device or bus condition that a caller may retry after a back-off."""


class DeviceNotFound(SensorError):
    """The device node or the chip on the bus is not there (wrong path, unplugged, no ACK)."""


class WrongDevice(SensorError):
    """Something answers, but it is not the chip the configuration names (bad id register)."""


class BusError(SensorError):
    """A transfer failed on the bus (I2C EIO/NACK, serial port vanished, CAN error frame)."""


class NoData(SensorError):
    """The device answered but has no value now (ELM327 'NO DATA', CAN timeout, no fix yet)."""


class ProtocolError(SensorError):
    """The device sent something that does not follow its protocol (garbage, bad checksum, bad length)."""
