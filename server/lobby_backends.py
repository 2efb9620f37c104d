"""The lobby's two back ends: where a room runs, and making it there (:mod:`server.lobby`).

:class:`LocalServers` (``--server URL``) reads every room server's ``/status`` and picks the one
running the room, else makes it on one with a free slot; :class:`AgonesAllocator`
(``--agones-allocator URL``) asks for one GameServerAllocation whose list selectors find the
server whose ``rooms`` list holds the name, else one with a free slot, and add the name to it.
Both speak blocking HTTP (urllib) in the lobby's own thread pool (:data:`BACKEND_THREADS`),
each call bounded in time; a timeout is a 503 with ``Retry-After``.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import ssl
import tomllib
import urllib.error
import urllib.request
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import urlsplit

from websockets.asyncio.client import connect
from websockets.exceptions import InvalidHandshake, InvalidStatus

from haptic_collab.server.urls import room_ws_path, url_host

log = logging.getLogger("haptic.lobby")

#: Time to wait for a room server's ``/status`` or for the allocator [s].
BACKEND_TIMEOUT_S = 5.0
#: ``Retry-After`` of a 503 that says nothing more precise [s].
RETRY_AFTER_S = 1
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
    """A request the lobby cannot serve: the HTTP status and a one-line reason.

    Parameters
    ----------
    status : HTTPStatus
        The answer's status.
    message : str
        One line for the user.
    retry_after_s : int, optional
        For a 503 or 429: seconds after which asking again may work (the ``Retry-After``
        header); None: :data:`RETRY_AFTER_S` for a 503, no header otherwise.
    """

    def __init__(self, status: HTTPStatus, message: str, retry_after_s: int | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        if retry_after_s is None and status == HTTPStatus.SERVICE_UNAVAILABLE:
            retry_after_s = RETRY_AFTER_S
        self.retry_after_s = retry_after_s


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
#: never waits behind other work of the process's default executor (nor holds it up). The
#: lobby runs at most ``MAX_PLACEMENTS`` (8) placements at once, each one allocation or one
#: ``/status`` per local server, so a pool this size does not queue them for up to 8 servers.
BACKEND_THREADS = 64
_POOL: ThreadPoolExecutor | None = None


async def _in_pool(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Run ``fn`` in the lobby's own thread pool (:data:`BACKEND_THREADS`)."""
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(BACKEND_THREADS, thread_name_prefix="lobby-backend")
    return await asyncio.get_running_loop().run_in_executor(
        _POOL, functools.partial(fn, *args, **kwargs)
    )


def _timed_out(exc: BaseException) -> bool:
    """Whether a failed request timed out (urllib wraps a connect timeout in a URLError)."""
    return isinstance(exc, TimeoutError) or isinstance(getattr(exc, "reason", None), TimeoutError)


def _http_json(
    method: str,
    url: str,
    body: Any = None,
    *,
    timeout_s: float = BACKEND_TIMEOUT_S,
    context: ssl.SSLContext | None = None,
    headers: dict[str, str] | None = None,
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
    headers = {"Accept": "application/json", **(headers or {})}
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
        """The server running room ``name``, else one not draining that makes it now (the
        most free slots first; docs/deploy.md).

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
        #: The allocator's answers by HTTP status (``"200"``, ``"429"``, ...), ``"timeout"``
        #: (none within ``timeout_s``) and ``"unreachable"`` (the lobby's ``/metrics``).
        self.answers: dict[str, int] = {}

    def _count(self, outcome: str) -> None:
        self.answers[outcome] = self.answers.get(outcome, 0) + 1

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
            503 when Agones has no server to allocate (429, ResourceExhausted), stays in
            contention (409, Aborted) after :data:`CONTENTION_RETRIES` tries or does not answer
            within ``timeout_s``; 502 when the allocator cannot be reached or answers
            otherwise. :attr:`answers` counts each answer.
        """
        body = allocation_request(name, namespace=self.namespace, match_labels=self.match_labels)
        for attempt in range(CONTENTION_RETRIES):
            try:
                code, answer = await _in_pool(
                    _http_json, "POST", self.url + "/gameserverallocation", body,
                    timeout_s=self.timeout_s, context=self.context,
                )  # fmt: skip
            except OSError as exc:
                self._count("timeout" if _timed_out(exc) else "unreachable")
                if _timed_out(exc):
                    log.error(
                        "the Agones allocator %s: no answer in %g s", self.url, self.timeout_s
                    )
                    raise LobbyError(
                        HTTPStatus.SERVICE_UNAVAILABLE,
                        f"the Agones allocator did not answer within {self.timeout_s:g} s; "
                        "try again",
                    ) from None
                log.error("the Agones allocator %s cannot be reached: %s", self.url, exc)
                raise LobbyError(
                    HTTPStatus.BAD_GATEWAY, "the Agones allocator cannot be reached"
                ) from None
            self._count(str(code))
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
