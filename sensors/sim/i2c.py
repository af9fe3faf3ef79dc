"""The I2C seam: a simulated Linux i2c-dev adapter underneath the real ``smbus2`` package.

smbus2 reaches the kernel through exactly two calls: ``os.open`` of ``/dev/i2c-N`` and ``fcntl.ioctl`` on
that descriptor. Replacing those two names inside ``smbus2.smbus2`` (once per process) and answering only
for descriptors opened on a simulated adapter lets every line of smbus2 run above the chip models, while a
real bus in the same process still reaches the real kernel.

The ioctl arguments are decoded from the caller's memory the way ``drivers/i2c/i2c-dev.c`` copies them
from user space, and SMBus requests are turned into I2C messages the way the kernel's SMBus emulation
(``i2c_smbus_xfer_emulated``) does. So byte order (SMBus words are little-endian on the wire, unlike the
big-endian registers of most sensors), block-length limits, PEC and error numbers are those a driver meets
on a board. A missing chip answers like an unacknowledged address: ``EREMOTEIO`` on the BeagleBone's
``i2c-omap``, ``ENXIO`` on adapters that follow the kernel's fault-code guide.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import itertools
import os
import sys
import threading
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import smbus2
import smbus2.smbus2 as _smbus2_module

# ioctl requests, uapi/linux/i2c-dev.h
I2C_RETRIES = 0x0701
I2C_TIMEOUT = 0x0702
I2C_SLAVE = 0x0703
I2C_FUNCS = 0x0705
I2C_SLAVE_FORCE = 0x0706
I2C_TENBIT = 0x0704
I2C_RDWR = 0x0707
I2C_PEC = 0x0708
I2C_SMBUS = 0x0720
I2C_RDWR_IOCTL_MAX_MSGS = 42
I2C_MSG_MAX_LEN = 8192  # i2c-dev refuses longer messages

# uapi/linux/i2c.h
I2C_SMBUS_READ = 1
I2C_SMBUS_WRITE = 0
I2C_SMBUS_QUICK = 0
I2C_SMBUS_BYTE = 1
I2C_SMBUS_BYTE_DATA = 2
I2C_SMBUS_WORD_DATA = 3
I2C_SMBUS_PROC_CALL = 4
I2C_SMBUS_BLOCK_DATA = 5
I2C_SMBUS_I2C_BLOCK_BROKEN = 6
I2C_SMBUS_BLOCK_PROC_CALL = 7
I2C_SMBUS_I2C_BLOCK_DATA = 8
I2C_SMBUS_BLOCK_MAX = 32
SMBUS_DATA_SIZE = I2C_SMBUS_BLOCK_MAX + 2  # sizeof(union i2c_smbus_data)

I2C_M_RD = 0x0001
I2C_M_TEN = 0x0010
I2C_M_RECV_LEN = 0x0400
I2C_M_IGNORE_NAK = 0x1000
I2C_CLIENT_PEC = 0x0004

I2C_FUNC_I2C = 0x00000001
I2C_FUNC_SMBUS_PEC = 0x00000008
I2C_FUNC_SMBUS_EMUL = 0x0EFF0008  # what a plain I2C master offers through the kernel's SMBus emulation
I2C_FUNC_SMBUS_READ_BLOCK_DATA = 0x01000000
I2C_FUNC_SMBUS_BLOCK_PROC_CALL = 0x00008000
DEFAULT_FUNCTIONALITY = (I2C_FUNC_I2C | I2C_FUNC_SMBUS_EMUL | I2C_FUNC_SMBUS_READ_BLOCK_DATA
                         | I2C_FUNC_SMBUS_BLOCK_PROC_CALL)


# The kernel's view of the ioctl arguments: raw pointers, decoded from whatever object the caller passed.
class _SmbusIoctlData(ctypes.Structure):
    _fields_ = [("read_write", ctypes.c_uint8), ("command", ctypes.c_uint8), ("size", ctypes.c_uint32),
                ("data", ctypes.c_void_p)]


class _RdwrIoctlData(ctypes.Structure):
    _fields_ = [("msgs", ctypes.c_void_p), ("nmsgs", ctypes.c_uint32)]


class _I2cMsg(ctypes.Structure):
    _fields_ = [("addr", ctypes.c_uint16), ("flags", ctypes.c_uint16), ("len", ctypes.c_uint16),
                ("buf", ctypes.c_void_p)]


class I2cChip(Protocol):
    """What the adapter needs from a chip: one call per I2C message, and what happens at power-up."""

    def i2c_write(self, data: bytes) -> None:
        """A write message (after the address byte) the chip acknowledged."""
        ...

    def i2c_read(self, n: int) -> bytes:
        """The ``n`` bytes the chip clocks out for a read message."""
        ...

    def power_on_reset(self) -> None:
        """Supply came back: registers to their reset values."""
        ...


class RegisterChip(ABC):
    """A chip whose bus protocol is a register pointer, as for nearly every I2C sensor.

    A write message's first byte sets the pointer and any further bytes are written from there; a read
    message clocks out bytes from the pointer. The pointer moves on after each byte (``next_register``
    says where: a FIFO port, for one, does not move), so a burst read is one message.
    """

    def __init__(self) -> None:
        self.pointer = 0

    def i2c_write(self, data: bytes) -> None:
        if not data:
            return
        reg = data[0]
        if len(data) > 1:
            self.write(reg, bytes(data[1:]))
        self.pointer = self.next_register(reg, len(data) - 1)

    def i2c_read(self, n: int) -> bytes:
        if n <= 0:
            return b""
        reg = self.pointer
        out = self.read(reg, n)
        if len(out) != n:
            raise AssertionError(f"{type(self).__name__}.read returned {len(out)} bytes for {n}")
        self.pointer = self.next_register(reg, n)
        return out

    def next_register(self, reg: int, n: int) -> int:
        """Where the pointer stands after ``n`` bytes from ``reg``."""
        return (reg + n) & 0xFF

    @abstractmethod
    def read(self, reg: int, n: int) -> bytes:
        """``n`` bytes of one read transfer starting at ``reg``."""

    @abstractmethod
    def write(self, reg: int, data: bytes) -> None:
        """The bytes of one write transfer starting at ``reg``."""

    @abstractmethod
    def power_on_reset(self) -> None:
        ...


@dataclass
class I2cMessage:
    """One ``struct i2c_msg`` as the adapter sees it: reads carry their buffer after the transfer."""

    addr: int
    flags: int
    length: int
    data: bytes = b""

    @property
    def is_read(self) -> bool:
        return bool(self.flags & I2C_M_RD)


@dataclass
class _Client:
    """Per open descriptor, like the kernel's ``struct i2c_client`` behind each /dev/i2c-N file."""

    adapter: SimI2cAdapter
    addr: int = 0
    flags: int = 0  # I2C_M_TEN | I2C_CLIENT_PEC
    retries: int = 0
    timeout_10ms: int = 100


