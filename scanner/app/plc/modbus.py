"""Modbus TCP framing and the register functions, without any I/O.

Why our own framing rather than the pymodbus 3.16 server: measured against 3.16.1, two
requests sent back to back on one connection are answered wrongly (the first can be dropped
and the second executed twice), three requests in one TCP segment get one answer, an unknown
function code is answered with function code 0x80, a frame whose protocol id is not 0 wedges
the connection, and there is no connection limit, idle timeout or address filter. A PLC that
retries or pipelines would then run a job twice or lose an acknowledgement. The part of
Modbus TCP the service needs is small (MBAP header plus functions 3, 4, 6, 16 and 23), so it
lives here as plain functions that are easy to test byte for byte; pymodbus stays the
reference *client* in the tests and the benchmark, where it is a faithful second
implementation of the protocol.

The rules implemented (Modbus Application Protocol v1.1b3 and Modbus Messaging on TCP/IP):

* :class:`FrameBuffer` takes bytes as they arrive and yields complete frames in order; a
  protocol id other than 0, a length field outside 2..254 (unit id plus a PDU of at most
  253 bytes) raises :class:`FramingError` and the connection must be closed.
* :func:`handle_pdu` answers one request PDU with one response PDU: an unknown function with
  exception 1 (function code | 0x80, code 1), a bad quantity or malformed request with 3, an
  address outside the map with 2; a :class:`ModbusException` raised by the register bank
  (e.g. 6, server busy) becomes the exception response.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

__all__ = [
    "MAX_PDU",
    "ExceptionCode",
    "FrameBuffer",
    "FramingError",
    "MbapFrame",
    "ModbusException",
    "RegisterBank",
    "encode_adu",
    "exception_pdu",
    "handle_pdu",
]

#: Largest PDU of Modbus (function code plus 252 bytes of data).
MAX_PDU = 253
_MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id


class ExceptionCode(enum.IntEnum):
    """Modbus exception codes the service answers with."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_FAILURE = 0x04
    SERVER_BUSY = 0x06


class ModbusException(Exception):
    """Raised by a register bank to answer a request with a Modbus exception."""

    def __init__(self, code: ExceptionCode, reason: str = "") -> None:
        self.code = ExceptionCode(code)
        self.reason = reason
        super().__init__(
            f"exception {int(code)} ({self.code.name}){': ' + reason if reason else ''}"
        )


class FramingError(Exception):
    """The byte stream is not Modbus TCP; the connection must be closed."""


@dataclass(frozen=True)
class MbapFrame:
    """One request: MBAP transaction id and unit id, and the PDU (function code first)."""

    transaction_id: int
    unit_id: int
    pdu: bytes


