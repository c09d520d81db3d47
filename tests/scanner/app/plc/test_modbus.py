from __future__ import annotations

import struct

import pytest

from scanner.app.plc.modbus import (
    ExceptionCode,
    FrameBuffer,
    FramingError,
    ModbusException,
    encode_adu,
    handle_pdu,
)


class DictBank:
    """Ten registers 0-9, refusing everything else with exception 2."""

    def __init__(self) -> None:
        self.regs = list(range(10))

    def read_registers(self, address: int, count: int) -> list[int]:
        if address + count > 10:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        return self.regs[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> None:
        if address + len(values) > 10:
            raise ModbusException(ExceptionCode.ILLEGAL_DATA_ADDRESS)
        self.regs[address : address + len(values)] = values


def test_frame_buffer_splits_pipelined_and_partial_frames_in_order():
    stream = b"".join(encode_adu(t, 1, bytes((3, 0, t, 0, 1))) for t in range(1, 4))
    buf = FrameBuffer()
    frames = list(buf.feed(stream[:5]))  # less than a header
    assert frames == []
    frames = list(buf.feed(stream[5:15]))  # first frame (12 bytes) plus a bit
    assert [f.transaction_id for f in frames] == [1]
    frames = list(buf.feed(stream[15:]))
    assert [f.transaction_id for f in frames] == [2, 3]
    assert frames[1].pdu == bytes((3, 0, 3, 0, 1))
    assert len(buf) == 0


@pytest.mark.parametrize(
    ("header", "message"),
    [
        (struct.pack(">HHHB", 1, 1, 6, 1), "protocol id 0"),
        (struct.pack(">HHHB", 1, 0, 255, 1), "length 2..254"),
        (struct.pack(">HHHB", 1, 0, 1, 1), "length 2..254"),
    ],
)
def test_frame_buffer_refuses_what_is_not_modbus_tcp(header: bytes, message: str):
    with pytest.raises(FramingError, match=message):
        list(FrameBuffer().feed(header + b"\x03\x00\x00\x00\x01"))


def test_read_and_write_multiple():
    bank = DictBank()
    assert handle_pdu(bank, bytes((3, 0, 2, 0, 3))) == bytes((3, 6, 0, 2, 0, 3, 0, 4))
    request = struct.pack(">BHHB2H", 16, 4, 2, 4, 500, 600)
    assert handle_pdu(bank, request) == struct.pack(">BHH", 16, 4, 2)
    assert bank.regs[4:6] == [500, 600]
    assert handle_pdu(bank, struct.pack(">BHH", 6, 9, 7)) == struct.pack(">BHH", 6, 9, 7)
    assert bank.regs[9] == 7


def test_read_write_multiple_writes_then_reads():
    bank = DictBank()
    request = struct.pack(">BHHHHB1H", 23, 0, 2, 1, 1, 2, 42)
    assert handle_pdu(bank, request) == bytes((23, 4, 0, 0, 0, 42))


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        (bytes((0x2B, 0x0E, 1, 0)), bytes((0xAB, 1))),  # unknown function: fc | 0x80, code 1
        (bytes((0x01, 0, 0, 0, 1)), bytes((0x81, 1))),  # coils are not served
        (bytes((3, 0, 8, 0, 5)), bytes((0x83, 2))),  # past the end
        (bytes((3, 0, 0, 0, 0)), bytes((0x83, 3))),  # count 0
        (bytes((3, 0, 0, 0, 126)), bytes((0x83, 3))),  # count over 125
        (bytes((3, 0, 0)), bytes((0x83, 3))),  # truncated
        (struct.pack(">BHHB1H", 16, 0, 2, 2, 1), bytes((0x90, 3))),  # byte count disagrees
        (struct.pack(">BHH", 6, 10, 1), bytes((0x86, 2))),
    ],
)
def test_bad_requests_get_the_right_exception(pdu: bytes, expected: bytes):
    bank = DictBank()
    before = list(bank.regs)
    assert handle_pdu(bank, pdu) == expected
    assert bank.regs == before
