"""A room in a process of its own (``haptic server --room-processes``): the child and its proxy.

Why: every room of a server otherwise steps on the one event loop, so a FEM solid's 20-50 ms tick
delays a balloon room's tick and every socket's writes. With room processes each room's
:class:`server.room.Room` and :class:`server.world.World` live in a child process with their own
event loop and tick schedule (forked from a fork server that has imported the server's modules,
:func:`_context`; one BLAS thread), and the front process (:class:`server.app.ServerApp`) keeps
the sockets: it accepts connections, checks origins, routes by URL, keeps the per-address
budgets across rooms (it alone sees the client's real address, which it hands to the room with
each connection), applies latency injection and relays every connection's frames, text and
binary, to and from its room's process. The room's process checks tokens and its own budgets.

The link between the two is one ``multiprocessing.Pipe`` (a unix socketpair) per room, read and
written with asyncio streams on both sides; each message is a 4-byte big-endian length and a
pickle of a tuple of the project's own values, only ever between a front and the children it
spawned. Front to room: ``connect``, ``frame``, ``disconnect``, ``sent`` (a frame whose
``on_sent`` the viewer stream waits for was written), ``design`` (a gain design's result),
``drain``, ``stop``. Room to front: ``ready``, ``failed``, ``out`` (a tick's or a frame's
:class:`server.room.Outgoing`, batched), ``named``, ``stall`` (a late tick: the front credits
its across-room budgets), ``job`` (a gain design the front's one design worker runs),
``checkpoint`` (with a snapshot directory, below), ``seats`` (the seats its users can resume,
as they change), ``report`` (every :data:`REPORT_S`: the tick count and schedule, users, viewers, tick-cost
percentiles, overruns and the two metric histograms, so ``/status``, ``/metrics`` and the Agones
agent read the room without asking it), ``drained``.

The per-room budgets (:meth:`server.room.Room.admit`) run in the room's process when a frame is
delivered there, after any injected latency (in one process they are charged on arrival); the
per-address budgets across rooms stay the front's and are charged on arrival.

A room's process that dies is noticed by the front (its stream ends); one that hangs (alive,
its event loop stuck in a tick that never returns, or stopped) is noticed when no message has
come from it, or its next tick is overdue, for :data:`HANG_S`, and is killed: either way the
front tells that room's clients ``room_restarting`` with close code 1012 and starts the room
again (:class:`RoomProxy`). With a snapshot directory the room's process sends the front a checkpoint
of its object state every :data:`CHECKPOINT_S` (``checkpoint``), which the front writes there as
the room's snapshot before starting it again, so it starts from where it was at most that long
before it died; without one it starts from rest. Its users keep their seats: the front keeps the
room's seats as its process last sent them (user id, name, the resume token's digest; never the
token) and the next process holds them as seats whose link dropped at its start
(:meth:`server.room.Room.hold_seats`), so a user who joins again with its resume token within
:data:`server.room.RESUME_HOLD_S` gets its user id and name (and so its colour) back.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # before numpy loads in a room's process (cli.blas_threads)

import asyncio  # noqa: E402
import contextlib  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import multiprocessing  # noqa: E402
import pickle  # noqa: E402
import signal  # noqa: E402
import socket  # noqa: E402
import time  # noqa: E402
from collections import OrderedDict  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from multiprocessing.connection import Connection  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

from haptic_collab.server.gains import IDLE_KINDS  # noqa: E402
from haptic_collab.server.metrics import LATENESS_BUCKETS_S, TICK_BUCKETS_S, Buckets  # noqa: E402
from haptic_collab.server.priority import TickPriority  # noqa: E402
from haptic_collab.server.room import Outgoing, Room, SeatRecord  # noqa: E402

log = logging.getLogger("haptic.server")

#: How often [s] a room's process reports its figures to the front.
REPORT_S = 0.25
#: How often [s] a room's process sends the front a checkpoint of its object state (only with
#: a snapshot directory): what the room starts from again if its process dies.
CHECKPOINT_S = 2.0
#: The error code a room's users get when its process died, before close code 1012.
RESTARTING_CODE = "room_restarting"
#: The message that goes with it.
RESTARTING_MESSAGE = (
    "this room's simulation stopped unexpectedly and is restarting; join again "
    "(with your resume token to keep your seat)"
)
#: How long [s] the front waits, once a room's process has started, without a message from it
#: (a report comes every :data:`REPORT_S`) or with its next tick overdue by as much, before it
#: deems the process hung (a tick that never returns, a stopped process), kills it and starts
#: it again as a dead one (:meth:`RoomProxy.run`). Far above any tick the server is meant to
#: run (a FEM solid's is tens of ms) and above the scheduler's pauses on a loaded machine;
#: low enough that the room's users are told within seconds.
HANG_S = 3.0
#: How long [s] a room's process may take to build its room and start at most.
START_TIMEOUT_S = 120.0
#: How long [s] a stopped room's process may take to exit before it is killed.
EXIT_TIMEOUT_S = 2.0
#: Acknowledgements a room's process waits for at most (older ones: the frame was replaced).
MAX_ACKS = 4096
#: Messages kept for a room process being (re)started at most (beyond: dropped).
MAX_PENDING = 10_000
_HEADER = 4


@dataclass(frozen=True)
class RoomSpec:
    """How to build one room in its process (pickled to the child).

    Attributes
    ----------
    name : str
        The room's name.
    build : callable
        Builds the :class:`server.room.Room` (called in the child; picklable: a module-level
        function or a ``functools.partial`` of one).
    sim_rate_hz : float
        Its simulation rate [Hz] (the front needs it before the room is built).
    max_users : int
        Its user cap (for ``/status``).
    auth : bool
        Whether its connections must present a token (for ``/status``).
    prefetch : bool or callable
        Whether to prefetch its patches (:class:`server.prefetch.PatchPrefetcher`); a callable
        of the room says so (picklable).
    log_level : int
        The child's logging level.
    tick_priority : str
        ``"realtime"``: the child's event loop thread asks for a real-time priority
        (:class:`server.priority.TickPriority`); ``"off"``: it keeps the ordinary policy.
    """

    name: str
    build: Callable[[], Room]
    sim_rate_hz: float
    max_users: int
    auth: bool = False
    prefetch: bool | Callable[[Room], bool] = False
    log_level: int = logging.INFO
    tick_priority: str = "off"


# ---------------------------------------------------------------------- framing
def _pack(msg: tuple[Any, ...]) -> bytes:
    body = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    return len(body).to_bytes(_HEADER, "big") + body


async def _unpack(reader: asyncio.StreamReader) -> tuple[Any, ...]:
    """The next message (raises ``asyncio.IncompleteReadError`` at the end of the stream)."""
    n = int.from_bytes(await reader.readexactly(_HEADER), "big")
    # only ever a message this project's front or room process wrote (module docstring)
    return pickle.loads(await reader.readexactly(n))  # noqa: S301


async def _streams(chan: Connection) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Asyncio streams over a duplex ``multiprocessing.Pipe`` end (a unix socket)."""
    sock = socket.socket(fileno=os.dup(chan.fileno()))
    chan.close()
    sock.setblocking(False)
    return await asyncio.open_unix_connection(sock=sock, limit=1 << 24)


