"""The room: the server's sans-I/O core. Frames and times in, frames out; the tick number passed in.

Why one module: :class:`Room` is one state machine (connections, the simulation schedule, the
tick) whose methods share its per-connection records and tick state, so it does not split by
method; what stands alone has moved out (admission budgets to :mod:`server.admission`, the
object's description to :mod:`server.object_info`).

One room owns one :class:`server.world.World` (the global deformable object). Each connection is a
haptic *user* or a *viewer*. Per simulation tick (:meth:`Room.tick`):

1. every user's latest ``state`` (probe and the force its device last rendered) is handed to the
   world (Step 3 of section 6: the simulation uses the last force returned to the device);
2. the world steps the object and fits each user's local model on the *current* surface
   (Step 1), with K_o, B_o and the coupling-aware K_o_eff (DESIGN section 6);
3. each user gets its ``patch``; viewers get the surface (binary) and a ``room`` summary.

The asyncio layer (:mod:`server.app`) only moves frames and keeps one timer: it calls
:meth:`Room.connect`, :meth:`Room.admit` (budgets, on arrival) and :meth:`Room.handle` (when due;
:meth:`Room.receive` does both) and :meth:`Room.disconnect`, sleeps until :meth:`Room.get_timer`
and calls :meth:`Room.handle_timer`, and sends what they return (the pattern of aioquic's
``QuicConnection.get_timer``/``handle_timer``). The simulation schedule is the room's: which tick
is due when, which missed ticks are skipped, and when the server is behind it, which credits the
budgets (:meth:`Room.behind_schedule`).
Hostile input never reaches the world: a bad frame gets an ``error`` reply on that connection only
(and a close where the connection cannot go on); the object and every other user are unaffected.

Rejoin: a user whose connection closes without ``bye`` keeps its *seat* for
:data:`RESUME_HOLD_S`: its user id, name, force-bound history and its contact in the world,
which goes on seeing it as a released probe (zero force, as a silent user). A ``hello`` whose
``resume`` is the seat's resume token (one use, rotated at every welcome) takes it back
(:meth:`Room._resume_seat`); a token that matches nothing joins as a new user. A held seat counts
against ``max_users``.

Safety (DESIGN section 7b): with a :class:`server.security.TokenTable` every ``hello`` must carry
a valid token (``unauthorized`` otherwise); every reported force is bounded by what that user's
local model could render at the penetration the server computes (:mod:`server.force_bound`,
``force_clamped``); and each source address has its own pre-hello, frame-rate and byte budgets
besides each connection's, so one address cannot lock others out or saturate the room.
"""

from __future__ import annotations

import json
import logging
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from haptic_collab.server.admission import FloodControl, Refusal, RoomLimits
from haptic_collab.server.force_bound import BoundedForce, ForceBoundParams, bound_force
from haptic_collab.server.gains import GainAdvisor
from haptic_collab.server.object_info import object_info, order_sides_by_coupling
from haptic_collab.server.security import (
    TokenBucket,
    TokenTable,
    new_resume_token,
    resume_digest,
    resume_matches,
)
from haptic_collab.server.viewer_stream import ViewerStream
from haptic_collab.server.world import ContactInput
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.primitives import Plane, Sphere
from haptic_collab.shared.protocol import (
    MAX_PROBE_DISTANCE_M,
    MAX_REPORTED_FORCE_N,
    PROTOCOL_VERSION,
    Bye,
    DeviceInfo,
    ErrorMsg,
    Hello,
    LinkConditions,
    Ping,
    Pong,
    ProtocolError,
    RecommendedGains,
    RoomState,
    State,
    UserView,
    Welcome,
    check_complexity,
    client_stream_frame,
    encode,
    encode_faces,
    frame_size_bytes,
    parse_client,
)
from haptic_collab.shared.rates import PERIOD_RTOL, Rates

if TYPE_CHECKING:
    from haptic_collab.server.world import World

log = logging.getLogger("haptic.server")

#: How long [s] the seat of a user whose connection closed without ``bye`` is held for it to
#: come back with its resume token, from when the server sees the close. Long enough for a
#: client that notices a dead link within 2 s and retries with the backoff of
#: :class:`client.link.Link` (0.2 s doubling to 5 s, each try up to 5 s) to come back several
#: times over; short enough that a user who is really gone frees its place in ``max_users``
#: (and its released contact on the object) within half a minute.
RESUME_HOLD_S = 30.0


@dataclass(frozen=True)
class Outgoing:
    """A frame for one connection.

    ``stream`` names a latest-wins stream (a newer frame of the same stream replaces a queued
    older one); None marks an event, delivered in order. ``close`` asks the I/O layer to close the
    connection after sending (``data`` None: close without sending), with websocket close code
    ``close_code`` (1000 after ``bye``, 1008 after a fatal error). ``on_sent``, when set, must be
    called right after ``data`` is written to the socket (never for a dropped frame): the viewer
    stream counts on it to know what each viewer holds (:mod:`server.viewer_stream`).
    """

    conn_id: str
    data: str | bytes | None
    stream: str | None = None
    close: bool = False
    close_code: int = 1008
    on_sent: Callable[[], None] | None = field(default=None, compare=False, repr=False)


