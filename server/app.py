"""The server's asyncio layer: websockets, static files, the simulation schedule, latency injection.

Everything that decides anything lives in :class:`server.room.Room`; this module only moves
frames between sockets and the room, wakes the room at its timer and injects latency. HTTP ``/`` serves the viewer (web/), ``/vendor/three/...`` the three.js package from
web/node_modules, ``/status`` a JSON summary; the websocket endpoint is ``/ws``.

With an :class:`ssl.SSLContext` everything is served as ``https://`` and ``wss://``. Browser
handshakes are checked by ``Origin`` (:func:`server.security.origin_allowed`), each connection is
registered with its source address (the room budgets per address), and a consumer whose send
buffer stays full for ``send_timeout_s`` (10 s) is dropped, viewers included.

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
import mimetypes
import multiprocessing
import ssl
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from haptic_collab.server.gains import GainJob, run_job
from haptic_collab.server.latency import LinkShaper
from haptic_collab.server.metrics import RoomFigures, ServerCollector, scrape_allowed
from haptic_collab.server.prefetch import PatchPrefetcher
from haptic_collab.server.room import Outgoing, Room
from haptic_collab.server.security import TokenTable, is_loopback, origin_allowed
from haptic_collab.shared.gain_table import warm_up
from haptic_collab.shared.protocol import LinkConditions
from haptic_collab.workers import background_worker, stop_pool

log = logging.getLogger("haptic.server")

#: websockets' own frame limit; the room answers frames above its smaller limit with an error.
WS_MAX_SIZE = 64 * 1024
#: The name of the one room a server runs today (rooms by URL come later; every per-room figure,
#: the Agones ``rooms`` list and the metrics' ``room`` label already name it).
DEFAULT_ROOM = "default"
#: A room whose next tick is overdue by more than this many periods (and at least
#: :data:`STALL_MIN_S`) counts as stalled (:meth:`ServerApp.room_reports`).
STALL_PERIODS = 3.0
#: The shortest overdue time [s] that counts as a stall.
STALL_MIN_S = 1.0
#: Worker processes that design recommended gains (niced; :func:`background_worker`).
DESIGN_WORKERS = 1
#: A consumer whose send buffer stays full this long [s] is dropped.
SEND_TIMEOUT_S = 10.0
#: The viewer's files: the package data ``haptic_collab/web`` (in a source checkout a link to
#: ``web/``); three.js is served from its ``node_modules/three`` (npm's copy in a checkout, the
#: files the page loads in a wheel).
WEB_DIR = Path(str(resources.files("haptic_collab") / "web"))
_STATIC_SUFFIXES = {".html", ".js", ".mjs", ".css", ".json", ".png", ".svg", ".ico", ".map"}


@dataclass(frozen=True)
class RoomReport:
    """What the orchestration layer needs of one room, read on the event loop's thread.

    Attributes
    ----------
    name : str
        The room's name (:data:`DEFAULT_ROOM` today).
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


