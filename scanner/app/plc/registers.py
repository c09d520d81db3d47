"""The Modbus register map of ``scanner serve`` and the error codes, in one place.

The map is a public contract (``shared/spec/interfaces.md``, section 4): holding registers,
zero-based addresses, 32-bit values high word first, ``0x80000000`` the invalid signed result.
Addresses 0-9 are written by the PLC and read back as written; 100-114 are written by the
scanner and refused to clients with exception 2 (illegal data address).
"""

from __future__ import annotations

import enum
import math

__all__ = [
    "INT32_INVALID",
    "PLC_FIRST",
    "PLC_LAST",
    "SCANNER_FIRST",
    "SCANNER_LAST",
    "WORD_ORDER_PROBE",
    "Command",
    "ErrorCode",
    "Reg",
    "State",
    "Status",
    "format_register_map",
    "int32_to_words",
    "micrometres_to_int32",
    "uint32_to_words",
    "words_to_int32",
    "words_to_uint32",
]

#: First and last address of the block the PLC writes.
PLC_FIRST, PLC_LAST = 0, 9
#: First and last address of the block the scanner writes.
SCANNER_FIRST, SCANNER_LAST = 100, 114
#: The invalid value of a signed 32-bit result (also what an unknown figure reads as).
INT32_INVALID = -0x80000000
#: The word-order probe in registers 113-114: reads 16909060 when the PLC's word order is right.
WORD_ORDER_PROBE = 0x01020304


class Reg(enum.IntEnum):
    """Holding-register addresses (zero-based)."""

    COMMAND = 0
    SEQUENCE = 1
    PLC_HEARTBEAT = 2
    PARAMETER = 3
    STATUS = 100
    ACK_SEQUENCE = 101
    ERROR_CODE = 102
    STATE = 103
    HEARTBEAT = 104
    RESULT1 = 105
    RESULT2 = 107
    RESULT3 = 109
    JOB_ID = 111
    PROBE = 113


class Command(enum.IntEnum):
    """Values of register 0."""

    NONE = 0
    CHECK = 1
    SCAN = 2
    CALIBRATE = 3
    CLEAR_ERROR = 4


class Status(enum.IntFlag):
    """Bits of register 100."""

    READY = 1 << 0
    BUSY = 1 << 1
    DONE = 1 << 2
    RESULT_VALID = 1 << 3
    PASS = 1 << 4
    ERROR = 1 << 5
    CALIBRATED = 1 << 6
    NOT_PROVEN = 1 << 7
    """A scan job's measurements under guarded acceptance: none failed, but at least one lies
    within its uncertainty U of a limit (conformity not proven, ISO 14253-1); DONE and
    RESULT_VALID are set, PASS is not."""


class State(enum.IntEnum):
    """Values of register 103."""

    IDLE = 0
    RUNNING = 1
    DONE = 2
    ERROR = 3


class ErrorCode(enum.IntEnum):
    """Values of register 102 (0 when none); also stored with every job in the history.

    The docstring of each member is the text ``scanner serve --print-map`` and docs/PLC.md show.
    """

    NONE = 0
    NO_SESSION = 1
    NO_CALIBRATION = 2
    BAD_INPUT = 3
    QUALITY_GATE = 4
    WATCHDOG = 5
    INTERNAL = 6
    INTERRUPTED = 7
    UNKNOWN_RECIPE = 8
    JOB_TIMEOUT = 9

    @property
    def text(self) -> str:
        """One line saying what the code means and what to do."""
        return _ERROR_TEXT[self]


_ERROR_TEXT = {
    ErrorCode.NONE: "no error",
    ErrorCode.NO_SESSION: "session source empty: no complete session to process",
    ErrorCode.NO_CALIBRATION: "no usable calibration: run a full calibration (command 3)",
    ErrorCode.BAD_INPUT: "job failed on bad input (session, plan or config); see the history",
    ErrorCode.QUALITY_GATE: "new calibration failed its quality gate; the old one is kept",
    ErrorCode.WATCHDOG: "watchdog: the PLC heartbeat (register 2) stopped during the job",
    ErrorCode.INTERNAL: "internal error (a bug); see the history and the service log",
    ErrorCode.INTERRUPTED: "job interrupted by a stop or crash of the service",
    ErrorCode.UNKNOWN_RECIPE: "parameter (register 3) names no recipe of the config",
    ErrorCode.JOB_TIMEOUT: "job took longer than the configured limit and was aborted",
}