class FrameBuffer:
    """Reassembles Modbus TCP frames from a byte stream (one buffer per connection)."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> Iterator[MbapFrame]:
        """Add ``data`` and yield every complete frame now buffered, in order.

        Raises
        ------
        FramingError
            A header with protocol id other than 0 or a length field outside 2..254.
        """
        self._buf += data
        while len(self._buf) >= 7:
            tid, proto, length, unit = _MBAP.unpack_from(self._buf)
            if proto != 0:
                raise FramingError(f"expected protocol id 0, got {proto}")
            if not 2 <= length <= MAX_PDU + 1:
                raise FramingError(f"expected MBAP length 2..{MAX_PDU + 1}, got {length}")
            end = 6 + length
            if len(self._buf) < end:
                return
            pdu = bytes(self._buf[7:end])
            del self._buf[:end]
            yield MbapFrame(tid, unit, pdu)

    def __len__(self) -> int:
        return len(self._buf)


def encode_adu(transaction_id: int, unit_id: int, pdu: bytes) -> bytes:
    """MBAP header plus ``pdu``: the bytes to send."""
    return _MBAP.pack(transaction_id, 0, len(pdu) + 1, unit_id) + pdu


def exception_pdu(function_code: int, code: ExceptionCode) -> bytes:
    """The exception response to ``function_code``: ``function_code | 0x80``, then the code."""
    return bytes(((function_code & 0x7F) | 0x80, int(code)))


class RegisterBank(Protocol):
    """What :func:`handle_pdu` reads and writes: holding registers by zero-based address.

    Both methods raise :class:`ModbusException` (e.g. illegal data address, server busy) to
    refuse a request; a refused write must change nothing.
    """

    def read_registers(self, address: int, count: int) -> list[int]: ...

    def write_registers(self, address: int, values: list[int]) -> None: ...


def _read(bank: RegisterBank, fc: int, data: bytes) -> bytes:
    if len(data) != 4:
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, "expected 4 data bytes")
    address, count = struct.unpack(">HH", data)
    if not 1 <= count <= 125:
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, f"count {count} not in 1..125")
    values = bank.read_registers(address, count)
    return struct.pack(f">BB{count}H", fc, 2 * count, *values)


def _write_single(bank: RegisterBank, fc: int, data: bytes) -> bytes:
    if len(data) != 4:
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, "expected 4 data bytes")
    address, value = struct.unpack(">HH", data)
    bank.write_registers(address, [value])
    return bytes((fc,)) + data


def _write_multiple(bank: RegisterBank, fc: int, data: bytes) -> bytes:
    if len(data) < 5:
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, "request too short")
    address, count, nbytes = struct.unpack_from(">HHB", data)
    if not 1 <= count <= 123 or nbytes != 2 * count or len(data) != 5 + nbytes:
        raise ModbusException(
            ExceptionCode.ILLEGAL_DATA_VALUE,
            f"count {count}, byte count {nbytes}, {len(data) - 5} data bytes do not agree",
        )
    values = list(struct.unpack_from(f">{count}H", data, 5))
    bank.write_registers(address, values)
    return struct.pack(">BHH", fc, address, count)


def _read_write_multiple(bank: RegisterBank, fc: int, data: bytes) -> bytes:
    if len(data) < 9:
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, "request too short")
    r_addr, r_count, w_addr, w_count, nbytes = struct.unpack_from(">HHHHB", data)
    if (
        not 1 <= r_count <= 125
        or not 1 <= w_count <= 121
        or nbytes != 2 * w_count
        or len(data) != 9 + nbytes
    ):
        raise ModbusException(ExceptionCode.ILLEGAL_DATA_VALUE, "counts do not agree")
    # Check the read range before writing, so that a refused request changes nothing.
    bank.read_registers(r_addr, r_count)
    bank.write_registers(w_addr, list(struct.unpack_from(f">{w_count}H", data, 9)))
    values = bank.read_registers(r_addr, r_count)
    return struct.pack(f">BB{r_count}H", fc, 2 * r_count, *values)


_FUNCTIONS = {
    0x03: _read,
    0x04: _read,
    0x06: _write_single,
    0x10: _write_multiple,
    0x17: _read_write_multiple,
}

#: Function codes answered (others get exception 1).
SUPPORTED_FUNCTIONS = tuple(sorted(_FUNCTIONS))


def handle_pdu(bank: RegisterBank, pdu: bytes) -> bytes:
    """Answer one request PDU with exactly one response PDU.

    Parameters
    ----------
    bank : RegisterBank
        The registers; its :class:`ModbusException` becomes an exception response.
    pdu : bytes
        Function code and data, at least one byte (the framing guarantees it).

    Returns
    -------
    bytes
        The normal response, or ``function | 0x80`` and the exception code.
    """
    if not pdu:
        raise ValueError("expected a PDU of at least 1 byte, got 0")
    fc = pdu[0]
    func = _FUNCTIONS.get(fc)
    if func is None:
        return exception_pdu(fc, ExceptionCode.ILLEGAL_FUNCTION)
    try:
        return func(bank, fc, pdu[1:])
    except ModbusException as exc:
        return exception_pdu(fc, exc.code)
