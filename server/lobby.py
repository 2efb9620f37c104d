"""``haptic lobby``: finding a room. Maps a room name to a server's address and a room token.

A client asks ``GET /rooms/NAME?role=user`` (``role=viewer`` to watch; user by default) and
gets ``{"url": "ws://HOST:PORT/rooms/NAME/ws", "token": ..., "expires": ..., "viewer":
"http://HOST:PORT/rooms/NAME/#token=...", "server": ...}``: where room NAME runs, and a room
token for it (:func:`server.security.make_room_token`, signed with the secret the lobby shares
with the room servers' ``--token-secret-file``). Two back ends find the server:

- :class:`LocalServers` (``--server URL``, repeated, or a TOML file): reads every room server's
  ``/status`` and picks the one already running the room; else one that makes rooms on demand
  and has a free room slot (the most free slots first), where it makes the room now by opening
  and closing a websocket to ``/rooms/NAME/ws`` (the server builds it from its template; a
  server whose templates do not allow the name answers 404 and the next one is tried); else
  no capacity (503). A draining server is never picked.
- :class:`AgonesAllocator` (``--agones-allocator URL``): one GameServerAllocation
  (``allocation.agones.dev/v1``) through the allocator service's REST API (``POST
  /gameserverallocation``, Agones' ``allocation.swagger.json``) with three selectors in order: a
  server of the fleet whose ``rooms`` list holds NAME, else an Allocated one with a free slot
  in ``rooms``, else a Ready one; the allocation adds NAME to the chosen server's ``rooms``
  list (``lists.rooms.addValues``, which ignores a value already there).

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
import functools
import json
import logging
import math
import ssl
import time
import tomllib
import urllib.error
import urllib.request
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.client import connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import InvalidHandshake, InvalidStatus
from websockets.http11 import Request, Response

from haptic_collab.server.security import (
    MAX_TOKEN_TTL_S,
    Role,
    TokenBucket,
    TokenTable,
    is_loopback,
    make_room_token,
)
from haptic_collab.server.urls import room_page_path, room_ws_path, url_host, valid_room_name

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
#: Time to wait for a room server's ``/status`` or for the allocator [s].
BACKEND_TIMEOUT_S = 5.0
#: Time a room server may take to make a room from its template [s]: it answers the websocket
#: handshake only once the room runs, and a FEM solid takes seconds to build.
ROOM_BUILD_TIMEOUT_S = 60.0
#: Largest ``/status`` or allocation answer read [bytes].
MAX_ANSWER_BYTES = 1 << 20
#: Rooms made that :attr:`LocalServers.made` remembers (the newest).
MADE_KEPT = 256
#: The Agones list that names the rooms a GameServer runs (server/agones.py lists them).
ROOMS_LIST = "rooms"
#: Allocations retried when the allocator answers Contention (409) [attempts].
CONTENTION_RETRIES = 3


class LobbyError(Exception):
    """A request the lobby cannot serve: the HTTP status and a one-line reason."""

    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass(frozen=True)
class Placement:
    """Where a room runs.

    Attributes
    ----------
    ws_base : str
        ``ws://HOST:PORT`` (or ``wss://``): the room's websocket is this plus its path.
    http_base : str
        ``http://HOST:PORT`` (or ``https://``): its viewer page is this plus its path.
    server : str
        Which server: the ``--server`` URL, or the GameServer's name.
    created : bool
        The lobby made the room (local) or added it to the server's list (Agones) now.
    full : bool
        The room has no seat for another user (its users and held seats reach its cap, as its
        server's ``/status`` says; the Agones back end does not know).
    """

    ws_base: str
    http_base: str
    server: str
    created: bool = False
    full: bool = False


class Backend(Protocol):
    """Finds (and makes) the server of a room: :class:`LocalServers`, :class:`AgonesAllocator`."""

    async def place(self, name: str) -> Placement:
        """The server of room ``name``. Raises :class:`LobbyError` (404, 502, 503)."""
        ...

    def describe(self) -> dict[str, Any]:
        """What the back end is, for the lobby's ``/healthz``."""
        ...


def _bases(url: str) -> tuple[str, str]:
    """``(ws_base, http_base)`` of a server URL of any of the four schemes, without a path.

    Raises
    ------
    ValueError
        Not an ``http``, ``https``, ``ws`` or ``wss`` URL with a host.
    """
    parts = urlsplit(url.strip())
    if parts.scheme not in ("http", "https", "ws", "wss") or not parts.hostname:
        raise ValueError(f"a room server is http(s)://HOST:PORT or ws(s)://HOST:PORT, got {url!r}")
    secure = parts.scheme in ("https", "wss")
    netloc = parts.netloc.rsplit("@", 1)[-1]
    return (
        f"{'wss' if secure else 'ws'}://{netloc}",
        f"{'https' if secure else 'http'}://{netloc}",
    )


@dataclass(frozen=True)
class RoomServer:
    """One room server of the local back end.

    Attributes
    ----------
    url : str
        Where the lobby reaches it: ``http://HOST:PORT`` (``https://`` with TLS).
    public : str
        Where clients reach it (its ``ws(s)://HOST:PORT``); by default the same host and port.
    """

    url: str
    public: str = ""

    @classmethod
    def parse(cls, text: str) -> RoomServer:
        """``URL`` or ``URL=PUBLIC_URL`` (``--server``): where the lobby reaches a server, and
        where clients do when that differs (a container network, a port mapping).

        Raises
        ------
        ValueError
            A URL that is not ``http(s)://`` or ``ws(s)://`` with a host.
        """
        url, sep, public = text.strip().partition("=")
        _bases(url)
        if sep:
            _bases(public)
        return cls(url.rstrip("/"), public.rstrip("/") if sep else "")

    @property
    def bases(self) -> tuple[str, str]:
        """``(ws_base, http_base)`` clients are given."""
        return _bases(self.public or self.url)


def load_servers(path: str | Path) -> list[RoomServer]:
    """The room servers of a TOML file: ``[[servers]]`` tables with ``url`` and ``public``.

    Raises
    ------
    ValueError
        An unreadable file, bad TOML, no server, or a bad URL.
    """
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: {exc}") from None
    entries = data.get("servers")
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{path}: no [[servers]] tables (each with url = 'http://HOST:PORT')")
    out = []
    for i, entry in enumerate(entries, start=1):
        if not isinstance(entry, dict) or not isinstance(entry.get("url"), str):
            raise ValueError(f"{path}: server {i} has no url")
        public = entry.get("public", "")
        if not isinstance(public, str):
            raise ValueError(f"{path}: server {i}: public must be a URL")
        out.append(RoomServer.parse(entry["url"] + (f"={public}" if public else "")))
    return out


#: Threads of the lobby's own pool for requests to the back end: a back end's blocking HTTP
#: never waits behind other work of the process's default executor (nor holds it up).
BACKEND_THREADS = 8
_POOL: ThreadPoolExecutor | None = None


async def _in_pool(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Run ``fn`` in the lobby's own thread pool (:data:`BACKEND_THREADS`)."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(BACKEND_THREADS, thread_name_prefix="lobby-backend")
    return await asyncio.get_running_loop().run_in_executor(
        _POOL, functools.partial(fn, *args, **kwargs)
    )


def _http_json(
    method: str,
    url: str,
    body: Any = None,
    *,
    timeout_s: float = BACKEND_TIMEOUT_S,
    context: ssl.SSLContext | None = None,
) -> tuple[int, Any]:
    """One HTTP request with a JSON body and answer, blocking (run it in a thread).

    Returns
    -------
    status : int
        The HTTP status (an error status is returned, not raised).
    answer : object
        The decoded JSON answer, or the answer's text when it is not JSON (at most
        :data:`MAX_ANSWER_BYTES`).

    Raises
    ------
    OSError
        Nothing answers, or the connection failed (urllib's URLError is an OSError).
    """
    data = None if body is None else json.dumps(body).encode()
    headers = {"Accept": "application/json"}
    if data is not None:
        headers["Content-Type"] = "application/json"
    req = urllib.request.Request(url, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=timeout_s, context=context) as resp:
            status, raw = resp.status, resp.read(MAX_ANSWER_BYTES)
    except urllib.error.HTTPError as exc:
        status, raw = exc.code, exc.read(MAX_ANSWER_BYTES)
    try:
        return status, json.loads(raw)
    except ValueError:
        return status, raw.decode("utf-8", "replace").strip()


# ------------------------------------------------------------------------------ local back end
class LocalServers:
    """The local back end: a fixed list of room servers, each asked for its ``/status``.

    Parameters
    ----------
    servers : sequence of RoomServer
        The room servers, in the order ties are broken.
    timeout_s : float
        Time to wait for each server's ``/status`` [s].
    context : ssl.SSLContext, optional
        TLS context for ``https://`` servers (default: the system's CAs).
    build_timeout_s : float
        Time a server may take to make a room [s] (:data:`ROOM_BUILD_TIMEOUT_S`).

    Raises
    ------
    ValueError
        No server.
    """

    def __init__(
        self,
        servers: Sequence[RoomServer],
        timeout_s: float = BACKEND_TIMEOUT_S,
        context: ssl.SSLContext | None = None,
        build_timeout_s: float = ROOM_BUILD_TIMEOUT_S,
    ) -> None:
        if not servers:
            raise ValueError("the local lobby needs at least one room server (--server URL)")
        self.servers = list(servers)
        self.timeout_s = float(timeout_s)
        self.context = context
        self.build_timeout_s = float(build_timeout_s)
        #: The last rooms the lobby made: (server URL, room name), oldest first.
        self.made: deque[tuple[str, str]] = deque(maxlen=MADE_KEPT)

    def describe(self) -> dict[str, Any]:
        return {"backend": "local", "servers": [s.url for s in self.servers]}

    async def status(self, server: RoomServer) -> dict[str, Any] | None:
        """A server's ``/status`` (None: it did not answer, or not with a status)."""
        try:
            code, answer = await _in_pool(
                _http_json, "GET", server.url + "/status", timeout_s=self.timeout_s,
                context=self.context,
            )  # fmt: skip
        except OSError as exc:
            log.warning("room server %s: no status (%s)", server.url, exc)
            return None
        if code != 200 or not isinstance(answer, dict) or not isinstance(answer.get("rooms"), dict):
            log.warning("room server %s: no status (HTTP %s)", server.url, code)
            return None
        return answer

    async def make_room(self, server: RoomServer, name: str) -> int:
        """Have ``server`` make room ``name`` from its template: open a websocket to the room's
        path (the server builds the room before it accepts the handshake) and close it.

        Returns
        -------
        int
            101 when the room runs now; else the server's HTTP status (404: no template allows
            the name, 503: full or draining), or 0 when it could not be reached.

        Raises
        ------
        LobbyError
            503 when the server took longer than ``build_timeout_s`` to answer: it may
            still be making the room, so no other server is asked to make it too.
        """
        ws_base = _bases(server.url)[0]
        url = ws_base + room_ws_path(name)
        tls = self.context if url.startswith("wss://") else None
        try:
            async with connect(url, open_timeout=self.build_timeout_s, ssl=tls) as ws:
                await ws.close(1000, "lobby: room made")
        except InvalidStatus as exc:
            return int(exc.response.status_code)
        except TimeoutError:
            log.warning("room server %s: still making room %r", server.url, name)
            raise LobbyError(
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"room {name!r} is still being made on a server; ask again in a moment",
            ) from None
        except (OSError, InvalidHandshake) as exc:
            log.warning("room server %s: could not make room %r (%s)", server.url, name, exc)
            return 0
        return 101

    async def place(self, name: str) -> Placement:
        """The server running room ``name``, else one that makes it now (see the module).

        Raises
        ------
        LobbyError
            503 when no server runs it and none that makes rooms has a free slot (or none
            answers), 404 when no server runs it and none may make a room of that name.
        """
        statuses = await asyncio.gather(*(self.status(s) for s in self.servers))
        up = [(s, st) for s, st in zip(self.servers, statuses, strict=True) if st is not None]
        live = [(s, st) for s, st in up if not st.get("draining")]
        for server, st in live:
            if name in st["rooms"]:
                ws, http = server.bases
                figures = st["rooms"][name] if isinstance(st["rooms"][name], dict) else {}
                try:
                    seats = int(figures.get("users", 0)) + int(figures.get("held_seats", 0))
                    full = seats >= int(figures["max_users"])
                except (KeyError, TypeError, ValueError):
                    full = False
                return Placement(ws, http, server.url, full=full)
        free = [
            (int(st.get("max_rooms", 0)) - len(st["rooms"]), i, server)
            for i, (server, st) in enumerate(live)
            if st.get("rooms_on_demand") and len(st["rooms"]) < int(st.get("max_rooms", 0))
        ]
        free.sort(key=lambda f: (-f[0], f[1]))  # the most free slots first, then in order
        answers = []
        for _, _, server in free:
            code = await self.make_room(server, name)
            answers.append(code)
            if code == 101:
                self.made.append((server.url, name))
                log.info("room %r made on %s", name, server.url)
                ws, http = server.bases
                return Placement(ws, http, server.url, created=True)
        if not up:
            raise LobbyError(HTTPStatus.SERVICE_UNAVAILABLE, "no room server answers; try later")
        if not free and not any(st.get("rooms_on_demand") for _, st in live):
            raise LobbyError(
                HTTPStatus.NOT_FOUND,
                f"no server runs room {name!r} and none makes rooms on demand",
            )
        if answers and all(a == 404 for a in answers):
            raise LobbyError(
                HTTPStatus.NOT_FOUND,
                f"no server runs room {name!r} and none may make a room of that name",
            )
        raise LobbyError(
            HTTPStatus.SERVICE_UNAVAILABLE,
            f"no room server has a free room slot for {name!r}; try later",
        )


# ----------------------------------------------------------------------------- Agones back end
def allocation_request(
    name: str,
    *,
    namespace: str = "default",
    match_labels: dict[str, str] | None = None,
    list_name: str = ROOMS_LIST,
) -> dict[str, Any]:
    """The GameServerAllocation request (allocator REST, ``allocationAllocationRequest``) that
    places room ``name``.

    Three ``gameServerSelectors``, tried in order by Agones: an Allocated server whose list
    ``list_name`` contains ``name``; an Allocated one with at least one free slot in that list;
    a Ready one. ``lists.<list_name>.addValues`` adds the name to whichever is chosen (Agones
    ignores a value already there), so the next request for the name matches the first
    selector. ``Packed`` scheduling fills Allocated servers before it takes a Ready one.
    int64 fields are decimal strings (proto3 JSON).

    Parameters
    ----------
    name : str
        A room name (:func:`server.urls.valid_room_name`).
    namespace : str
        The Kubernetes namespace of the fleet.
    match_labels : dict, optional
        Labels every selector requires, e.g. ``{"agones.dev/fleet": "haptic-collab"}``.
    list_name : str
        The Fleet's list of rooms (:data:`ROOMS_LIST`).

    Returns
    -------
    dict
        The request body.

    Source
    ------
    Agones ``pkg/allocation/go/allocation.swagger.json`` (v1.56) and the GameServerAllocation
    reference (``allocation.agones.dev/v1``: selectors, Counters and Lists actions).
    """
    labels = dict(match_labels or {})

    def selector(state: str, lists: dict[str, Any] | None) -> dict[str, Any]:
        sel: dict[str, Any] = {"gameServerState": state}
        if labels:
            sel["matchLabels"] = labels
        if lists is not None:
            sel["lists"] = {list_name: lists}
        return sel

    return {
        "namespace": namespace,
        "gameServerSelectors": [
            selector("ALLOCATED", {"containsValue": name}),
            selector("ALLOCATED", {"minAvailable": "1"}),
            selector("READY", None),
        ],
        "scheduling": "Packed",
        "lists": {list_name: {"addValues": [name]}},
    }


class AgonesAllocator:
    """The Agones back end: the allocator service's REST API (``POST /gameserverallocation``).

    Parameters
    ----------
    url : str
        The allocator service, ``https://HOST:PORT`` (the allocator speaks mutual TLS: give
        ``context`` with the client certificate), or ``http://`` for a stand-in.
    namespace : str
        The fleet's namespace.
    match_labels : dict, optional
        Labels every selector requires (e.g. the fleet's ``agones.dev/fleet``).
    port_name : str, optional
        The GameServer port clients use (default: the first port of the answer).
    scheme : {"ws", "wss"}
        What clients speak to the servers (``wss`` behind TLS).
    context : ssl.SSLContext, optional
        TLS context for the allocator (client certificate and CA).
    timeout_s : float
        Time to wait for the allocator [s].
    """

    def __init__(
        self,
        url: str,
        *,
        namespace: str = "default",
        match_labels: dict[str, str] | None = None,
        port_name: str | None = None,
        scheme: str = "ws",
        context: ssl.SSLContext | None = None,
        timeout_s: float = BACKEND_TIMEOUT_S,
    ) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"the Agones allocator is https://HOST:PORT, got {url!r}")
        if scheme not in ("ws", "wss"):
            raise ValueError(f"scheme must be ws or wss, got {scheme!r}")
        self.url = url.rstrip("/")
        self.namespace = namespace
        self.match_labels = dict(match_labels or {})
        self.port_name = port_name
        self.scheme = scheme
        self.context = context
        self.timeout_s = float(timeout_s)

    def describe(self) -> dict[str, Any]:
        return {"backend": "agones", "allocator": self.url, "namespace": self.namespace}

    def placement(self, name: str, answer: Any) -> Placement:
        """Where an ``allocationAllocationResponse`` says room ``name`` runs.

        Raises
        ------
        LobbyError
            502 when the answer has no address or no port (of ``port_name``).
        """
        if not isinstance(answer, dict):
            raise LobbyError(HTTPStatus.BAD_GATEWAY, "the allocator's answer is not an object")
        address = answer.get("address")
        ports = [p for p in answer.get("ports") or [] if isinstance(p, dict)]
        if self.port_name is not None:
            ports = [p for p in ports if p.get("name") == self.port_name]
        port = ports[0].get("port") if ports else None
        if not isinstance(address, str) or not address or not isinstance(port, int):
            raise LobbyError(
                HTTPStatus.BAD_GATEWAY, "the allocator's answer has no address or port"
            )
        values = ((answer.get("lists") or {}).get(ROOMS_LIST) or {}).get("values")
        if isinstance(values, list) and name not in values:
            log.warning(
                "allocated %s, but its rooms list lacks %r", answer.get("gameServerName"), name
            )
        host = f"{url_host(address)}:{port}"
        http = "https" if self.scheme == "wss" else "http"
        return Placement(
            f"{self.scheme}://{host}", f"{http}://{host}", str(answer.get("gameServerName", host))
        )

    async def place(self, name: str) -> Placement:
        """Allocate the server of room ``name`` (:func:`allocation_request`).

        Raises
        ------
        LobbyError
            503 when Agones has no server to allocate (429, ResourceExhausted) or stays in
            contention (409, Aborted) after :data:`CONTENTION_RETRIES` tries; 502 when the
            allocator cannot be reached or answers otherwise.
        """
        body = allocation_request(name, namespace=self.namespace, match_labels=self.match_labels)
        for attempt in range(CONTENTION_RETRIES):
            try:
                code, answer = await _in_pool(
                    _http_json, "POST", self.url + "/gameserverallocation", body,
                    timeout_s=self.timeout_s, context=self.context,
                )  # fmt: skip
            except OSError as exc:
                log.error("the Agones allocator %s cannot be reached: %s", self.url, exc)
                raise LobbyError(
                    HTTPStatus.BAD_GATEWAY, "the Agones allocator cannot be reached"
                ) from None
            if code == 200:
                return self.placement(name, answer)
            if code == HTTPStatus.TOO_MANY_REQUESTS:  # ResourceExhausted: nothing to allocate
                raise LobbyError(
                    HTTPStatus.SERVICE_UNAVAILABLE, f"no game server free for room {name!r}"
                )
            if code != HTTPStatus.CONFLICT:  # Aborted: contention, try again
                break
            await asyncio.sleep(0.05 * (attempt + 1))
        log.error("the Agones allocator answered %s: %.200s", code, answer)
        if code == HTTPStatus.CONFLICT:
            raise LobbyError(HTTPStatus.SERVICE_UNAVAILABLE, "the allocator is busy; try again")
        raise LobbyError(HTTPStatus.BAD_GATEWAY, f"the Agones allocator answered {code}")


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