def _oserror(code: int) -> OSError:
    return OSError(code, os.strerror(code))


def _smbus_pec(crc: int, data: Iterable[int]) -> int:
    """CRC-8 (x^8 + x^2 + x + 1) as ``i2c_smbus_pec`` computes it."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def _msg_pec(crc: int, msg: I2cMessage, payload: bytes) -> int:
    address_byte = ((msg.addr << 1) | (1 if msg.is_read else 0)) & 0xFF
    return _smbus_pec(_smbus_pec(crc, (address_byte,)), payload)


_adapter_numbers = itertools.count(1)


class SimI2cAdapter:
    """A simulated I2C controller with chip models at 7-bit addresses, opened through ``smbus2``.

    The adapter serialises transfers like the kernel's bus lock, so several descriptors (one per driver,
    as on a board) may share it from several threads. Faults are injected here, at the bus.
    """

    def __init__(self, chips: Mapping[int, I2cChip] | None = None, *, path: str | None = None,
                 nack_errno: int = errno.EREMOTEIO, functionality: int = DEFAULT_FUNCTIONALITY) -> None:
        self.path = path if path is not None else f"/dev/i2c-sim{next(_adapter_numbers)}"
        self.nack_errno = nack_errno
        self.functionality = functionality
        self.transfer_count = 0
        self.trace: list[tuple[int, str, bytes]] | None = None  # set to [] to record (addr, "R"/"W", bytes)
        self._lock = threading.RLock()
        self._chips: dict[int, I2cChip] = {}
        self._unplugged: set[int] = set()
        self._kernel_bound: set[int] = set()
        self._faults: list[int | None] = []  # per coming transfer: an errno, or None to pass
        for address, chip in (chips or {}).items():
            self.attach(address, chip)
        install()
        _registry.add_path(self)

    # ---- the hardware around the bus -------------------------------------------------------------
    def attach(self, address: int, chip: I2cChip) -> None:
        if not 0 <= address <= 0x7F:
            raise ValueError(f"I2C address 0x{address:x} is not a 7-bit address")
        with self._lock:
            if address in self._chips:
                raise ValueError(f"two chips at I2C address 0x{address:02x}")
            self._chips[address] = chip

    def chip(self, address: int) -> I2cChip:
        return self._chips[address]

    def unplug(self, address: int) -> None:
        """The chip stops answering (loose wire, lost supply): transfers to it are not acknowledged."""
        with self._lock:
            if address not in self._chips:
                raise KeyError(f"no chip was ever at I2C address 0x{address:02x}")
            self._unplugged.add(address)

    def replug(self, address: int) -> None:
        """The chip answers again, after a power-on reset, as a chip whose supply came back does."""
        with self._lock:
            self._unplugged.discard(address)
            self._chips[address].power_on_reset()

    def fail_next(self, count: int = 1, code: int = errno.EIO, after: int = 0) -> None:
        """After ``after`` good transfers, ``count`` transfers fail with ``code`` and reach no chip."""
        with self._lock:
            self._faults.extend([None] * after + [code] * count)

    def bind_kernel_driver(self, address: int) -> None:
        """A kernel driver owns ``address``: I2C_SLAVE answers EBUSY, I2C_SLAVE_FORCE still works."""
        self._kernel_bound.add(address)

    # ---- i2c_transfer ----------------------------------------------------------------------------
    def transfer(self, msgs: list[I2cMessage]) -> int:
        """Run messages with repeated starts, as ``i2c_transfer``: returns how many, or raises OSError."""
        with self._lock:
            fault = self._faults.pop(0) if self._faults else None
            if fault is not None:
                raise _oserror(fault)
            for msg in msgs:
                chip = self._chips.get(msg.addr)
                if msg.flags & I2C_M_TEN or chip is None or msg.addr in self._unplugged:
                    if msg.flags & I2C_M_IGNORE_NAK:
                        msg.data = b"\xff" * msg.length if msg.is_read else msg.data
                        continue
                    raise _oserror(self.nack_errno)
                if not msg.is_read:
                    chip.i2c_write(msg.data)
                elif msg.flags & I2C_M_RECV_LEN:
                    msg.data = self._read_block(chip, msg)
                else:
                    msg.data = chip.i2c_read(msg.length)
                if self.trace is not None:
                    self.trace.append((msg.addr, "R" if msg.is_read else "W", bytes(msg.data)))
            self.transfer_count += 1
            return len(msgs)

    @staticmethod
    def _read_block(chip: I2cChip, msg: I2cMessage) -> bytes:
        """A read whose first byte is its own length (SMBus block read): ``msg.length`` extra bytes."""
        count = chip.i2c_read(1)[0]
        if count == 0 or count > I2C_SMBUS_BLOCK_MAX:
            raise _oserror(errno.EPROTO)
        rest = chip.i2c_read(count + msg.length - 1)
        msg.length += count
        return bytes((count,)) + rest

    # ---- i2c_smbus_xfer, emulated with I2C messages --------------------------------------------
    def smbus_xfer(self, addr: int, flags: int, read_write: int, command: int, size: int,
                   data: bytearray) -> None:
        """``i2c_smbus_xfer_emulated``: ``data`` is the 34-byte union, updated in place for reads."""
        flags &= I2C_M_TEN | I2C_CLIENT_PEC
        msg_flags = flags & I2C_M_TEN
        out = bytes((command,))
        wr = I2cMessage(addr, msg_flags, 1, out)
        rd = I2cMessage(addr, msg_flags | I2C_M_RD, 0)
        nmsgs = 2 if read_write == I2C_SMBUS_READ else 1
        if size == I2C_SMBUS_QUICK:
            wr = I2cMessage(addr, msg_flags | (I2C_M_RD if read_write == I2C_SMBUS_READ else 0), 0)
            nmsgs = 1
        elif size == I2C_SMBUS_BYTE:
            if read_write == I2C_SMBUS_READ:
                wr = I2cMessage(addr, msg_flags | I2C_M_RD, 1)
                nmsgs = 1
        elif size == I2C_SMBUS_BYTE_DATA:
            if read_write == I2C_SMBUS_READ:
                rd.length = 1
            else:
                wr.data = out + bytes((data[0],))
        elif size == I2C_SMBUS_WORD_DATA:
            if read_write == I2C_SMBUS_READ:
                rd.length = 2
            else:
                wr.data = out + bytes((data[0], data[1]))
        elif size == I2C_SMBUS_PROC_CALL:
            nmsgs, read_write = 2, I2C_SMBUS_READ
            wr.data = out + bytes((data[0], data[1]))
            rd.length = 2
        elif size == I2C_SMBUS_BLOCK_DATA:
            if read_write == I2C_SMBUS_READ:
                rd.flags |= I2C_M_RECV_LEN
                rd.length = 1
            else:
                if data[0] > I2C_SMBUS_BLOCK_MAX:
                    raise _oserror(errno.EINVAL)
                wr.data = out + bytes(data[: data[0] + 1])
        elif size == I2C_SMBUS_BLOCK_PROC_CALL:
            nmsgs, read_write = 2, I2C_SMBUS_READ
            if data[0] > I2C_SMBUS_BLOCK_MAX:
                raise _oserror(errno.EINVAL)
            wr.data = out + bytes(data[: data[0] + 1])
            rd.flags |= I2C_M_RECV_LEN
            rd.length = 1
        elif size == I2C_SMBUS_I2C_BLOCK_DATA:
            if data[0] > I2C_SMBUS_BLOCK_MAX:
                raise _oserror(errno.EINVAL)
            if read_write == I2C_SMBUS_READ:
                rd.length = data[0]
            else:
                wr.data = out + bytes(data[1: data[0] + 1])
        else:
            raise _oserror(errno.EOPNOTSUPP)
        if not wr.is_read:
            wr.length = len(wr.data)
        msgs = [wr, rd][:nmsgs]

        wants_pec = bool(flags & I2C_CLIENT_PEC) and size not in (I2C_SMBUS_QUICK, I2C_SMBUS_I2C_BLOCK_DATA)
        partial_pec = 0
        if wants_pec:
            if not msgs[0].is_read:
                if nmsgs == 1:
                    msgs[0].data += bytes((_msg_pec(0, msgs[0], msgs[0].data),))
                    msgs[0].length += 1
                else:
                    partial_pec = _msg_pec(0, msgs[0], msgs[0].data)
            if msgs[-1].is_read:
                msgs[-1].length += 1

        self.transfer(msgs)

        last = msgs[-1]
        if wants_pec and last.is_read:
            received = last.data[-1]
            last.data = last.data[:-1]
            last.length -= 1
            if received != _msg_pec(partial_pec, last, last.data):
                raise _oserror(errno.EBADMSG)
        if read_write != I2C_SMBUS_READ:
            return
        if size == I2C_SMBUS_BYTE:
            data[0] = msgs[0].data[0]
        elif size == I2C_SMBUS_BYTE_DATA:
            data[0] = rd.data[0]
        elif size in (I2C_SMBUS_WORD_DATA, I2C_SMBUS_PROC_CALL):
            data[0], data[1] = rd.data[0], rd.data[1]
        elif size == I2C_SMBUS_I2C_BLOCK_DATA:
            data[1: 1 + data[0]] = rd.data[: data[0]]
        elif size in (I2C_SMBUS_BLOCK_DATA, I2C_SMBUS_BLOCK_PROC_CALL):
            data[: rd.data[0] + 1] = rd.data[: rd.data[0] + 1]

    # ---- i2cdev_ioctl ----------------------------------------------------------------------------
    def ioctl(self, client: _Client, request: int, arg: Any, mutate_flag: bool) -> Any:
        if request in (I2C_SLAVE, I2C_SLAVE_FORCE):
            address = _int_arg(arg)
            if address > (0x3FF if client.flags & I2C_M_TEN else 0x7F):
                raise _oserror(errno.EINVAL)
            if request == I2C_SLAVE and address in self._kernel_bound:
                raise _oserror(errno.EBUSY)
            client.addr = address
            return 0
        if request == I2C_TENBIT:
            client.flags = client.flags | I2C_M_TEN if _int_arg(arg) else client.flags & ~I2C_M_TEN
            return 0
        if request == I2C_PEC:
            client.flags = client.flags | I2C_CLIENT_PEC if _int_arg(arg) else client.flags & ~I2C_CLIENT_PEC
            return 0
        if request == I2C_RETRIES:
            client.retries = _int_arg(arg)
            return 0
        if request == I2C_TIMEOUT:
            client.timeout_10ms = _int_arg(arg)
            return 0
        if request == I2C_FUNCS:
            # put_user of an unsigned long; fcntl.ioctl copies back only as many bytes as the caller gave.
            value = self.functionality.to_bytes(ctypes.sizeof(ctypes.c_ulong), sys.byteorder)
            return _write_arg(arg, value, mutate_flag)
        if request == I2C_SMBUS:
            return self._ioctl_smbus(client, arg)
        if request == I2C_RDWR:
            return self._ioctl_rdwr(client, arg)
        raise _oserror(errno.ENOTTY)

    def _ioctl_smbus(self, client: _Client, arg: Any) -> Any:
        req = _SmbusIoctlData.from_buffer_copy(_read_arg(arg, ctypes.sizeof(_SmbusIoctlData)))
        size, read_write = req.size, req.read_write
        if size not in range(I2C_SMBUS_QUICK, I2C_SMBUS_I2C_BLOCK_DATA + 1):
            raise _oserror(errno.EINVAL)
        if read_write not in (I2C_SMBUS_READ, I2C_SMBUS_WRITE):
            raise _oserror(errno.EINVAL)
        if size == I2C_SMBUS_QUICK or (size == I2C_SMBUS_BYTE and read_write == I2C_SMBUS_WRITE):
            self.smbus_xfer(client.addr, client.flags, read_write, req.command, size, bytearray(1))
            return _ioctl_return(arg)
        if not req.data:
            raise _oserror(errno.EINVAL)
        if size in (I2C_SMBUS_BYTE_DATA, I2C_SMBUS_BYTE):
            datasize = 1
        elif size in (I2C_SMBUS_WORD_DATA, I2C_SMBUS_PROC_CALL):
            datasize = 2
        else:
            datasize = SMBUS_DATA_SIZE
        temp = bytearray(SMBUS_DATA_SIZE)
        if (size in (I2C_SMBUS_PROC_CALL, I2C_SMBUS_BLOCK_PROC_CALL, I2C_SMBUS_I2C_BLOCK_DATA)
                or read_write == I2C_SMBUS_WRITE):
            temp[:datasize] = ctypes.string_at(req.data, datasize)
        if size == I2C_SMBUS_I2C_BLOCK_BROKEN:
            size = I2C_SMBUS_I2C_BLOCK_DATA
            if read_write == I2C_SMBUS_READ:
                temp[0] = I2C_SMBUS_BLOCK_MAX
        self.smbus_xfer(client.addr, client.flags, read_write, req.command, size, temp)
        if size in (I2C_SMBUS_PROC_CALL, I2C_SMBUS_BLOCK_PROC_CALL) or read_write == I2C_SMBUS_READ:
            ctypes.memmove(req.data, bytes(temp[:datasize]), datasize)
        return _ioctl_return(arg)

    def _ioctl_rdwr(self, client: _Client, arg: Any) -> Any:
        if not self.functionality & I2C_FUNC_I2C:  # an SMBus-only controller has no master_xfer: the kernel refuses
            raise _oserror(errno.EOPNOTSUPP)
        req = _RdwrIoctlData.from_buffer_copy(_read_arg(arg, ctypes.sizeof(_RdwrIoctlData)))
        if not req.msgs or req.nmsgs == 0 or req.nmsgs > I2C_RDWR_IOCTL_MAX_MSGS:
            raise _oserror(errno.EINVAL)
        raw = (_I2cMsg * req.nmsgs).from_buffer_copy(
            ctypes.string_at(req.msgs, ctypes.sizeof(_I2cMsg) * req.nmsgs))
        msgs: list[I2cMessage] = []
        for m in raw:
            if m.len > I2C_MSG_MAX_LEN or (m.len and not m.buf):
                raise _oserror(errno.EINVAL)
            length = m.len
            if m.flags & I2C_M_RECV_LEN:
                first = ctypes.string_at(m.buf, 1)[0] if m.len else 0
                if not m.flags & I2C_M_RD or not m.len or first < 1 or m.len < first + I2C_SMBUS_BLOCK_MAX:
                    raise _oserror(errno.EINVAL)
                length = first
            data = b"" if m.flags & I2C_M_RD else ctypes.string_at(m.buf, m.len)
            msgs.append(I2cMessage(m.addr, m.flags, length, data))
        count = self.transfer(msgs)
        for m, msg in zip(raw, msgs, strict=True):
            if msg.is_read and msg.length:
                ctypes.memmove(m.buf, bytes(msg.data[: msg.length]), msg.length)
        return count


class SimI2cBus(smbus2.SMBus):
    """An ``smbus2.SMBus`` opened on a simulated adapter: smbus2's own ``open`` and transfers run."""

    def __init__(self, adapter: SimI2cAdapter | Mapping[int, I2cChip], force: bool = False) -> None:
        self.adapter = adapter if isinstance(adapter, SimI2cAdapter) else SimI2cAdapter(adapter)
        super().__init__(self.adapter.path, force)