#: A SHA-256 digest (named apart: ``_Conn.bytes`` is a byte budget).
_Digest = bytes


@dataclass
class _Conn:
    conn_id: str
    connected_at_s: float
    address: str
    frames: TokenBucket
    bytes: TokenBucket
    hello: Hello | None = None
    user_id: str = ""
    state: State | None = None
    state_at_s: float = -math.inf
    errors: int = 0
    closed: bool = False
    output: SurfacePatch | None = None
    #: The seat: the world's and the gain advisor's key for this user, kept across a resume
    #: (the conn_id of the connection that first took it; :meth:`Room.connect` sets it).
    seat: str = ""
    #: SHA-256 of the seat's current resume token (users only; None before the welcome).
    resume_digest: _Digest | None = None
    #: The newest ``state.seq`` on this connection (a resumed seat's new connection may start
    #: its sequence again).
    last_seq: int = -1
    #: Until when [s] a seat whose connection dropped is held (inf while connected).
    held_until_s: float = math.inf
    #: (primitive, K_o, F_s) of the latest patches, newest last, each with its rest plane as
    #: (rest plane, K_o, 0) when it had one (the force bound's geometry).
    recent: deque[tuple[tuple[Plane | Sphere, float, float], ...]] = field(
        default_factory=lambda: deque(maxlen=3)
    )
    applied: BoundedForce | None = None
    applied_at_s: float = -math.inf
    clamps: int = 0
    clamp_reported_s: float = -math.inf


@dataclass(frozen=True)
class SeatRecord:
    """A user's seat as it crosses a restart of its room's process (:meth:`Room.seat_records`,
    :meth:`Room.hold_seats`): what a ``hello`` with the seat's resume token takes back.

    Only the token's SHA-256 digest is kept, never the token. The seat's contact and force
    history are not: they are the old process's, gone with it.

    Attributes
    ----------
    seat : str
        The seat's key (the world's and the gain advisor's).
    user_id : str
        The user id the seat's user was welcomed with.
    name : str
        Its name (the viewers' colour for the user is a hash of it).
    address : str
        The source address of its last connection (for logs).
    resume_digest : bytes
        SHA-256 of its current resume token.
    held_until_s : float
        Until when [s, monotonic] it is held after its connection dropped; inf while it was
        connected.
    """

    seat: str
    user_id: str
    name: str
    address: str
    resume_digest: bytes
    held_until_s: float


@dataclass
class TickStats:
    """Simulation tick costs the I/O layer measured (:meth:`Room.tick_cost`) and ticks skipped."""

    window: deque[float] = field(default_factory=lambda: deque(maxlen=512))
    overruns: int = 0
    last_ms: float = 0.0

    def record(self, cost_ms: float, overran: bool) -> None:
        """Record one tick's cost [ms] and whether it overran its period."""
        self.last_ms = cost_ms
        self.window.append(cost_ms)
        if overran:
            self.overruns += 1

    def percentile(self, q: float) -> float:
        """Percentile ``q`` in [0, 100] of recent tick costs [ms] (0 when none)."""
        return float(np.percentile(np.fromiter(self.window, float), q)) if self.window else 0.0


