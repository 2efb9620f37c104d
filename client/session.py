"""A haptic user's side of the protocol, sans-I/O: server frames and times in, frames and patches out.

The asyncio link (:mod:`client.link`) pumps bytes; this class decides. On each ``patch`` it looks
the local model's gains up in a :class:`shared.gain_design.GainTable`: the full-loop design (hand in
the loop, every sampling tick, a K_o margin) for the patch's K_o_eff, the rate ratio N and the
*measured* delay (round-trip time in whole simulation ticks), within the device's maximum stiffness
and damping (Step 2 of section 6). A lookup is a dict access; a cell not designed yet is named in
:attr:`ClientSession.design_wanted` for the link to design off its event loop, and meanwhile the
nearest designed cell renders no stiffer relative to K_o (the very first patch waits for its
design: forces are off until then). Primitive and gains go to the servo loop as one
:class:`PatchUpdate` (zero-order hold: it replaces the old one between servo ticks).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from shared.gain_design import GainDesign, GainKey, GainTable
from shared.primitives import Primitive, make_plane, make_sphere
from shared.protocol import (
    PROTOCOL_VERSION,
    DeviceInfo,
    ErrorMsg,
    Hello,
    ObjectInfo,
    Patch,
    Ping,
    PlaneModel,
    Pong,
    ProtocolError,
    RoomState,
    State,
    Welcome,
    encode,
    parse_server,
)
from shared.stability import rate_ratio as _rate_ratio

#: Pings (one every 0.5 s) over which the loop delay is estimated.
RTT_WINDOW = 20


@dataclass(frozen=True)
class PatchUpdate:
    """What the servo loop needs from one patch: the primitive and the gains, swapped atomically.

    Attributes
    ----------
    primitive : Plane | Sphere
        The local geometric model.
    k_h : float
        K_h [N/m].
    i_gain : float
        I [N/(m*s)].
    tick : int
        Simulation tick of the patch.
    k_o, k_o_eff, b_o : float
        As reported by the server [N/m].
    delay_ticks : int
        Delay assumed in the gain choice [simulation ticks].
    spectral_radius : float
        Worst full-loop spectral radius of the design over the hand box (below its decay limit).
    b_h : float
        Probe damper B_h [N*s/m].
    proxy_hold : {"zoh", "foh"}
        How the servo moves to the new surface.
    hold_ticks : int
        N, servo ticks per simulation tick (the first-order hold's length).
    felt_stiffness_ratio_1hz : float
        Designed felt stiffness over K_o at 1 Hz.
    fallback : bool
        True while the exact design for this K_o is still being computed.
    """

    primitive: Primitive
    k_h: float
    i_gain: float
    tick: int
    k_o: float
    k_o_eff: float
    b_o: float
    delay_ticks: int
    spectral_radius: float
    b_h: float = 0.0
    proxy_hold: str = "zoh"
    hold_ticks: int = 1
    felt_stiffness_ratio_1hz: float = math.nan
    fallback: bool = False


@dataclass(frozen=True)
class ServoSample:
    """The servo loop's latest state, as the link reports it to the server (latest wins)."""

    probe_m: tuple[float, float, float]
    force_n: tuple[float, float, float]
    penetration_m: float
    in_contact: bool
    k_h: float
    i_gain: float
    servo_rate_hz: float
    period_us_p99: float


class ClientSession:
    """Protocol state of one haptic user (or a viewer, with ``role="viewer"``).

    Parameters
    ----------
    name : str
        User name shown to others.
    servo_rate_hz : float
        The servo loop's rate 1/T [Hz].
    device : DeviceInfo
        Profile name, max force [N], max stable stiffness [N/m].
    mode : {"p", "pi"}
        Local model type.
    margin : float
        Fraction by which K_o may be overestimated (gain selection margin).
    role : {"user", "viewer"}
    b_h_max : float
        The device's largest virtual damping [N*s/m] (0: no probe damper).
    gain_table : GainTable, optional
        Where designs are cached (default: a new table over the default hand box).
    """

    def __init__(
        self,
        name: str,
        *,
        servo_rate_hz: float = 1000.0,
        device: DeviceInfo | None = None,
        mode: Literal["p", "pi"] = "pi",
        margin: float = 0.15,
        role: Literal["user", "viewer"] = "user",
        b_h_max: float = 0.0,
        gain_table: GainTable | None = None,
    ) -> None:
        self.name = name
        self.servo_rate_hz = servo_rate_hz
        self.device = device or DeviceInfo()
        self.mode: Literal["p", "pi"] = mode
        self.margin = margin
        self.role: Literal["user", "viewer"] = role
        self.welcome: Welcome | None = None
        self.last_patch: Patch | None = None
        self.last_update: PatchUpdate | None = None
        self.errors: list[ErrorMsg] = []
        self.room: RoomState | None = None
        self._seq = 0
        self._ping_id = 0
        self.rtt_s: deque[float] = deque(maxlen=64)
        self.rtt_all_ms: list[float] = []
        self.patches = 0
        self.b_h_max = b_h_max
        self.gain_table = gain_table if gain_table is not None else GainTable()
        #: (key, K_o) of a design the table lacks; the link designs it off the event loop.
        self.design_wanted: tuple[GainKey, float] | None = None

    # ------------------------------------------------------------------ outgoing
    def hello(self) -> str:
        """The first frame to send on every (re)connection."""
        return encode(
            Hello(
                protocol=PROTOCOL_VERSION,
                role=self.role,
                name=self.name,
                device=self.device,
                servo_rate_hz=self.servo_rate_hz,
                local_model=self.mode,
            )
        )

    def ping(self, now_s: float) -> str:
        """A ping frame stamped with the local monotonic time ``now_s`` [s]."""
        self._ping_id += 1
        return encode(Ping(id=self._ping_id, t_client_s=now_s))

    def state(self, sample: ServoSample) -> str:
        """The ``state`` frame for the servo loop's latest sample."""
        self._seq += 1
        return encode(
            State(
                seq=self._seq,
                probe_m=sample.probe_m,
                force_n=sample.force_n,
                penetration_m=sample.penetration_m,
                in_contact=sample.in_contact,
                k_h=sample.k_h,
                i_gain=sample.i_gain,
                servo_rate_hz=sample.servo_rate_hz,
                period_us_p99=sample.period_us_p99,
                rtt_ms=self.rtt_ms(),
                patch_tick=self.last_patch.tick if self.last_patch else -1,
            )
        )

    # ------------------------------------------------------------------ incoming
    def receive(self, frame: str | bytes, now_s: float) -> PatchUpdate | None:
        """Handle one server frame at local time ``now_s`` [s]; return a patch update if any.

        Raises
        ------
        ProtocolError
            The frame is not a valid server message (the link logs it and goes on).
        """
        if isinstance(frame, bytes | bytearray):
            return None  # surface frames are for viewers
        msg = parse_server(frame)
        if isinstance(msg, Welcome):
            self.welcome = msg
            self.last_patch = None  # a new session: its ticks start afresh
            return None
        if isinstance(msg, Pong):
            rtt = now_s - msg.t_client_s
            if 0.0 <= rtt < 60.0:
                self.rtt_s.append(rtt)
                self.rtt_all_ms.append(rtt * 1000.0)
            return None
        if isinstance(msg, ErrorMsg):
            self.errors.append(msg)
            return None
        if isinstance(msg, RoomState):
            self.room = msg
            return None
        if isinstance(msg, Patch):
            return self._patch(msg)
        return None

    @property
    def object(self) -> ObjectInfo | None:
        """The shared object's rest-state description, after ``welcome``."""
        return self.welcome.object if self.welcome else None

    @property
    def sim_rate_hz(self) -> float:
        """Simulation rate announced by the server (20 Hz before ``welcome``)."""
        return self.welcome.sim_rate_hz if self.welcome else 20.0

    def rtt_ms(self) -> float | None:
        """Median of recent round-trip times [ms], None before the first pong."""
        return float(np.median(self.rtt_s)) * 1000.0 if self.rtt_s else None

    def delay_ticks(self) -> int:
        """Extra loop delay in whole simulation ticks, from recent round trips.

        The force the server samples at tick k+1 reflects patch k only if the patch's trip down,
        the state's age (up to :attr:`state_interval_s`) and its trip up fit in one simulation
        period; every further period adds one tick: ``ceil((rtt + age) / period) - 1``. The round
        trip is the 90th percentile of the last :data:`RTT_WINDOW` pings (10 s): conservative under
        steady jitter, yet one stall does not make the local model soft for long.
        """
        if not self.rtt_s:
            return 0
        recent = list(self.rtt_s)[-RTT_WINDOW:]
        worst = float(np.percentile(recent, 90)) + self.state_interval_s
        return max(0, math.ceil(worst * self.sim_rate_hz - 1e-9) - 1)

    @property
    def state_interval_s(self) -> float:
        """Interval [s] at which the link sends ``state``: half a simulation period."""
        return 0.5 / self.sim_rate_hz

    def gain_key(self, b_o: float, delay_ticks: int) -> GainKey:
        """What the gain design depends on besides K_o, for this user now.

        B_o is quantized *down* to 1 N/m steps (a design for less object damping).
        """
        return GainKey(
            servo_rate_hz=float(self.servo_rate_hz),
            sim_rate_hz=float(self.sim_rate_hz),
            delay_ticks=int(delay_ticks),
            mode=self.mode,
            margin=float(self.margin),
            k_h_max=float(self.device.max_stiffness_n_per_m),
            b_h_max=float(self.b_h_max),
            b_o=float(math.floor(max(0.0, b_o))),
        )

    def _patch(self, msg: Patch) -> PatchUpdate | None:
        if self.last_patch is not None and msg.tick <= self.last_patch.tick:
            return None  # stale
        prim: Primitive
        p = msg.primitive
        try:
            if isinstance(p, PlaneModel):
                prim = make_plane(p.point, p.normal)
            else:
                prim = make_sphere(p.center, p.radius)
        except ValueError as exc:
            raise ProtocolError("invalid_primitive", str(exc)) from None
        try:
            n = _rate_ratio(self.servo_rate_hz, self.sim_rate_hz)
        except ValueError as exc:
            raise ProtocolError("unsupported_rates", str(exc)) from None
        d = self.delay_ticks()
        key = self.gain_key(msg.b_o, d)
        design = self.gain_table.lookup(key, msg.k_o_eff)
        fallback = design is None
        if design is None:
            self.design_wanted = (key, msg.k_o_eff)
            design = self.gain_table.fallback(key, msg.k_o_eff)
            if design is None and self.last_update is not None:
                # a new delay or damping: keep rendering the gains in use until the design is done
                # (patches keep flowing, so the servo's link watchdog stays quiet)
                lu = self.last_update
                design = GainDesign(
                    k_h=lu.k_h,
                    i_gain=lu.i_gain,
                    b_h=lu.b_h,
                    proxy_hold=lu.proxy_hold,  # type: ignore[arg-type]
                    worst_spectral_radius=lu.spectral_radius,
                    rho_limit=math.nan,
                    felt_stiffness_ratio_1hz=lu.felt_stiffness_ratio_1hz,
                    felt_stiffness_ratio_8hz=math.nan,
                    k_o=lu.k_o_eff,
                    k_o_range=(lu.k_o_eff, lu.k_o_eff),
                    rate_ratio=n,
                    delay_ticks=lu.delay_ticks,
                    mode=self.mode,
                )
            if design is None:
                return None  # the first patch waits for its design (forces are still off)
        self.last_patch = msg
        self.patches += 1
        self.last_update = PatchUpdate(
            primitive=prim,
            k_h=design.k_h,
            i_gain=design.i_gain,
            tick=msg.tick,
            k_o=msg.k_o,
            k_o_eff=msg.k_o_eff,
            b_o=msg.b_o,
            delay_ticks=d,
            spectral_radius=design.worst_spectral_radius,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            hold_ticks=n,
            felt_stiffness_ratio_1hz=design.felt_stiffness_ratio_1hz,
            fallback=fallback,
        )
        return self.last_update