# ---- the process-wide replacement of smbus2's kernel contact ------------------------------------------
def _int_arg(arg: Any) -> int:
    if isinstance(arg, int):
        return arg
    raise _oserror(errno.EINVAL)  # the kernel would take a user-space pointer as the number


def _read_arg(arg: Any, size: int) -> bytes:
    """``copy_from_user`` of the ioctl's argument structure."""
    if isinstance(arg, ctypes._SimpleCData | ctypes.Structure | ctypes.Union | ctypes.Array):
        raw = ctypes.string_at(ctypes.addressof(arg), ctypes.sizeof(arg))
    elif isinstance(arg, int):
        raise _oserror(errno.EFAULT)
    else:
        raw = memoryview(arg).tobytes()
    if len(raw) < size:
        raise _oserror(errno.EFAULT)
    return raw[:size]


def _write_arg(arg: Any, value: bytes, mutate_flag: bool) -> Any:
    """``put_user`` into the argument buffer, with ``fcntl.ioctl``'s copy-back rules."""
    if isinstance(arg, int):
        raise _oserror(errno.EFAULT)
    if isinstance(arg, bytes | str):
        raw = arg.encode() if isinstance(arg, str) else arg
        return value[: len(raw)] + raw[len(value):]
    if isinstance(arg, ctypes._SimpleCData | ctypes.Structure | ctypes.Union | ctypes.Array):
        size = ctypes.sizeof(arg)
        if not mutate_flag:
            return value[:size] + ctypes.string_at(ctypes.addressof(arg), size)[len(value):]
        ctypes.memmove(ctypes.addressof(arg), value, min(size, len(value)))
        return 0
    view = memoryview(arg).cast("B")
    if not mutate_flag:
        return value[: len(view)] + view.tobytes()[len(value):]
    n = min(len(view), len(value))
    view[:n] = value[:n]
    return 0