class Room:
    """Sans-I/O room around one world. Not thread-safe: call it from one event loop.

    Parameters
    ----------
    world : World
        The simulation core (object + contacts).
    rates : shared.rates.Rates, float or None
        The rates the server runs at (:func:`server.main.build_rates`): the room ticks and
        announces ``rates.sim_rate_hz`` [Hz]. A bare float is the simulation rate 1/(N*T) [Hz]
        alone (older callers and tests). None: the world's ``rates``. Either way the world's
        object must step with the same period ``world.sim_period_s``.
    link : LinkConditions
        Injected latency, announced to clients and viewers.
    limits : RoomLimits
        Abuse limits.
    auth : TokenTable, optional
        Tokens the room accepts in ``hello``; None admits everyone (a loopback server).
    force_bound : ForceBoundParams, optional
        Tolerances of the bound on reported forces (:mod:`server.force_bound`).
    resume_hold_s : float
        How long [s] the seat of a user whose connection closed without ``bye`` is held for
        it to resume (default :data:`RESUME_HOLD_S`; 0: never held).

    Raises
    ------
    ValueError
        No rates given nor known to the world, a simulation rate that is not a finite number
        > 0, or one that disagrees with the period the world's object steps with.
    """

    def __init__(
        self,
        world: World,
        rates: Rates | float | None = None,
        link: LinkConditions | None = None,
        limits: RoomLimits | None = None,
        auth: TokenTable | None = None,
        force_bound: ForceBoundParams | None = None,
        resume_hold_s: float = RESUME_HOLD_S,
    ) -> None:
        self.world = world
        hold = float(resume_hold_s)
        if not (math.isfinite(hold) and hold >= 0.0):
            raise ValueError(f"resume_hold_s must be finite and >= 0 s, got {resume_hold_s!r}")
        #: How long [s] a dropped user's seat is held (:data:`RESUME_HOLD_S`).
        self.resume_hold_s = hold
        if rates is None:
            rates = world.rates
            if rates is None:
                raise ValueError(
                    "the room needs its rates: give Rates, or build the world with them"
                )
        #: The server's rates (None when the room was given a bare simulation rate).
        self.rates: Rates | None = rates if isinstance(rates, Rates) else None
        self.sim_rate_hz = _check_sim_rate(world, rates)
        self.link = link or LinkConditions()
        self.limits = limits or RoomLimits()
        self.auth = auth
        self.force_bound = force_bound or ForceBoundParams()
        #: Connection and address budgets (:mod:`server.admission`).
        self.flood = FloodControl(self.limits, 1.0 / self.sim_rate_hz)
        #: Clamped force reports per user name since the room started.
        self.clamp_counts: dict[str, int] = {}
        self.stats = TickStats()
        self.object_info = order_sides_by_coupling(
            object_info(world.vertices, world.faces), getattr(world, "obj", None)
        )
        self._faces_frame = encode_faces(world.faces)
        self._viewer_stream = ViewerStream.of_world(world, self.sim_rate_hz)
        #: Recommended gains for every patch (server.gains; designs run by the I/O layer).
        self.gains = GainAdvisor(self.sim_rate_hz)
        self._conns: dict[str, _Conn] = {}
        #: Seats of users whose connection dropped, by seat, until they resume or expire.
        self._held: dict[str, _Conn] = {}
        #: Seats given back (:meth:`_resume_seat`) and resume tokens that matched none.
        self.resumes = 0
        self.resume_misses = 0
        #: The latest time [s] the room was told (a :meth:`disconnect` without one uses it).
        self._now_s = -math.inf
        self._next_user = 1
        #: The number of the last simulation tick run (0 before the first); ticks skipped
        #: behind schedule (:meth:`handle_timer`) are numbered too, so it runs ahead of
        #: :attr:`ticks_run` on a late loop.
        self.tick_count = 0
        #: Simulation ticks this room object ran (:meth:`handle_timer`), skipped ones not counted.
        self.ticks_run = 0
        #: The schedule (:meth:`start`): tick k is due at ``_t0_s + k / sim_rate_hz`` [s].
        self._t0_s = math.inf
        #: A tick ran whose cost the I/O layer has not reported yet (:meth:`tick_cost`).
        self._cost_due = False

    # ------------------------------------------------------------------ schedule
    def start(self, now_s: float) -> None:
        """Start the simulation schedule at ``now_s`` [s]: tick k is due at ``now_s + k * N * T``.

        Tick numbers go on from the last tick run, so a restarted schedule never reuses one.
        """
        self._t0_s = float(now_s) - self.tick_count / self.sim_rate_hz

    def restored(self, tick: int) -> None:
        """The world's object was given a saved state (:func:`server.snapshots.restore`) whose
        last tick was ``tick``: the world takes its surface, and the tick numbers go on from
        there. Call it before :meth:`start`, with no connection.

        Raises
        ------
        ValueError
            ``tick`` negative.
        """
        self.world.restore(tick)
        self.tick_count = int(tick)

    def stop(self) -> None:
        """End the schedule: no tick is due any more, and the server is behind nothing."""
        self._t0_s = math.inf

    def get_timer(self) -> float:
        """When [s] the I/O layer must next call :meth:`handle_timer` (inf when not started).

        The due time of the next simulation tick, on the drift-free schedule :meth:`start` set.
        """
        return self._t0_s + (self.tick_count + 1) / self.sim_rate_hz

    def handle_timer(self, now_s: float) -> list[Outgoing]:
        """Run what is due at ``now_s`` [s]: the next simulation tick (:meth:`tick`).

        Returns the frames to send, [] when nothing is due yet. A late tick runs once: whole
        periods missed are skipped (never piled up) and counted in ``stats.overruns``, and the
        lateness is credited to the budgets (:meth:`behind_schedule`). The tick's number is
        taken before it runs, so a tick that raises is not run again.
        """
        due_s = self.get_timer()
        if not now_s >= due_s:
            return []
        period = 1.0 / self.sim_rate_hz
        if now_s > due_s:
            self.behind_schedule(due_s, now_s)
        behind = int((now_s - due_s) // period)
        if behind > 0:  # missed whole ticks: skip them
            self.stats.overruns += behind
        k = self.tick_count + 1 + behind
        self.tick_count = k
        self.ticks_run += 1
        self._cost_due = True
        return self.tick(k, now_s)

    def tick_cost(self, cost_s: float) -> None:
        """The I/O layer's measure of the last tick's cost [s] (wall time around :meth:`handle_timer`).

        Recorded once per tick run (a call after a :meth:`handle_timer` that ran nothing is
        ignored); a tick that took longer than its period counts as an overrun.
        """
        if not self._cost_due:
            return
        self._cost_due = False
        self.stats.record(cost_s * 1000.0, overran=cost_s > 1.0 / self.sim_rate_hz)

    def describe(self, conn_id: str) -> str | None:
        """``ROLE 'NAME' (USER_ID)`` of a welcomed connection, for logs; None before its hello."""
        conn = self._conns.get(conn_id)
        if conn is None or conn.hello is None:
            return None
        return f"{conn.hello.role} {conn.hello.name!r} ({conn.user_id})"

    # ------------------------------------------------------------------ connections
    @property
    def users(self) -> list[str]:
        """Connection ids of the haptic users."""
        return [c.conn_id for c in self._conns.values() if c.hello and c.hello.role == "user"]

    @property
    def viewers(self) -> list[str]:
        """Connection ids of the viewers."""
        return [c.conn_id for c in self._conns.values() if c.hello and c.hello.role == "viewer"]

    @property
    def held_seats(self) -> list[str]:
        """User ids of the seats held for users whose connection dropped (they count against
        ``max_users`` until they resume or :attr:`resume_hold_s` has passed)."""
        return [c.user_id for c in self._held.values()]

    def seat_records(self) -> tuple[list[SeatRecord], int]:
        """Every user seat that a resume token can take back (connected or held), and the
        number the next new user's id takes: what a room process restarted from scratch needs
        to give its users their seats back (:meth:`hold_seats`)."""
        out = []
        for conn in (*self._conns.values(), *self._held.values()):
            hello, digest = conn.hello, conn.resume_digest
            if hello is None or hello.role != "user" or digest is None:
                continue
            out.append(
                SeatRecord(
                    conn.seat, conn.user_id, hello.name, conn.address, digest, conn.held_until_s
                )
            )
        return out, self._next_user

    def hold_seats(self, seats: list[SeatRecord], next_user: int, now_s: float) -> None:
        """Hold ``seats`` (:meth:`seat_records` of the room's previous process) as seats whose
        connection dropped at ``now_s`` [s]: a ``hello`` with a seat's resume token within
        :attr:`resume_hold_s` gets its user id and name back (a seat already held keeps its
        own deadline), and new users' ids go on from ``next_user``.

        Why: when a room's process dies and is started again, its users' links all drop at
        once; they rejoin as they would after a link of their own dropped.
        """
        self._next_user = max(self._next_user, int(next_user))
        if self.resume_hold_s <= 0.0:
            return
        lim = self.limits
        for rec in seats:
            until = min(rec.held_until_s, now_s + self.resume_hold_s)
            if until <= now_s or rec.seat in self._held or rec.seat in self._conns:
                continue
            hello = Hello(protocol=PROTOCOL_VERSION, role="user", name=rec.name)
            self._held[rec.seat] = _Conn(
                rec.seat,
                now_s,
                rec.address,
                TokenBucket(lim.rate_per_s, lim.burst, now_s),
                TokenBucket(lim.bytes_per_s, lim.bytes_burst, now_s),
                hello=hello,
                user_id=rec.user_id,
                seat=rec.seat,
                resume_digest=rec.resume_digest,
                held_until_s=until,
                recent=deque(maxlen=max(1, self.force_bound.history_patches)),
            )
        if seats:
            log.info("%d seat(s) held from the room's previous process", len(self._held))

    def connect(self, conn_id: str, now_s: float, address: str = "local") -> list[Outgoing]:
        """Register a new connection from source ``address`` at ``now_s`` [s].

        It must send ``hello`` first. Refused (a fatal error for ``conn_id``) when the room holds
        ``max_connections``, when ``address`` holds ``max_connections_per_address`` or
        ``max_pending_per_address`` connections, or when ``max_pending`` connections wait in
        total and no address holds more of them than ``address`` does; otherwise, with the
        pending total full, the oldest pending connection of the address holding the most is
        closed to make room (the returned frames include its error); see
        :meth:`server.admission.FloodControl.connect`.
        """
        verdict = self.flood.connect(self._conns.values(), address)
        if isinstance(verdict, Refusal):
            return [self._error(conn_id, verdict.code, verdict.message, fatal=True)]
        out: list[Outgoing] = []
        if verdict is not None:
            out += self._close(verdict, "too_many_pending", "evicted: too many waiting for hello")
        self._now_s = max(self._now_s, now_s)
        frames, nbytes = self.flood.open(address, now_s)
        self._conns[conn_id] = _Conn(
            conn_id,
            now_s,
            address,
            frames,
            nbytes,
            seat=conn_id,
            recent=deque(maxlen=max(1, self.force_bound.history_patches)),
        )
        return out

    def disconnect(self, conn_id: str, now_s: float | None = None, hold: bool = True) -> None:
        """Forget a connection that closed at ``now_s`` [s] (default: the latest time the room
        was told).

        A welcomed user's seat is held for :attr:`resume_hold_s` when ``hold`` (the connection
        dropped without ``bye``): from the next tick its force is zero (the object sees a
        released probe, as for a silent user) while its contact stays in the world, and a
        ``hello`` with its resume token takes it back (:meth:`_resume_seat`). Otherwise (and
        for viewers) the user's load and contact leave the object from the next tick on.
        ``hold`` False: the server closed it on purpose (drain, the router's rate limit).
        """
        conn = self._conns.pop(conn_id, None)
        if conn is None:
            return
        at = self._now_s if now_s is None else float(now_s)
        self._now_s = max(self._now_s, at)
        if (
            hold
            and self.resume_hold_s > 0.0
            and conn.hello is not None
            and conn.hello.role == "user"
            and conn.resume_digest is not None
        ):
            self._release(conn)
            conn.held_until_s = at + self.resume_hold_s
            self._held[conn.seat] = conn
            log.info(
                "user %r (%s): connection dropped; seat held for %g s",
                conn.hello.name,
                conn.user_id,
                self.resume_hold_s,
            )
            return
        self.gains.forget(conn.seat)

    @staticmethod
    def _release(conn: _Conn) -> None:
        """The seat's user is gone: from now on its hand loads the object with nothing (its
        last probe stays, so its contact stays on the object, released)."""
        if conn.state is not None:
            conn.state = conn.state.model_copy(
                update={"force_n": (0.0, 0.0, 0.0), "k_h": 0.0, "i_gain": 0.0, "own_gain": 0.0}
            )
        conn.applied = BoundedForce((0.0, 0.0, 0.0), 0.0)

    def _expire_held(self, now_s: float) -> None:
        """Drop the held seats whose hold has run out at ``now_s`` [s]."""
        for seat, conn in list(self._held.items()):
            if now_s >= conn.held_until_s:
                del self._held[seat]
                self.gains.forget(seat)
                name = conn.hello.name if conn.hello is not None else "?"
                log.info("user %r (%s): seat released, not resumed in time", name, conn.user_id)

    def force_clamps(self) -> dict[str, int]:
        """Clamped force reports per user name (connected or not) since the room started."""
        return dict(self.clamp_counts)

    def _error(self, conn_id: str, code: str, message: str, fatal: bool = False) -> Outgoing:
        return Outgoing(
            conn_id, encode(ErrorMsg(code=code, message=message, fatal=fatal)), close=fatal
        )

    def receive(self, conn_id: str, frame: str | bytes, now_s: float) -> list[Outgoing]:
        """Handle one incoming frame at time ``now_s`` [s]; return the frames to send.

        :meth:`admit` and then :meth:`handle` at the same time. Never raises on bad input:
        replies ``error`` (closing where the connection cannot go on).
        """
        admitted, out = self.admit(conn_id, frame, now_s)
        if not admitted:
            return out
        return out + self.handle(conn_id, frame, now_s)

    def admit(self, conn_id: str, frame: str | bytes, now_s: float) -> tuple[bool, list[Outgoing]]:
        """Charge one frame that arrived at ``now_s`` [s] to the budgets; nothing else.

        A frame read while the server is behind its schedule may be a backlog from a stall: the
        budgets are credited for it first (:meth:`behind_schedule`).

        Flood control (:mod:`server.admission`): token buckets per connection (frames, bytes),
        then per source address, and the frame size limit. The I/O layer calls it when a frame
        arrives, before latency injection holds the frame back, and hands admitted frames to
        :meth:`handle` when they are due. Returns whether the frame is admitted and the frames to
        send (a fatal ``rate_limited`` or ``frame_too_large`` for this connection, or for the
        busiest one of its address, which may be another).
        """
        conn = self._conns.get(conn_id)
        if conn is None or conn.closed:
            return False, []
        due_s = self.get_timer()
        if now_s > due_s:  # behind schedule: this may be a backlog from a stall
            self.behind_schedule(due_s, now_s)
        size = frame_size_bytes(frame)
        refusal = self.flood.charge(conn, size, now_s)
        if refusal is not None:
            return False, self._close(conn, refusal.code, refusal.message)
        heavy = self.flood.charge_address(conn, self._conns.values(), size, now_s)
        out: list[Outgoing] = []
        if heavy is not None:
            out = self._close(
                heavy,
                "rate_limited",
                "this address sends too much; its busiest connection is closed",
            )
        return not conn.closed, out

    @staticmethod
    def droppable(frame: str | bytes) -> bool:
        """Whether latency injection's loss may drop this incoming frame.

        Stream messages (``state``, ``ping``: each supersedes the last) may be lost; events
        (``hello``, ``bye``) and anything the room would refuse are always delivered
        (:func:`shared.protocol.client_stream_frame`).
        """
        return client_stream_frame(frame)

    def handle(self, conn_id: str, frame: str | bytes, now_s: float) -> list[Outgoing]:
        """Handle a frame :meth:`admit` admitted, at its delivery time ``now_s`` [s].

        Returns the frames to send; nothing once the connection is gone. Never raises on bad
        input: replies ``error`` (closing where the connection cannot go on).
        """
        conn = self._conns.get(conn_id)
        if conn is None or conn.closed:
            return []
        return self._handle(conn, frame, now_s)

    def behind_schedule(self, due_s: float, now_s: float) -> None:
        """The simulation tick due at ``due_s`` [s] has not run by ``now_s`` [s]: credit every
        budget for the stall, so a backlog read at once is charged as if read on time
        (:meth:`server.admission.FloodControl.credit_stall` says why and how far)."""
        self.flood.credit_stall(self._conns.values(), due_s, now_s)

    def _handle(self, conn: _Conn, frame: str | bytes, now_s: float) -> list[Outgoing]:
        conn_id = conn.conn_id
        try:
            msg = parse_client(frame)
        except ProtocolError as exc:
            if conn.hello is None:  # before hello nothing is kept: a refused frame closes
                return self._close(conn, exc.code, str(exc))
            return self._soft_error(conn, exc.code, str(exc))
        if conn.hello is None:
            if not isinstance(msg, Hello):
                return self._close(conn, "expected_hello", "the first message must be hello")
            return self._hello(conn, msg, now_s)
        if isinstance(msg, Hello):
            return self._soft_error(conn, "duplicate_hello", "hello was already received")
        if isinstance(msg, Ping):
            return [
                Outgoing(
                    conn_id,
                    encode(Pong(id=msg.id, t_client_s=msg.t_client_s, tick=self.tick_count)),
                    stream="pong",
                )
            ]
        if isinstance(msg, Bye):  # leaving on purpose: the seat goes at once, nothing is held
            self._drop(conn)
            return [Outgoing(conn_id, None, close=True, close_code=1000)]
        if isinstance(msg, State):
            if conn.hello.role != "user":
                return self._soft_error(conn, "not_a_user", "viewers do not send state")
            return self._state(conn, msg, now_s)
        return []  # pragma: no cover - the union is exhausted above

    def _close(self, conn: _Conn, code: str, message: str) -> list[Outgoing]:
        self._drop(conn)
        return [self._error(conn.conn_id, code, message, fatal=True)]

    def _drop(self, conn: _Conn) -> None:
        """The room closes ``conn`` (or it said ``bye``): forgotten, its seat not held."""
        conn.closed = True
        self._conns.pop(conn.conn_id, None)
        self.gains.forget(conn.seat)

    def _soft_error(self, conn: _Conn, code: str, message: str) -> list[Outgoing]:
        conn.errors += 1
        if conn.errors > self.limits.max_errors:
            return self._close(
                conn,
                "too_many_errors",
                f"closed after {self.limits.max_errors} bad messages; last: {message}",
            )
        return [self._error(conn.conn_id, code, message)]

    def _hello(self, conn: _Conn, msg: Hello, now_s: float) -> list[Outgoing]:
        if msg.protocol != PROTOCOL_VERSION:
            return self._close(
                conn,
                "protocol_version",
                f"server speaks protocol {PROTOCOL_VERSION}, client sent {msg.protocol}",
            )
        bound: str | None = None
        if self.auth is not None:
            entry = self.auth.check(msg.token)
            if entry is None:
                what = "a token is required" if msg.token is None else "the token is not valid"
                return self._close(conn, "unauthorized", f"{what} (hello.token)")
            if msg.role == "user" and entry.role != "user":
                return self._close(conn, "unauthorized", "this token may only watch (viewer)")
            bound = entry.name
        out: list[Outgoing] = []
        seat: _Conn | None = None
        if msg.role == "user" and msg.resume is not None:
            seat, out = self._resume_seat(conn, msg.resume, bound, now_s)
        if seat is None:
            if msg.role == "user" and len(self.users) + len(self._held) >= self.limits.max_users:
                return self._close(
                    conn, "room_full", f"the room holds {self.limits.max_users} users"
                )
            if msg.role == "viewer" and len(self.viewers) >= self.limits.max_viewers:
                return self._close(
                    conn, "room_full", f"the room holds {self.limits.max_viewers} viewers"
                )
            # names bound to tokens belong to their token, connected or not; a held seat's
            # name is its user's until the hold runs out
            taken = {c.hello.name for c in (*self._conns.values(), *self._held.values()) if c.hello}
            if self.auth is not None:
                taken |= self.auth.bound_names - {bound}
            base = bound if bound is not None else msg.name
            name, k = base, 2
            while name in taken:
                name, k = f"{base}-{k}", k + 1
            conn.user_id = f"u{self._next_user}"
            self._next_user += 1
        else:
            assert seat.hello is not None
            name = seat.hello.name
        # forget the access token and the resume token
        conn.hello = msg.model_copy(update={"name": name, "token": None, "resume": None})
        token: str | None = None
        if msg.role == "user":
            token, conn.resume_digest = new_resume_token()
        welcome = Welcome(
            user_id=conn.user_id,
            name=name,
            role=msg.role,
            sim_rate_hz=self.sim_rate_hz,
            object=self.object_info,
            link=self.link,
            resume_token=token,
            resumed=seat is not None,
        )
        out.append(Outgoing(conn.conn_id, encode(welcome)))
        if msg.role == "viewer":
            out.append(Outgoing(conn.conn_id, self._faces_frame))
            # keyframe (rest VTX1, NRM1, dense DSP1) as events: never dropped
            keyframe = self._viewer_stream.join(conn.conn_id, self.tick_count, self.world.vertices)
            out += [Outgoing(conn.conn_id, f) for f in keyframe]
        return out

    def _resume_seat(
        self, conn: _Conn, token: str, bound: str | None, now_s: float
    ) -> tuple[_Conn | None, list[Outgoing]]:
        """Give ``conn`` the seat whose resume token is ``token``, if one in this room has it.

        The seat is a held one (its connection dropped less than :attr:`resume_hold_s` ago) or
        one still connected: a link that died without the server seeing a close (a network
        cut) is replaced, its connection closed with ``seat_resumed``. The token is compared by
        its SHA-256 digest with :func:`hmac.compare_digest` against every seat of this room
        (the tokens are the room's: another room's never match) and is used up: the welcome
        carries a new one. With an access token bound to a name, only that name's seat can be
        taken. ``conn`` takes the seat's key, user id, last state (its force zero), patches and
        force-bound history, so the world goes on with the same contact.

        Returns the seat (None: no seat has the token; a log line, and the caller joins ``conn``
        as a new user) and the frames to send (the replaced connection's close).
        """
        self._expire_held(now_s)
        digest = resume_digest(token)
        found: _Conn | None = None
        for cand in (*self._held.values(), *self._conns.values()):
            # every candidate is compared (no early exit): the time taken says nothing
            if cand is not conn and resume_matches(digest, cand.resume_digest):
                found = cand
        if found is not None and found.hello is not None and bound not in (None, found.hello.name):
            found = None  # a token bound to another name cannot take this seat
        if found is None or found.hello is None:
            self.resume_misses += 1
            log.info(
                "hello from %r: its resume token matches no seat of this room (wrong, used, "
                "expired or another room's); joining it as a new user",
                conn.address,
            )
            return None, []
        out: list[Outgoing] = []
        if found.conn_id in self._conns:  # its old connection is still open: replace it
            found.closed = True  # (not _close: the seat's gain advice goes on)
            self._conns.pop(found.conn_id, None)
            msg = "this user's seat was resumed by a new connection"
            out = [self._error(found.conn_id, "seat_resumed", msg, fatal=True)]
            self._release(found)
        else:
            del self._held[found.seat]
        found.resume_digest = None  # used up
        conn.seat = found.seat
        conn.user_id = found.user_id
        conn.state, conn.state_at_s = found.state, found.state_at_s
        conn.output, conn.recent = found.output, found.recent
        conn.applied, conn.applied_at_s = found.applied, found.applied_at_s
        conn.clamps, conn.clamp_reported_s = found.clamps, found.clamp_reported_s
        self.resumes += 1
        log.info("user %r (%s): seat resumed", found.hello.name, found.user_id)
        return found, out

    def _state(self, conn: _Conn, msg: State, now_s: float) -> list[Outgoing]:
        force = math.sqrt(sum(c * c for c in msg.force_n))
        limit = MAX_REPORTED_FORCE_N
        device = conn.hello.device if conn.hello else None
        if device is not None:
            limit = min(limit, 1.5 * device.max_force_n)
        if force > limit:
            return self._soft_error(
                conn, "force_limit", f"reported force {force:.3g} N exceeds the limit {limit:.3g} N"
            )
        if math.sqrt(sum(c * c for c in msg.probe_m)) > MAX_PROBE_DISTANCE_M:
            return self._soft_error(
                conn,
                "probe_out_of_range",
                f"probe farther than {MAX_PROBE_DISTANCE_M} m from the origin",
            )
        if msg.seq <= conn.last_seq:
            return []  # older than what we have: latest wins
        conn.last_seq = msg.seq
        conn.state = msg
        self.gains.observe_rtt(conn.seat, msg.rtt_ms, msg.delay_rtt_ms)
        conn.state_at_s = now_s
        return []

    # ------------------------------------------------------------------ simulation tick
    def tick(self, tick: int, now_s: float) -> list[Outgoing]:
        """Advance the world one simulation period (tick number ``tick``) at time ``now_s`` [s].

        Returns the patches for users and the surface and summary for viewers.
        """
        self.tick_count = tick
        self._now_s = max(self._now_s, now_s)
        self._expire_held(now_s)
        out: list[Outgoing] = []
        for c in list(self._conns.values()):
            if c.hello is None and now_s - c.connected_at_s > self.limits.hello_timeout_s:
                out += self._close(
                    c, "hello_timeout", f"no hello within {self.limits.hello_timeout_s:g} s"
                )
        self.flood.forget_idle(self._conns.values(), now_s)
        inputs: dict[str, ContactInput] = {}
        seats: dict[str, _Conn] = {}
        for c in self._conns.values():
            if c.state is None or c.hello is None or c.hello.role != "user":
                continue
            force = self._bounded_force(c, now_s, out)
            inputs[c.seat] = ContactInput(probe=np.array(c.state.probe_m), force=np.array(force))
            seats[c.seat] = c
        for c in self._held.values():  # a dropped user's contact stays, released
            if c.state is not None:
                c.applied, c.applied_at_s = BoundedForce((0.0, 0.0, 0.0), 0.0), now_s
                inputs[c.seat] = ContactInput(probe=np.array(c.state.probe_m), force=np.zeros(3))
                seats[c.seat] = c
        outputs = self.world.tick(inputs, tick)
        recs: dict[str, RecommendedGains | None] = {}
        for seat, res in outputs.items():
            conn = seats.get(seat)
            if conn is None:
                continue
            conn.output = res
            k_o = float(res.k_o)
            sent = (res.primitive, k_o, float(res.own_force_n))
            rest = res.rest_plane
            conn.recent.append((sent,) if rest is None else (sent, (rest, k_o, 0.0)))
            if conn.closed or conn.conn_id not in self._conns:
                continue  # a held seat: its patch has nobody to go to
            if conn.hello is not None:
                recs[seat] = self.gains.recommend(
                    seat,
                    conn.hello,
                    k_o_eff=float(res.k_o_eff),
                    k_o_stiff=float(res.k_o_stiff),
                    b_o=float(res.b_o),
                    tick=tick,
                    in_contact=bool(res.in_contact or res.own_force_n > 0.0),
                )
        # a resting user keeps its gains where its coupled pair, as rendered, is verified
        recs = self.gains.hold_pairs(self.world.coupling, outputs, recs)
        # and a FEM contact's checked on the solid's own modes
        recs = self.gains.guard_modes(recs, self.world.modal_contact, self.world.contact_modes)
        for seat, res in outputs.items():
            conn = seats.get(seat)
            if conn is None or conn.closed or conn.conn_id not in self._conns:
                continue
            rec = recs.get(seat)
            out.append(Outgoing(conn.conn_id, encode(res.to_wire(rec)), stream="patch"))
        viewers = self.viewers
        vframes = self._viewer_stream.frames(tick, self.world.vertices, viewers)
        if viewers:
            summary = encode(self.room_state(tick))
            for v in viewers:
                vf = vframes[v]
                out.append(Outgoing(v, vf.data, stream="vertices", on_sent=vf.sent))
                out.append(Outgoing(v, summary, stream="room"))
        return out

    def _bounded_force(
        self, c: _Conn, now_s: float, out: list[Outgoing]
    ) -> tuple[float, float, float]:
        """The force [N] user ``c`` loads the object with this tick (appends a clamp report)."""
        assert c.state is not None and c.hello is not None
        if now_s - c.state_at_s > self.limits.stale_after_s:
            # silent user: its hand no longer loads the object
            c.applied = BoundedForce((0.0, 0.0, 0.0), 0.0)
            c.applied_at_s = now_s
            return c.applied.force_n
        s = c.state
        device = c.hello.device or DeviceInfo()
        prev = c.applied
        res = bound_force(
            s.force_n,
            s.probe_m,
            tuple(contact for patch in c.recent for contact in patch),
            k_h=s.k_h,
            i_gain=s.i_gain,
            own_gain=s.own_gain,
            integral_limit_n=min(device.max_force_n, MAX_REPORTED_FORCE_N),
            integral_bound_n=prev.integral_bound_n if prev is not None else 0.0,
            dt_s=now_s - c.applied_at_s,
            params=self.force_bound,
        )
        c.applied, c.applied_at_s = res, now_s
        if res.reason is not None:
            c.clamps += 1
            name = c.hello.name
            self.clamp_counts[name] = self.clamp_counts.get(name, 0) + 1
            if now_s - c.clamp_reported_s >= self.limits.clamp_report_interval_s:
                c.clamp_reported_s = now_s
                msg = (
                    f"reported force clamped ({res.reason.replace('_', ' ')}): "
                    f"{res.excess_n:.3g} N over what your local model can render here "
                    f"(<= {res.limit_n:.3g} N along the surface normal); {c.clamps} clamps so far"
                )
                out.append(self._error(c.conn_id, "force_clamped", msg))
        return res.force_n

    def room_state(self, tick: int) -> RoomState:
        """The summary viewers get each tick."""
        users = []
        for c in (*self._conns.values(), *self._held.values()):
            if c.hello is None or c.hello.role != "user" or c.state is None:
                continue
            s, res = c.state, c.output
            users.append(
                UserView(
                    user_id=c.user_id,
                    name=c.hello.name,
                    probe_m=s.probe_m,
                    proxy_m=res.proxy if res is not None else s.probe_m,
                    normal=res.normal if res is not None else (0.0, 0.0, 1.0),
                    # the force the server applied (bounded; zero for a silent user)
                    force_n=c.applied.force_n if c.applied is not None else s.force_n,
                    penetration_m=s.penetration_m,
                    in_contact=s.in_contact,
                    k_o=float(res.k_o) if res is not None else 0.0,
                    k_o_eff=float(res.k_o_eff) if res is not None else 0.0,
                    k_h=s.k_h,
                    i_gain=s.i_gain,
                    servo_rate_hz=s.servo_rate_hz,
                    rtt_ms=s.rtt_ms,
                    device=(c.hello.device or DeviceInfo()).profile,
                )
            )
        return RoomState(
            tick=tick,
            sim_rate_hz=self.sim_rate_hz,
            tick_ms=self.stats.last_ms,
            tick_ms_p99=self.stats.percentile(99),
            overruns=self.stats.overruns,
            link=self.link,
            users=users,
        )


def is_bye(frame: str | bytes) -> bool:
    """Whether a client frame is ``bye`` (a cheap look: frames without the word are not parsed).

    The I/O layer reads it on arrival, before latency injection holds the frame back, so that
    a socket closed right after its ``bye`` does not have its seat held
    (:meth:`Room.disconnect`).
    """
    if not isinstance(frame, str) or '"bye"' not in frame:
        return False
    try:
        check_complexity(frame)
        msg = json.loads(frame)
    except (ValueError, ProtocolError, RecursionError):
        return False
    return isinstance(msg, dict) and msg.get("type") == "bye"


def _check_sim_rate(world: World, rates: Rates | float) -> float:
    """The room's simulation rate [Hz], checked against the period the world steps with."""
    if isinstance(rates, Rates):
        rates.check_sim_period(world.sim_period_s, "the world")
        return rates.sim_rate_hz
    rate = float(rates)
    if not (math.isfinite(rate) and rate > 0.0):
        raise ValueError(f"the simulation rate must be a finite number > 0 Hz, got {rates!r}")
    period = float(world.sim_period_s)
    if abs(period * rate - 1.0) > PERIOD_RTOL:
        raise ValueError(
            f"the world steps every {period * 1e3:g} ms ({1.0 / period:g} Hz) but the room was "
            f"given {rate:g} Hz: build both from one Rates"
        )
    return rate
