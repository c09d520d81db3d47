"""The network side, byte for byte over loopback: pipelining, limits, malformed input."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest

from scanner.app.plc.registers import WORD_ORDER_PROBE, int32_to_words
from tests.scanner.app.plc.conftest import (
    Running,
    adu,
    connect,
    is_closed_by_peer,
    make_config,
    read_pdu,
    recv_adu,
    running_service,
    write_pdu,
)
from tests.scanner.app.plc.fakes import FakeJobs

pytestmark = pytest.mark.timeout(60)

PROBE = list(int32_to_words(WORD_ORDER_PROBE))


def _read_reply(values: list[int]) -> bytes:
    return struct.pack(f">BB{len(values)}H", 3, 2 * len(values), *values)


@pytest.mark.parametrize("count", [2, 3])
def test_requests_in_one_segment_are_each_answered_once_in_order(service: Running, count: int):
    with connect(service.port) as sock:
        requests = [
            adu(10, write_pdu(5, [111])),
            adu(11, read_pdu(5, 1)),
            adu(12, read_pdu(113, 2)),
        ][:count]
        sock.sendall(b"".join(requests))  # one segment (TCP_NODELAY, one send)
        answers = [recv_adu(sock) for _ in range(count)]
        expected = [
            (10, 1, struct.pack(">BHH", 16, 5, 1)),
            (11, 1, _read_reply([111])),
            (12, 1, _read_reply(PROBE)),
        ][:count]
        assert answers == expected
        sock.settimeout(0.3)
        with pytest.raises(TimeoutError):  # nothing more: each answered exactly once
            sock.recv(1)


def test_back_to_back_writes_are_each_executed_once(service: Running):
    with connect(service.port) as sock:
        burst = b"".join(adu(100 + i, write_pdu(6, [i])) for i in range(50))
        burst += adu(999, read_pdu(6, 1))
        sock.sendall(burst)
        answers = [recv_adu(sock) for _ in range(51)]
    assert [tid for tid, _, _ in answers] == [*range(100, 150), 999]
    assert answers[-1][2] == _read_reply([49])


def test_a_frame_split_across_segments_is_answered(service: Running):
    with connect(service.port) as sock:
        frame = adu(7, read_pdu(113, 2), unit=0)
        for byte in frame:
            sock.sendall(bytes((byte,)))
            time.sleep(0.002)
        assert recv_adu(sock) == (7, 0, _read_reply(PROBE))


@pytest.mark.parametrize(
    "bad",
    [
        struct.pack(">HHHB", 1, 1, 6, 1) + read_pdu(100, 1),  # protocol id 1
        struct.pack(">HHHB", 1, 0, 255, 1) + b"\x03" * 254,  # MBAP length over 254
        b"GET / HTTP/1.1\r\nHost: plc\r\n\r\n",  # garbage
    ],
    ids=["protocol-id", "length", "garbage"],
)
def test_malformed_connections_are_closed_after_answering_what_came_before(
    service: Running, bad: bytes
):
    with connect(service.port) as sock:
        sock.sendall(adu(1, read_pdu(113, 2)) + bad)
        assert recv_adu(sock) == (1, 1, _read_reply(PROBE))
        assert is_closed_by_peer(sock)
    with connect(service.port) as sock:  # the server itself carries on
        sock.sendall(adu(2, read_pdu(113, 2)))
        assert recv_adu(sock)[0] == 2


@pytest.mark.parametrize(
    ("pdu", "expected"),
    [
        (bytes((0x2B, 0x0E, 0x01, 0x00)), bytes((0xAB, 0x01))),  # unknown function
        (bytes((0x05, 0, 0, 0xFF, 0)), bytes((0x85, 0x01))),  # coils: not served
        (read_pdu(10, 1), bytes((0x83, 0x02))),  # between the blocks
        (read_pdu(110, 6), bytes((0x83, 0x02))),  # past 114
        (read_pdu(8, 3), bytes((0x83, 0x02))),  # across the end of 0-9
        (read_pdu(0, 126), bytes((0x83, 0x03))),
        (write_pdu(100, [1]), bytes((0x90, 0x02))),  # scanner registers are read-only
        (struct.pack(">BHH", 6, 104, 0), bytes((0x86, 0x02))),
        (write_pdu(9, [1, 2]), bytes((0x90, 0x02))),
        (write_pdu(0, [9, 1]), bytes((0x90, 0x03))),  # unknown command
    ],
)
def test_illegal_requests_get_proper_exceptions(service: Running, pdu: bytes, expected: bytes):
    with connect(service.port) as sock:
        sock.sendall(adu(3, read_pdu(100, 15)))
        _, _, before = recv_adu(sock)
        sock.sendall(adu(4, pdu, unit=17))
        assert recv_adu(sock) == (4, 17, expected)
        sock.sendall(adu(5, read_pdu(100, 15)))
        _, _, after = recv_adu(sock)
        sock.sendall(adu(6, read_pdu(0, 10)))
        _, _, plc_block = recv_adu(sock)
    assert after[:8] == before[:8] and after[10:] == before[10:]  # all but the heartbeat
    assert plc_block == _read_reply([0] * 10)


def test_connections_beyond_the_cap_are_closed(tmp_path: Path):
    config = make_config(tmp_path, max_connections=2)
    with running_service(config, FakeJobs(config)) as svc:
        first, second = connect(svc.port), connect(svc.port)
        for s in (first, second):
            s.sendall(adu(1, read_pdu(113, 2)))
            assert recv_adu(s)[0] == 1
        third = connect(svc.port)
        assert is_closed_by_peer(third)
        first.close()
        time.sleep(0.2)
        fourth = connect(svc.port)
        fourth.sendall(adu(2, read_pdu(113, 2)))
        assert recv_adu(fourth)[0] == 2
        for s in (second, third, fourth):
            s.close()


def test_addresses_not_allowed_are_closed(tmp_path: Path):
    config = make_config(tmp_path, allowed_clients=["192.0.2.10", "10.1.0.0/16"])
    with running_service(config, FakeJobs(config)) as svc, connect(svc.port) as sock:
        try:
            sock.sendall(adu(1, read_pdu(113, 2)))
        except OSError:
            pass
        assert is_closed_by_peer(sock)


def test_idle_connections_are_closed(tmp_path: Path):
    config = make_config(tmp_path, idle_timeout_s=0.5)
    with running_service(config, FakeJobs(config)) as svc, connect(svc.port) as sock:
        sock.sendall(adu(1, read_pdu(113, 2)))
        recv_adu(sock)
        t0 = time.monotonic()
        assert is_closed_by_peer(sock, timeout=5.0)
        assert 0.3 < time.monotonic() - t0 < 4.5  # not at once, and before the 5 s guard


def test_a_busy_client_is_not_idle(tmp_path: Path):
    config = make_config(tmp_path, idle_timeout_s=0.5)
    with running_service(config, FakeJobs(config)) as svc, connect(svc.port) as sock:
        for i in range(8):
            sock.sendall(adu(i, read_pdu(100, 1)))
            assert recv_adu(sock)[0] == i
            time.sleep(0.2)


def test_input_registers_and_read_write_multiple_serve_the_same_map(service: Running):
    with connect(service.port) as sock:
        sock.sendall(adu(1, struct.pack(">BHH", 4, 113, 2)))
        assert recv_adu(sock) == (1, 1, struct.pack(">BB2H", 4, 4, *PROBE))
        fc23 = struct.pack(">BHHHHB1H", 23, 113, 2, 7, 1, 2, 77)
        sock.sendall(adu(2, fc23))
        assert recv_adu(sock) == (2, 1, struct.pack(">BB2H", 23, 4, *PROBE))
        sock.sendall(adu(3, read_pdu(7, 1)))
        assert recv_adu(sock)[2] == _read_reply([77])
