"""The lobby's back ends: where a room runs, and making it there (:mod:`server.lobby`).

:class:`LocalServers` (``--server URL``) reads every room server's ``/status`` and picks the one
running the room, else makes it on one with a free slot; the Agones back end
(:mod:`server.lobby_agones`) asks the allocator. Both speak blocking HTTP (urllib) in the
lobby's own thread pool (:data:`BACKEND_THREADS`), each call bounded in time; a timeout is a 503 with ``Retry-After``.
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

from haptic_collab.server.urls import room_ws_path

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


def load_status_token(path: str | Path) -> str:
    """The room servers' metrics token of a file (its one line, whitespace stripped), which
    :class:`LocalServers` sends with each ``/status`` request (``--status-token-file``).

    Raises
    ------
    ValueError
        A file that cannot be read, or whose content is not one token (16-256 printable
        characters without spaces or ``#``); the message never shows the file's content.
    """
    from haptic_collab.server.main import ServerOptions, build_metrics_token

    build_metrics_token(ServerOptions(metrics_token_file=str(path)))  # readable, one token
    return Path(path).read_text(encoding="utf-8").strip()


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
    room_token : callable, optional
        ``room_token(name)``: a room token for room ``name`` (a user's, signed with the secret
        the servers share), sent as ``Authorization: Bearer`` in the handshake that makes the
        room: a server with tokens makes a room at the handshake only for a token that names it
        (docs/rooms-operations.md). :class:`server.lobby.Lobby` sets it (its own signer) when
        None. Without one the handshake carries no token.
    status_token : str, optional
        The servers' metrics token (their ``--metrics-token-file``), sent as ``Authorization:
        Bearer`` with each ``/status`` request: a server listening off loopback answers
        ``/status`` only with it (401 with another or none, 403 when it has none).

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
        *,
        room_token: Callable[[str], str] | None = None,
        status_token: str | None = None,
    ) -> None:
        if not servers:
            raise ValueError("the local lobby needs at least one room server (--server URL)")
        self.servers = list(servers)
        self.timeout_s = float(timeout_s)
        self.context = context
        self.build_timeout_s = float(build_timeout_s)
        self.room_token = room_token
        self.status_token = status_token
        #: The last rooms the lobby made: (server URL, room name), oldest first.
        self.made: deque[tuple[str, str]] = deque(maxlen=MADE_KEPT)

    def describe(self) -> dict[str, Any]:
        return {"backend": "local", "servers": [s.url for s in self.servers]}

    async def status(self, server: RoomServer) -> dict[str, Any] | None:
        """A server's ``/status`` (None: it did not answer, or not with a status), asked with
        :attr:`status_token` when there is one."""
        headers = (
            {} if self.status_token is None else {"Authorization": f"Bearer {self.status_token}"}
        )
        try:
            code, answer = await _in_pool(
                _http_json, "GET", server.url + "/status", timeout_s=self.timeout_s,
                context=self.context, headers=headers,
            )  # fmt: skip
        except OSError as exc:
            log.warning("room server %s: no status (%s)", server.url, exc)
            return None
        if code in (HTTPStatus.UNAUTHORIZED, HTTPStatus.FORBIDDEN):
            log.warning(
                "room server %s refuses its /status to the lobby (HTTP %s): off loopback it "
                "answers only with its metrics token; %s",
                server.url,
                code,
                "give the server --metrics-token-file"
                if code == HTTPStatus.FORBIDDEN
                else "give the lobby the same token (--status-token-file)",
            )
            return None
        if code != 200 or not isinstance(answer, dict) or not isinstance(answer.get("rooms"), dict):
            log.warning("room server %s: no status (HTTP %s)", server.url, code)
            return None
        return answer

    async def make_room(self, server: RoomServer, name: str) -> int:
        """Have ``server`` make room ``name`` from its template: open a websocket to the room's
        path with the room's token (:attr:`room_token`) as ``Authorization: Bearer`` (the server
        builds the room before it accepts the handshake) and close it.

        Returns
        -------
        int
            101 when the room runs now; else the server's HTTP status (404: no template allows
            the name, 503: full or draining, 401: the server does not take the lobby's room
            token), or 0 when it could not be reached.

        Raises
        ------
        LobbyError
            503 when the server took longer than ``build_timeout_s`` to answer: it may
            still be making the room, so no other server is asked to make it too.
        """
        ws_base = _bases(server.url)[0]
        url = ws_base + room_ws_path(name)
        tls = self.context if url.startswith("wss://") else None
        headers = {}
        if self.room_token is not None:
            headers["Authorization"] = f"Bearer {self.room_token(name)}"
        try:
            async with connect(
                url, open_timeout=self.build_timeout_s, ssl=tls, additional_headers=headers
            ) as ws:
                await ws.close(1000, "lobby: room made")
        except InvalidStatus as exc:
            code = int(exc.response.status_code)
            if code == HTTPStatus.UNAUTHORIZED:
                log.error(
                    "room server %s refuses the lobby's token for room %r: its "
                    "--token-secret-file is not the lobby's",
                    server.url,
                    name,
                )
            return code
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
            answers, or every one refuses its ``/status`` to the lobby), 404 when no server runs
            it and none may make a room of that name, 502 when every server with a free slot
            refused the lobby's room token (another token secret).
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
        if answers and all(a == HTTPStatus.UNAUTHORIZED for a in answers):
            raise LobbyError(
                HTTPStatus.BAD_GATEWAY,
                f"the room servers refuse the lobby's token for room {name!r}: their token "
                "secret is not the lobby's",
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
