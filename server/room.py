"""The room: the server's sans-I/O core. Frames and times in, frames out; the tick number passed in.

One room owns one :class:`server.world.World` (the global deformable object). Each connection is a
haptic *user* or a *viewer*. Per simulation tick (:meth:`Room.tick`):

1. every user's latest ``state`` (probe and the force its device last rendered) is handed to the
   world (Step 3 of section 6: the simulation uses the last force returned to the device);
2. the world steps the object and fits each user's local model on the *current* surface
   (Step 1), with K_o, B_o and the coupling-aware K_o_eff (DESIGN section 6);
3. each user gets its ``patch``; viewers get the surface (binary) and a ``room`` summary.

The asyncio layer (:mod:`server.app`) only moves frames: it calls :meth:`Room.connect`,
:meth:`Room.receive`, :meth:`Room.disconnect` and :meth:`Room.tick` and sends what they return.
Hostile input never reaches the world: a bad frame gets an ``error`` reply on that connection only
(and a close where the connection cannot go on); the object and every other user are unaffected.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from server.world import ContactInput
from shared.protocol import (
    MAX_CLIENT_FRAME_BYTES,
    MAX_PROBE_DISTANCE_M,
    MAX_REPORTED_FORCE_N,
    PROTOCOL_VERSION,
    Bye,
    DeviceInfo,
    ErrorMsg,
    Hello,
    LinkConditions,
    ObjectInfo,
    Patch,
    Ping,
    PlaneModel,
    Pong,
    ProtocolError,
    RoomState,
    SphereModel,
    State,
    UserView,
    Welcome,
    encode,
    encode_faces,
    encode_vertices,
    parse_client,
)

if TYPE_CHECKING:
    from server.world import ContactOutput, World


@dataclass(frozen=True)
class Outgoing:
    """A frame for one connection.

    ``stream`` names a latest-wins stream (a newer frame of the same stream replaces a queued
    older one); None marks an event, delivered in order. ``close`` asks the I/O layer to close the
    connection after sending.
    """

    conn_id: str
    data: str | bytes
    stream: str | None = None
    close: bool = False


@dataclass(frozen=True)
class RoomLimits:
    """Abuse limits per connection.

    Attributes
    ----------
    max_users : int
        Haptic users in the room at once.
    max_viewers : int
        Viewers at once.
    max_pending : int
        Connections that have not sent ``hello`` yet.
    hello_timeout_s : float
        A connection that has not sent ``hello`` within this [s] is closed.
    max_connections : int
        Users, viewers and pending connections together.
    rate_per_s, burst : float
        Token bucket on incoming frames: sustained frames per second and burst size.
    stale_after_s : float
        A user whose last state is older than this [s] no longer loads the object.
    max_errors : int
        Non-fatal errors on one connection before it is closed.
    """

    max_users: int = 32
    max_viewers: int = 64
    max_pending: int = 32
    hello_timeout_s: float = 5.0
    max_connections: int = 128
    rate_per_s: float = 400.0
    burst: float = 400.0
    stale_after_s: float = 0.5
    max_errors: int = 50


@dataclass
class _Conn:
    conn_id: str
    connected_at_s: float
    tokens: float
    last_refill_s: float
    hello: Hello | None = None
    user_id: str = ""
    state: State | None = None
    state_at_s: float = -math.inf
    errors: int = 0
    closed: bool = False
    output: ContactOutput | None = None


@dataclass
class TickStats:
    """Simulation tick costs measured by the I/O layer (for viewers and reports)."""

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


def object_info(vertices: np.ndarray, faces: np.ndarray) -> ObjectInfo:
    """Rest-state description of the object: bounds, bounding radius, a top and a side anchor.

    The top is the vertex with the largest z, the side the one with the largest x; their normals
    are area-weighted vertex normals. Shapes: vertices (n, 3) [m], faces (m, 3).
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-18)
    lo, hi = v.min(axis=0), v.max(axis=0)
    center = 0.5 * (lo + hi)
    top, side = int(np.argmax(v[:, 2])), int(np.argmax(v[:, 0]))

    def t3(a: np.ndarray) -> tuple[float, float, float]:
        return (float(a[0]), float(a[1]), float(a[2]))

    return ObjectInfo(
        n_vertices=int(v.shape[0]),
        n_faces=int(f.shape[0]),
        center_m=t3(center),
        radius_m=float(np.max(np.linalg.norm(v - center, axis=1))),
        bounds_min_m=t3(lo),
        bounds_max_m=t3(hi),
        top_m=t3(v[top]),
        top_normal=t3(vn[top]),
        side_m=t3(v[side]),
        side_normal=t3(vn[side]),
    )


def _t3(a: Iterable[float]) -> tuple[float, float, float]:
    x, y, z = (float(c) for c in a)
    return (x, y, z)