@dataclass
class _Peer:
    conn_id: str
    ws: ServerConnection
    up: LinkShaper
    down: LinkShaper
    ready: deque[Outgoing] = field(default_factory=deque)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    #: Who, for log lines: "HOST:PORT", then "HOST:PORT user 'A' (u1)" once welcomed.
    who: str = ""
    named: bool = False
    #: The figures of the room it is in (patches and viewer bytes its sender writes).
    figures: RoomFigures = field(default_factory=RoomFigures)


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
    """Runs one room over websockets.

    Parameters
    ----------
    room : Room
        The sans-I/O core.
    host, port : str, int
        Where to listen (port 0 picks a free port; see :attr:`port` after start).
    link : LinkConditions, optional
        Latency injection applied to each direction of each connection (default: none). Give
        the room's ``link``: the room announces its own to clients in ``welcome`` and ``room``.
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
    prefetch : bool
        Solve the load patches next to the users' contacts in a worker thread between ticks
        (:class:`server.prefetch.PatchPrefetcher`); ``haptic server`` turns it on for the FEM
        solid.
    metrics_token : TokenTable, optional
        The token a scrape of ``/metrics`` must carry (``Authorization: Bearer``); without one
        only a server on loopback answers it (:func:`server.metrics.scrape_allowed`).
    """

    def __init__(
        self,
        room: Room,
        host: str = "127.0.0.1",
        port: int = 8765,
        link: LinkConditions | None = None,
        seed: int = 0,
        web_dir: Path = WEB_DIR,
        ssl_context: ssl.SSLContext | None = None,
        allowed_origins: tuple[str, ...] | frozenset[str] = (),
        send_timeout_s: float = SEND_TIMEOUT_S,
        gain_executor: Executor | None = None,
        prefetch: bool = False,
        metrics_token: TokenTable | None = None,
    ) -> None:
        self.room = room
        #: What this layer counts per room, by name (:mod:`server.metrics`).
        self.figures: dict[str, RoomFigures] = {DEFAULT_ROOM: RoomFigures()}
        self.metrics_token = metrics_token
        #: The registry ``/metrics`` exposes: one collector reading the rooms when scraped.
        self.metrics_registry = CollectorRegistry(auto_describe=False)
        self.metrics_registry.register(ServerCollector(self))
        #: Solve the patches next to the users' contacts between ticks (server.prefetch).
        self.prefetch = bool(prefetch)
        #: Where recommended-gain designs run (default: one spawned worker process, made on the
        #: first design; server.gains). Never the event loop's thread.
        self.gain_executor = gain_executor
        self._own_executor = gain_executor is None
        self._gain_tasks: set[asyncio.Task[None]] = set()
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
        self._sim_task: asyncio.Task[None] | None = None
        #: Solves the patches next to the users' contacts between ticks (server.prefetch).
        self.prefetcher: PatchPrefetcher | None = None

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Listen and start the simulation loop."""
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
        if self.prefetch:
            self.prefetcher = PatchPrefetcher(self.room.world)
        self._sim_task = asyncio.create_task(self._sim_loop())
        if self._own_executor:  # an injected executor (tests) is the caller's to warm
            self._gain_tasks.add(asyncio.create_task(self._warm_design_pool()))

    async def stop(self) -> None:
        """Stop the simulation and close every connection."""
        if self._sim_task:
            self._sim_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._sim_task
        self.room.stop()  # no schedule any more: nothing is behind it
        if self.prefetcher is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.prefetcher.close)
            self.prefetcher = None
        pending = list(self._gain_tasks)
        for task in pending:
            task.cancel()
        for task in pending:  # let them finish their cancellation while the loop still runs
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        if self._own_executor and self.gain_executor is not None:
            stop_pool(self.gain_executor)  # a running design must not hold up the stop
            self.gain_executor = None
        if self._server:
            self._server.close()
            await self._server.wait_closed()

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

    # ------------------------------------------------------------------ HTTP
    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path in ("/ws", "/ws/"):
            origin = request.headers.get("Origin")
            if origin_allowed(
                origin, request.headers.get("Host"), self.allowed_origins, is_loopback(self.host)
            ):
                return None
            self.origins_refused += 1
            log.warning("refused a websocket handshake from origin %.100r", origin)
            return _text(HTTPStatus.FORBIDDEN, "origin not allowed (see --allow-origin)\n")
        if path == "/status":
            body = json.dumps(self.status())
            return _text(HTTPStatus.OK, body, "application/json")
        if path == "/metrics":
            return self._metrics(request)
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return _text(HTTPStatus.NOT_FOUND, "the websocket endpoint is /ws\n")
        return _static_response(self.web_dir, path)

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
            "node_modules/three/build/three.module.js",
        )
        return [rel for rel in need if not (self.web_dir / rel).is_file()]

    def rooms(self) -> dict[str, Room]:
        """The rooms this server runs, by name: today one, :data:`DEFAULT_ROOM`.

        The Agones agent (:mod:`server.agones`) and the metrics (:mod:`server.metrics`) read
        every room through this mapping, so that a server of several rooms only changes it.
        """
        return {DEFAULT_ROOM: self.room}

    def room_reports(self) -> list[RoomReport]:
        """A :class:`RoomReport` of every room of :meth:`rooms`; call it on the event loop.

        A room is alive while the simulation task runs and its next tick is not overdue by
        more than ``max(STALL_MIN_S, STALL_PERIODS / sim_rate_hz)`` [s]: a dead loop (task ended)
        or one whose ticks stopped (a tick that never returns blocks this very call, which is
        how a caller on another thread sees a blocked loop: no answer).
        """
        now = asyncio.get_running_loop().time()
        running = self._sim_task is not None and not self._sim_task.done()
        out = []
        for name, room in self.rooms().items():
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

    def status(self) -> dict[str, Any]:
        """JSON-able summary: tick, users, viewers, tick costs, overruns, link conditions."""
        room = self.room
        return {
            "tick": room.tick_count,
            "sim_rate_hz": room.sim_rate_hz,
            "users": len(room.users),
            "viewers": len(room.viewers),
            "tick_ms_p50": room.stats.percentile(50),
            "tick_ms_p99": room.stats.percentile(99),
            "overruns": room.stats.overruns,
            "latency_ms": self.link.latency_ms,
            "jitter_ms": self.link.jitter_ms,
            "loss": self.link.loss,
            "tls": self.ssl_context is not None,
            "auth": room.auth is not None,
            "force_clamps": sum(room.clamp_counts.values()),
            "send_timeouts": self.send_timeouts,
            "origins_refused": self.origins_refused,
        }

    # ------------------------------------------------------------------ websockets
    async def _handler(self, ws: ServerConnection) -> None:
        self._next_conn += 1
        conn_id = f"c{self._next_conn}"
        peer = _Peer(
            conn_id,
            ws,
            up=LinkShaper(self.link, seed=f"{self.seed}:{conn_id}:up"),
            down=LinkShaper(self.link, seed=f"{self.seed}:{conn_id}:down"),
        )
        peer.figures = self.figures[DEFAULT_ROOM]
        self._peers[conn_id] = peer
        loop = asyncio.get_running_loop()
        sender = asyncio.create_task(self._sender(peer))
        address = _address(ws)
        remote = ws.remote_address
        port = remote[1] if isinstance(remote, tuple) and len(remote) > 1 else None
        peer.who = address if port is None else f"{address}:{port}"
        log.info("connection %s open: %s", conn_id, peer.who)
        try:
            self._dispatch(self.room.connect(conn_id, loop.time(), address))
            async for frame in ws:  # after a refusal: keep draining for the close handshake
                now = loop.time()
                # flood control on arrival, before latency injection holds anything in memory
                admitted, outs = self.room.admit(conn_id, frame, now)
                if outs:
                    self._dispatch(outs)
                if not admitted:
                    continue
                if not self.link.active:
                    self._deliver(conn_id, frame)
                    continue
                at = peer.up.schedule(now, droppable=self.room.droppable(frame))
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
            self.room.disconnect(conn_id)
            self._peers.pop(conn_id, None)
            sender.cancel()
            # bounded: on Python 3.11 a cancel that lands as the sender's wait_for(send) finishes
            # is swallowed, and an unbounded await would never return
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed, TimeoutError):
                await asyncio.wait_for(sender, 5.0)

    def _deliver(self, conn_id: str, frame: str | bytes) -> None:
        """Hand an admitted frame to the room when it is due (after any injected latency)."""
        if conn_id not in self._peers:
            return
        try:
            outs = self.room.handle(conn_id, frame, asyncio.get_running_loop().time())
        except Exception:  # a bug must cost one frame, not the connection or the room
            log.exception("frame from %s could not be handled", conn_id)
            return
        peer = self._peers.get(conn_id)
        if peer is not None and not peer.named:
            who = self.room.describe(conn_id)
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
        """Queue a due frame; a newer frame of a state stream replaces the queued older one."""
        if out.stream is not None and any(o.stream == out.stream for o in peer.ready):
            peer.ready = deque(o for o in peer.ready if o.stream != out.stream)
        peer.ready.append(out)
        peer.wake.set()

    async def _sender(self, peer: _Peer) -> None:
        """Send queued frames in order until a closing frame or the connection ends.

        A send that cannot complete within ``send_timeout_s`` (the peer does not read and its
        buffer stays full) drops the peer: the room forgets it and the socket is aborted.
        """
        try:
            while True:
                await peer.wake.wait()
                peer.wake.clear()
                while peer.ready:
                    out = peer.ready.popleft()
                    if out.data is not None:
                        await asyncio.wait_for(peer.ws.send(out.data), self.send_timeout_s)
                        if out.stream == "patch":
                            peer.figures.patches_sent += 1
                        elif isinstance(out.data, bytes):  # the viewers' surface stream
                            peer.figures.viewer_bytes_sent += len(out.data)
                        if out.on_sent is not None:  # the viewer stream tracks what was sent
                            out.on_sent()
                    if out.close:
                        reason = "bye" if out.close_code == 1000 else "closed by server, see error"
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
            self.room.disconnect(peer.conn_id)
            peer.ws.transport.abort()

    # ------------------------------------------------------------------ simulation
    async def _sim_loop(self) -> None:
        """Sleep until the room's timer (:meth:`Room.get_timer`), call :meth:`Room.handle_timer`.

        The schedule (drift-free ticks, skipped overruns, crediting budgets when late) is the
        room's; this loop measures each tick's wall-clock cost for it (:meth:`Room.tick_cost`).
        It yields to the event loop before every tick, also when the tick is already due: the
        previous tick's frames are queued latest-wins (:meth:`_ready`), so without the yield a
        late tick would replace them before the senders had a chance to write them, and every
        user would lose that patch.
        """
        loop = asyncio.get_running_loop()
        room = self.room
        figures = self.figures[DEFAULT_ROOM]
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
            try:
                outs = room.handle_timer(start)
            except Exception:  # a bug in the physics must not take every user down silently
                log.exception("simulation tick %d failed", room.tick_count)
                outs = []
            cost = loop.time() - start
            room.tick_cost(cost)
            if room.tick_count != before:  # a tick ran (not an early wake-up)
                figures.tick_s.add(cost)  # the metrics' share: two integer histograms
                figures.lateness_s.add(max(0.0, start - due))
            self._dispatch(outs)
            self._start_designs()
            if self.prefetcher is not None:
                self.prefetcher.after_tick()

    def _start_designs(self) -> None:
        """Keep the design worker busy with the most urgent queued job (``GainAdvisor.next_job``:
        interim checks first, then the newest designs), one job per worker at a time, so that an
        urgent check never waits behind a queue of designs already handed to the pool."""
        while len(self._gain_tasks) < DESIGN_WORKERS:
            job = self.room.gains.next_job()
            if job is None:
                return
            self._gain_tasks.add(asyncio.create_task(self._design(job)))

    def _design_pool(self) -> Executor:
        """The design workers (started once, at the server's start or on the first job)."""
        if self.gain_executor is None:
            ctx = multiprocessing.get_context("spawn")
            self.gain_executor = ProcessPoolExecutor(
                max_workers=DESIGN_WORKERS, mp_context=ctx, initializer=background_worker
            )
        return self.gain_executor

    async def _warm_design_pool(self) -> None:
        """Start the design workers and import the design code in them before anyone joins: a
        worker spawned on the first user's first patch took seconds (imports) before its first
        interim check on a busy 2-core machine."""
        loop = asyncio.get_running_loop()
        me = asyncio.current_task()
        try:
            await loop.run_in_executor(self._design_pool(), warm_up)
        except Exception:  # no warm worker: the first job starts it
            log.exception("the gain design worker could not be started")
        finally:
            self._gain_tasks.discard(me)  # type: ignore[arg-type]
        self._start_designs()

    async def _design(self, job: GainJob) -> None:
        """Run one gain design off the simulation loop (a worker process) and hand it back."""
        self._design_pool()
        table = self.room.gains.table
        loop = asyncio.get_running_loop()
        me = asyncio.current_task()
        try:
            design = await loop.run_in_executor(
                self.gain_executor, run_job, job, table.grid_ratio, table.hand_box
            )
        except Exception:  # a broken worker must not stop the room: no recommendation
            log.exception("gain design %s failed", job.kind)
            design = None
        finally:
            self._gain_tasks.discard(me)  # type: ignore[arg-type]
        self.room.gains.store(job, design)
        self._start_designs()


def _address(ws: ServerConnection) -> str:
    """The peer's source address (host part only; ports change on every connection)."""
    remote = ws.remote_address
    if isinstance(remote, tuple) and remote:
        host = str(remote[0])
        return host.removeprefix("::ffff:")  # an IPv4 peer on a dual-stack socket
    return "unknown"
