"""``haptic lobby``: finding a room. Maps a room name to a server's address and a room token.

A client asks ``GET /rooms/NAME?role=user`` (``role=viewer`` to watch; user by default) and
gets ``{"url": "ws://HOST:PORT/rooms/NAME/ws", "token": ..., "expires": ..., "viewer":
"http://HOST:PORT/rooms/NAME/#token=...", "server": ...}``: where room NAME runs, and a room
token for it (:func:`server.security.make_room_token`, signed with the secret the lobby shares
with the room servers' ``--token-secret-file``). Two back ends find the server (:mod:`server.lobby_backends`): :class:`LocalServers`
(``--server URL``: the room servers' ``/status``, a room made on demand) and
:class:`AgonesAllocator` (``--agones-allocator URL``: one GameServerAllocation with list
selectors on the fleet's ``rooms`` list).

Each name is placed once: requests for one name are serialised in the lobby (a lock per name),
so two users asking at once for a room nobody has made get the same server, and the second asks
only after the first's room (local) or list entry (Agones) exists. Several lobby processes do
not share these locks (see docs/deploy.md).

HTTP is websockets' (``process_request``, as the room server serves ``/status``): it parses
the request and answers what it refuses itself, with its own limits. A request line over
``websockets.http11.MAX_LINE_LENGTH`` (8192 bytes) gets 414, a header line over it or more
than ``MAX_NUM_HEADERS`` (128) header lines 431; a body, a ``Transfer-Encoding`` or bytes
that are not HTTP/1.x get the connection closed without an answer (websockets' parser takes no
request body, so the lobby is GET only: a role is a query parameter). The lobby adds: a request
not read within :data:`READ_TIMEOUT_S` of the connection, or more than :data:`MAX_HEAD_BYTES`
before its end, is cut off (no answer); a method other than GET 405, a bad room name or role
400, an unknown path 404, more
than :data:`ADDRESS_RATE_PER_S` requests a second from one address (burst
:data:`ADDRESS_BURST`) 429, more than :data:`MAX_CONNECTIONS` connections at once 503.
With a token file (``TOKEN ROLE [NAME]`` lines, :class:`server.security.TokenTable`) every room
request needs ``Authorization: Bearer TOKEN`` and a viewer's token gets only viewer tokens;
off loopback the lobby refuses to start without one (``--insecure`` to allow it).

Standard library and websockets only; one request per connection (``Connection: close``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import ssl
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from haptic_collab.server.lobby_backends import (
    BACKEND_TIMEOUT_S,
    ROOM_BUILD_TIMEOUT_S,
    AgonesAllocator,
    Backend,
    LobbyError,
    LocalServers,
    Placement,
    RoomServer,
    allocation_request,
    load_servers,
)
from haptic_collab.server.security import (
    MAX_TOKEN_TTL_S,
    Role,
    TokenBucket,
    TokenTable,
    is_loopback,
    make_room_token,
)
from haptic_collab.server.urls import room_page_path, room_ws_path, url_host, valid_room_name

__all__ = [
    "BACKEND_TIMEOUT_S",
    "ROOM_BUILD_TIMEOUT_S",
    "AgonesAllocator",
    "Backend",
    "Lobby",
    "LobbyError",
    "LocalServers",
    "Placement",
    "RoomServer",
    "allocation_request",
    "load_servers",
]

log = logging.getLogger("haptic.lobby")

#: Largest request line and headers together [bytes]: websockets bounds each line (8192 bytes)
#: and their number (128), so up to 1 MiB; the lobby cuts off a request larger than this.
MAX_HEAD_BYTES = 65536
#: Time to read a whole request [s] (a slow sender is cut off).
READ_TIMEOUT_S = 5.0
#: Time to answer a request once read [s]: the back ends bound each step (statuses, a room's
#: build, the allocator), this bounds a request waiting behind others for the same name.
ANSWER_TIMEOUT_S = 120.0
#: Requests a second one address may make, sustained, and saved up.
ADDRESS_RATE_PER_S = 5.0
ADDRESS_BURST = 20.0
#: Connections open at once, over every address; more are answered 503 at once.
MAX_CONNECTIONS = 256
#: Room placements in flight at once (each reads every server's status); more wait.
MAX_PLACEMENTS = 16
#: Addresses whose flood budgets are kept at most (full buckets are forgotten first).
MAX_ADDRESSES = 4096
#: Default lifetime of the room tokens the lobby signs [s].
TOKEN_TTL_S = 600.0


# ------------------------------------------------------------------------------------- the lobby
@dataclass
class _NameLock:
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    holders: int = 0


def _response(status: HTTPStatus, payload: Any, extra: Sequence[tuple[str, str]] = ()) -> Response:
    """A JSON answer (websockets sends it and closes the connection)."""
    body = (json.dumps(payload) + "\n").encode()
    headers = Headers(
        [
            ("Content-Type", "application/json"),
            ("Content-Length", str(len(body))),
            ("Cache-Control", "no-store"),
            ("Connection", "close"),
            *extra,
        ]
    )
    return Response(status.value, status.phrase, headers, body)


class _LobbyConnection(ServerConnection):
    """websockets' server connection with the lobby's limits on a request not yet read.

    websockets' parser bounds each line (:data:`websockets.http11.MAX_LINE_LENGTH`) and the
    number of header lines (:data:`websockets.http11.MAX_NUM_HEADERS`), not their sum, and its
    ``open_timeout`` covers the whole handshake, the lobby's answer included (a room may take
    :data:`ROOM_BUILD_TIMEOUT_S` to build). So this subclass (websockets' ``create_connection``)
    counts the connections open, cuts off one whose request is not read within the lobby's
    ``read_timeout_s`` or whose bytes before its request exceed :data:`MAX_HEAD_BYTES`, and
    leaves the parsing to websockets. :meth:`Lobby.start` makes a subclass bound to its lobby.
    """

    lobby: Lobby

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._head_bytes = 0
        self.lobby._connections += 1
        super().connection_made(transport)
        self._deadline = self.loop.call_later(self.lobby.read_timeout_s, self._read_late)

    def data_received(self, data: bytes) -> None:
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

    def connection_lost(self, exc: Exception | None) -> None:
        self._deadline.cancel()
        self.lobby._connections -= 1
        super().connection_lost(exc)


class Lobby:
    """The lobby's HTTP service: answers room requests with a server's URL and a room token.

    websockets serves it (``process_request`` answers every request; nothing is ever upgraded
    to a websocket), as the room server serves its viewer and ``/status``: websockets parses
    the request and takes GET only.

    Parameters
    ----------
    backend : Backend
        :class:`LocalServers` or :class:`AgonesAllocator`.
    secret : bytes
        The token secret the room servers share (:func:`server.security.load_secret`).
    host : str
        Address to listen on.
    port : int
        TCP port (0: any free port; :attr:`port` then says which).
    token_ttl_s : float
        Lifetime of the room tokens signed [s], in (0, 30 days].
    auth : TokenTable, optional
        Tokens a request must carry (``Authorization: Bearer``); None: anyone may ask.
    insecure : bool
        Listen off loopback without ``auth``.
    ssl_context : ssl.SSLContext, optional
        Serve https.
    clock : callable
        Unix time [s] (tokens' expiry); ``time.time``.
    read_timeout_s : float
        Time a client has, after its connection (and TLS handshake), to send its whole
        request [s] (:data:`READ_TIMEOUT_S`); the TLS handshake has as long again.

    Raises
    ------
    ValueError
        A bad lifetime, or an address off loopback without ``auth`` or ``insecure``.
    """

    def __init__(
        self,
        backend: Backend,
        secret: bytes,
        *,
        host: str = "127.0.0.1",
        port: int = 8780,
        token_ttl_s: float = TOKEN_TTL_S,
        auth: TokenTable | None = None,
        insecure: bool = False,
        ssl_context: ssl.SSLContext | None = None,
        clock: Callable[[], float] = time.time,
        read_timeout_s: float = READ_TIMEOUT_S,
    ) -> None:
        if not (math.isfinite(token_ttl_s) and 0.0 < token_ttl_s <= MAX_TOKEN_TTL_S):
            raise ValueError(f"token lifetime must be in (0, {MAX_TOKEN_TTL_S:g}] s")
        if auth is None and not insecure and not is_loopback(host):
            raise ValueError(
                f"the lobby would hand room tokens to anyone who reaches {host}: give it a "
                "--token-file (or --insecure)"
            )
        make_room_token(secret, "default", "user", clock() + 1.0)  # a usable secret, or raise
        self.backend = backend
        self._secret = secret
        self.host = host
        self.port = port
        self.token_ttl_s = float(token_ttl_s)
        self.auth = auth
        self.ssl_context = ssl_context
        self.clock = clock
        self.read_timeout_s = float(read_timeout_s)
        self._names: dict[str, _NameLock] = {}
        self._budgets: dict[str, TokenBucket] = {}
        self._placements = asyncio.Semaphore(MAX_PLACEMENTS)
        self._connections = 0
        self._server: Server | None = None
        #: Answers given, by HTTP status (the tests and /healthz read it).
        self.answered: dict[int, int] = {}
        #: Connections cut off before their request was read (too slow, too large).
        self.dropped = 0

    # -- the service -------------------------------------------------------------------------
    async def start(self) -> None:
        """Listen; :attr:`port` is the port taken."""
        connection = type("LobbyConnection", (_LobbyConnection,), {"lobby": self})
        self._server = await serve(
            self._never_upgraded,
            self.host,
            self.port,
            process_request=self._process_request,
            ssl=self.ssl_context,
            ssl_handshake_timeout=self.read_timeout_s if self.ssl_context is not None else None,
            open_timeout=None,  # the read deadline is _LobbyConnection's; the answer's, ours
            server_header=None,
            create_connection=connection,
            logger=logging.getLogger("haptic.lobby.http"),
        )
        self.port = int(next(iter(self._server.sockets)).getsockname()[1])
        scheme = "https" if self.ssl_context is not None else "http"
        log.info(
            "lobby listening on %s://%s:%d (%s)",
            scheme, url_host(self.host), self.port, self.backend.describe()["backend"],
        )  # fmt: skip

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
            self._server = None

    async def serve_forever(self, stop: asyncio.Event) -> None:
        """Serve until ``stop`` is set."""
        await self.start()
        try:
            await stop.wait()
        finally:
            await self.stop()

    @staticmethod
    async def _never_upgraded(ws: ServerConnection) -> None:
        """The websocket handler websockets wants: never runs (every request is answered)."""
        await ws.close(1008, "the lobby speaks HTTP only")

    def _dropped(self, why: str) -> None:
        self.dropped += 1
        log.info("lobby: a connection cut off: %s", why)

    async def _process_request(self, connection: ServerConnection, request: Request) -> Response:
        """Answer one request (websockets has parsed it: GET, no body, bounded lines)."""
        peer = connection.remote_address
        address = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        try:
            if self._connections > MAX_CONNECTIONS:
                return self._answer(HTTPStatus.SERVICE_UNAVAILABLE, "the lobby is busy; try again")
            async with asyncio.timeout(ANSWER_TIMEOUT_S):
                return await self._handle(request, address)
        except TimeoutError:
            return self._answer(HTTPStatus.SERVICE_UNAVAILABLE, "no answer in time; try again")
        except Exception:  # never let one request end the service
            log.exception("lobby: request from %s failed", address)
            return self._answer(HTTPStatus.INTERNAL_SERVER_ERROR, "the lobby failed; try again")

    def _answer(
        self, status: HTTPStatus, message_or_payload: Any, extra: Sequence[tuple[str, str]] = ()
    ) -> Response:
        self.answered[status.value] = self.answered.get(status.value, 0) + 1
        payload = (
            {"error": message_or_payload, "status": status.value}
            if isinstance(message_or_payload, str)
            else message_or_payload
        )
        return _response(status, payload, extra)

    def _within_budget(self, address: str) -> bool:
        """Charge one request to ``address``'s budget (:data:`ADDRESS_RATE_PER_S`)."""
        now = time.monotonic()
        bucket = self._budgets.get(address)
        if bucket is None:
            if len(self._budgets) >= MAX_ADDRESSES:  # forget the addresses that are quiet
                for a in [a for a, b in self._budgets.items() if b.refill(now) >= b.burst]:
                    del self._budgets[a]
                if len(self._budgets) >= MAX_ADDRESSES:
                    return False
            bucket = self._budgets[address] = TokenBucket(ADDRESS_RATE_PER_S, ADDRESS_BURST, now)
        return bucket.take(1.0, now)

    async def _handle(self, request: Request, address: str) -> Response:
        if not self._within_budget(address):
            log.warning("lobby: %s is over its request budget", address)
            return self._answer(
                HTTPStatus.TOO_MANY_REQUESTS, "too many requests; slow down", [("Retry-After", "1")]
            )
        # websockets >= 16 parses any method (a body it refuses); older ones take GET only
        method = getattr(request, "method", "GET")
        if method != "GET":
            return self._answer(
                HTTPStatus.METHOD_NOT_ALLOWED, "the lobby answers GET only", [("Allow", "GET")]
            )
        parts = urlsplit(request.path)
        if parts.path == "/healthz":
            return self._answer(HTTPStatus.OK, {"ok": True, **self.backend.describe()})
        if not parts.path.startswith("/rooms/"):
            return self._answer(HTTPStatus.NOT_FOUND, "ask GET /rooms/NAME?role=user|viewer")
        name = parts.path[len("/rooms/") :].rstrip("/")
        try:
            if not valid_room_name(name):
                raise LobbyError(
                    HTTPStatus.BAD_REQUEST,
                    "a room name is 1-32 of a-z, 0-9 and -, starting and ending with a letter "
                    "or digit",
                )
            role = self._role(parse_qs(parts.query), request.headers)
            answer = await self.join(name, role)
        except LobbyError as exc:
            return self._answer(exc.status, exc.message)
        return self._answer(HTTPStatus.OK, answer)

    def _role(self, query: dict[str, list[str]], headers: Headers) -> Role:
        """The role asked (query ``role``, once; default user), checked against the token."""
        asked = query.get("role", ["user"])
        if len(asked) != 1 or asked[0] not in ("user", "viewer"):
            raise LobbyError(HTTPStatus.BAD_REQUEST, "role is user or viewer (once)")
        role: Role = "user" if asked[0] == "user" else "viewer"
        if self.auth is not None:
            scheme, _, token = headers.get("Authorization", "").partition(" ")
            entry = self.auth.check(token.strip()) if scheme.lower() == "bearer" else None
            if entry is None:
                raise LobbyError(HTTPStatus.UNAUTHORIZED, "a lobby token is needed (Bearer)")
            if role == "user" and entry.role != "user":
                raise LobbyError(HTTPStatus.FORBIDDEN, "this token may only watch (role viewer)")
        return role

    async def join(self, name: str, role: Role) -> dict[str, Any]:
        """Where room ``name`` runs and a token for ``role`` in it (the answer's JSON).

        Requests for one name wait for each other (one lock per name, dropped when no request
        holds it), so a name is placed once.

        Raises
        ------
        LobbyError
            What the back end refused (404, 502, 503), or 503 for a user when the room is full
            (a viewer may still watch).
        """
        entry = self._names.setdefault(name, _NameLock())
        entry.holders += 1
        try:
            async with entry.lock, self._placements:
                placement = await self.backend.place(name)
        finally:
            entry.holders -= 1
            if entry.holders == 0:
                self._names.pop(name, None)
        if placement.full and role == "user":
            raise LobbyError(
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"room {name!r} is full (every seat taken); try later, or watch it as a viewer",
            )
        expires = int(self.clock() + self.token_ttl_s)
        token = make_room_token(self._secret, name, role, expires)
        return {
            "room": name,
            "role": role,
            "url": placement.ws_base + room_ws_path(name),
            "viewer": f"{placement.http_base}{room_page_path(name)}#token={token}",
            "token": token,
            "expires": expires,
            "server": placement.server,
        }
