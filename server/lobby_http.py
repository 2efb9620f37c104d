"""The lobby's connections before their request is read (:mod:`server.lobby`): the limits on
an unread request (its size, its time) and the refusals written as a connection arrives.

websockets parses the lobby's HTTP (``process_request``); :class:`LobbyConnection`, the
connection class websockets is given, adds what its parser does not bound and what must happen
before any parsing: a connection over a cap (:class:`server.lobby_limits.ConnectionCounts`) or
from an address whose request budget is spent is answered with canned bytes and let go.
"""

from __future__ import annotations

import asyncio
import json
import time
from http import HTTPStatus
from typing import TYPE_CHECKING, cast

from websockets.asyncio.server import ServerConnection

from haptic_collab.server.lobby_limits import is_trusted

if TYPE_CHECKING:
    from haptic_collab.server.lobby import Lobby

#: Largest request line and headers together [bytes]: websockets bounds each line (8192 bytes)
#: and their number (128), so up to 1 MiB; the lobby cuts off a request larger than this.
MAX_HEAD_BYTES = 65536
#: Time a refused connection (answered 429 or 503 as it arrives) is kept to read its answer
#: before it is cut off [s].
REFUSED_READ_TIMEOUT_S = 1.0


def _canned(status: HTTPStatus, message: str) -> bytes:
    """The bytes of a refusal written before a request is read (see :class:`LobbyConnection`)."""
    body = (json.dumps({"error": message, "status": status.value}) + "\n").encode()
    head = (
        f"HTTP/1.1 {status.value} {status.phrase}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nCache-Control: no-store\r\nRetry-After: 1\r\n"
        "Connection: close\r\n\r\n"
    )
    return head.encode() + body


_REFUSALS = {
    "budget": _canned(HTTPStatus.TOO_MANY_REQUESTS, "too many requests; slow down"),
    "address": _canned(
        HTTPStatus.SERVICE_UNAVAILABLE, "too many connections from your address at once; try again"
    ),
    "total": _canned(HTTPStatus.SERVICE_UNAVAILABLE, "the lobby is busy; try again"),
}


class LobbyConnection(ServerConnection):
    """websockets' server connection with the lobby's limits on a request not yet read.

    websockets' parser bounds each line (:data:`websockets.http11.MAX_LINE_LENGTH`) and the
    number of header lines (:data:`websockets.http11.MAX_NUM_HEADERS`), not their sum, and its
    ``open_timeout`` covers the whole handshake, the lobby's answer included (a room may take
    :data:`server.lobby_backends.ROOM_BUILD_TIMEOUT_S` to build). So this subclass (websockets'
    ``create_connection``) counts the connections open, cuts off one whose request is not read
    within the lobby's ``read_timeout_s`` or whose bytes before its request exceed
    :data:`MAX_HEAD_BYTES`, and leaves the parsing to websockets. :meth:`Lobby.start` makes a
    subclass bound to its lobby.

    A connection from an address whose request budget is spent (429), or over a connection
    limit (503; :class:`server.lobby_limits.ConnectionCounts`: per address, in all), is refused
    as it arrives, before websockets sees it: a canned answer with ``Retry-After`` is written,
    the connection half-closed and cut off :data:`REFUSED_READ_TIMEOUT_S` later whatever it
    sends. A flood from one address so costs little more than its accept, idle sockets from one
    address hold at most ``per_address`` places, and everyone else is served. (A trusted
    proxy's budget is its clients', charged once their request is read.)
    """

    lobby: Lobby
    refused: str | None = None  #: why it was refused ("budget", "address", "total"), or None
    peer: str = "?"

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._head_bytes = 0
        peer = transport.get_extra_info("peername")
        self.peer = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        lobby = self.lobby
        proxy = is_trusted(self.peer, lobby.trusted_proxies)
        if not proxy and lobby.budgets.spent(self.peer, time.monotonic()):
            self.refused = "budget"
        else:
            self.refused = lobby.connections.admit(self.peer, proxy=proxy)
        if self.refused is not None:
            self._refuse(transport, self.refused)
            return
        super().connection_made(transport)
        self._deadline = self.loop.call_later(lobby.read_timeout_s, self._read_late)

    def _refuse(self, transport: asyncio.BaseTransport, why: str) -> None:
        """Answer a refused connection with a canned 429 or 503 and let it go."""
        transport = cast(asyncio.Transport, transport)
        self.lobby._count("connections_refused", why)
        status = HTTPStatus.SERVICE_UNAVAILABLE
        if why == "budget":
            status = HTTPStatus.TOO_MANY_REQUESTS
        self.lobby.answered[status.value] = self.lobby.answered.get(status.value, 0) + 1
        transport.write(_REFUSALS[why])
        if transport.can_write_eof():
            transport.write_eof()  # the answer, then FIN; the client's bytes are read and dropped
        else:
            transport.close()
        self._deadline = self.loop.call_later(REFUSED_READ_TIMEOUT_S, transport.abort)

    def data_received(self, data: bytes) -> None:
        if self.refused is not None:
            return
        if self.request is None:
            self._head_bytes += len(data)
            if self._head_bytes > MAX_HEAD_BYTES:
                self.lobby._dropped("headers over the lobby's limit")
                self.transport.abort()
                return
        super().data_received(data)

    def _read_late(self) -> None:
        if self.request is None:
            self.lobby._dropped("request not read in time")
            self.transport.abort()

    def eof_received(self) -> None:
        if self.refused is not None:
            return  # the client is done: asyncio closes the transport
        super().eof_received()

    def connection_lost(self, exc: Exception | None) -> None:
        self._deadline.cancel()
        if self.refused is not None:
            return  # websockets never saw it
        self.lobby.connections.release(self.peer)
        super().connection_lost(exc)
