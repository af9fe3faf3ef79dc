"""The I2C seam: the real smbus2 code on top, a simulated i2c-dev adapter below its ioctl."""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import pty
import struct
import termios
import threading

import pytest
import smbus2
import smbus2.smbus2 as smbus2_module
from smbus2 import i2c_msg

from sensors.sim import i2c as sim_i2c
from sensors.sim.i2c import RegisterChip, SimI2cAdapter, SimI2cBus


class RamChip(RegisterChip):
    """256 bytes behind a register pointer, like a 24C02 EEPROM without its write delay."""

    def __init__(self) -> None:
        super().__init__()
        self.mem = bytearray(256)
        self.resets = 0

    def read(self, reg: int, n: int) -> bytes:
        return bytes(self.mem[(reg + i) & 0xFF] for i in range(n))

    def write(self, reg: int, data: bytes) -> None:
        for i, value in enumerate(data):
            self.mem[(reg + i) & 0xFF] = value

    def power_on_reset(self) -> None:
        self.mem[:] = bytes(256)
        self.pointer = 0
        self.resets += 1


def crc8_smbus(data: bytes) -> int:
    """CRC-8 with polynomial 0x07, written independently of the seam's table-free loop."""
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    crc = 0
    for b in data:
        crc = table[crc ^ b]
    return crc


@pytest.fixture
def ram() -> RamChip:
    return RamChip()


@pytest.fixture
def bus(ram: RamChip):
    with SimI2cBus({0x50: ram}) as b:
        yield b


def test_smbus2_kernel_contact_is_replaced_once() -> None:
    SimI2cAdapter()
    SimI2cAdapter()
    assert smbus2_module.ioctl == sim_i2c._registry.ioctl
    assert sim_i2c._registry.real_ioctl is fcntl.ioctl
    assert isinstance(smbus2_module.os, sim_i2c._OsForSmbus2)


def test_funcs_reported_through_smbus2_open(bus: SimI2cBus) -> None:
    assert bus.funcs == bus.adapter.functionality
    assert bus.funcs & smbus2.I2cFunc.SMBUS_I2C_BLOCK
    assert bus.funcs & smbus2.I2cFunc.SMBUS_PEC


@pytest.mark.parametrize("ctype", [ctypes.c_uint32, ctypes.c_ulong])
def test_funcs_into_either_width(bus: SimI2cBus, ctype: type) -> None:
    # smbus2 0.4.2 passes a c_uint32, 0.6.1 a c_ulong: the kernel's unsigned long must fit both.
    value = ctype(0)
    assert smbus2_module.ioctl(bus.fd, sim_i2c.I2C_FUNCS, value) == 0
    assert value.value == bus.adapter.functionality


def test_funcs_into_immutable_bytes_returns_copy(bus: SimI2cBus) -> None:
    out = smbus2_module.ioctl(bus.fd, sim_i2c.I2C_FUNCS, bytes(8))
    assert int.from_bytes(out, "little") == bus.adapter.functionality


def test_byte_data_round_trip(bus: SimI2cBus, ram: RamChip) -> None:
    bus.write_byte_data(0x50, 0x10, 0xA5)
    assert ram.mem[0x10] == 0xA5
    assert bus.read_byte_data(0x50, 0x10) == 0xA5