# ---------------------------------------------------------------------- the child
def room_main(
    spec: RoomSpec,
    chan: Connection,
    snapshot_dir: str | None,
    seats: tuple[list[SeatRecord], int] | None = None,
) -> None:
    """A room process's entry point: build the room (holding ``seats``, the seats of the
    room's previous process, :meth:`server.room.Room.hold_seats`), serve the front until told
    to stop or until the front's end of the pipe closes (the front is gone: exit)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the front's: it drains us
    logging.basicConfig(
        level=spec.log_level,
        format=f"%(asctime)s %(levelname)s %(name)s [room {spec.name}]: %(message)s",
    )
    asyncio.run(_Child(spec, snapshot_dir, seats).run(chan))


@dataclass
class _Child:
    spec: RoomSpec
    snapshot_dir: str | None
    seats: tuple[list[SeatRecord], int] | None = None
    #: The seats last sent to the front (``seats``).
    seats_sent: Any = None
    room: Room | None = None
    writer: asyncio.StreamWriter | None = None
    prefetcher: Any = None
    tick_s: Buckets = field(default_factory=lambda: Buckets(TICK_BUCKETS_S))
    lateness_s: Buckets = field(default_factory=lambda: Buckets(LATENESS_BUCKETS_S))
    named: set[str] = field(default_factory=set)
    acks: OrderedDict[int, Callable[[], None]] = field(default_factory=OrderedDict)
    next_ack: int = 0
    job_out: bool = False
    sim: asyncio.Task[None] | None = None

    def send(self, *msg: Any) -> None:
        if self.writer is not None and not self.writer.is_closing():
            self.writer.write(_pack(msg))

    async def run(self, chan: Connection) -> None:
        reader, self.writer = await _streams(chan)
        try:
            room = await asyncio.to_thread(self.spec.build)
            if self.snapshot_dir is not None:
                from haptic_collab.server import snapshots

                snapshots.restore(self.snapshot_dir, self.spec.name, room)
        except Exception as exc:  # noqa: BLE001 - told to the front, which logs and refuses
            log.exception("room %r could not be built", self.spec.name)
            self.send("failed", f"{type(exc).__name__}: {exc}")
            await self.writer.drain()
            return
        self.room = room
        # the room's ticks run on this thread: real-time where allowed, before the prefetch
        # thread is started (it then keeps the ordinary policy: SCHED_RESET_ON_FORK)
        TickPriority(self.spec.tick_priority, f"room {self.spec.name!r}").ask()
        want = self.spec.prefetch(room) if callable(self.spec.prefetch) else self.spec.prefetch
        if want:
            from haptic_collab.server.prefetch import PatchPrefetcher

            self.prefetcher = PatchPrefetcher(room.world)
        loop = asyncio.get_running_loop()
        if self.seats is not None:  # the previous process's seats, for their users to resume
            room.hold_seats(*self.seats, loop.time())
            self.seats = None
        room.start(loop.time())
        self.send("ready", os.getpid(), room.object_info, room.tick_count)
        self._send_seats()
        self.sim = asyncio.create_task(self._sim_loop())
        reporter = asyncio.create_task(self._report_loop())
        if self.snapshot_dir is not None:
            checkpoints = asyncio.create_task(self._checkpoint_loop())
            self.sim.add_done_callback(lambda _t: checkpoints.cancel())
        try:
            while True:
                try:
                    msg = await _unpack(reader)
                except (asyncio.IncompleteReadError, ConnectionError):
                    return  # the front is gone
                if not self._handle(msg):
                    return
        finally:
            reporter.cancel()
            self.sim.cancel()
            if self.prefetcher is not None:
                self.prefetcher.close()
            with contextlib.suppress(Exception):
                await self.writer.drain()

    def _outs(self, outs: list[Outgoing]) -> None:
        """Send a batch of frames to the front (an ``on_sent`` becomes an acknowledgement id)."""
        if not outs:
            return
        wire = []
        for out in outs:
            ack = 0
            if out.on_sent is not None:
                self.next_ack += 1
                ack = self.next_ack
                self.acks[ack] = out.on_sent
                if len(self.acks) > MAX_ACKS:
                    self.acks.popitem(last=False)
            wire.append((out.conn_id, out.data, out.stream, out.close, out.close_code, ack))
        self.send("out", wire)

    def _handle(self, msg: tuple[Any, ...]) -> bool:
        """One message from the front; False: stop serving."""
        room = self.room
        assert room is not None
        now = asyncio.get_running_loop().time()
        kind = msg[0]
        if kind == "frame":
            conn_id, frame = msg[1], msg[2]
            try:
                outs = room.receive(conn_id, frame, now)
            except Exception:  # a bug must cost one frame, not the room
                log.exception("frame from %s could not be handled", conn_id)
                return True
            if conn_id not in self.named:
                who = room.describe(conn_id)
                if who is not None:  # welcomed: a new seat, or a resumed one's new token
                    self.named.add(conn_id)
                    self.send("named", conn_id, who)
                    self._send_seats()
            self._outs(outs)
        elif kind == "connect":
            self._outs(room.connect(msg[1], now, msg[2]))
        elif kind == "disconnect":
            self.named.discard(msg[1])
            room.disconnect(msg[1], now, hold=msg[2])
            self._send_seats()
        elif kind == "sent":
            on_sent = self.acks.pop(msg[1], None)
            if on_sent is not None:
                on_sent()
        elif kind == "design":
            room.gains.store(msg[1], msg[2])
            self.job_out = False
            self._next_job()
        elif kind == "drain":
            self._drain(bool(msg[1]))
        elif kind == "stop":
            return False
        return True

    def _drain(self, snapshot: bool) -> None:
        """Stop ticking, save the room's state when asked, say so (``drained``, the path)."""
        room = self.room
        assert room is not None
        if self.sim is not None:
            self.sim.cancel()
        room.stop()
        written = None
        if snapshot and self.snapshot_dir is not None:
            from haptic_collab.server import snapshots

            try:
                written = str(
                    snapshots.write(self.snapshot_dir, snapshots.capture(self.spec.name, room))
                )
            except Exception:  # noqa: BLE001 - the drain goes on without it
                log.exception("room %r: its state could not be saved", self.spec.name)
        self.send("drained", written)

    def _send_seats(self) -> None:
        """Send the front the room's seats (:meth:`server.room.Room.seat_records`) when they
        changed since last sent: what the room's next process holds if this one dies. Sent as
        each user is welcomed (its resume token is new) or leaves, and with each report (held
        seats that ran out)."""
        if self.room is None:
            return
        seats = self.room.seat_records()
        if seats != self.seats_sent:
            self.seats_sent = seats
            self.send("seats", *seats)

    def _next_job(self) -> None:
        """Hand the front the room's most urgent gain design, one at a time."""
        if self.job_out or self.room is None:
            return
        job = self.room.gains.next_job()
        if job is not None:
            table = self.room.gains.table
            self.job_out = True
            self.send("job", job, table.grid_ratio, table.hand_box)

    async def _sim_loop(self) -> None:
        """The room's tick schedule, as :meth:`server.app.ServerApp._sim_loop` runs it."""
        room = self.room
        assert room is not None
        loop = asyncio.get_running_loop()
        while True:
            due = room.get_timer()
            delay = due - loop.time()
            await asyncio.sleep(delay if delay > 0 else 0)
            start = loop.time()
            before = room.tick_count
            if start > due:
                self.send("stall", due, start)
            try:
                outs = room.handle_timer(start)
            except Exception:
                log.exception("room %r: simulation tick %d failed", self.spec.name, room.tick_count)
                outs = []
            cost = loop.time() - start
            room.tick_cost(cost)
            if room.tick_count != before:
                self.tick_s.add(cost)
                self.lateness_s.add(max(0.0, start - due))
            self._outs(outs)
            self._next_job()
            if self.prefetcher is not None:
                self.prefetcher.after_tick()

    async def _checkpoint_loop(self) -> None:
        """Send the front the room's object state every :data:`CHECKPOINT_S` (copies taken
        between ticks, :func:`server.snapshots.capture`)."""
        from haptic_collab.server import snapshots

        room = self.room
        assert room is not None
        while True:
            await asyncio.sleep(CHECKPOINT_S)
            try:
                self.send("checkpoint", snapshots.capture(self.spec.name, room))
            except Exception:  # noqa: BLE001 - no checkpoint: a restart starts from rest
                log.exception("room %r: its state could not be taken", self.spec.name)
                return

    async def _report_loop(self) -> None:
        room = self.room
        assert room is not None
        while True:
            self.send(
                "report",
                {
                    "tick": room.tick_count,
                    "ticks_run": room.ticks_run,
                    "due": room.get_timer(),
                    "users": room.users,
                    "viewers": room.viewers,
                    "held": len(room.held_seats),
                    "resumes": room.resumes,
                    "p50": room.stats.percentile(50),
                    "p99": room.stats.percentile(99),
                    "overruns": room.stats.overruns,
                    "clamps": sum(room.clamp_counts.values()),
                    "tick_s": (list(self.tick_s.counts), self.tick_s.total),
                    "lateness_s": (list(self.lateness_s.counts), self.lateness_s.total),
                },
            )
            self._send_seats()
            await asyncio.sleep(REPORT_S)


