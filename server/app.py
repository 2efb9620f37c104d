"""The server's asyncio layer: websockets, static files, the simulation schedules, latency injection.

Everything that decides anything lives in :class:`server.room.Room`; this module only moves
frames between sockets and the rooms, wakes each room at its timer and injects latency. HTTP
``/`` serves the viewer (web/), ``/vendor/three/...`` the three.js package from web/node_modules,
``/status`` a JSON summary (off loopback only with the metrics token); the websocket endpoint is
``/ws``.

Rooms: a server runs several rooms by name, each its own :class:`server.room.Room` (object,
rates, caps, tokens) with its own simulation loop task, so no room waits for another's tick
(:class:`_Slot`). ``/ws`` and ``/`` are the default room's (:data:`DEFAULT_ROOM`);
``/rooms/NAME/ws`` and ``/rooms/NAME/`` room NAME's (:mod:`server.urls`). Rooms are given at the
start (the configuration's ``[rooms.NAME]``) or built on demand by a :class:`RoomMaker` (its
``[room_templates]``) when a client first joins a name it allows, up to ``max_rooms``; an
on-demand room is closed after ``room_idle_s`` without a connection. A bad name is answered 400,
a name no room has and no template allows 404, a full server 503. On a server with tokens
(``room_admits``) an on-demand room is made only for a connection whose token names it: an
``Authorization: Bearer`` token in the handshake (what a lobby can send), else the token of its
first frame, a ``hello`` (what a browser sends), read before any room exists; a connection
without one is closed and costs no room (:meth:`ServerApp._room_by_hello`). The routing of
connections to rooms is all in :meth:`ServerApp._process_request` and :meth:`ServerApp._handler`, and a room is
reached only through its slot, so that a room can later run in a process of its own.

With ``--room-processes`` a room is a :class:`server.room_process.RoomProxy`: its ``Room`` and
``World`` tick in a process of their own, this layer relays its connections' frames to it and
supervises it (:meth:`ServerApp._supervise`: a process that dies is reported to that room's
clients as ``room_restarting`` with close code 1012 and started again); the across-room address
budgets, origins and latency injection stay here.

Across rooms, one source address shares one budget (:data:`ADDRESS_LIMITS`, the router's
:attr:`ServerApp.flood`): its connections and its frames and bytes in every room together, at
most :data:`ADDRESS_ROOMS_FACTOR` times what one room allows it, so an address cannot multiply
its budget by spreading over rooms. Each room keeps its own budgets as before.

With an :class:`ssl.SSLContext` everything is served as ``https://`` and ``wss://``. Browser
handshakes are checked by ``Origin`` (:func:`server.security.origin_allowed`), each connection is
registered with its source address (the room budgets per address), and a consumer whose send
buffer stays full for ``send_timeout_s`` (10 s) is dropped, viewers included.

Stopping: :meth:`ServerApp.drain` (what SIGTERM runs, :func:`server.main.run_server`) takes no
new connection or room, stops every room's tick, saves each room's object state to the snapshot
directory (:mod:`server.snapshots`), tells every client ``server_draining`` and closes it with
code 1012, all within a grace period; a room made with a snapshot of its own in that directory
starts from it.

Flood control is the room's (:meth:`server.room.Room.admit`), charged when a frame arrives and
before latency injection holds it back. So is the simulation schedule: this layer sleeps until
:meth:`server.room.Room.get_timer` and calls :meth:`server.room.Room.handle_timer` (the room
skips missed ticks and, when the server is behind, credits the budgets so that the backlog
clients sent meanwhile is not taken for a flood). After every tick the loop yields to the event
loop, also when it is late, so the senders write each tick's frames before the next tick
replaces them (latest wins). Frames are sent uncompressed (no permessage-deflate): compression
took a fifth of the server's time at 32 users (docs/bench-load.md), and the viewer stream caps its
own bytes (:mod:`server.viewer_stream`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import mimetypes
import multiprocessing
import ssl
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any, Protocol

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from haptic_collab.client.workers import background_worker, check_worker, stop_pool
from haptic_collab.server import snapshots
from haptic_collab.server.admission import FloodControl, Refusal, RoomLimits
from haptic_collab.server.gains import GainJob, JobKind, run_job_measured
from haptic_collab.server.latency import LinkShaper
from haptic_collab.server.metrics import RoomFigures, ServerCollector, scrape_allowed
from haptic_collab.server.prefetch import PatchPrefetcher
from haptic_collab.server.priority import TickPriority
from haptic_collab.server.room import Outgoing, Room, is_bye
from haptic_collab.server.room_process import (
    RESTARTING_CODE,
    RESTARTING_MESSAGE,
    START_TIMEOUT_S,
    RoomEvents,
    RoomProxy,
)
from haptic_collab.server.security import TokenBucket, TokenTable, is_loopback, origin_allowed
from haptic_collab.server.urls import (
    DEFAULT_ROOM,
    RoomPath,
    room_page_path,
    room_path,
    room_ws_path,
    valid_room_name,
)
from haptic_collab.shared.gains.table import warm_up
from haptic_collab.shared.protocol import (
    ErrorMsg,
    Hello,
    LinkConditions,
    ProtocolError,
    encode,
    frame_size_bytes,
    parse_client,
)

log = logging.getLogger("haptic.server")

#: A room as the I/O layer holds it: in this process, or in a process of its own
#: (``--room-processes``, :class:`server.room_process.RoomProxy`).
AnyRoom = Room | RoomProxy

#: websockets' own frame limit; the room answers frames above its smaller limit with an error.
WS_MAX_SIZE = 64 * 1024
#: Rooms a server runs at most unless told otherwise (``haptic server --max-rooms``).
MAX_ROOMS = 16
#: An on-demand room without a connection for this long [s] is closed.
ROOM_IDLE_S = 300.0
#: Connections waiting for their ``hello`` before an on-demand room is made for them: at most
#: this many from one address, and in all (more are closed with 1013 at once). Each costs an
#: open socket and nothing else until its hello names the room with a token.
ROOMLESS_PER_ADDRESS = RoomLimits.max_pending_per_address
ROOMLESS_MAX = RoomLimits.max_pending
#: Time [s] a connection to a room that does not exist yet has to send its ``hello``.
ROOMLESS_HELLO_S = RoomLimits.hello_timeout_s
#: How many times one room's per-address budget a source address may spend in all rooms.
ADDRESS_ROOMS_FACTOR = 2
#: The router's budgets of one source address across every room (:attr:`ServerApp.flood`): its
#: connections, frames/s and bytes/s in all rooms together, :data:`ADDRESS_ROOMS_FACTOR` times
#: a room's (:class:`server.admission.RoomLimits`). Totals and pending counts stay the rooms'.
ADDRESS_LIMITS = RoomLimits(
    max_connections=1 << 30,
    max_pending=1 << 30,
    max_pending_per_address=1 << 30,
    max_connections_per_address=ADDRESS_ROOMS_FACTOR * RoomLimits.max_connections_per_address,
    address_rate_per_s=ADDRESS_ROOMS_FACTOR * RoomLimits.address_rate_per_s,
    address_burst=ADDRESS_ROOMS_FACTOR * RoomLimits.address_burst,
    address_bytes_per_s=ADDRESS_ROOMS_FACTOR * RoomLimits.address_bytes_per_s,
    address_bytes_burst=ADDRESS_ROOMS_FACTOR * RoomLimits.address_bytes_burst,
)
#: A room whose next tick is overdue by more than this many periods (and at least
#: :data:`STALL_MIN_S`) counts as stalled (:meth:`ServerApp.room_reports`).
STALL_PERIODS = 3.0
#: The shortest overdue time [s] that counts as a stall.
STALL_MIN_S = 1.0
#: Worker processes that design recommended gains (niced; :func:`background_worker`).
DESIGN_WORKERS = 1
#: Worker processes that run only the interim checks, so that a check (about 0.05 s of CPU)
#: never waits behind a design already running (1-4 s quiet; tens of seconds with two busy
#: processes beside a niced worker). The client keeps its checks apart from its designs the same
#: way (client.link). At normal priority, as the client's (:func:`client.workers.check_worker`):
#: niced like the designs, a check of 0.045 s of CPU came back after 0.08-0.6 s in the quiet
#: palpation demo, the designs taking the CPU it waited for, and every tick of that wait a
#: contact rendered a wider class's gains. The tick does not wait for it: its thread runs at
#: real-time priority or nice -10 (:mod:`server.priority`); where both are refused they share the
#: CPU as equals (a check is about 0.045 s of CPU).
CHECK_WORKERS = 1
#: The gain workers do the checks no contact waits for (band checks, checks ahead:
#: :data:`server.gains.IDLE_KINDS`) only while the check worker's last jobs had, as a median, at
#: least this share of a core (CPU time over the wall time the server waited, its pickling and
#: wake-ups included). In the palpation demo a check is about 0.045 s of CPU: quiet, the share
#: was 0.33-0.56 (median about 0.5); beside two spinning processes 0.06-0.29 (median 0.25), and
#: there the extra checks took the CPU the resting user's design needed (no design finished for
#: B in 4 runs of 6, 0 of 4 without them; docs/gains.md, "Interim gains over a band of B_o").
IDLE_WORK_MIN_SHARE = 0.4
#: Check jobs the share is the median of.
IDLE_WORK_WINDOW = 5
#: Jobs shorter than this [s] of wall time tell nothing of the share (IPC dominates).
IDLE_WORK_MIN_WALL_S = 0.02
#: A consumer whose send buffer stays full this long [s] is dropped.
SEND_TIMEOUT_S = 10.0
#: How long a drain may take at most [s], SIGTERM to exit (``haptic server --drain-grace-s``): well
#: under Kubernetes' default ``terminationGracePeriodSeconds`` (30 s), after which it kills.
DRAIN_GRACE_S = 10.0
#: The part of the grace [s] kept for stopping after the clients are gone (at most half of it).
DRAIN_STOP_RESERVE_S = 1.0
#: The error code every client gets when the server drains, before close code 1012.
DRAINING_CODE = "server_draining"
#: Websocket close code of a drain: 1012 "service restart" (IANA's registry).
DRAIN_CLOSE_CODE = 1012
#: The drain's error message: what a client (or its user) should do.
DRAINING_MESSAGE = (
    "the server is shutting down (restart or scale-down); join again in a moment, or ask the "
    "lobby for another server"
)
#: The viewer's files: the package data ``haptic_collab/web`` (in a source checkout a link to
#: ``web/``); three.js is served from its ``node_modules/three`` (npm's copy in a checkout, the
#: files the page loads in a wheel).
WEB_DIR = Path(str(resources.files("haptic_collab") / "web"))
#: The reason sent with a close code (others: "closed by server, see error").
_CLOSE_REASONS = {1000: "bye", DRAIN_CLOSE_CODE: "service restart, see error"}
#: A room whose process failed to start is started again after this long [s].
RESTART_BACKOFF_S = 1.0
#: The HTTP body of a room refused because the server drains.
_DRAINING_TEXT = "the server is draining (shutting down); try again or another server\n"
_STATIC_SUFFIXES = {".html", ".js", ".mjs", ".css", ".json", ".png", ".svg", ".ico", ".map"}


@dataclass(frozen=True)
class RoomReport:
    """What the orchestration layer needs of one room, read on the event loop's thread.

    Attributes
    ----------
    name : str
        The room's name (:data:`DEFAULT_ROOM`, a configured room's or an on-demand one's).
    ticks : int
        Simulation ticks run so far (0 before the first).
    alive : bool
        Its simulation loop runs and is on schedule: the loop task has not ended and the next
        tick is overdue by less than ``max(STALL_MIN_S, STALL_PERIODS / sim_rate_hz)``.
    users, viewers : int
        Connections welcomed as users and as viewers.
    """

    name: str
    ticks: int
    alive: bool
    users: int
    viewers: int


class RoomMaker(Protocol):
    """Builds rooms on demand (``[room_templates]``; :class:`server.main.RoomTemplates`)."""

    def allows(self, name: str) -> bool:
        """Whether a room of this (valid) name may be built."""
        ...

    def build(self, name: str) -> AnyRoom:
        """A new room of this name; called in a worker thread. Raises ValueError."""
        ...


@dataclass(frozen=True)
class DrainReport:
    """What a drain did (:meth:`ServerApp.drain`).

    Attributes
    ----------
    told : int
        Connections told ``server_draining`` and closed with code 1012.
    left_open : int
        Of those, connections still open when the grace ran out (aborted).
    snapshots : tuple of Path
        The snapshot files written, one per room (none without a snapshot directory).
    seconds : float
        How long the drain took [s].
    """

    told: int
    left_open: int
    snapshots: tuple[Path, ...]
    seconds: float


@dataclass
class _Slot:
    """One room as the I/O layer runs it: its own loop task, prefetcher and figures."""

    name: str
    room: AnyRoom
    figures: RoomFigures = field(default_factory=RoomFigures)
    on_demand: bool = False
    task: asyncio.Task[None] | None = None
    prefetcher: PatchPrefetcher | None = None
    #: Connections routed to it that are open.
    peers: int = 0
    #: Since when [s, loop time] it has had no connection (None: it has one).
    empty_since_s: float | None = None


class _RoomRefused(Exception):
    """A request for a room that cannot be served: the HTTP status and the reason."""

    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass
class _Peer:
    conn_id: str
    ws: ServerConnection
    up: LinkShaper
    down: LinkShaper
    #: The room it is in (None: the default room).
    slot: _Slot | None = None
    address: str = "unknown"
    connected_at_s: float = 0.0
    #: Its budgets in the router's across-rooms accounting (:attr:`ServerApp.flood`).
    frames: TokenBucket = field(default_factory=lambda: TokenBucket(1.0, 1.0, 0.0))
    bytes: TokenBucket = field(default_factory=lambda: TokenBucket(1.0, 1.0, 0.0))
    ready: deque[Outgoing] = field(default_factory=deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    #: Who, for log lines: "HOST:PORT", then "HOST:PORT user 'A' (u1)" once welcomed.
    who: str = ""
    named: bool = False
    closed: bool = False
    #: It sent ``bye`` (seen on arrival, before latency injection delays it): its seat is not
    #: held when its socket closes.
    said_bye: bool = False

    @property
    def hello(self) -> object | None:
        """Truthy once its room welcomed it (what :class:`FloodControl` reads as pending)."""
        return True if self.named else None


def _static_response(web_dir: Path, path: str) -> Response:
    path = path.split("?", 1)[0]
    if path in ("", "/"):
        path = "/index.html"
    if path.startswith("/vendor/three/"):
        root = web_dir / "node_modules" / "three"
        rel = path[len("/vendor/three/") :]
    else:
        root = web_dir
        rel = path.lstrip("/")
    try:
        target = (root / rel).resolve()
        target.relative_to(root.resolve())
    except (ValueError, OSError):
        return _text(HTTPStatus.NOT_FOUND, "not found\n")
    if target.suffix not in _STATIC_SUFFIXES or not target.is_file() or "node_modules" in rel:
        return _text(HTTPStatus.NOT_FOUND, "not found\n")
    ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
    if target.suffix in (".js", ".mjs"):
        ctype = "text/javascript"
    body = target.read_bytes()
    headers = Headers(
        [("Content-Type", ctype), ("Content-Length", str(len(body))), ("Cache-Control", "no-cache")]
    )
    return Response(200, "OK", headers, body)


def _text(status: HTTPStatus, text: str, ctype: str = "text/plain; charset=utf-8") -> Response:
    body = text.encode()
    return Response(
        status.value,
        status.phrase,
        Headers([("Content-Type", ctype), ("Content-Length", str(len(body)))]),
        body,
    )


class ServerApp:
    """Runs rooms over websockets: the default room, configured rooms and on-demand rooms.

    Parameters
    ----------
    room : Room or RoomProxy
        The default room's sans-I/O core (``/ws``, ``/``); also :attr:`room`. A
        :class:`server.room_process.RoomProxy` runs it in a process of its own
        (``--room-processes``), as it does any room of ``rooms`` or of ``room_maker``.
    host, port : str, int
        Where to listen (port 0 picks a free port; see :attr:`port` after start).
    link : LinkConditions, optional
        Latency injection applied to each direction of each connection (default: none). Give
        the rooms' ``link``: a room announces its own to clients in ``welcome`` and ``room``.
    seed : int
        Seed of the latency injection's random draws (reproducible runs).
    web_dir : Path
        The viewer's files.
    ssl_context : ssl.SSLContext, optional
        Serve ``https://`` and ``wss://`` with it (``haptic server --tls-cert/--tls-key``).
    allowed_origins : iterable of str
        Browser origins allowed besides the server's own (``--allow-origin``; ``*``: any).
    send_timeout_s : float
        Drop a consumer whose send buffer stays full this long [s].
    prefetch : bool or callable
        Solve the load patches next to the users' contacts in a worker thread between ticks
        (:class:`server.prefetch.PatchPrefetcher`, one per room); a callable says it per room
        (``haptic server`` turns it on for the FEM solids).
    metrics_token : TokenTable, optional
        The token a scrape of ``/metrics`` must carry (``Authorization: Bearer``); without one
        only a server on loopback answers it (:func:`server.metrics.scrape_allowed`).
    rooms : mapping of str to Room or RoomProxy, optional
        More rooms by name (``[rooms.NAME]``), reached at ``/rooms/NAME/``.
    room_maker : RoomMaker, optional
        Builds a room on demand when a client joins a name it allows (``[room_templates]``).
    room_admits : callable, optional
        ``room_admits(name, token) -> bool``: whether ``token`` (None: no token) may have the
        on-demand room ``name`` made (:meth:`server.main.RoomTemplates.admits`: a room token for
        that room or a server-wide token). With it, a room is made only for a handshake whose
        ``Authorization: Bearer`` token it admits, or once a connection's ``hello`` carries one
        (a connection that sends none costs no room, no slot and no memory once closed). None:
        the rooms take no tokens, and the handshake makes the room.
    room_gate : callable, optional
        ``await room_gate(name)`` before an on-demand room is built: None to build it, else why
        not (answered 503). Under Agones, :meth:`server.agones.AgonesAgent.claim_room` puts
        the name in the ``rooms`` list first; also settable as the attribute.
    max_rooms : int
        Rooms this server runs at most, the default one included (>= 1).
    room_idle_s : float
        An on-demand room without a connection this long [s] is closed.
    address_limits : RoomLimits
        The router's budgets of one source address across every room (:data:`ADDRESS_LIMITS`).
    snapshot_dir : path, optional
        Where :meth:`drain` writes each room's snapshot and where a room made (at the start or
        on demand) looks for its own (:mod:`server.snapshots`); None: no snapshots.
    tick_priority : str
        ``"realtime"``: the thread running the event loop (it ticks the rooms) asks for
        SCHED_FIFO at a low priority from :meth:`start` until :meth:`stop`, or a negative nice
        where refused (:class:`server.priority.TickPriority`): on a busy machine the tick was
        late for want of a CPU, not of work; ``"off"`` (default here, ``haptic server``'s is
        ``"realtime"``): the thread keeps its policy.

    Raises
    ------
    ValueError
        A bad room name, a room named :data:`DEFAULT_ROOM` among ``rooms``, or more rooms than
        ``max_rooms``.
    """

    def __init__(
        self,
        room: AnyRoom,
        host: str = "127.0.0.1",
        port: int = 8765,
        link: LinkConditions | None = None,
        seed: int = 0,
        web_dir: Path = WEB_DIR,
        ssl_context: ssl.SSLContext | None = None,
        allowed_origins: tuple[str, ...] | frozenset[str] = (),
        send_timeout_s: float = SEND_TIMEOUT_S,
        gain_executor: Executor | None = None,
        prefetch: bool | Callable[[Room], bool] = False,
        metrics_token: TokenTable | None = None,
        rooms: Mapping[str, AnyRoom] | None = None,
        room_maker: RoomMaker | None = None,
        max_rooms: int = MAX_ROOMS,
        room_admits: Callable[[str, str | None], bool] | None = None,
        room_gate: Callable[[str], Awaitable[str | None]] | None = None,
        room_idle_s: float = ROOM_IDLE_S,
        address_limits: RoomLimits = ADDRESS_LIMITS,
        snapshot_dir: str | Path | None = None,
        tick_priority: str = "off",
    ) -> None:
        #: The event loop thread's scheduling priority, asked in start(), given back in stop().
        self.tick_priority = TickPriority(tick_priority, "server")
        self.room: AnyRoom = room
        self._slots: dict[str, _Slot] = {DEFAULT_ROOM: _Slot(DEFAULT_ROOM, room)}
        for name, extra in (rooms or {}).items():
            if not valid_room_name(name) or name == DEFAULT_ROOM:
                raise ValueError(f"bad room name {name!r} (a slug, not {DEFAULT_ROOM!r})")
            self._slots[name] = _Slot(name, extra)
        if not (isinstance(max_rooms, int) and max_rooms >= 1):
            raise ValueError(f"max_rooms must be a whole number >= 1, got {max_rooms!r}")
        if len(self._slots) > max_rooms:
            raise ValueError(
                f"{len(self._slots)} rooms configured, more than max_rooms {max_rooms}"
            )
        self.room_maker = room_maker
        self.max_rooms = max_rooms
        self.room_admits = room_admits
        self.room_gate = room_gate
        #: Connections waiting for a hello before their room is made, by source address.
        self._roomless: dict[str, int] = {}
        #: Connections closed before a room was made for them (no hello, or no good token).
        self.roomless_refused = 0
        self.room_idle_s = float(room_idle_s)
        self._building: dict[str, asyncio.Future[_Slot]] = {}
        #: What this layer counts per room, by name (:mod:`server.metrics`).
        self.figures: dict[str, RoomFigures] = {n: s.figures for n, s in self._slots.items()}
        #: The router's budgets of each source address across every room.
        self.flood = FloodControl(address_limits, self._shortest_period())
        self.metrics_token = metrics_token
        #: The registry ``/metrics`` exposes: one collector reading the rooms when scraped.
        self.metrics_registry = CollectorRegistry(auto_describe=False)
        self.metrics_registry.register(ServerCollector(self))
        #: Solve the patches next to the users' contacts between ticks (server.prefetch).
        self.prefetch = prefetch
        #: Where recommended-gain designs run (default: one spawned worker process, made on the
        #: first design; server.gains). Never the event loop's thread.
        self.gain_executor = gain_executor
        #: Where the interim checks run (default: a second spawned worker process; an injected
        #: ``gain_executor`` runs them too).
        self.check_executor = gain_executor
        self._own_executor = gain_executor is None
        self._gain_tasks: set[asyncio.Task[None]] = set()
        self._check_tasks: set[asyncio.Task[None]] = set()
        #: The check worker's share of a core in its last jobs (IDLE_WORK_MIN_SHARE).
        self.check_cpu_share: deque[float] = deque(maxlen=IDLE_WORK_WINDOW)
        self._idle_work = False
        self._design_turn = 0
        self.host = host
        self.port = port
        self.link = link if link is not None else LinkConditions()
        self.seed = seed
        self.web_dir = web_dir
        self.ssl_context = ssl_context
        self.allowed_origins = frozenset(o.rstrip("/") for o in allowed_origins)
        self.send_timeout_s = float(send_timeout_s)
        #: Consumers dropped because their send buffer stayed full.
        self.send_timeouts = 0
        #: Browser handshakes refused for their Origin.
        self.origins_refused = 0
        self._peers: dict[str, _Peer] = {}
        self._next_conn = 0
        self._server: Server | None = None
        self._started = False
        #: Where rooms are snapshotted at a drain and resumed from (None: nowhere).
        self.snapshot_dir = Path(snapshot_dir) if snapshot_dir is not None else None
        #: Set by :meth:`drain`: no new connection or room from then on.
        self.draining = False
        self._drain: asyncio.Future[DrainReport] | None = None
        #: Set whenever no connection is open (what a drain waits for).
        self._no_peers = asyncio.Event()
        self._no_peers.set()

    @property
    def prefetcher(self) -> PatchPrefetcher | None:
        """The default room's patch prefetcher (None without ``prefetch`` or before start)."""
        return self._slots[DEFAULT_ROOM].prefetcher

    @property
    def _sim_task(self) -> asyncio.Task[None] | None:
        """The default room's simulation loop task (None before start)."""
        return self._slots[DEFAULT_ROOM].task

    def _slot(self, peer: _Peer) -> _Slot:
        """The room a peer is in."""
        return peer.slot if peer.slot is not None else self._slots[DEFAULT_ROOM]

    def _shortest_period(self) -> float:
        return min(1.0 / s.room.sim_rate_hz for s in self._slots.values())

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Listen and start every room's simulation loop."""
        self._server = await serve(
            self._handler,
            self.host,
            self.port,
            process_request=self._process_request,
            ssl=self.ssl_context,
            max_size=WS_MAX_SIZE,
            compression=None,  # permessage-deflate cost a fifth of the server's time
            max_queue=64,
            close_timeout=1.0,
            ping_interval=5.0,
            ping_timeout=10.0,
        )
        sock = next(iter(self._server.sockets))
        self.port = int(sock.getsockname()[1])
        self._started = True
        for slot in self._slots.values():
            self._resume(slot.name, slot.room)
            self._start_slot(slot)
        if self._own_executor:  # an injected executor (tests) is the caller's to warm
            self._gain_tasks.add(asyncio.create_task(self._warm_design_pool()))
            self._check_tasks.add(asyncio.create_task(self._warm_design_pool(checks=True)))
        await self._rooms_started(list(self._slots.values()))
        # last: a start that raised leaves the thread as it was (stop() gives it back); threads
        # and processes started from here on keep the ordinary policy (server.priority)
        self.tick_priority.ask()

    async def _rooms_started(self, slots: list[_Slot]) -> None:
        """Wait until every room of ``slots`` running in a process of its own has built its
        room and ticks (:data:`server.room_process.START_TIMEOUT_S` at most).

        Raises
        ------
        RuntimeError
            A room's process could not build its room (a bad mesh, say: its log says why) or
            did not start in time; every room is stopped first.
        """
        try:
            await self._rooms_ready(slots)
        except RuntimeError:
            await self.stop()
            raise

    @staticmethod
    async def _rooms_ready(slots: list[_Slot]) -> None:
        """Wait until the rooms of ``slots`` that run in processes have started.

        Raises
        ------
        RuntimeError
            One could not build its room, or did not start within the time.
        """
        waits = []
        for slot in slots:
            if isinstance(slot.room, RoomProxy):
                while slot.room.ready is None:  # its supervisor has not spawned it yet
                    if slot.task is None or slot.task.done():
                        raise RuntimeError(f"room {slot.name!r}: its process was not started")
                    await asyncio.sleep(0.01)
                waits.append(slot.room.ready)
        if not waits:
            return
        try:
            await asyncio.wait_for(asyncio.gather(*waits), START_TIMEOUT_S)
        except (RuntimeError, TimeoutError) as exc:
            raise RuntimeError(f"a room's process did not start: {exc}") from None

    def _resume(self, name: str, room: AnyRoom) -> bool:
        """Start room ``name`` from its snapshot when the snapshot directory holds one
        (:func:`server.snapshots.restore`: checked, consumed, logged; never raises). A room in
        a process of its own does that itself, at every start."""
        if self.snapshot_dir is None or isinstance(room, RoomProxy):
            return False
        return snapshots.restore(self.snapshot_dir, name, room)

    def _start_slot(self, slot: _Slot) -> None:
        """Start one room's simulation loop (and its prefetcher), or its process."""
        if isinstance(slot.room, RoomProxy):
            slot.room.snapshot_dir = str(self.snapshot_dir) if self.snapshot_dir else None
            slot.empty_since_s = asyncio.get_running_loop().time() if slot.peers == 0 else None
            slot.task = asyncio.create_task(self._supervise(slot), name=f"room {slot.name}")
            return
        want = self.prefetch(slot.room) if callable(self.prefetch) else self.prefetch
        if want:
            slot.prefetcher = PatchPrefetcher(slot.room.world)
        slot.empty_since_s = asyncio.get_running_loop().time() if slot.peers == 0 else None
        slot.task = asyncio.create_task(self._sim_loop(slot), name=f"room {slot.name}")

    async def _stop_slot(self, slot: _Slot) -> None:
        """Stop one room's loop, its schedule and its prefetcher (or its process)."""
        task = slot.task
        if isinstance(slot.room, RoomProxy):
            await slot.room.close()
            if task is not None and task is not asyncio.current_task():
                with contextlib.suppress(asyncio.CancelledError, TimeoutError):
                    await asyncio.wait_for(asyncio.shield(task), 5.0)
                if not task.done():
                    slot.room.kill()
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
            return
        if task is not None and task is not asyncio.current_task():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        slot.room.stop()  # no schedule any more: nothing is behind it
        if slot.prefetcher is not None:
            await asyncio.get_running_loop().run_in_executor(None, slot.prefetcher.close)
            slot.prefetcher = None

    async def stop(self) -> None:
        """Stop every room's simulation and close every connection (a drain still running is
        cut short)."""
        if self._drain is not None and not self._drain.done():
            self._drain.cancel()
        for pending in list(self._building.values()):
            pending.cancel()
        for slot in list(self._slots.values()):
            await self._stop_slot(slot)
        pending_tasks = [*self._gain_tasks, *self._check_tasks]
        for task in pending_tasks:
            task.cancel()
        for task in pending_tasks:  # let them finish their cancellation while the loop still runs
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._own_executor:
            for pool in (self.gain_executor, self.check_executor):
                if pool is not None:
                    stop_pool(pool)  # a running design must not hold up the stop
            self.gain_executor = self.check_executor = None
        if self._server:
            self._server.close()
            await self._server.wait_closed()
            log.info("server closed: every room stopped, every connection closed")
        self.tick_priority.restore()

    async def drain(self, grace_s: float = DRAIN_GRACE_S) -> DrainReport:
        """Drain the server for a shutdown (SIGTERM, :func:`server.main.run_server`).

        In order: no new connection or room from now on (a websocket that opens during the
        drain gets the same ``server_draining`` error and close; a room being built is refused
        with HTTP 503); every room's simulation stops, so the state kept is the one its users
        last felt; each room's state is taken (:func:`server.snapshots.capture`); every
        connection gets an ``error`` ``server_draining`` (fatal) and is closed with code 1012
        (service restart), before any frame still queued for it, without injected latency; the
        snapshots are written (one file per room, atomically, off the event loop's thread) while
        the clients close. It waits for every connection to close until ``grace_s`` less a
        reserve for stopping (:data:`DRAIN_STOP_RESERVE_S`, at most half) has passed since the
        drain began, then aborts those left. The listening socket, the gain workers and the
        rooms' prefetchers are :meth:`stop`'s. Calling it again waits for the same drain.

        Parameters
        ----------
        grace_s : float
            The time [s] a drain and the stop after it may take (> 0; default
            :data:`DRAIN_GRACE_S`).

        Returns
        -------
        DrainReport

        Raises
        ------
        ValueError
            ``grace_s`` not a finite number > 0.
        """
        if not (isinstance(grace_s, int | float) and math.isfinite(grace_s) and grace_s > 0.0):
            raise ValueError(f"the drain's grace must be a number of seconds > 0, got {grace_s!r}")
        if self._drain is None:
            self._drain = asyncio.ensure_future(self._drain_now(float(grace_s)))
        return await asyncio.shield(self._drain)

    async def _drain_now(self, grace_s: float) -> DrainReport:
        loop = asyncio.get_running_loop()
        began = loop.time()
        self.draining = True
        slots = list(self._slots.values())
        # a room in a process of its own stops ticking and saves itself (RoomProxy.drain)
        remote = [
            asyncio.ensure_future(s.room.drain(self.snapshot_dir is not None))
            for s in slots
            if isinstance(s.room, RoomProxy)
        ]
        for slot in slots:  # no tick after this: the state kept is the one users felt last
            if isinstance(slot.room, RoomProxy):
                continue
            task = slot.task
            if task is not None and not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            slot.room.stop()
        taken: list[snapshots.Snapshot] = []
        if self.snapshot_dir is not None:
            for slot in slots:
                if isinstance(slot.room, RoomProxy):
                    continue
                try:
                    taken.append(snapshots.capture(slot.name, slot.room))
                except Exception:  # noqa: BLE001 - one room's state must not stop the drain
                    log.exception("room %r: its state could not be taken", slot.name)
        peers = [p for p in self._peers.values() if not p.closed]  # not already being closed
        for peer in peers:
            self._tell_draining(peer)
        log.info(
            "draining: no new connection or room; %d connections told %s (close %d); %s",
            len(peers),
            DRAINING_CODE,
            DRAIN_CLOSE_CODE,
            f"{len(taken)} rooms snapshotted to {self.snapshot_dir}"
            if self.snapshot_dir is not None
            else "no snapshot directory",
        )
        writing = asyncio.ensure_future(
            asyncio.to_thread(snapshots.write_all, self.snapshot_dir, taken)
            if taken and self.snapshot_dir is not None
            else asyncio.sleep(0, result=[])
        )
        reserve = min(DRAIN_STOP_RESERVE_S, 0.5 * grace_s)
        wait_s = max(0.0, began + grace_s - reserve - loop.time())
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._no_peers.wait(), wait_s)
        left = list(self._peers.values())
        for peer in left:  # not closed within the grace: the pod is going away anyway
            log.warning("drain: %s did not close within the grace; aborting it", peer.who)
            peer.ws.transport.abort()
        written: list[Path] = await writing
        if remote:
            done, _ = await asyncio.wait(remote, timeout=max(0.0, began + grace_s - loop.time()))
            for fut in done:
                if not fut.cancelled() and fut.exception() is None and fut.result() is not None:
                    written.append(Path(fut.result()))  # type: ignore[arg-type]
        for path in written:
            log.info("drain: snapshot %s written", path)
        report = DrainReport(
            told=len(peers),
            left_open=len(left),
            snapshots=tuple(sorted(written)),
            seconds=loop.time() - began,
        )
        log.info(
            "drained in %.3f s: %d of %d connections closed by their clients",
            report.seconds,
            report.told - report.left_open,
            report.told,
        )
        return report

    def _tell_draining(self, peer: _Peer) -> None:
        """Queue ``server_draining`` and a close with code 1012 for a connection, ahead of every
        state frame still queued for it (patches and surfaces are stale now), with no injected
        latency (the drain has a deadline); its room forgets it."""
        peer.closed = True
        self._slot(peer).room.disconnect(peer.conn_id, hold=False)  # the server is going
        peer.ready = deque(o for o in peer.ready if o.stream is None and not o.close)
        frame = encode(ErrorMsg(code=DRAINING_CODE, message=DRAINING_MESSAGE, fatal=True))
        self._ready(peer, Outgoing(peer.conn_id, frame, close=True, close_code=DRAIN_CLOSE_CODE))

    async def run(
        self, duration_s: float | None = None, on_ready: Callable[[int], None] | None = None
    ) -> None:
        """Start, call ``on_ready(port)``, serve until cancelled or ``duration_s`` elapses."""
        await self.start()
        if on_ready:
            on_ready(self.port)
        try:
            if duration_s is None:
                await asyncio.Future()
            else:
                await asyncio.sleep(duration_s)
        finally:
            await self.stop()

    # ------------------------------------------------------------------ rooms
    def rooms(self) -> dict[str, AnyRoom]:
        """The rooms this server runs now, by name: the default one first, then the configured
        ones, then those made on demand (in the order they were made).

        The Agones agent (:mod:`server.agones`) and the metrics (:mod:`server.metrics`) read
        every room through this mapping.
        """
        return {name: slot.room for name, slot in self._slots.items()}

    async def _room_for(self, name: str) -> _Slot:
        """The running room ``name``, built now from a template when one allows it.

        Raises
        ------
        _RoomRefused
            404 when no room has that name and no template allows it, 503 when the server runs
            ``max_rooms`` rooms already, 500 when building it failed (logged).
        """
        slot = self._slots.get(name)
        if slot is not None:
            return slot
        pending = self._building.get(name)
        if pending is None:
            self._check_room_slot(name)
            pending = asyncio.ensure_future(self._build_room(name))
            self._building[name] = pending
        return await asyncio.shield(pending)

    def _check_room_slot(self, name: str) -> None:
        """Whether room ``name`` (not running, not being built) could be made now.

        Raises
        ------
        _RoomRefused
            404 when no template allows the name, 503 when the server drains or runs
            ``max_rooms`` rooms (those being built included).
        """
        if self.room_maker is None or not self.room_maker.allows(name):
            raise _RoomRefused(HTTPStatus.NOT_FOUND, f"no room {name!r} on this server\n")
        if self.draining:
            raise _RoomRefused(HTTPStatus.SERVICE_UNAVAILABLE, _DRAINING_TEXT)
        if len(self._slots) + len(self._building) >= self.max_rooms:
            raise _RoomRefused(
                HTTPStatus.SERVICE_UNAVAILABLE,
                f"this server runs its most rooms ({self.max_rooms}); try another server\n",
            )

    async def _build_room(self, name: str) -> _Slot:
        """Build an on-demand room in a worker thread (a FEM solid takes seconds), start it."""
        assert self.room_maker is not None
        try:
            why = None if self.room_gate is None else await self.room_gate(name)
            if why is not None:
                log.debug("room %r refused: %s", name, why)  # the gate said why
                raise _RoomRefused(
                    HTTPStatus.SERVICE_UNAVAILABLE,
                    f"no room {name!r} here: {why}; try another server\n",
                )
            room = await asyncio.to_thread(self._make_room, name)
        except _RoomRefused:
            raise
        except Exception as exc:
            log.exception("room %r could not be built", name)
            raise _RoomRefused(
                HTTPStatus.INTERNAL_SERVER_ERROR, f"room {name!r} could not be built\n"
            ) from exc
        finally:
            self._building.pop(name, None)
        if self.draining:  # built while the server began to drain: never started
            raise _RoomRefused(HTTPStatus.SERVICE_UNAVAILABLE, _DRAINING_TEXT)
        slot = _Slot(name, room, on_demand=True)
        self._slots[name] = slot
        self.figures[name] = slot.figures
        self.flood.sim_period_s = self._shortest_period()
        if self._started:
            self._start_slot(slot)
            if isinstance(room, RoomProxy):  # a room that cannot be built is refused now
                try:
                    await self._rooms_ready([slot])
                except RuntimeError as exc:
                    log.error("room %r could not be started: %s", name, exc)
                    self._slots.pop(name, None)
                    self.figures.pop(name, None)
                    await self._stop_slot(slot)
                    raise _RoomRefused(
                        HTTPStatus.INTERNAL_SERVER_ERROR, f"room {name!r} could not be built\n"
                    ) from None
        log.info(
            "room %r made on demand (%d of at most %d rooms)",
            name,
            len(self._slots),
            self.max_rooms,
        )
        return slot

    def _make_room(self, name: str) -> AnyRoom:
        """Build an on-demand room and resume its snapshot (in a worker thread)."""
        assert self.room_maker is not None
        room = self.room_maker.build(name)
        self._resume(name, room)
        return room

    async def _retire(self, slot: _Slot) -> None:
        """Close an on-demand room nobody used for ``room_idle_s``."""
        log.info("room %r closed: no connection for %g s", slot.name, self.room_idle_s)
        self._slots.pop(slot.name, None)
        self.figures.pop(slot.name, None)
        await self._stop_slot(slot)

    def room_reports(self) -> list[RoomReport]:
        """A :class:`RoomReport` of every room of :meth:`rooms`; call it on the event loop.

        A room is alive while its simulation task runs and its next tick is not overdue by
        more than ``max(STALL_MIN_S, STALL_PERIODS / sim_rate_hz)`` [s]: a dead loop (task ended)
        or one whose ticks stopped (a tick that never returns blocks this very call, which is
        how a caller on another thread sees a blocked loop: no answer). A room in a process of
        its own is judged by its process's last report: a hung process's next tick is overdue
        from when its reports stop, and the room is not alive from when the front kills it
        (:data:`server.room_process.HANG_S`) until its new process has started.
        """
        now = asyncio.get_running_loop().time()
        out = []
        for name, slot in list(self._slots.items()):
            room = slot.room
            running = slot.task is not None and not slot.task.done()
            if isinstance(room, RoomProxy):  # its process runs (not dead nor restarting)
                running = running and room.running
            stall_s = max(STALL_MIN_S, STALL_PERIODS / room.sim_rate_hz)
            on_time = now - room.get_timer() < stall_s
            out.append(
                RoomReport(
                    name=name,
                    ticks=room.tick_count,
                    alive=running and on_time,
                    users=len(room.users),
                    viewers=len(room.viewers),
                )
            )
        return out

    @staticmethod
    def _room_status(room: AnyRoom) -> dict[str, Any]:
        process = (
            {
                "process": {
                    "pid": room.pid,
                    "restarts": room.restarts,
                    "hangs": room.hangs,
                    "start_s": room.start_s,
                }
            }
            if isinstance(room, RoomProxy)
            else {}
        )
        return {
            **process,
            "tick": room.tick_count,
            "sim_rate_hz": room.sim_rate_hz,
            "users": len(room.users),
            "viewers": len(room.viewers),
            "max_users": room.limits.max_users,
            "held_seats": len(room.held_seats),
            "resumes": room.resumes,
            "tick_ms_p50": room.stats.percentile(50),
            "tick_ms_p99": room.stats.percentile(99),
            "overruns": room.stats.overruns,
            "auth": room.auth is not None,
            "force_clamps": sum(room.clamp_counts.values()),
        }

    def status(self) -> dict[str, Any]:
        """JSON-able summary: the default room's tick, users, viewers, tick costs, overruns at
        the top level (as before rooms), the link conditions, ``roomless_refused`` (connections
        closed before a room was made for them: no hello, or no token naming the room), and
        ``rooms``: every room's own figures by name with its websocket and page paths."""
        room = self.room
        rooms = {}
        for name, slot in list(self._slots.items()):
            rooms[name] = {
                **self._room_status(slot.room),
                "on_demand": slot.on_demand,
                "ws": room_ws_path(name),
                "page": room_page_path(name),
            }
        return {
            **self._room_status(room),
            "latency_ms": self.link.latency_ms,
            "jitter_ms": self.link.jitter_ms,
            "loss": self.link.loss,
            "tls": self.ssl_context is not None,
            "send_timeouts": self.send_timeouts,
            "origins_refused": self.origins_refused,
            "roomless_refused": self.roomless_refused,
            "rooms": rooms,
            "max_rooms": self.max_rooms,
            "rooms_on_demand": self.room_maker is not None,
            "draining": self.draining,
        }

    # ------------------------------------------------------------------ HTTP
    async def _process_request(
        self, connection: ServerConnection, request: Request
    ) -> Response | None:
        path = request.path.split("?", 1)[0]
        where = room_path(path)
        if where is not None:
            return await self._room_request(request, where)
        if path == "/status":
            refused = self._status_refused(request)
            if refused is not None:
                return refused
            body = json.dumps(self.status())
            return _text(HTTPStatus.OK, body, "application/json")
        if path == "/metrics":
            return self._metrics(request)
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return _text(
                HTTPStatus.NOT_FOUND, "the websocket endpoints are /ws and /rooms/NAME/ws\n"
            )
        return _static_response(self.web_dir, path)

    async def _room_request(self, request: Request, where: RoomPath) -> Response | None:
        """A request under a room's path: its websocket (routed, made on demand), its page, or a
        redirect of ``/rooms/NAME`` to ``/rooms/NAME/``."""
        name = where.room
        if not valid_room_name(name):
            return _text(
                HTTPStatus.BAD_REQUEST,
                "a room name is 1-32 of a-z, 0-9 and -, starting and ending with a letter or "
                "digit\n",
            )
        if where.rest == "ws":
            origin = request.headers.get("Origin")
            if not origin_allowed(
                origin, request.headers.get("Host"), self.allowed_origins, is_loopback(self.host)
            ):
                self.origins_refused += 1
                log.warning("refused a websocket handshake from origin %.100r", origin)
                return _text(HTTPStatus.FORBIDDEN, "origin not allowed (see --allow-origin)\n")
            if self.draining:  # no new room: the handler tells it server_draining
                return None
            try:
                if name not in self._slots and not self._handshake_admits(name, request):
                    # no room yet, and no token for it in the handshake: the handler waits
                    # for the hello's token (a browser cannot send headers)
                    if name not in self._building:
                        self._check_room_slot(name)
                    return None
                await self._room_for(name)
            except _RoomRefused as exc:
                return _text(exc.status, str(exc))
            return None
        known = name in self._slots or (
            self.room_maker is not None and self.room_maker.allows(name)
        )
        if not known:
            return _text(HTTPStatus.NOT_FOUND, f"no room {name!r} on this server\n")
        if where.rest is None:
            return Response(
                HTTPStatus.MOVED_PERMANENTLY.value,
                HTTPStatus.MOVED_PERMANENTLY.phrase,
                Headers([("Location", room_page_path(name)), ("Content-Length", "0")]),
                b"",
            )
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return _text(HTTPStatus.NOT_FOUND, f"the websocket endpoint is {room_ws_path(name)}\n")
        return _static_response(self.web_dir, "/" + where.rest)

    def _handshake_admits(self, name: str, request: Request) -> bool:
        """Whether the handshake may have room ``name`` made: the rooms take no tokens
        (:attr:`room_admits` None), or its ``Authorization: Bearer`` token is admitted.

        Raises
        ------
        _RoomRefused
            401 for a bearer token that does not name the room (nor is a server-wide token).
        """
        if self.room_admits is None:
            return True
        auth = request.headers.get("Authorization")
        if auth is None:
            return False
        scheme, _, token = auth.partition(" ")
        if scheme.lower() != "bearer" or not self.room_admits(name, token.strip()):
            raise _RoomRefused(
                HTTPStatus.UNAUTHORIZED, f"the bearer token is not valid for room {name!r}\n"
            )
        return True

    async def _room_by_hello(
        self, ws: ServerConnection, name: str, address: str
    ) -> tuple[_Slot, str | bytes] | None:
        """Room ``name`` made (or found) for a connection whose hello carries a token it admits
        (:attr:`room_admits`); the slot and that hello, or None once the connection is closed
        with the reason (no hello in time, not a hello, a token that does not name the room,
        no room slot, or too many connections waiting so).

        Nothing of the connection is kept once it is closed: the room is made only after the
        token is checked, and the count of waiting connections per address goes back down.
        """
        waiting = self._roomless.get(address, 0)
        if waiting >= ROOMLESS_PER_ADDRESS or sum(self._roomless.values()) >= ROOMLESS_MAX:
            self.roomless_refused += 1
            await ws.close(1013, "too many connections waiting to join; try again")
            return None
        self._roomless[address] = waiting + 1
        code, message, close_code = "", "", 1008
        try:
            try:
                frame = await asyncio.wait_for(ws.recv(), ROOMLESS_HELLO_S)
            except TimeoutError:
                code, message = "hello_timeout", f"no hello within {ROOMLESS_HELLO_S:g} s"
            except ConnectionClosed:
                self.roomless_refused += 1
                return None
            else:
                try:
                    msg = parse_client(frame)
                except ProtocolError as exc:
                    code, message = exc.code, str(exc)
                else:
                    token = msg.token if isinstance(msg, Hello) else None
                    if not isinstance(msg, Hello):
                        code, message = "hello_expected", "the first message must be hello"
                    elif not self.room_admits or not self.room_admits(name, token):
                        what = "a token is required" if token is None else "the token is not valid"
                        code, message = "unauthorized", f"{what} (hello.token) in room {name!r}"
                    else:
                        try:
                            return await self._room_for(name), frame
                        except _RoomRefused as exc:
                            code, close_code = "room_unavailable", 1013
                            message = str(exc).strip()
        finally:
            left = self._roomless.get(address, 1) - 1
            if left > 0:
                self._roomless[address] = left
            else:
                self._roomless.pop(address, None)
        self.roomless_refused += 1
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            error = encode(ErrorMsg(code=code, message=message, fatal=True))
            await asyncio.wait_for(ws.send(error), self.send_timeout_s)
            await ws.close(close_code, "closed by server, see error")
        return None

    def _status_refused(self, request: Request) -> Response | None:
        """``/status`` names every room and its processes' ids: on loopback anyone local may read
        it (the lobby of docs/usage.md does); off loopback only a request with the metrics token
        (``Authorization: Bearer``, ``--metrics-token-file``). None when it may be answered, else
        the refusal (403 without a metrics token configured, 401 without the right one)."""
        if is_loopback(self.host):
            return None
        auth = request.headers.get("Authorization")
        if self.metrics_token is None:
            return _text(
                HTTPStatus.FORBIDDEN,
                "/status off loopback needs a metrics token (--metrics-token-file)\n",
            )
        if scrape_allowed(False, auth, self.metrics_token):
            return None
        return Response(
            HTTPStatus.UNAUTHORIZED.value,
            HTTPStatus.UNAUTHORIZED.phrase,
            Headers([("WWW-Authenticate", 'Bearer realm="status"'), ("Content-Length", "0")]),
            b"",
        )

    def _metrics(self, request: Request) -> Response:
        """``/metrics``: the Prometheus text format, for those :func:`scrape_allowed` admits."""
        auth = request.headers.get("Authorization")
        if not scrape_allowed(is_loopback(self.host), auth, self.metrics_token):
            if self.metrics_token is None:
                return _text(
                    HTTPStatus.FORBIDDEN,
                    "/metrics off loopback needs a metrics token (docs/security.md)\n",
                )
            return Response(
                HTTPStatus.UNAUTHORIZED.value,
                HTTPStatus.UNAUTHORIZED.phrase,
                Headers([("WWW-Authenticate", 'Bearer realm="metrics"'), ("Content-Length", "0")]),
                b"",
            )
        return _text(
            HTTPStatus.OK, generate_latest(self.metrics_registry).decode(), CONTENT_TYPE_LATEST
        )

    def viewer_missing(self) -> list[str]:
        """The viewer's files that are not there (relative to :attr:`web_dir`); [] when complete."""
        need = (
            "index.html",
            "viewer.js",
            "protocol.js",
            "lump.js",
            "node_modules/three/build/three.module.js",
        )
        return [rel for rel in need if not (self.web_dir / rel).is_file()]

    # ------------------------------------------------------------------ websockets
    async def _handler(self, ws: ServerConnection) -> None:
        self._next_conn += 1
        conn_id = f"c{self._next_conn}"
        loop = asyncio.get_running_loop()
        if self.draining:
            await self._refuse_draining(ws)
            return
        where = room_path(ws.request.path) if ws.request is not None else None
        slot = self._slots.get(where.room if where is not None else DEFAULT_ROOM)
        first: str | bytes | None = None
        if slot is None and where is not None and self.room_admits is not None:
            # no room yet: made only once the hello's token names it (or it was made meanwhile)
            made = await self._room_by_hello(ws, where.room, _address(ws))
            if made is None:
                return
            slot, first = made
            if self.draining:
                await self._refuse_draining(ws)
                return
        if slot is None:  # closed between the handshake and now (idle on-demand room)
            await ws.close(1013, "room closed, join again")
            return
        peer = _Peer(
            conn_id,
            ws,
            up=LinkShaper(self.link, seed=f"{self.seed}:{conn_id}:up"),
            down=LinkShaper(self.link, seed=f"{self.seed}:{conn_id}:down"),
            slot=slot,
            address=_address(ws),
            connected_at_s=loop.time(),
        )
        room = slot.room
        self._peers[conn_id] = peer
        self._no_peers.clear()
        slot.peers += 1
        slot.empty_since_s = None
        sender = asyncio.create_task(self._sender(peer))
        address = peer.address
        remote = ws.remote_address
        port = remote[1] if isinstance(remote, tuple) and len(remote) > 1 else None
        peer.who = address if port is None else f"{address}:{port}"
        if slot.name != DEFAULT_ROOM:
            peer.who += f" room {slot.name}"
        log.info("connection %s open: %s", conn_id, peer.who)
        try:
            others = [p for p in self._peers.values() if p is not peer and not p.closed]
            refusal = self.flood.connect(others, address)
            if isinstance(refusal, Refusal):  # the address holds too many in all rooms
                self._refuse(peer, refusal.code, refusal.message + " in all rooms together")
            else:
                peer.frames, peer.bytes = self.flood.open(address, peer.connected_at_s)
                self._dispatch(room.connect(conn_id, loop.time(), address))
            async for frame in _frames(first, ws):  # after a refusal: drain for the close
                now = loop.time()
                if peer.closed:
                    continue
                # flood control on arrival, before latency injection holds anything in memory
                admitted, outs = room.admit(conn_id, frame, now)
                if outs:
                    self._dispatch(outs)
                if admitted:
                    admitted = self._charge_address(peer, frame, now)
                if not admitted:
                    continue
                if not self.link.active:
                    self._deliver(conn_id, frame)
                    continue
                if not peer.said_bye and is_bye(frame):
                    peer.said_bye = True
                at = peer.up.schedule(now, droppable=room.droppable(frame))
                if at is not None:  # strictly increasing times: the timers fire in order
                    loop.call_at(at, self._deliver, conn_id, frame)
        except ConnectionClosed:
            pass
        finally:
            log.info(
                "connection %s closed: %s%s, code %s",
                conn_id,
                peer.who,
                "" if peer.named else " (before hello)",
                ws.close_code,
            )
            # a user gone without bye keeps its seat for a while (Room.disconnect); a bye still
            # held back by latency injection is a bye all the same
            room.disconnect(conn_id, loop.time(), hold=not peer.said_bye)
            peer.closed = True
            self._peers.pop(conn_id, None)
            if not self._peers:
                self._no_peers.set()
            slot.peers -= 1
            if slot.peers == 0:
                slot.empty_since_s = loop.time()
            sender.cancel()
            # bounded: on Python 3.11 a cancel that lands as the sender's wait_for(send) finishes
            # is swallowed, and an unbounded await would never return
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed, TimeoutError):
                await asyncio.wait_for(sender, 5.0)

    async def _refuse_draining(self, ws: ServerConnection) -> None:
        """A connection that opened while the server drains: ``server_draining``, close 1012."""
        log.info("connection from %s refused: the server is draining", _address(ws))
        frame = encode(ErrorMsg(code=DRAINING_CODE, message=DRAINING_MESSAGE, fatal=True))
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            await asyncio.wait_for(ws.send(frame), self.send_timeout_s)
            await ws.close(DRAIN_CLOSE_CODE, _CLOSE_REASONS[DRAIN_CLOSE_CODE])

    def _refuse(self, peer: _Peer, code: str, message: str) -> None:
        """Close a connection for the router (its room forgets it): a fatal ``error`` frame."""
        peer.closed = True
        self._slot(peer).room.disconnect(peer.conn_id, hold=False)  # closed on purpose
        frame = encode(ErrorMsg(code=code, message=message, fatal=True))
        self._dispatch([Outgoing(peer.conn_id, frame, close=True)])

    def _charge_address(self, peer: _Peer, frame: str | bytes, now: float) -> bool:
        """Charge a frame its room admitted to its address's budget across every room.

        When the address has spent it (:data:`ADDRESS_LIMITS`), its heaviest connection in any
        room is closed with ``rate_limited``. Returns whether the frame is still admitted (False
        when its own connection was the one closed).
        """
        slot = self._slot(peer)
        # behind schedule: the backlog of a stall is credited (a room process says so itself)
        if not isinstance(slot.room, RoomProxy) and now > slot.room.get_timer():
            self.flood.credit_stall(self._live_peers(), slot.room.get_timer(), now)
        size = frame_size_bytes(frame)
        self.flood.charge(peer, size, now)  # its share, to find the heaviest; the room decides
        heavy = self.flood.charge_address(peer, self._live_peers(), size, now)
        if heavy is None:
            return True
        log.warning("address %s sends too much in all rooms: closing %s", peer.address, heavy.who)
        self._refuse(
            heavy,
            "rate_limited",
            "this address sends too much in all rooms together; its busiest connection is closed",
        )
        return heavy is not peer

    def _live_peers(self) -> Iterator[_Peer]:
        """The open connections of every room (lazily: most frames never read them)."""
        return (p for p in self._peers.values() if not p.closed)

    def _deliver(self, conn_id: str, frame: str | bytes) -> None:
        """Hand an admitted frame to its room when it is due (after any injected latency)."""
        peer = self._peers.get(conn_id)
        if peer is None or peer.closed:
            return
        room = self._slot(peer).room
        try:
            outs = room.handle(conn_id, frame, asyncio.get_running_loop().time())
        except Exception:  # a bug must cost one frame, not the connection or the room
            log.exception("frame from %s could not be handled", conn_id)
            return
        if not peer.named:
            who = room.describe(conn_id)
            if who is not None:  # welcomed: now we know who it is
                peer.named = True
                peer.who += f" {who}"
                log.info("connection %s: %s joined", conn_id, peer.who)
        self._dispatch(outs)

    def _dispatch(self, outs: list[Outgoing]) -> None:
        loop = asyncio.get_running_loop()
        now = loop.time()
        for out in outs:
            peer = self._peers.get(out.conn_id)
            if peer is None:
                continue
            if not self.link.active:
                self._ready(peer, out)
                continue
            at = peer.down.schedule(now, droppable=out.stream is not None and not out.close)
            if at is not None:
                loop.call_at(at, self._ready, peer, out)

    @staticmethod
    def _ready(peer: _Peer, out: Outgoing) -> None:
        """Queue a due frame; a newer frame of a state stream replaces the queued older one in its
        place (moved to the end, a viewer's ``room`` frame queued behind each slow surface frame
        was replaced before it went out, tick after tick: 0 sent in 15 s to a slow reader)."""
        if out.stream is not None:
            for i, queued in enumerate(peer.ready):
                if queued.stream == out.stream:
                    peer.ready[i] = out  # latest wins, in the older frame's place
                    peer.wake.set()
                    return
        peer.ready.append(out)
        peer.wake.set()

    async def _sender(self, peer: _Peer) -> None:
        """Send queued frames in order until a closing frame or the connection ends.

        A send that cannot complete within ``send_timeout_s`` (the peer does not read and its
        buffer stays full) drops the peer: the room forgets it and the socket is aborted.
        """
        figures = self._slot(peer).figures
        try:
            while True:
                await peer.wake.wait()
                peer.wake.clear()
                while peer.ready:
                    out = peer.ready.popleft()
                    if out.data is not None:
                        await asyncio.wait_for(peer.ws.send(out.data), self.send_timeout_s)
                        if out.stream == "patch":
                            figures.patches_sent += 1
                        elif isinstance(out.data, bytes):  # the viewers' surface stream
                            figures.viewer_bytes_sent += len(out.data)
                        if out.on_sent is not None:  # the viewer stream tracks what was sent
                            out.on_sent()
                    if out.close:
                        reason = _CLOSE_REASONS.get(out.close_code, "closed by server, see error")
                        await peer.ws.close(out.close_code, reason)
                        return
        except ConnectionClosed:
            return
        except TimeoutError:
            self.send_timeouts += 1
            log.warning(
                "dropping %s: its send buffer stayed full for %g s",
                peer.conn_id,
                self.send_timeout_s,
            )
            # not reading is not leaving: the seat is held for a resume
            self._slot(peer).room.disconnect(peer.conn_id, asyncio.get_running_loop().time())
            peer.ws.transport.abort()

    # ------------------------------------------------------------------ simulation
    async def _sim_loop(self, slot: _Slot | None = None) -> None:
        """One room's loop: sleep until its timer (:meth:`Room.get_timer`), call
        :meth:`Room.handle_timer`; each room has its own, so no room waits for another's tick.

        The schedule (drift-free ticks, skipped overruns, crediting budgets when late) is the
        room's; this loop measures each tick's wall-clock cost for it (:meth:`Room.tick_cost`).
        It yields to the event loop before every tick, also when the tick is already due: the
        previous tick's frames are queued latest-wins (:meth:`_ready`), so without the yield a
        late tick would replace them before the senders had a chance to write them, and every
        user would lose that patch. A late tick also credits the router's across-rooms address
        budgets for the stall (:meth:`FloodControl.credit_stall`). An on-demand room without a
        connection for ``room_idle_s`` ends its loop and is closed (:meth:`_retire`).
        ``slot`` None is the default room.
        """
        if slot is None:
            slot = self._slots[DEFAULT_ROOM]
        loop = asyncio.get_running_loop()
        room = slot.room
        assert isinstance(room, Room), "a room in a process of its own ticks there"
        figures = slot.figures
        room.start(loop.time())
        while True:
            due = room.get_timer()
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            else:  # late: still let the senders write the last tick's frames first
                await asyncio.sleep(0)
            start = loop.time()
            before = room.tick_count
            if start > due:
                self.flood.credit_stall(self._live_peers(), due, start)
            try:
                outs = room.handle_timer(start)
            except Exception:  # a bug in the physics must not take every user down silently
                log.exception("room %r: simulation tick %d failed", slot.name, room.tick_count)
                outs = []
            cost = loop.time() - start
            room.tick_cost(cost)
            if room.tick_count != before:  # a tick ran (not an early wake-up)
                figures.tick_s.add(cost)  # the metrics' share: two integer histograms
                figures.lateness_s.add(max(0.0, start - due))
            self._dispatch(outs)
            self._start_designs()
            if slot.prefetcher is not None:
                slot.prefetcher.after_tick()
            if slot.name == DEFAULT_ROOM:  # once per default tick is often enough
                self.flood.forget_idle(self._live_peers(), start)
            idle = slot.empty_since_s
            if slot.on_demand and idle is not None and start - idle >= self.room_idle_s:
                await self._retire(slot)
                return

    async def _supervise(self, slot: _Slot) -> None:
        """Run a room in a process of its own (:class:`server.room_process.RoomProxy`): start
        it, relay its messages, and when it dies (or hangs and is killed for it,
        :data:`server.room_process.HANG_S`), log it, tell its connections
        ``room_restarting`` (close 1012) and start it again (from its snapshot, if the snapshot
        directory holds one); an on-demand room without a connection for ``room_idle_s`` is
        closed. Other rooms are not touched."""
        proxy = slot.room
        assert isinstance(proxy, RoomProxy)
        loop = asyncio.get_running_loop()
        events = RoomEvents(
            dispatch=self._dispatch,
            named=self._named,
            stall=lambda due, start: self.flood.credit_stall(self._live_peers(), due, start),
            job=self._start_designs,
            figures=slot.figures,
        )
        while not proxy.closing:
            running = asyncio.ensure_future(proxy.run(events))
            try:
                while not running.done():
                    await asyncio.wait({running}, timeout=1.0)
                    if slot.peers == 0 and not proxy.running:
                        # idle time counts from the process's first tick: on a busy machine a
                        # process starts (or restarts) slower than room_idle_s, and the user
                        # whose handshake made the room, or who rejoins it, finds it closed
                        slot.empty_since_s = loop.time()
                    idle = slot.empty_since_s
                    if (
                        slot.on_demand
                        and not proxy.closing
                        and idle is not None
                        and loop.time() - idle >= self.room_idle_s
                    ):
                        log.info(
                            "room %r closed: no connection for %g s", slot.name, self.room_idle_s
                        )
                        self._slots.pop(slot.name, None)
                        self.figures.pop(slot.name, None)
                        await proxy.close()
                code = await running
            except Exception:  # noqa: BLE001 - starting it failed (no process, no pipe): retry
                log.exception("room %r: its process could not be run", slot.name)
                code = None
            finally:
                if not running.done():  # cancelled (stop): the process is killed
                    proxy.kill()
                    running.cancel()
            if proxy.closing:
                return
            was_ready = (
                proxy.ready is not None and proxy.ready.done() and not (proxy.ready.exception())
            )
            log.error(
                "room %r: its process ended (exit code %s); its connections are told %s and "
                "it starts again",
                slot.name,
                code,
                RESTARTING_CODE,
            )
            self._room_died(slot)
            proxy.restarts += 1
            if not was_ready:  # it could not even start: do not spin
                await asyncio.sleep(RESTART_BACKOFF_S)

    def _room_died(self, slot: _Slot) -> None:
        """Tell every connection of a room whose process died ``room_restarting`` and close
        it with code 1012, ahead of any state frame still queued for it."""
        frame = encode(ErrorMsg(code=RESTARTING_CODE, message=RESTARTING_MESSAGE, fatal=True))
        for peer in list(self._peers.values()):
            if peer.closed or self._slot(peer) is not slot:
                continue
            peer.closed = True
            peer.ready = deque(o for o in peer.ready if o.stream is None and not o.close)
            self._ready(
                peer, Outgoing(peer.conn_id, frame, close=True, close_code=DRAIN_CLOSE_CODE)
            )

    def _named(self, conn_id: str, who: str) -> None:
        """A room in a process of its own welcomed a connection: now we know who it is."""
        peer = self._peers.get(conn_id)
        if peer is not None and not peer.named:
            peer.named = True
            peer.who += f" {who}"
            log.info("connection %s: %s joined", conn_id, peer.who)

    def _start_designs(self) -> None:
        """Keep the gain workers busy with the most urgent queued jobs (``GainAdvisor.next_job``):
        the check worker with interim checks, and when none waits band checks
        (:mod:`shared.gains.b_o_band`: two acceptance tests each) and checks of the cells
        beside a damped contact's, so a check asked meanwhile waits at most one of those; the
        design worker with the most urgent job of any kind (interim checks first, then the
        newest designs, band checks, checks ahead, pair checks, then checks of a FEM contact's
        gains on the solid's modes: ``GainAdvisor.guard_modes``, 0.26-1.0 s each, one of which
        takes the turn after each design; in the check
        worker they delayed interim checks, and a resting user pressed on by another rendered an
        uncompensated interim felt 4 times softer for two seconds). One job per
        worker at a time, so that an urgent check never waits behind a queue of jobs already
        handed to a pool, nor behind a design running. The rooms take turns: each pick starts
        with the room after the one served last."""
        idle = self.idle_work_ok()
        while len(self._check_tasks) < CHECK_WORKERS:
            picked = self._next_gain_job("interim")
            if picked is None and idle:
                picked = self._next_gain_job("band") or self._next_gain_job("ahead")
            if picked is None:
                break
            self._check_tasks.add(asyncio.create_task(self._design(*picked, checks=True)))
        while len(self._gain_tasks) < DESIGN_WORKERS:
            picked = self._next_gain_job(None, idle)
            if picked is None:
                return
            self._gain_tasks.add(asyncio.create_task(self._design(*picked)))

    def idle_work_ok(self) -> bool:
        """Whether the gain workers have CPU to spare for checks no contact waits for: the check
        worker's median share of a core over its last jobs is at least
        :data:`IDLE_WORK_MIN_SHARE` (none measured yet: no)."""
        shares = sorted(self.check_cpu_share)
        ok = bool(shares) and shares[len(shares) // 2] >= IDLE_WORK_MIN_SHARE
        if ok != self._idle_work:
            self._idle_work = ok
            log.info(
                "gain workers: %s (the check worker's median share of a core: %.2f)",
                "checks ahead of need on" if ok else "checks ahead of need off: no CPU to spare",
                shares[len(shares) // 2] if shares else 0.0,
            )
        return ok

    def _next_gain_job(
        self, only: JobKind | None, idle: bool = True
    ) -> tuple[AnyRoom, GainJob] | None:
        """The next room's most urgent gain job (``only`` one of that kind; ``idle``: band
        checks and checks ahead too), in turn."""
        slots = list(self._slots.values())
        for i in range(len(slots)):
            slot = slots[(self._design_turn + i) % len(slots)]
            job = slot.room.gains.next_job(only, idle)
            if job is not None:
                self._design_turn = (self._design_turn + i + 1) % len(slots)
                return slot.room, job
        return None

    def _design_pool(self, checks: bool = False) -> Executor:
        """The design worker, or with ``checks`` the check worker (each started once, at the
        server's start or on its first job)."""

        def spawn(workers: int, init: Callable[[], None] = background_worker) -> Executor:
            ctx = multiprocessing.get_context("spawn")
            return ProcessPoolExecutor(workers, mp_context=ctx, initializer=init)

        if checks:
            if self.check_executor is None:
                self.check_executor = spawn(CHECK_WORKERS, check_worker)
            return self.check_executor
        if self.gain_executor is None:
            self.gain_executor = spawn(DESIGN_WORKERS)
        return self.gain_executor

    def _tasks(self, checks: bool) -> set[asyncio.Task[None]]:
        """The running jobs of the check worker (``checks``) or of the design worker."""
        return self._check_tasks if checks else self._gain_tasks

    async def _warm_design_pool(self, checks: bool = False) -> None:
        """Start the design (or check) worker and import the design code in it before anyone
        joins: a worker spawned on the first user's first patch took seconds (imports) before its
        first interim check on a busy 2-core machine."""
        loop = asyncio.get_running_loop()
        me = asyncio.current_task()
        try:
            await loop.run_in_executor(self._design_pool(checks), warm_up)
        except Exception:  # no warm worker: the first job starts it
            log.exception(
                "the gain %s worker could not be started", "check" if checks else "design"
            )
        finally:
            self._tasks(checks).discard(me)  # type: ignore[arg-type]
        self._start_designs()

    async def _design(self, room: AnyRoom, job: GainJob, checks: bool = False) -> None:
        """Run one gain job of ``room`` off the simulation loop (in the design worker, or with
        ``checks`` the check worker) and hand its result back."""
        pool = self._design_pool(checks)
        table = room.gains.table
        loop = asyncio.get_running_loop()
        me = asyncio.current_task()
        start = loop.time()
        try:
            design, cpu_s = await loop.run_in_executor(
                pool, run_job_measured, job, table.grid_ratio, table.hand_box
            )
            wall_s = loop.time() - start
            if checks and wall_s >= IDLE_WORK_MIN_WALL_S:
                self.check_cpu_share.append(min(1.0, cpu_s / wall_s))
            log.debug(
                "gain job %s (the %s worker): %.3f s of CPU in %.3f s", job.kind,
                "check" if checks else "design", cpu_s, wall_s,
            )  # fmt: skip
        except Exception:  # a broken worker must not stop the room: no recommendation
            log.exception("gain design %s failed", job.kind)
            design = None
        finally:
            self._tasks(checks).discard(me)  # type: ignore[arg-type]
        room.gains.store(job, design)
        self._start_designs()


async def _frames(first: str | bytes | None, ws: ServerConnection) -> AsyncIterator[str | bytes]:
    """``first`` (a hello already read, when not None), then every frame of ``ws``."""
    if first is not None:
        yield first
    async for frame in ws:
        yield frame


def _address(ws: ServerConnection) -> str:
    """The peer's source address (host part only; ports change on every connection)."""
    remote = ws.remote_address
    if isinstance(remote, tuple) and remote:
        host = str(remote[0])
        return host.removeprefix("::ffff:")  # an IPv4 peer on a dual-stack socket
    return "unknown"