def _ioctl_return(arg: Any) -> Any:
    return bytes(arg) if isinstance(arg, bytes) else 0


class _Registry:
    """Which descriptors and paths belong to simulated adapters; everything else goes to the kernel."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._paths: weakref.WeakValueDictionary[str, SimI2cAdapter] = weakref.WeakValueDictionary()
        self._clients: dict[int, _Client] = {}
        self.real_ioctl: Callable[..., Any] = fcntl.ioctl
        self.real_os = os

    def add_path(self, adapter: SimI2cAdapter) -> None:
        with self._lock:
            other = self._paths.get(adapter.path)
            if other is not None and other is not adapter:
                raise ValueError(f"{adapter.path} is already a simulated I2C adapter")
            self._paths[adapter.path] = adapter

    def open(self, path: Any, flags: int, mode: int = 0o777, *args: Any, **kwargs: Any) -> int:
        adapter = self._paths.get(os.fspath(path)) if isinstance(path, str | os.PathLike) else None
        if adapter is None:
            return self.real_os.open(path, flags, mode, *args, **kwargs)
        fd = self.real_os.open(os.devnull, os.O_RDWR)
        with self._lock:
            self._clients[fd] = _Client(adapter)
        return fd

    def close(self, fd: int) -> None:
        with self._lock:
            self._clients.pop(fd, None)
        self.real_os.close(fd)

    def ioctl(self, fd: Any, request: int, arg: Any = 0, mutate_flag: bool = True) -> Any:
        fdn = fd if isinstance(fd, int) else fd.fileno()
        client = self._clients.get(fdn)
        if client is None:
            return self.real_ioctl(fd, request, arg, mutate_flag)
        return client.adapter.ioctl(client, request, arg, mutate_flag)


class _OsForSmbus2:
    """The ``os`` module as smbus2 sees it: ``open``/``close`` know simulated adapters."""

    def __init__(self, registry: _Registry) -> None:
        self._registry = registry

    def open(self, path: Any, flags: int, mode: int = 0o777, *args: Any, **kwargs: Any) -> int:
        return self._registry.open(path, flags, mode, *args, **kwargs)

    def close(self, fd: int) -> None:
        self._registry.close(fd)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._registry.real_os, name)


_registry = _Registry()
_install_lock = threading.Lock()


def install() -> None:
    """Put the simulated kernel under smbus2 (idempotent; adapters call it themselves)."""
    with _install_lock:
        if _smbus2_module.ioctl != _registry.ioctl:
            _smbus2_module.ioctl = _registry.ioctl
        if not isinstance(_smbus2_module.os, _OsForSmbus2):
            _smbus2_module.os = _OsForSmbus2(_registry)