# ---------------------------------------------------------------------- the front's side
#: Modules the fork server imports once, so that a room's process starts without importing them
#: (seconds on a busy 2-core machine): a room restarted after its process died is back sooner.
PRELOAD = ("haptic_collab.server.main", "haptic_collab.server.room_process")


def _context() -> Any:
    """How room processes start: forked from a fork server that has imported :data:`PRELOAD`
    (a clean process, started on first use; never a fork of the front with its sockets and
    threads), or spawned where there is no fork server."""
    try:
        ctx = multiprocessing.get_context("forkserver")
    except ValueError:
        return multiprocessing.get_context("spawn")
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


class _Stats:
    """The room's tick figures as last reported (what :class:`server.room.TickStats` gives)."""

    def __init__(self) -> None:
        self.p50 = 0.0
        self.p99 = 0.0
        self.overruns = 0
        self.base_overruns = 0

    def percentile(self, q: float) -> float:
        """The reported median (q <= 50) or 99th percentile of recent tick costs [ms]."""
        return self.p50 if q <= 50 else self.p99


class _Table:
    def __init__(self) -> None:
        self.grid_ratio = 1.0
        self.hand_box: Any = None


class _RemoteGains:
    """The room's gain designs as the front's design worker sees them (next_job, store)."""

    def __init__(self, proxy: RoomProxy) -> None:
        self.proxy = proxy
        self.table = _Table()
        self.jobs: list[Any] = []

    def next_job(self, only: str | None = None, idle: bool = True) -> Any:
        for i, job in enumerate(self.jobs):
            kind = getattr(job, "kind", None)
            if (only is None or kind == only) and (idle or kind not in IDLE_KINDS):
                return self.jobs.pop(i)
        return None

    def store(self, job: Any, design: Any) -> None:
        self.proxy._send("design", job, design)


