"""Slow and numerous connections cannot tie the server up: uvicorn's HTTP/1.1 protocol with a
header timeout, a body timeout and a cap on connections per client address.

    config = uvicorn.Config(app, http=guarded_protocol(settings), …)    # ``serve`` does this

- **Header timeout** (``INVISIBLE_MAP_HEADER_TIMEOUT_S``, 10 s): a request's line and headers
  must arrive whole within it, counted from the connection's start (or, on a kept-alive
  connection, from the request's first byte); a client that sends them a byte at a time, or
  connects and sends nothing, is disconnected when it runs out. (uvicorn has no such timeout;
  its keep-alive timeout only covers the time between requests.)
- **Body timeout** (``INVISIBLE_MAP_BODY_TIMEOUT_S``, 30 s): while a body is being read, every
  such span must bring at least :data:`MIN_BODY_BYTES_PER_TIMEOUT` (1 KiB, about 34 bytes/s at
  30 s: far below any phone's link) of it; a stalled upload, or one trickled a few bytes at a
  time (a "slow POST"), is disconnected (the server's own pauses, when the route reads slower
  than the client sends, do not count).
- **Connections per address** (``INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS``, 128; 0: no cap):
  a client address with that many connections open gets ``503`` with ``Retry-After: 1`` and the
  connection closed on its next one. Addresses of ``INVISIBLE_MAP_TRUSTED_PROXIES`` are exempt
  (a proxy carries many clients).

The client address here is the TCP peer's: a cap on a forwarded address could be dodged by
sending another header.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
from collections import Counter
from typing import Any, ClassVar

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from app.config import Settings

logger = logging.getLogger("uvicorn.error")

#: Least body bytes a client must send in each ``body_timeout_s`` while its body is read.
MIN_BODY_BYTES_PER_TIMEOUT = 1024

_TOO_MANY = (
    b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\nConnection: close\r\n"
    b"Content-Type: text/plain; charset=utf-8\r\nContent-Length: 42\r\n\r\n"
    b"too many connections from your address\r\n\r\n"
)


def guarded_protocol(settings: Settings) -> type[H11Protocol]:
    """An :class:`H11Protocol` class with ``settings``' timeouts and cap (see the module
    docstring); each call makes a class with its own count of connections per address."""
    proxies = [
        ipaddress.ip_network(entry, strict=False)
        for entry in settings.trusted_proxies.split(",")
        if entry
    ]

    class GuardedH11Protocol(_Guarded):
        header_timeout_s = settings.header_timeout_s
        body_timeout_s = settings.body_timeout_s
        max_per_address = settings.max_connections_per_address
        exempt = tuple(proxies)
        open_per_address: ClassVar[Counter[str]] = Counter()

    return GuardedH11Protocol


class _Guarded(H11Protocol):
    header_timeout_s: float
    body_timeout_s: float
    max_per_address: int
    exempt: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]
    open_per_address: ClassVar[Counter[str]]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None
        self._body_timer: asyncio.TimerHandle | None = None
        self._body_bytes = 0  # received since the body timer was armed
        self._counted: str | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        address = self.client[0] if self.client else None
        if address is not None and self.max_per_address and not self._is_exempt(address):
            if self.open_per_address[address] >= self.max_per_address:
                logger.warning(
                    "%s has %d connections open: refusing another (503)",
                    address,
                    self.open_per_address[address],
                )
                transport.write(_TOO_MANY)
                transport.close()
                return
            self.open_per_address[address] += 1
            self._counted = address
        self._arm_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._header_timer, self._body_timer):
            if timer is not None:
                timer.cancel()
        if self._counted is not None:
            self.open_per_address[self._counted] -= 1
            if self.open_per_address[self._counted] <= 0:
                del self.open_per_address[self._counted]
            self._counted = None
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        state = self.conn.their_state
        if state is h11.IDLE:  # part of a request's headers: the clock runs from its first byte
            self._arm_header_timer()
            return
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None
        if state is not h11.SEND_BODY:
            if self._body_timer is not None:
                self._body_timer.cancel()
                self._body_timer = None
            return
        self._body_bytes += len(data)
        if self._body_timer is None:  # the body began: its first span starts now
            self._arm_body_timer()

    def _arm_body_timer(self) -> None:
        self._body_bytes = 0
        self._body_timer = self.loop.call_later(self.body_timeout_s, self._body_timed_out)

    def on_response_complete(self) -> None:
        super().on_response_complete()  # arms the keep-alive timer for the time between requests
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    # ----------------------------------------------------------------------- timers

    def _arm_header_timer(self) -> None:
        if self._header_timer is None and self.header_timeout_s > 0:
            self._header_timer = self.loop.call_later(
                self.header_timeout_s, self._headers_timed_out
            )

    def _headers_timed_out(self) -> None:
        self._header_timer = None
        if self.conn.their_state is h11.IDLE and self.cycle_idle():
            self._close("its request's headers did not arrive within", self.header_timeout_s)

    def cycle_idle(self) -> bool:
        """No request is being answered on this connection now."""
        return self.cycle is None or self.cycle.response_complete

    def _body_timed_out(self) -> None:
        self._body_timer = None
        if self.conn.their_state is not h11.SEND_BODY:
            return
        if self.flow.read_paused or self._body_bytes >= MIN_BODY_BYTES_PER_TIMEOUT:
            self._arm_body_timer()  # it kept up (or the server paused it): the next span
            return
        if self._body_bytes == 0:
            self._close("no byte of its request's body came for", self.body_timeout_s)
        else:
            self._close(
                f"its request's body brought {self._body_bytes} bytes (fewer than "
                f"{MIN_BODY_BYTES_PER_TIMEOUT}) in",
                self.body_timeout_s,
            )

    def _close(self, why: str, seconds: float) -> None:
        if self.transport.is_closing():
            return
        address = self.client[0] if self.client else "?"
        logger.warning("closing the connection of %s: %s %g s", address, why, seconds)
        if self.cycle is not None and not self.cycle.response_complete:
            self.cycle.disconnected = True
            self.cycle.message_event.set()
        self.transport.close()

    def _is_exempt(self, address: str) -> bool:
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in network for network in self.exempt)
