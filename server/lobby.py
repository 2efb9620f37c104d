"""``haptic lobby``: finding a room. Maps a room name to a server's address and a room token.

A client asks ``GET /rooms/NAME?role=user`` (``role=viewer`` to watch; user by default) and
gets ``{"url": "ws://HOST:PORT/rooms/NAME/ws", "token": ..., "expires": ..., "viewer":
"http://HOST:PORT/rooms/NAME/#token=...", "server": ...}``: where room NAME runs, and a room
token for it (:func:`server.security.make_room_token`, signed with the secret the lobby shares
with the room servers' ``--token-secret-file``). Two back ends find the server
(:mod:`server.lobby_backends`): :class:`LocalServers` (``--server URL``: the room servers'
``/status``, a room made on demand) and :class:`AgonesAllocator` (``--agones-allocator URL``:
one GameServerAllocation with list selectors on the fleet's ``rooms`` list,
:mod:`server.lobby_agones`).

Each name is placed once: a request for a name whose placement is under way gets that
placement's outcome instead of placing it again, so two users asking at once for a room nobody
has made get the same server. Several replicas (``--peer``, :mod:`server.lobby_peers`) give
each name one owner that places it; the others ask the owner.

HTTP is websockets' (``process_request``, as the room server serves ``/status``): it parses
the request and answers what it refuses itself, with its own limits. A request line over
``websockets.http11.MAX_LINE_LENGTH`` (8192 bytes) gets 414, a header line over it or more
than ``MAX_NUM_HEADERS`` (128) header lines 431; a body, a ``Transfer-Encoding`` or bytes
that are not HTTP/1.x get the connection closed without an answer (websockets' parser takes no
request body, so the lobby is GET only: a role is a query parameter). The lobby adds
(:mod:`server.lobby_http`): a request not read within :data:`READ_TIMEOUT_S` of the
connection, or over 64 KiB before its end, is cut off (no answer); a method other than GET
405, a bad room name or role 400, an unknown path 404, more than :data:`ADDRESS_RATE_PER_S`
requests a second from one client (burst :data:`ADDRESS_BURST`) 429 with ``Retry-After``. A
connection over :data:`MAX_CONNECTIONS_PER_ADDRESS` open from its address, or over
:data:`MAX_CONNECTIONS` in all, is answered 503 with ``Retry-After`` as it arrives, and one
from an address whose budget is spent 429, before its request is read. The client is the TCP
peer, or, from a trusted proxy (``--trusted-proxy``), the address its ``X-Forwarded-For``
names (:mod:`server.lobby_limits`). At most :data:`MAX_PLACEMENTS` placements run at once; one
that waits :data:`PLACEMENT_WAIT_S` for a turn, or whose back end does not answer within its
timeout, is answered 503 with ``Retry-After``, never queued.

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
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from haptic_collab.server.lobby_agones import AgonesAllocator, allocation_request
from haptic_collab.server.lobby_backends import (
    BACKEND_TIMEOUT_S,
    ROOM_BUILD_TIMEOUT_S,
    Backend,
    LobbyError,
    LocalServers,
    Placement,
    RoomServer,
    load_servers,
)
from haptic_collab.server.lobby_http import (
    LobbyConnection,
)
from haptic_collab.server.lobby_limits import (
    ADDRESS_BURST,
    ADDRESS_RATE_PER_S,
    MAX_CONNECTIONS,
    MAX_CONNECTIONS_PER_ADDRESS,
    AddressBudgets,
    ConnectionCounts,
    client_address,
    parse_proxies,
)
from haptic_collab.server.lobby_metrics import PlacementTimes, lobby_registry
from haptic_collab.server.lobby_peers import (
    PEER_PATH,
    Peers,
    check_peer_request,
    placement_json,
)
from haptic_collab.server.metrics import scrape_allowed
from haptic_collab.server.security import (
    MAX_TOKEN_TTL_S,
    Role,
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

#: Time to read a whole request [s] (a slow sender is cut off).
READ_TIMEOUT_S = 5.0
#: Time to answer a request once read [s]: the back ends bound each step (statuses, a room's
#: build, the allocator), this bounds a request waiting behind others for the same name.
ANSWER_TIMEOUT_S = 120.0
#: Connections the kernel queues before the lobby accepts them: a burst of connections from
#: one address (refused at once, but accepted first) must not overflow the queue, or others'
#: connection attempts are dropped and retried by TCP a second later.
LISTEN_BACKLOG = 1024
#: Room placements in flight at once (each one allocation, or one ``/status`` per server).
MAX_PLACEMENTS = 8
#: Time a placement waits for one of the :data:`MAX_PLACEMENTS` slots [s]; then 503 with
#: ``Retry-After``, rather than a queue behind a back end that hangs.
PLACEMENT_WAIT_S = 1.0
#: Default lifetime of the room tokens the lobby signs [s].
TOKEN_TTL_S = 600.0


# ------------------------------------------------------------------------------------- the lobby
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


class Lobby:
    """The lobby's HTTP service: answers room requests with a server's URL and a room token.

    websockets serves it (``process_request`` answers every request; nothing is ever upgraded
    to a websocket), as the room server serves its viewer and ``/status``: websockets parses
    the request and takes GET only.

    Parameters
    ----------
    backend : Backend
        :class:`LocalServers` or :class:`AgonesAllocator`. A :class:`LocalServers` without a
        ``room_token`` gets the lobby's: the handshake that makes a room carries a user's token
        for it (a server with tokens makes the room at once only for that).
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
    trusted_proxies : sequence of str
        Addresses or networks (``10.0.0.0/8``) of proxies whose ``X-Forwarded-For`` names the
        client (:func:`server.lobby_limits.client_address`); from anyone else it is ignored.
    max_connections_per_address : int
        Connections one address may hold open at once (a trusted proxy: no cap of its own).
    max_connections : int
        Connections open at once in all.
    peers : Peers, optional
        The lobby replicas (:mod:`server.lobby_peers`): a name another replica owns is placed
        by it. None: this lobby places every name itself. May be set before :meth:`start`.
    metrics_token : TokenTable, optional
        The token a scrape of ``/metrics`` must carry (``Authorization: Bearer``); without one
        only a lobby on loopback serves it (:func:`server.metrics.scrape_allowed`).

    Raises
    ------
    ValueError
        A bad lifetime, an address off loopback without ``auth`` or ``insecure``, a trusted
        proxy that is no address or network, or a connection limit below 1.
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
        trusted_proxies: Sequence[str] = (),
        max_connections_per_address: int = MAX_CONNECTIONS_PER_ADDRESS,
        max_connections: int = MAX_CONNECTIONS,
        peers: Peers | None = None,
        metrics_token: TokenTable | None = None,
    ) -> None:
        if not (math.isfinite(token_ttl_s) and 0.0 < token_ttl_s <= MAX_TOKEN_TTL_S):
            raise ValueError(f"token lifetime must be in (0, {MAX_TOKEN_TTL_S:g}] s")
        if auth is None and not insecure and not is_loopback(host):
            raise ValueError(
                f"the lobby would hand room tokens to anyone who reaches {host}: give it a "
                "--token-file (or --insecure)"
            )
        make_room_token(secret, "default", "user", clock() + 1.0)  # a usable secret, or raise
        if isinstance(backend, LocalServers) and backend.room_token is None:
            # the handshake that makes a room carries the token its user will get (a server
            # with tokens makes the room at once only then, so /status counts it at once)
            backend.room_token = self._user_token
        self.backend = backend
        self._secret = secret
        self.host = host
        self.port = port
        self.token_ttl_s = float(token_ttl_s)
        self.auth = auth
        self.ssl_context = ssl_context
        self.clock = clock
        self.read_timeout_s = float(read_timeout_s)
        self.trusted_proxies = parse_proxies(trusted_proxies)
        self.connections = ConnectionCounts(max_connections_per_address, max_connections)
        self.budgets = AddressBudgets(ADDRESS_RATE_PER_S, ADDRESS_BURST)
        self.peers = peers
        self.metrics_token = metrics_token
        #: Time each room request took to get its placement (``/metrics``).
        self.placement_times = PlacementTimes()
        #: The registry ``/metrics`` exposes (:mod:`server.lobby_metrics`).
        self.metrics_registry = lobby_registry(self)
        self._flights: dict[str, asyncio.Future[Placement]] = {}
        self._placements = asyncio.Semaphore(MAX_PLACEMENTS)
        self._server: Server | None = None
        #: Answers given, by HTTP status (the tests, /healthz and /metrics read it).
        self.answered: dict[int, int] = {}
        #: Connections cut off before their request was read (too slow, too large).
        self.dropped = 0
        #: Events by (kind, reason), read by /metrics: ``connections_refused`` (``budget``,
        #: ``address``, ``total``), ``dropped`` (why), ``rooms_refused`` (``full``, ``busy``, an
        #: HTTP status), ``placement_busy``, ``peer_asked``, ``peer_requests``.
        self.counts: dict[tuple[str, str], int] = {}

    # -- the service -------------------------------------------------------------------------
    async def start(self) -> None:
        """Listen; :attr:`port` is the port taken."""
        connection = type("BoundLobbyConnection", (LobbyConnection,), {"lobby": self})
        self._server = await serve(
            self._never_upgraded,
            self.host,
            self.port,
            process_request=self._process_request,
            ssl=self.ssl_context,
            ssl_handshake_timeout=self.read_timeout_s if self.ssl_context is not None else None,
            open_timeout=None,  # the read deadline is LobbyConnection's; the answer's, ours
            server_header=None,
            create_connection=connection,
            backlog=LISTEN_BACKLOG,
            logger=logging.getLogger("haptic.lobby.http"),
        )
        self.port = int(next(iter(self._server.sockets)).getsockname()[1])
        scheme = "https" if self.ssl_context is not None else "http"
        log.info(
            "lobby listening on %s://%s:%d (%s)",
            scheme, url_host(self.host), self.port, self.backend.describe()["backend"],
        )  # fmt: skip

    async def stop(self) -> None:
        """Stop listening and give up the placements under way (their waiters are gone)."""
        for flight in list(self._flights.values()):
            flight.cancel()
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

    def _count(self, kind: str, reason: str = "") -> None:
        self.counts[kind, reason] = self.counts.get((kind, reason), 0) + 1

    def _dropped(self, why: str) -> None:
        self.dropped += 1
        self._count("dropped", why)
        log.info("lobby: a connection cut off: %s", why)

    async def _process_request(self, connection: ServerConnection, request: Request) -> Response:
        """Answer one request (websockets has parsed it: GET, no body, bounded lines)."""
        peer = str(getattr(connection, "peer", "?"))
        try:
            address = client_address(
                peer, request.headers.get_all("X-Forwarded-For"), self.trusted_proxies
            )
        except ValueError as exc:
            return self._answer(HTTPStatus.BAD_REQUEST, str(exc))
        try:
            async with asyncio.timeout(ANSWER_TIMEOUT_S):
                return await self._handle(request, address)
        except TimeoutError:
            return self._answer(
                HTTPStatus.SERVICE_UNAVAILABLE,
                "no answer in time; try again",
                [("Retry-After", "1")],
            )
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

    async def _handle(self, request: Request, address: str) -> Response:
        path = urlsplit(request.path).path
        if path.startswith(PEER_PATH) and self._from_peer(path, request.headers):
            return await self._serve_peer(path[len(PEER_PATH) :])  # a replica: no budget
        if not self.budgets.take(address, time.monotonic()):
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
        if parts.path == "/metrics":
            return self._metrics(request.headers.get("Authorization"))
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
            return self._refusal(exc)
        return self._answer(HTTPStatus.OK, answer)

    def _metrics(self, authorization: str | None) -> Response:
        """``/metrics`` in Prometheus' text format, for those :func:`scrape_allowed` admits."""
        if not scrape_allowed(is_loopback(self.host), authorization, self.metrics_token):
            if self.metrics_token is None:
                return self._answer(
                    HTTPStatus.FORBIDDEN, "/metrics off loopback needs a metrics token"
                )
            return self._answer(
                HTTPStatus.UNAUTHORIZED,
                "a metrics token is needed (Bearer)",
                [("WWW-Authenticate", 'Bearer realm="metrics"')],
            )
        self.answered[200] = self.answered.get(200, 0) + 1
        body = generate_latest(self.metrics_registry)
        headers = Headers(
            [
                ("Content-Type", CONTENT_TYPE_LATEST),
                ("Content-Length", str(len(body))),
                ("Cache-Control", "no-store"),
                ("Connection", "close"),
            ]
        )
        return Response(200, "OK", headers, body)

    def _refusal(self, exc: LobbyError) -> Response:
        retry = [] if exc.retry_after_s is None else [("Retry-After", str(exc.retry_after_s))]
        return self._answer(exc.status, exc.message, retry)

    def _from_peer(self, path: str, headers: Headers) -> bool:
        """Whether a ``/peer/place/NAME`` request carries a replica's signature for NAME."""
        scheme, _, value = headers.get("Authorization", "").partition(" ")
        return scheme == "Peer" and check_peer_request(
            self._secret, path[len(PEER_PATH) :], value, self.clock()
        )

    async def _serve_peer(self, name: str) -> Response:
        """Place room ``name`` for another replica (which signs the user's token itself)."""
        if not valid_room_name(name):
            return self._answer(HTTPStatus.BAD_REQUEST, f"{name[:40]!r} is not a room name")
        self._count("peer_requests")
        try:
            placement = await self._place_once(name, from_peer=True)
        except LobbyError as exc:
            return self._refusal(exc)
        return self._answer(HTTPStatus.OK, placement_json(placement))

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

    def _user_token(self, name: str) -> str:
        """A user's room token for room ``name``, valid :attr:`token_ttl_s` seconds."""
        return make_room_token(self._secret, name, "user", int(self.clock() + self.token_ttl_s))

    async def join(self, name: str, role: Role) -> dict[str, Any]:
        """Where room ``name`` runs and a token for ``role`` in it (the answer's JSON).

        A request for a name whose placement is under way gets that placement's outcome (it
        does not place the name again), so a name is placed once; with :attr:`peers`, by the
        replica that owns it.

        Raises
        ------
        LobbyError
            What the back end refused (404, 502, 503), or 503 for a user when the room is full
            (a viewer may still watch).
        """
        started = time.monotonic()
        try:
            placement = await self._place_once(name)
        except LobbyError as exc:
            busy = "busy placing" in exc.message
            self._count("rooms_refused", "busy" if busy else str(exc.status.value))
            raise
        finally:
            self.placement_times.add(time.monotonic() - started)
        if placement.full and role == "user":
            self._count("rooms_refused", "full")
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

    async def _place_once(self, name: str, *, from_peer: bool = False) -> Placement:
        """The placement of ``name``: the one under way, else a new one (:meth:`_place`)."""
        flight = self._flights.get(name)
        if flight is None:
            flight = asyncio.ensure_future(self._place(name, from_peer=from_peer))
            self._flights[name] = flight

            def done(f: asyncio.Future[Placement]) -> None:
                if self._flights.get(name) is f:
                    del self._flights[name]
                if not f.cancelled():
                    f.exception()  # retrieved: a failure every waiter left is not logged

            flight.add_done_callback(done)
        # a waiter that gives up (its answer's deadline) leaves the placement to the others
        return await asyncio.shield(flight)

    async def _place(self, name: str, *, from_peer: bool) -> Placement:
        """Place ``name`` here, or have its owner among :attr:`peers` place it.

        Raises
        ------
        LobbyError
            503 with ``Retry-After`` when :data:`MAX_PLACEMENTS` placements stay under way for
            :data:`PLACEMENT_WAIT_S`; what the back end or the owner refused.
        """
        try:
            async with asyncio.timeout(PLACEMENT_WAIT_S):
                await self._placements.acquire()
        except TimeoutError:
            self._count("placement_busy")
            raise LobbyError(
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"the lobby is busy placing {MAX_PLACEMENTS} other rooms; try again",
            ) from None
        try:
            peers = self.peers
            owner = None if peers is None or from_peer else peers.owner(name)
            if peers is not None and owner is not None and owner != peers.self_url:
                self._count("peer_asked")
                return await peers.ask(owner, name, self._secret)
            return await self.backend.place(name)
        finally:
            self._placements.release()