@dataclass
class RoomEvents:
    """What the front does with a room process's messages (:meth:`RoomProxy.run`)."""

    dispatch: Callable[[list[Outgoing]], None]
    named: Callable[[str, str], None]
    stall: Callable[[float, float], None]
    job: Callable[[], None]
    figures: Any  # server.metrics.RoomFigures: its two histograms are the room's


class RoomProxy:
    """The front's handle of a room in its own process: what :class:`server.app.ServerApp`
    calls of a :class:`server.room.Room`, relayed to the process, and the figures it last
    reported. Not thread-safe: use it on the front's event loop.

    Parameters
    ----------
    spec : RoomSpec
        How the room is built.
    snapshot_dir : path, optional
        Where the room's snapshot is looked for at each (re)start and written at a drain.
    """

    remote = True

    def __init__(self, spec: RoomSpec, snapshot_dir: str | Path | None = None) -> None:
        self.spec = spec
        self.name = spec.name
        self.snapshot_dir = str(snapshot_dir) if snapshot_dir is not None else None
        self.sim_rate_hz = float(spec.sim_rate_hz)
        self.limits = _Limits(spec.max_users)
        self.auth = spec.auth or None
        self.object_info: Any = None
        self.stats = _Stats()
        self.gains = _RemoteGains(self)
        self.tick_count = 0
        #: Ticks its processes ran, over restarts (from their reports).
        self.ticks_run = 0
        self.users: list[str] = []
        self.viewers: list[str] = []
        self.held_seats: list[str] = []
        self.resumes = 0
        self.clamp_counts: dict[str, int] = {}
        #: The process's id (None while none runs) and how many times it was started again.
        self.pid: int | None = None
        self.restarts = 0
        #: How many times its process was found hung and killed (:data:`HANG_S`).
        self.hangs = 0
        #: How long [s] its process's latest start took, from the spawn until it had built
        #: (or restored) its room and started ticking (None before it has).
        self.start_s: float | None = None
        self._spawned = math.inf
        #: How long [s] it may stay silent or overdue before it counts as hung.
        self.hang_s = HANG_S
        #: Set once it must not be started again (stop, drain).
        self.closing = False
        self.ready: asyncio.Future[None] | None = None
        self._due = math.inf
        #: When [s, monotonic] the process last sent anything.
        self._heard = -math.inf
        self._writer: asyncio.StreamWriter | None = None
        self._process: Any = None
        self._conns: set[str] = set()
        self._names: dict[str, str] = {}
        self._drained: asyncio.Future[str | None] | None = None
        #: The room's latest checkpoint (:data:`CHECKPOINT_S`; a server.snapshots.Snapshot).
        self._checkpoint: Any = None
        #: Its seats as its process last sent them (``seats``): held by its next process.
        self._seats: tuple[list[SeatRecord], int] | None = None
        #: Messages for a process being (re)started; and which start this is.
        self._pending: list[bytes] = []
        self._generation = 0
        self._base: dict[str, tuple[list[int], float]] = {}
        self._last: dict[str, tuple[list[int], float]] = {}
        self._base_clamps = 0
        self._base_resumes = 0
        self._base_ticks_run = 0

    # ------------------------------------------------------------------ Room's calls
    def _send(self, *msg: Any) -> None:
        """Write a message to the process; while it is being (re)started, keep it for then."""
        if self._writer is not None and not self._writer.is_closing():
            self._writer.write(_pack(msg))
        elif not self.closing and len(self._pending) < MAX_PENDING:
            self._pending.append(_pack(msg))

    def _ack(self, ack: int, generation: int) -> None:
        """A frame with ``on_sent`` was written: tell the process that made it (not a later
        one, whose acknowledgement numbers start again)."""
        if generation == self._generation:
            self._send("sent", ack)

    def connect(self, conn_id: str, now_s: float, address: str = "local") -> list[Outgoing]:
        """Register a connection with the room's process (its replies come as ``out``)."""
        self._conns.add(conn_id)
        self._send("connect", conn_id, address)
        return []

    def admit(self, conn_id: str, frame: str | bytes, now_s: float) -> tuple[bool, list[Outgoing]]:
        """Always admitted here: the room's own budgets are charged in its process."""
        return True, []

    droppable = staticmethod(Room.droppable)

    def handle(self, conn_id: str, frame: str | bytes, now_s: float) -> list[Outgoing]:
        """Relay a frame to the room's process."""
        if conn_id in self._conns:
            self._send("frame", conn_id, frame)
        return []

    def describe(self, conn_id: str) -> str | None:
        return self._names.get(conn_id)

    def disconnect(self, conn_id: str, now_s: float | None = None, hold: bool = True) -> None:
        if conn_id in self._conns:
            self._conns.discard(conn_id)
            self._names.pop(conn_id, None)
            self._send("disconnect", conn_id, hold)

    def get_timer(self) -> float:
        """When [s, the monotonic clock every process shares] the room's next tick was due at
        its last report (inf while no process runs)."""
        return self._due

    def stop(self) -> None:
        """Nothing to do here: the process stops its own schedule (:meth:`drain`)."""

    # ------------------------------------------------------------------ the process
    @property
    def running(self) -> bool:
        """Its process has built the room and not exited."""
        return (
            self.ready is not None
            and self.ready.done()
            and not self.ready.cancelled()
            and self.ready.exception() is None
            and self._process is not None
            and self._process.exitcode is None
        )

    async def run(self, events: RoomEvents) -> int | None:
        """Start the room's process and serve its messages until it exits; returns its exit
        code (None: it closed its end without exiting, and was killed)."""
        loop = asyncio.get_running_loop()
        self.ready = loop.create_future()
        if self._checkpoint is not None and self.snapshot_dir is not None:
            # started again after a death: from the last checkpoint, as from a drain's snapshot
            from haptic_collab.server import snapshots

            snap, self._checkpoint = self._checkpoint, None
            try:
                await asyncio.to_thread(snapshots.write, self.snapshot_dir, snap)
            except OSError:
                log.exception("room %r: its checkpoint could not be written", self.name)
        self._spawned = loop.time()
        try:
            ctx = _context()
            ours, theirs = ctx.Pipe(duplex=True)
            self._process = ctx.Process(
                target=room_main,
                args=(self.spec, theirs, self.snapshot_dir, self._seats),
                name=f"haptic room {self.name}",
                daemon=True,
            )
            self._process.start()
            theirs.close()
            reader, writer = await _streams(ours)
        except BaseException as exc:  # no process: whoever waits for it to start hears so
            if not self.ready.done():
                self.ready.set_exception(RuntimeError(f"room {self.name!r}: {exc!r}"))
                self.ready.exception()
            if self._process is not None and self._process.exitcode is None:
                with contextlib.suppress(Exception):
                    self._process.kill()
            self._process = None
            raise
        self._generation += 1
        for data in self._pending:  # connections made while it was being started
            writer.write(data)
        self._pending.clear()
        if self.closing:  # stopped while it was being started
            writer.write(_pack(("stop",)))
        self._writer = writer
        self._heard = loop.time()
        watchdog = asyncio.create_task(self._watch(), name=f"room {self.name} watchdog")
        try:
            while True:
                try:
                    msg = await _unpack(reader)
                except (asyncio.IncompleteReadError, ConnectionError):
                    break
                self._heard = loop.time()
                self._on(msg, events)
        finally:
            watchdog.cancel()
            self._went(events)
        return await self._reap()

    async def _watch(self) -> None:
        """Kill the process once it has started and has been silent, or its next tick overdue,
        for :attr:`hang_s` [s]: its stream then ends and it is started again as a dead one.

        A round in which the front itself woke late (its own loop was held up) judges nothing:
        what the process sent meanwhile may still be unread.
        """
        loop = asyncio.get_running_loop()
        period = min(REPORT_S, self.hang_s / 4.0)
        last = loop.time()
        while True:
            await asyncio.sleep(period)
            now = loop.time()
            held_up = now - last > 2.0 * period
            last = now
            if held_up or self.closing or not self.running:
                continue
            silent, overdue = now - self._heard, now - self._due
            if max(silent, overdue) <= self.hang_s:
                continue
            self.hangs += 1
            log.error(
                "room %r: its process %s is hung (no message for %.1f s, its tick overdue by "
                "%.1f s): killed, to start again",
                self.name,
                self.pid,
                silent,
                max(0.0, overdue),
            )
            self.kill()
            return

    def _went(self, events: RoomEvents) -> None:
        """The process's stream ended: forget its connections, keep its counters."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self.ready is not None and not self.ready.done():
            self.ready.set_exception(RuntimeError(f"room {self.name!r} exited before it started"))
            self.ready.exception()  # retrieved: start() reads it, a restart may not
        if self._drained is not None and not self._drained.done():
            self._drained.set_result(None)
        self._conns.clear()
        self._names.clear()
        self.users, self.viewers, self.held_seats = [], [], []
        self._due = math.inf
        self.pid = None
        for key, last in self._last.items():  # counters go on from here after a restart
            counts, total = self._base.get(key, ([0] * len(last[0]), 0.0))
            self._base[key] = (
                [a + b for a, b in zip(counts, last[0], strict=True)],
                total + last[1],
            )
        self._last = {}
        self.stats.base_overruns = self.stats.overruns
        self._base_clamps = sum(self.clamp_counts.values())
        self._base_resumes = self.resumes
        self._base_ticks_run = self.ticks_run

    async def _reap(self) -> int | None:
        """Wait for the process to exit (killed after :data:`EXIT_TIMEOUT_S`)."""
        proc = self._process
        deadline = time.monotonic() + EXIT_TIMEOUT_S
        while proc.is_alive() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        if proc.is_alive():
            proc.kill()
            await asyncio.to_thread(proc.join, 1.0)
        code: int | None = proc.exitcode
        self._process = None
        with contextlib.suppress(ValueError):
            proc.close()
        return code

    def _on(self, msg: tuple[Any, ...], events: RoomEvents) -> None:
        kind = msg[0]
        if kind == "out":
            outs = []
            for conn_id, data, stream, close, close_code, ack in msg[1]:
                on_sent = (lambda n=ack, g=self._generation: self._ack(n, g)) if ack else None
                outs.append(Outgoing(conn_id, data, stream, close, close_code, on_sent))
            events.dispatch(outs)
        elif kind == "report":
            self._report(msg[1], events)
        elif kind == "named":
            self._names[msg[1]] = msg[2]
            events.named(msg[1], msg[2])
        elif kind == "stall":
            events.stall(msg[1], msg[2])
        elif kind == "job":
            self.gains.table.grid_ratio, self.gains.table.hand_box = msg[2], msg[3]
            self.gains.jobs.append(msg[1])
            events.job()
        elif kind == "ready":
            self.pid, self.object_info, self.tick_count = msg[1], msg[2], msg[3]
            self.start_s = asyncio.get_running_loop().time() - self._spawned
            if self.ready is not None and not self.ready.done():
                self.ready.set_result(None)
        elif kind == "failed":
            if self.ready is not None and not self.ready.done():
                self.ready.set_exception(RuntimeError(f"room {self.name!r}: {msg[1]}"))
                self.ready.exception()
        elif kind == "checkpoint":
            self._checkpoint = msg[1]
        elif kind == "seats":
            self._seats = (msg[1], msg[2])
        elif kind == "drained":
            if self._drained is not None and not self._drained.done():
                self._drained.set_result(msg[1])

    def _report(self, rep: dict[str, Any], events: RoomEvents) -> None:
        self.tick_count = rep["tick"]
        self.ticks_run = self._base_ticks_run + rep["ticks_run"]
        self._due = rep["due"]
        self.users, self.viewers = rep["users"], rep["viewers"]
        self.held_seats = [""] * rep["held"]
        self.resumes = self._base_resumes + rep["resumes"]
        self.stats.p50, self.stats.p99 = rep["p50"], rep["p99"]
        self.stats.overruns = self.stats.base_overruns + rep["overruns"]
        self.clamp_counts = {"": self._base_clamps + rep["clamps"]}
        for key in ("tick_s", "lateness_s"):
            self._last[key] = rep[key]
            counts, total = rep[key]
            base_counts, base_total = self._base.get(key, ([0] * len(counts), 0.0))
            buckets: Buckets = getattr(events.figures, key)
            buckets.counts = [a + b for a, b in zip(base_counts, counts, strict=True)]
            buckets.total = base_total + total

    async def drain(self, snapshot: bool) -> str | None:
        """Ask the process to stop ticking and (``snapshot``) save its room; returns the
        snapshot's path (None: none written, or the process is gone). It is not restarted."""
        self.closing = True
        if self._writer is None:
            return None
        self._drained = asyncio.get_running_loop().create_future()
        self._send("drain", snapshot)
        return await self._drained

    def kill(self) -> None:
        """Kill the process at once (its room is then started again, unless closing)."""
        if self._process is not None and self._process.exitcode is None:
            self._process.kill()

    async def close(self) -> None:
        """Stop the process for good (``stop``; killed after :data:`EXIT_TIMEOUT_S`)."""
        self.closing = True
        self._send("stop")
        if self._writer is not None:
            with contextlib.suppress(ConnectionError):
                await self._writer.drain()


class _Limits:
    def __init__(self, max_users: int) -> None:
        self.max_users = max_users