def test_word_data_is_little_endian_on_the_wire(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[0x20:0x22] = b"\x12\x34"
    assert bus.read_word_data(0x50, 0x20) == 0x3412
    bus.write_word_data(0x50, 0x30, 0xABCD)
    assert ram.mem[0x30:0x32] == b"\xcd\xab"


def test_i2c_block_read_write_auto_increment(bus: SimI2cBus, ram: RamChip) -> None:
    bus.write_i2c_block_data(0x50, 0x40, list(range(1, 33)))
    assert ram.mem[0x40:0x60] == bytes(range(1, 33))
    assert bus.read_i2c_block_data(0x50, 0x41, 5) == [2, 3, 4, 5, 6]
    assert ram.pointer == 0x46


def test_send_byte_sets_pointer_and_receive_byte_reads_on(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[0x80:0x83] = b"\x07\x08\x09"
    bus.write_byte(0x50, 0x80)
    assert [bus.read_byte(0x50) for _ in range(3)] == [7, 8, 9]


def test_quick_write_acks_present_chip_only(bus: SimI2cBus) -> None:
    bus.write_quick(0x50)
    with pytest.raises(OSError) as exc:
        bus.write_quick(0x51)
    assert exc.value.errno == errno.EREMOTEIO


def test_process_call(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[0x62:0x64] = b"\x55\x66"
    # The word goes to 0x60..0x61, the reply comes from where the pointer then stands.
    assert bus.process_call(0x50, 0x60, 0x2211) == 0x6655
    assert ram.mem[0x60:0x62] == b"\x11\x22"


def test_smbus_block_read_uses_first_byte_as_length(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[0x70:0x74] = b"\x03\xaa\xbb\xcc"
    assert bus.read_block_data(0x50, 0x70) == [0xAA, 0xBB, 0xCC]
    ram.mem[0x70] = 0x40  # more than SMBus allows
    with pytest.raises(OSError) as exc:
        bus.read_block_data(0x50, 0x70)
    assert exc.value.errno == errno.EPROTO


def test_smbus_block_write_sends_length_first(bus: SimI2cBus, ram: RamChip) -> None:
    bus.write_block_data(0x50, 0x90, [1, 2, 3])
    assert ram.mem[0x90:0x94] == b"\x03\x01\x02\x03"


def test_i2c_rdwr_combined_transfer(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[0xA0:0xA4] = b"\xde\xad\xbe\xef"
    write, read = i2c_msg.write(0x50, [0xA0]), i2c_msg.read(0x50, 4)
    bus.i2c_rdwr(write, read)
    assert bytes(read) == b"\xde\xad\xbe\xef"
    bus.i2c_rdwr(i2c_msg.write(0x50, [0xB0, 9, 8, 7]))
    assert ram.mem[0xB0:0xB3] == b"\x09\x08\x07"


def test_i2c_rdwr_limits(bus: SimI2cBus) -> None:
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(*[i2c_msg.write(0x50, [0])] * (sim_i2c.I2C_RDWR_IOCTL_MAX_MSGS + 1))
    assert exc.value.errno == errno.EINVAL
    with pytest.raises(OSError) as exc:
        bus.i2c_rdwr(i2c_msg.read(0x50, sim_i2c.I2C_MSG_MAX_LEN + 1))
    assert exc.value.errno == errno.EINVAL


def test_pec_write_appends_crc_the_chip_sees(bus: SimI2cBus, ram: RamChip) -> None:
    bus.pec = 1
    bus.write_byte_data(0x50, 0x10, 0x42)
    # A chip without PEC takes the PEC byte as data for the next register.
    assert ram.mem[0x11] == crc8_smbus(bytes((0x50 << 1, 0x10, 0x42)))


def test_pec_read_checked(bus: SimI2cBus, ram: RamChip) -> None:
    bus.pec = 1
    ram.mem[0x20] = 0x99
    ram.mem[0x21] = crc8_smbus(bytes((0x50 << 1, 0x20, (0x50 << 1) | 1, 0x99)))
    assert bus.read_byte_data(0x50, 0x20) == 0x99
    ram.mem[0x21] ^= 0xFF
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x50, 0x20)
    assert exc.value.errno == errno.EBADMSG


@pytest.mark.parametrize("code", [errno.EREMOTEIO, errno.ENXIO])
def test_absent_chip_is_not_acknowledged(code: int) -> None:
    with SimI2cBus(SimI2cAdapter({}, nack_errno=code)) as b, pytest.raises(OSError) as exc:
        b.read_byte_data(0x68, 0x75)
    assert exc.value.errno == code


def test_injected_eio_then_recovery(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[5] = 55
    bus.adapter.fail_next(2)
    for _ in range(2):
        with pytest.raises(OSError) as exc:
            bus.read_byte_data(0x50, 5)
        assert exc.value.errno == errno.EIO
    assert bus.read_byte_data(0x50, 5) == 55


def test_unplug_and_replug_with_power_on_reset(bus: SimI2cBus, ram: RamChip) -> None:
    ram.mem[1] = 1
    bus.adapter.unplug(0x50)
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x50, 1)
    assert exc.value.errno == errno.EREMOTEIO
    bus.adapter.replug(0x50)
    assert ram.resets == 1
    assert bus.read_byte_data(0x50, 1) == 0


def test_address_owned_by_kernel_driver_needs_force(bus: SimI2cBus, ram: RamChip) -> None:
    bus.adapter.bind_kernel_driver(0x50)
    ram.mem[0] = 3
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x50, 0)
    assert exc.value.errno == errno.EBUSY
    assert bus.read_byte_data(0x50, 0, force=True) == 3


def test_address_beyond_7_bits_is_invalid(bus: SimI2cBus) -> None:
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x80, 0)
    assert exc.value.errno == errno.EINVAL


def test_unknown_request_is_not_a_tty_ioctl(bus: SimI2cBus) -> None:
    with pytest.raises(OSError) as exc:
        smbus2_module.ioctl(bus.fd, 0x0799, 0)
    assert exc.value.errno == errno.ENOTTY


def test_real_descriptors_reach_the_kernel() -> None:
    SimI2cAdapter()
    master, slave = pty.openpty()
    try:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
        out = smbus2_module.ioctl(slave, termios.TIOCGWINSZ, bytes(8))
        assert struct.unpack("HHHH", out)[:2] == (24, 80)
    finally:
        os.close(master)
        os.close(slave)
    with pytest.raises(FileNotFoundError):
        smbus2.SMBus("/dev/i2c-does-not-exist-here")


def test_each_descriptor_keeps_its_own_address(ram: RamChip) -> None:
    other = RamChip()
    adapter = SimI2cAdapter({0x50: ram, 0x51: other})
    ram.mem[0], other.mem[0] = 1, 2
    with smbus2.SMBus(adapter.path) as a, smbus2.SMBus(adapter.path) as b:
        assert (a.read_byte_data(0x50, 0), b.read_byte_data(0x51, 0)) == (1, 2)
        # No I2C_SLAVE between these: each open file remembers its client address, as in i2c-dev.
        request = _byte_data_read(0)
        assert smbus2_module.ioctl(a.fd, sim_i2c.I2C_SMBUS, request) == 0
        assert request.data.contents.byte == 1


def _byte_data_read(register: int) -> smbus2_module.i2c_smbus_ioctl_data:
    return smbus2_module.i2c_smbus_ioctl_data.create(read_write=1, command=register, size=2)


def test_closing_releases_the_descriptor(ram: RamChip) -> None:
    b = SimI2cBus({0x50: ram})
    fd = b.fd
    b.close()
    assert fd not in sim_i2c._registry._clients
    with pytest.raises(OSError):
        os.fstat(fd)


def test_transfers_are_serialised_between_threads(ram: RamChip) -> None:
    adapter = SimI2cAdapter({0x50: ram})
    errors: list[BaseException] = []

    def hammer(reg: int) -> None:
        try:
            with smbus2.SMBus(adapter.path) as b:
                for i in range(300):
                    b.write_i2c_block_data(0x50, reg, [i & 0xFF] * 8)
                    got = b.read_i2c_block_data(0x50, reg, 8)
                    assert got == [i & 0xFF] * 8
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=hammer, args=(reg,)) for reg in (0x00, 0x40)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert adapter.transfer_count == 4 * 300


def test_trace_records_messages(bus: SimI2cBus, ram: RamChip) -> None:
    bus.adapter.trace = []
    ram.mem[3] = 0x33
    bus.read_byte_data(0x50, 3)
    assert bus.adapter.trace == [(0x50, "W", b"\x03"), (0x50, "R", b"\x33")]


def test_fault_after_some_good_transfers(bus: SimI2cBus, ram: RamChip) -> None:
    bus.adapter.fail_next(1, code=errno.ETIMEDOUT, after=2)
    bus.read_byte_data(0x50, 0)
    bus.read_byte_data(0x50, 0)
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x50, 0)
    assert exc.value.errno == errno.ETIMEDOUT
    bus.read_byte_data(0x50, 0)