def int32_to_words(value: int) -> tuple[int, int]:
    """Split a signed 32-bit integer into two registers, high word first.

    Raises
    ------
    ValueError
        ``value`` is outside the int32 range.
    """
    if not -(2**31) <= value < 2**31:
        raise ValueError(f"expected an int32 (-2**31 .. 2**31-1), got {value}")
    raw = value & 0xFFFFFFFF
    return raw >> 16, raw & 0xFFFF


def uint32_to_words(value: int) -> tuple[int, int]:
    """Split an unsigned 32-bit integer into two registers, high word first."""
    if not 0 <= value < 2**32:
        raise ValueError(f"expected a uint32 (0 .. 2**32-1), got {value}")
    return value >> 16, value & 0xFFFF


def words_to_int32(high: int, low: int) -> int:
    """Join two registers (high word first) into a signed 32-bit integer."""
    raw = ((high & 0xFFFF) << 16) | (low & 0xFFFF)
    return raw - 2**32 if raw >= 2**31 else raw


def words_to_uint32(high: int, low: int) -> int:
    """Join two registers (high word first) into an unsigned 32-bit integer."""
    return ((high & 0xFFFF) << 16) | (low & 0xFFFF)


def micrometres_to_int32(value_um: float | None) -> int:
    """A figure in µm as the int32 the PLC reads: rounded, or ``INT32_INVALID`` when unknown.

    ``None``, NaN, infinities and values outside the int32 range (other than the invalid
    value itself) all read as invalid: a PLC must never mistake a saturated value for a figure.
    """
    if value_um is None or not math.isfinite(value_um):
        return INT32_INVALID
    rounded = round(value_um)
    if not -(2**31) < rounded < 2**31:
        return INT32_INVALID
    return int(rounded)


_PLC_ROWS = (
    ("0", "command: 0 none, 1 recalibration check, 2 scan job, 3 full calibration, 4 clear error"),
    ("1", "sequence number: a new value for each new command, 1..65535, never 0"),
    ("2", "PLC heartbeat: changed by the PLC at least once per watchdog period"),
    ("3", "parameter: recipe number of a scan job"),
    ("4-9", "reserved parameters (accepted, stored)"),
)
_SCANNER_ROWS = (
    (
        "100",
        "status bits: 0 READY, 1 BUSY, 2 DONE, 3 RESULT_VALID, 4 PASS, 5 ERROR, 6 CALIBRATED, "
        "7 NOT_PROVEN",
    ),
    ("101", "sequence number of the command last accepted"),
    ("102", "error code, 0 when none (below)"),
    ("103", "state: 0 idle, 1 running, 2 done, 3 error"),
    ("104", "scanner heartbeat, incremented every second"),
    ("105-106", "result 1, int32 µm (check: mean absolute EF error)"),
    ("107-108", "result 2, int32 µm (check: largest absolute EF error)"),
    ("109-110", "result 3, int32 µm (check: spread of O in the base frame)"),
    ("111-112", "id of the job in the job history, uint32"),
    ("113-114", "word-order probe: int32 16909060 (0x01020304)"),
)


def format_register_map() -> str:
    """The register map and error codes as the plain-text table ``--print-map`` prints."""
    lines = [
        "Modbus TCP register map of `scanner serve` (holding registers, zero-based, any unit id;",
        "32-bit values high word first; invalid int32 = 0x80000000 = -2147483648)",
        "",
        "Written by the PLC (read back as written):",
    ]
    lines += [f"  {addr:>7}  {text}" for addr, text in _PLC_ROWS]
    lines += ["", "Written by the scanner (a client write is refused with exception 2):"]
    lines += [f"  {addr:>7}  {text}" for addr, text in _SCANNER_ROWS]
    lines += ["", "Error codes (register 102):"]
    lines += [f"  {code.value:>7}  {code.text}" for code in ErrorCode]
    lines += [
        "",
        "Modbus exceptions: 1 illegal function, 2 illegal data address (also any write to",
        "100-114), 3 illegal data value (also an unknown command), 6 server busy (new command",
        "while BUSY; nothing is changed).",
    ]
    return "\n".join(lines)