class Room:
    """Sans-I/O room around one world. Not thread-safe: call it from one event loop.

    Parameters
    ----------
    world : World
        The simulation core (object + contacts).
    sim_rate_hz : float
        Simulation rate 1/(N*T) [Hz], announced to clients.
    link : LinkConditions
        Injected latency, announced to clients and viewers.
    limits : RoomLimits
        Abuse limits.
    """

    def __init__(
        self,
        world: World,
        sim_rate_hz: float,
        link: LinkConditions | None = None,
        limits: RoomLimits | None = None,
    ) -> None:
        self.world = world
        self.sim_rate_hz = float(sim_rate_hz)
        self.link = link or LinkConditions()
        self.limits = limits or RoomLimits()
        self.stats = TickStats()
        self.object_info = object_info(world.vertices, world.faces)
        self._faces_frame = encode_faces(world.faces)
        self._conns: dict[str, _Conn] = {}
        self._next_user = 1
        self.tick_count = 0

    # ------------------------------------------------------------------ connections
    @property
    def users(self) -> list[str]:
        """Connection ids of the haptic users."""
        return [c.conn_id for c in self._conns.values() if c.hello and c.hello.role == "user"]

    @property
    def viewers(self) -> list[str]:
        """Connection ids of the viewers."""
        return [c.conn_id for c in self._conns.values() if c.hello and c.hello.role == "viewer"]

    def connect(self, conn_id: str, now_s: float) -> list[Outgoing]:
        """Register a new connection; it must send ``hello`` first."""
        pending = sum(1 for c in self._conns.values() if c.hello is None)
        if len(self._conns) >= self.limits.max_connections or pending >= self.limits.max_pending:
            return [self._error(conn_id, "room_full", "too many connections", fatal=True)]
        self._conns[conn_id] = _Conn(conn_id, now_s, self.limits.burst, now_s)
        return []

    def disconnect(self, conn_id: str) -> None:
        """Forget a connection; a user's load leaves the object from the next tick on."""
        self._conns.pop(conn_id, None)

    def _error(self, conn_id: str, code: str, message: str, fatal: bool = False) -> Outgoing:
        return Outgoing(
            conn_id, encode(ErrorMsg(code=code, message=message, fatal=fatal)), close=fatal
        )

    def receive(self, conn_id: str, frame: str | bytes, now_s: float) -> list[Outgoing]:
        """Handle one incoming frame at time ``now_s`` [s]; return the frames to send.

        Never raises on bad input: replies ``error`` (closing where the connection cannot go on).
        """
        conn = self._conns.get(conn_id)
        if conn is None or conn.closed:
            return []
        # flood control: token bucket
        conn.tokens = min(
            self.limits.burst, conn.tokens + (now_s - conn.last_refill_s) * self.limits.rate_per_s
        )
        conn.last_refill_s = now_s
        if conn.tokens < 1.0:
            return self._close(
                conn, "rate_limited", "too many messages; slow down to the simulation rate"
            )
        conn.tokens -= 1.0
        if len(frame) > MAX_CLIENT_FRAME_BYTES:
            return self._close(
                conn, "frame_too_large", f"frames are limited to {MAX_CLIENT_FRAME_BYTES} bytes"
            )
        try:
            msg = parse_client(frame)
        except ProtocolError as exc:
            return self._soft_error(conn, exc.code, str(exc))
        if conn.hello is None:
            if not isinstance(msg, Hello):
                return self._close(conn, "expected_hello", "the first message must be hello")
            return self._hello(conn, msg)
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
        if isinstance(msg, Bye):
            conn.closed = True
            self._conns.pop(conn_id, None)
            return []
        if isinstance(msg, State):
            if conn.hello.role != "user":
                return self._soft_error(conn, "not_a_user", "viewers do not send state")
            return self._state(conn, msg, now_s)
        return []  # pragma: no cover - the union is exhausted above

    def _close(self, conn: _Conn, code: str, message: str) -> list[Outgoing]:
        conn.closed = True
        self._conns.pop(conn.conn_id, None)
        return [self._error(conn.conn_id, code, message, fatal=True)]

    def _soft_error(self, conn: _Conn, code: str, message: str) -> list[Outgoing]:
        conn.errors += 1
        if conn.errors > self.limits.max_errors:
            return self._close(
                conn,
                "too_many_errors",
                f"closed after {self.limits.max_errors} bad messages; last: {message}",
            )
        return [self._error(conn.conn_id, code, message)]

    def _hello(self, conn: _Conn, msg: Hello) -> list[Outgoing]:
        if msg.protocol != PROTOCOL_VERSION:
            return self._close(
                conn,
                "protocol_version",
                f"server speaks protocol {PROTOCOL_VERSION}, client sent {msg.protocol}",
            )
        if msg.role == "user" and len(self.users) >= self.limits.max_users:
            return self._close(conn, "room_full", f"the room holds {self.limits.max_users} users")
        if msg.role == "viewer" and len(self.viewers) >= self.limits.max_viewers:
            return self._close(
                conn, "room_full", f"the room holds {self.limits.max_viewers} viewers"
            )
        taken = {c.hello.name for c in self._conns.values() if c.hello}
        name, k = msg.name, 2
        while name in taken:
            name, k = f"{msg.name}-{k}", k + 1
        conn.hello = msg.model_copy(update={"name": name})
        conn.user_id = f"u{self._next_user}"
        self._next_user += 1
        out = [
            Outgoing(
                conn.conn_id,
                _welcome(
                    conn.user_id, name, msg.role, self.sim_rate_hz, self.object_info, self.link
                ),
            )
        ]
        if msg.role == "viewer":
            out.append(Outgoing(conn.conn_id, self._faces_frame))
            out.append(
                Outgoing(
                    conn.conn_id,
                    encode_vertices(self.tick_count, self.world.vertices),
                    stream="vertices",
                )
            )
        return out

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
        if conn.state is not None and msg.seq <= conn.state.seq:
            return []  # older than what we have: latest wins
        conn.state = msg
        conn.state_at_s = now_s
        return []

    # ------------------------------------------------------------------ simulation tick
    def tick(self, tick: int, now_s: float) -> list[Outgoing]:
        """Advance the world one simulation period (tick number ``tick``) at time ``now_s`` [s].

        Returns the patches for users and the surface and summary for viewers.
        """
        self.tick_count = tick
        out: list[Outgoing] = []
        for c in list(self._conns.values()):
            if c.hello is None and now_s - c.connected_at_s > self.limits.hello_timeout_s:
                out += self._close(
                    c, "hello_timeout", f"no hello within {self.limits.hello_timeout_s:g} s"
                )
        inputs: dict[str, ContactInput] = {}
        for c in self._conns.values():
            if c.state is None or c.hello is None or c.hello.role != "user":
                continue
            force = c.state.force_n
            if now_s - c.state_at_s > self.limits.stale_after_s:
                force = (0.0, 0.0, 0.0)  # silent user: its hand no longer loads the object
            inputs[c.conn_id] = ContactInput(probe=np.array(c.state.probe_m), force=np.array(force))
        outputs = self.world.tick(inputs)
        for conn_id, res in outputs.items():
            conn = self._conns.get(conn_id)
            if conn is None:
                continue
            conn.output = res
            out.append(Outgoing(conn_id, encode(_patch(tick, res)), stream="patch"))
        viewers = self.viewers
        if viewers:
            vframe = encode_vertices(tick, self.world.vertices)
            summary = encode(self.room_state(tick))
            for v in viewers:
                out.append(Outgoing(v, vframe, stream="vertices"))
                out.append(Outgoing(v, summary, stream="room"))
        return out

    def room_state(self, tick: int) -> RoomState:
        """The summary viewers get each tick."""
        users = []
        for c in self._conns.values():
            if c.hello is None or c.hello.role != "user" or c.state is None:
                continue
            s, res = c.state, c.output
            users.append(
                UserView(
                    user_id=c.user_id,
                    name=c.hello.name,
                    probe_m=s.probe_m,
                    proxy_m=_t3(res.proxy) if res is not None else s.probe_m,
                    normal=_t3(res.normal) if res is not None else (0.0, 0.0, 1.0),
                    force_n=s.force_n,
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


def _welcome(
    user_id: str,
    name: str,
    role: Literal["user", "viewer"],
    sim_rate_hz: float,
    info: ObjectInfo,
    link: LinkConditions,
) -> str:
    return encode(
        Welcome(
            user_id=user_id, name=name, role=role, sim_rate_hz=sim_rate_hz, object=info, link=link
        )
    )


def _patch(tick: int, res: ContactOutput) -> Patch:
    prim = res.primitive
    model: PlaneModel | SphereModel
    if prim.kind == "plane":
        model = PlaneModel(point=prim.point, normal=prim.normal)  # type: ignore[union-attr]
    else:
        model = SphereModel(center=prim.center, radius=prim.radius)  # type: ignore[union-attr]
    return Patch(
        tick=tick,
        primitive=model,
        proxy_m=_t3(res.proxy),
        normal=_t3(res.normal),
        penetration_m=float(res.penetration_m),
        in_contact=bool(res.in_contact),
        k_o=float(res.k_o),
        k_o_eff=float(res.k_o_eff),
        k_o_stiff=float(res.k_o if res.k_o_stiff is None else res.k_o_stiff),
        b_o=float(res.b_o),
    )
