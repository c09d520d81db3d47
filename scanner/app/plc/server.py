"""The asyncio Modbus TCP server: connections, limits and framing, in front of a register bank.

One :class:`asyncio.Protocol` per connection with its own :class:`FrameBuffer`: every complete
frame is answered exactly once, in the order received, before the next bytes are read, so
pipelined requests (several in one TCP segment, or sent back to back) are all answered
correctly. The bank is called on the event loop thread only, so a request sees the registers
as one consistent snapshot.

Guards (all from ``[server]`` in ``configs/plc.toml``): clients whose address is not allowed
and connections beyond ``max_connections`` are closed at once; a connection without a complete
request for ``idle_timeout_s`` is closed (the bytes of a partial frame do not count, so a client
trickling a frame byte by byte cannot hold a connection); bytes that are not Modbus TCP
(protocol id not 0, length over 254, garbage) close the connection after the frames before them
are answered.

A connection counts against ``max_connections`` until its peer has gone, not until the event
loop has read the end of its stream: when a new client would exceed the limit, connections
whose peer has already closed (or reset) are dropped first. Many clients connecting and closing
quickly therefore never lock a new one out.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import select
import socket
from collections.abc import Sequence
from typing import cast

from scanner.app.plc.modbus import (
    ExceptionCode,
    FrameBuffer,
    FramingError,
    RegisterBank,
    encode_adu,
    exception_pdu,
    handle_pdu,
)

__all__ = ["ModbusTcpServer"]

log = logging.getLogger(__name__)

Network = ipaddress.IPv4Network | ipaddress.IPv6Network


class _Connection(asyncio.Protocol):
    def __init__(self, server: ModbusTcpServer) -> None:
        self.server = server
        self.frames = FrameBuffer()
        self.transport: asyncio.Transport | None = None
        self.peer = "?"
        self._idle: asyncio.TimerHandle | None = None
        self.accepted = False

    # asyncio.Protocol -----------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.Transport, transport)  # a TCP server makes only these
        peername = transport.get_extra_info("peername")
        self.peer = f"{peername[0]}:{peername[1]}" if peername else "?"
        host = peername[0] if peername else ""
        if not self.server.is_allowed(host):
            log.warning("refused %s: address not in allowed_clients", self.peer)
            self.server.refused += 1
            transport.abort()
            return
        if len(self.server.connections) >= self.server.max_connections:
            self.server.drop_gone_connections()
        if len(self.server.connections) >= self.server.max_connections:
            log.warning(
                "refused %s: already %d connections (max_connections)",
                self.peer,
                len(self.server.connections),
            )
            self.server.refused += 1
            transport.abort()
            return
        self.accepted = True
        self.server.connections.add(self)
        log.info("connection from %s", self.peer)
        self._arm_idle()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._idle is not None:
            self._idle.cancel()
        if self.accepted:
            self.accepted = False
            self.server.connections.discard(self)
            log.info("connection from %s closed", self.peer)

    def data_received(self, data: bytes) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        out: list[bytes] = []
        try:
            for frame in self.frames.feed(data):
                out.append(encode_adu(frame.transaction_id, frame.unit_id, self._answer(frame.pdu)))
        except FramingError as exc:
            log.warning("closing %s: %s", self.peer, exc)
            self.transport.write(b"".join(out))
            self.transport.close()
            return
        if out:  # only a complete request re-arms the idle timer, never a partial frame
            self._arm_idle()
            self.transport.write(b"".join(out))

    def pause_writing(self) -> None:  # a client that does not read its answers
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    # helpers --------------------------------------------------------------------------------
    def _answer(self, pdu: bytes) -> bytes:
        try:
            return handle_pdu(self.server.bank, pdu)
        except Exception:  # a bug in the bank must not take the connection or server down
            log.exception("internal error answering %s", pdu[:1].hex())
            return exception_pdu(pdu[0], ExceptionCode.SERVER_FAILURE)

    def _arm_idle(self) -> None:
        if self._idle is not None:
            self._idle.cancel()
        loop = asyncio.get_running_loop()
        self._idle = loop.call_later(self.server.idle_timeout_s, self._on_idle)

    def _on_idle(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            log.info("closing %s: idle for %.1f s", self.peer, self.server.idle_timeout_s)
            self.transport.close()

    def close(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.close()

    def peer_gone(self) -> bool:
        """Whether the peer has closed or reset the connection (its end of stream may still be
        unread by the event loop)."""
        if self.transport is None or self.transport.is_closing():
            return True
        sock = self.transport.get_extra_info("socket")
        if sock is None:
            return False
        try:
            fd = sock.fileno()
        except OSError:
            return True
        if fd < 0:
            return True
        rdhup = getattr(select, "POLLRDHUP", 0)
        if hasattr(select, "poll"):
            poller = select.poll()
            poller.register(fd, select.POLLIN | rdhup)
            for _, events in poller.poll(0):
                if events & (rdhup | select.POLLHUP | select.POLLERR | select.POLLNVAL):
                    return True
            if rdhup:
                return False
        try:  # no POLLRDHUP: an end of stream with nothing before it reads as b"" when peeked
            peek = socket.fromfd(fd, sock.family, sock.type)  # a duplicate: closing it is safe
        except OSError:
            return True
        try:
            peek.setblocking(False)
            return peek.recv(1, socket.MSG_PEEK) == b""
        except (BlockingIOError, InterruptedError):
            return False
        except OSError:
            return True
        finally:
            peek.close()

    def drop(self) -> None:
        """Close at once and stop counting this connection (its peer has gone)."""
        if self.accepted:
            self.accepted = False
            self.server.connections.discard(self)
            log.info("connection from %s closed (peer gone)", self.peer)
        if self._idle is not None:
            self._idle.cancel()
        if self.transport is not None:
            self.transport.abort()


class ModbusTcpServer:
    """Modbus TCP in front of ``bank``.

    Parameters
    ----------
    bank : RegisterBank
        What requests read and write.
    host, port : str, int
        Where to listen; port 0 picks a free one (see :attr:`port` after :meth:`start`).
    allowed : sequence of networks
        Client addresses allowed to connect; empty allows every address.
    max_connections : int
        Connections beyond this many are closed at once.
    idle_timeout_s : float
        A connection silent for this long is closed.
    """

    def __init__(
        self,
        bank: RegisterBank,
        host: str = "127.0.0.1",
        port: int = 5020,
        allowed: Sequence[Network] = (ipaddress.ip_network("127.0.0.1/32"),),
        max_connections: int = 8,
        idle_timeout_s: float = 60.0,
    ) -> None:
        if max_connections < 1:
            raise ValueError(f"expected max_connections >= 1, got {max_connections}")
        if idle_timeout_s <= 0:
            raise ValueError(f"expected idle_timeout_s > 0, got {idle_timeout_s}")
        self.bank = bank
        self.host = host
        self.port = port
        self.allowed = tuple(allowed)
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self.connections: set[_Connection] = set()
        #: Connections closed at once (address not allowed, or over the limit).
        self.refused = 0
        self._server: asyncio.base_events.Server | None = None

    def is_allowed(self, host: str) -> bool:
        """Whether a client at ``host`` may connect."""
        if not self.allowed:
            return True
        try:
            address = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
            address = address.ipv4_mapped
        return any(address in net for net in self.allowed)

    def drop_gone_connections(self) -> int:
        """Drop the connections whose peer has already closed; return how many."""
        gone = [c for c in self.connections if c.peer_gone()]
        for conn in gone:
            conn.drop()
        return len(gone)

    async def start(self) -> None:
        """Listen; :attr:`port` is the port actually bound.

        Raises
        ------
        ValueError
            :attr:`host` is neither an IP address nor a name that resolves.
        OSError
            Listening failed (address in use, not an address of this machine, ...); the
            message names the address.
        """
        loop = asyncio.get_running_loop()
        try:
            self._server = await loop.create_server(
                lambda: _Connection(self), self.host, self.port, reuse_address=True
            )
        except socket.gaierror as exc:
            raise ValueError(
                f"host: expected an IP address or a resolvable host name, got {self.host!r} "
                f"({exc.strerror or exc})"
            ) from None
        except OSError as exc:
            raise OSError(
                f"cannot listen on {self.host}:{self.port} ({exc.strerror or exc})"
            ) from None
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("Modbus TCP server listening on %s:%d", self.host, self.port)

    async def stop(self) -> None:
        """Stop listening and close every connection."""
        if self._server is None:
            return
        self._server.close()
        for conn in list(self.connections):
            conn.close()
        await self._server.wait_closed()
        self._server = None
