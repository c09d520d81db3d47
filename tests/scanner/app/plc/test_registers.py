from __future__ import annotations

import math

import pytest

from scanner.app.plc.registers import (
    INT32_INVALID,
    WORD_ORDER_PROBE,
    ErrorCode,
    Status,
    format_register_map,
    int32_to_words,
    micrometres_to_int32,
    uint32_to_words,
    words_to_int32,
    words_to_uint32,
)


def test_int32_high_word_first_round_trip():
    assert int32_to_words(WORD_ORDER_PROBE) == (0x0102, 0x0304)
    assert int32_to_words(-1) == (0xFFFF, 0xFFFF)
    assert int32_to_words(INT32_INVALID) == (0x8000, 0x0000)
    for value in (0, 1, -1, 123456, -123456, 2**31 - 1, -(2**31)):
        assert words_to_int32(*int32_to_words(value)) == value


def test_uint32_round_trip_and_range_checks():
    assert words_to_uint32(*uint32_to_words(2**32 - 1)) == 2**32 - 1
    with pytest.raises(ValueError, match="expected a uint32"):
        uint32_to_words(-1)
    with pytest.raises(ValueError, match="expected an int32"):
        int32_to_words(2**31)


def test_unknown_or_saturated_figures_read_invalid():
    assert micrometres_to_int32(12.6) == 13
    assert micrometres_to_int32(-12.4) == -12
    for bad in (None, math.nan, math.inf, 3e9, -3e9):
        assert micrometres_to_int32(bad) == INT32_INVALID


def test_status_bits_match_the_contract():
    # bits 0-6 as the contract names them; bit 7 (NOT_PROVEN) is this project's extension
    assert [int(b) for b in Status] == [1, 2, 4, 8, 16, 32, 64, 128]
    assert Status.NOT_PROVEN.name == "NOT_PROVEN"


def test_print_map_lists_every_register_and_error_code():
    text = format_register_map()
    for addr in ("0", "4-9", "100", "104", "105-106", "111-112", "113-114"):
        assert f" {addr}  " in text
    for code in ErrorCode:
        assert code.text in text
    assert len({c.text for c in ErrorCode}) == len(ErrorCode)
