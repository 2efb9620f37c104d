"""A haptic user's side of the protocol, sans-I/O: server frames and times in, frames and patches out.

The asyncio link (:mod:`client.link`) pumps bytes; this class decides. On each ``patch`` it looks
the local model's gains up in a :class:`shared.gain_table.GainTable`: the full-loop design (hand in
the loop, every sampling tick, a K_o margin) for the patch's K_o_eff, the rate ratio N and the
*measured* delay (round-trip time in whole simulation ticks), within the device's maximum stiffness
and damping (Step 2 of section 6). A lookup is a dict access; a cell not designed yet is named in
:attr:`ClientSession.design_wanted` for the link to design off its event loop (about a second for
PI, up to ten).

Interim gains. Until that design is done the cell renders *verified interim gains*: gains that
pass exactly the design's acceptance test for the cell (:func:`shared.interim_gains.verify_gains`: every hand of the
box, every sampling tick, K_o' over the cell's range with the margin, oscillations decaying at
:data:`shared.stability_margin.MIN_DECAY_RATE_PER_S`), found by :func:`shared.interim_gains.interim_design` among gains
already known (the nearest designed cell, the gains in use) and a short ladder of generic gains
(:data:`shared.interim_gains.INTERIM_LADDER`), a P design as the last resort. That takes one or a few checks of
0.1-0.5 s of CPU each (a PI design takes 2-3 s on the same machine), so the first contact no
longer waits for the PI design; forces stay off only until the first verified gains. Designs for
one key are not safe on another without this check: one for fewer delay ticks than the loop now
has was unstable in every case tried (spectral radius up to 1.18), one for more delay or a
softer cell missed the design's decay margin in about a third of them
(tests/client/test_first_contact.py). :attr:`ClientSession.interim_wanted` names the check for
the link; while it runs after a mid-contact change (new cell, coupling class or delay) the
nearest designed cell (no stiffer relative to K_o) renders, else the gains in use for a new cell,
else (a new coupling class or more delay) the fallback of :data:`shared.gain_policy.FALLBACK_K_RATIO`, all flagged
``verified=False``.

The rest plane. A patch for a user alone on the object (the only user in the room) carries the
object's rest surface at the contact. Where no verified plane renders (and, in a contact that has
rendered one, none has for :data:`shared.rest_plane.HOLD_BACK_S`), the session renders that plane
with the gains of :func:`shared.rest_plane.rest_plane_gains` (K_h = min(K_o, the device's), the
damper closest to eq. 9's object and at least K_h T / 2 at the session's servo period, no
integral, no own-force compensation): at once, with nothing
to design or check first, since its force does not go through the simulation. When another user
joins, the patch comes without it and the design renders the simulation's surface again. The
renderer slides the surface's step off over the gain transfer time
(:meth:`client.render.LocalRenderer.hand_over`). ``rest_plane=False`` never renders it.

The patch is read once into a :class:`shared.local_model_update.SurfacePatch`; it goes to the servo
loop inside one :class:`shared.local_model_update.LocalModelUpdate` with the gains and how they
were chosen (:class:`shared.local_model_update.GainChoice`; zero-order hold: it replaces the old
one between servo ticks).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from haptic_collab.shared.full_loop import monodromy
from haptic_collab.shared.gain_design import GainDesign
from haptic_collab.shared.gain_key import (
    GainKey,
    covering_classes,
    held_stiff_ratio,
    make_gain_key,
)
from haptic_collab.shared.gain_policy import (
    FALLBACK_K_RATIO,
    OWN_RESPONSE_SLIDE_M,
    DelayHold,
    measured_delay_ticks,
)
from haptic_collab.shared.gain_table import GainTable
from haptic_collab.shared.local_model_update import GainChoice, LocalModelUpdate, SurfacePatch
from haptic_collab.shared.own_response import OwnResponse
from haptic_collab.shared.protocol import (
    PROTOCOL_VERSION,
    DeviceInfo,
    ErrorMsg,
    Hello,
    ObjectInfo,
    Patch,
    Ping,
    Pong,
    ProtocolError,
    RoomState,
    State,
    Welcome,
    encode,
    parse_server,
)
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.rest_plane import HOLD_BACK_S as REST_HOLD_BACK_S
from haptic_collab.shared.rest_plane import rest_plane_gains
from haptic_collab.shared.verified_plane import ahead_cells, plane_applies

if TYPE_CHECKING:
    from haptic_collab.client.servo import ServoSnapshot

#: The design cell of a verified plane checked alone (:attr:`ClientSession.planes`): the cell of
#: the K_o reported had no design when the own-response check verified there. The plane renders
#: (it passed its check in its cell) until that design is made and it is compared with it.
PLANE_ALONE = -1


def rendered(update: LocalModelUpdate) -> tuple[SurfacePatch, GainChoice]:
    """The surface patch and the gain choice of an update this session returned.

    Raises
    ------
    ValueError
        ``update`` was not made by a session (no surface patch or no gain choice).
    """
    if update.surface is None or update.choice is None:
        raise ValueError("a session's update carries its surface patch and gain choice")
    return update.surface, update.choice


def _known_gains(
    k_h: float,
    i_gain: float,
    b_h: float,
    proxy_hold: Literal["zoh", "foh"],
    *,
    k_o_eff: float,
    rate_ratio: int,
    delay_ticks: int,
    spectral_radius: float = math.nan,
    felt_1hz: float = math.nan,
    own_gain: float = 0.0,
) -> GainDesign:
    """Gains chosen elsewhere (in use, or recommended by the server) as a :class:`GainDesign`."""
    return GainDesign(
        k_h=k_h,
        i_gain=i_gain,
        b_h=b_h,
        proxy_hold=proxy_hold,
        worst_spectral_radius=spectral_radius,
        rho_limit=math.nan,
        felt_stiffness_ratio_1hz=felt_1hz,
        felt_stiffness_ratio_8hz=math.nan,
        k_o=k_o_eff,
        k_o_range=(k_o_eff, k_o_eff),
        rate_ratio=rate_ratio,
        delay_ticks=delay_ticks,
        mode="pi" if i_gain > 0.0 else "p",
        own_gain=own_gain,
    )


def warm_up_worker() -> None:
    """Import the full-loop code and run it once (a worker process does this while the client
    joins, so the first check does not also pay for imports)."""
    from haptic_collab.shared.full_loop import DEFAULT_HAND

    monodromy(hand=DEFAULT_HAND, k_o=300.0, k_h=100.0, i_gain=1000.0, b_h=1.0, rate_ratio=50)


@dataclass(frozen=True)
class ServoSample:
    """The servo loop's latest state, as the link reports it to the server (latest wins).

    Attributes
    ----------
    probe_m : (3,) float
        Probe position x_h [m].
    force_n : (3,) float
        Force [N] the device last rendered on the user.
    penetration_m : float or None
        Penetration e [m] into the local model; None before the first patch (no local model:
        no penetration to speak of, which is not a zero one).
    in_contact : bool
        The local model was in contact.
    k_h, i_gain : float
        K_h [N/m] and I [N/(m*s)] in use.
    own_gain : float
        Own-force compensation C_h [m/N] in use.
    servo_rate_hz : float
        Achieved servo rate [Hz] (0 before it is measured).
    period_us_p99 : float
        99th percentile of the servo period [us] (0 before it is measured).
    """

    probe_m: tuple[float, float, float]
    force_n: tuple[float, float, float]
    penetration_m: float | None
    in_contact: bool
    k_h: float
    i_gain: float
    servo_rate_hz: float
    period_us_p99: float
    own_gain: float = 0.0

    @classmethod
    def from_snapshot(cls, snap: ServoSnapshot) -> ServoSample:
        """The sample of a servo snapshot (:meth:`client.servo.ServoCore.latest`).

        A NaN penetration (the servo's "no patch yet") becomes None; a rate and period not
        measured yet (NaN) become 0.
        """
        pen = snap.penetration_m if math.isfinite(snap.penetration_m) else None
        p99 = snap.period_p99_s if math.isfinite(snap.period_p99_s) else 0.0
        rate = snap.servo_rate_hz if math.isfinite(snap.servo_rate_hz) else 0.0
        return cls(
            probe_m=snap.probe_m,
            force_n=snap.force_n,
            penetration_m=pen,
            in_contact=snap.in_contact,
            k_h=snap.k_h,
            i_gain=snap.i_gain,
            own_gain=snap.own_gain,
            servo_rate_hz=rate,
            period_us_p99=p99 * 1e6,
        )


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
    gains : {"server", "local"}
        ``server``: render the gains the server recommends in a patch (``patch.gains``, designed
        by the same code for this device) when they are within this device's limits, this local
        model kind and cover at least the delay this client measures; else design locally.
        ``local``: always design locally.
    rest_plane : bool
        Render the rest plane a patch carries (the user alone on the object;
        :mod:`shared.rest_plane`) where no verified plane renders
        (default True; after a verified plane in a contact, only once none has rendered for
        :data:`shared.rest_plane.HOLD_BACK_S`); False: the designs through the simulation loop
        everywhere (the paper's local model alone).
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
        gains: Literal["server", "local"] = "server",
        rest_plane: bool = True,
    ) -> None:
        if gains not in ("server", "local"):
            raise ValueError(f"gains must be 'server' or 'local', got {gains!r}")
        self.gains_source: Literal["server", "local"] = gains
        #: Patches rendered with the server's recommended gains.
        self.server_gain_patches = 0
        self.name = name
        self.servo_rate_hz = servo_rate_hz
        self.device = device or DeviceInfo()
        self.mode: Literal["p", "pi"] = mode
        self.margin = margin
        self.role: Literal["user", "viewer"] = role
        self.welcome: Welcome | None = None
        self.last_patch: SurfacePatch | None = None
        self.last_update: LocalModelUpdate | None = None
        self.errors: list[ErrorMsg] = []
        self.room: RoomState | None = None
        self._seq = 0
        self._ping_id = 0
        self.rtt_s: deque[float] = deque(maxlen=64)
        # the loop delay the gains are designed for (rises at once, falls only out of contact)
        self._delay = DelayHold()
        self.rtt_all_ms: list[float] = []
        self.patches = 0
        self.b_h_max = b_h_max
        self.gain_table = gain_table if gain_table is not None else GainTable()
        #: (key, K_o) of a design the table lacks; the link designs it off the event loop.
        self.design_wanted: tuple[GainKey, float] | None = None
        #: (key, cell, candidates) of interim gains to verify (:func:`shared.interim_gains.interim_design`); the link
        #: runs it off the event loop and calls :meth:`store_interim` or :meth:`interim_failed`.
        self.interim_wanted: tuple[GainKey, int, tuple[GainDesign, ...]] | None = None
        #: Verified interim gains per (key, cell), until the cell's design is in the table.
        self.interim: dict[tuple[GainKey, int], GainDesign] = {}
        self._interim_asked: set[tuple[GainKey, int]] = set()
        #: Local times [s] of the first patch received and of the first one rendered (gains
        #: ready): how long the first contact waited.
        self.first_patch_s: float | None = None
        self.first_update_s: float | None = None
        #: Patches rendered with gains not (yet) verified for their key and cell.
        self.unverified_patches = 0
        self._waiting: tuple[Patch, SurfacePatch] | None = None
        self._hello_s: float | None = None
        #: The coupled contact's K_o_stiff / K_o_eff class in use (GainKey.stiff_ratio), with
        #: hysteresis: it rises at once and falls only when the ratio is 4x below it.
        self.stiff_ratio = 1.0
        #: The own-response check of the contact (:mod:`shared.own_response`), the proxy it
        #: measures depth from [m] and its last patch's tick.
        self.own_response = OwnResponse()
        self._own_ref: np.ndarray | None = None
        self._own_tick: int | None = None
        #: Verified planes per (key, plane cell, design cell): the plane of the cell holding the
        #: stiffness the own-response check holds the object to, checked against the design of
        #: the cell of the K_o reported (:func:`shared.verified_plane.verified_plane`; None:
        #: none passed), or alone while that cell has no design (design cell
        #: :data:`PLANE_ALONE`), and the one the link is to check off the event loop.
        self.planes: dict[tuple[GainKey, int, int], GainDesign | None] = {}
        #: (key, plane cell, design cell) whose verified plane the link is to check, in the
        #: order asked (the link takes the newest first).
        self.plane_wanted: list[tuple[GainKey, int, int]] = []
        self._plane_asked: set[tuple[GainKey, int, int]] = set()
        #: (key, cell) whose plane the link is to check alone in the background once nothing
        #: above is asked, in this order: the cells around the K_o the patches report
        #: (:func:`shared.verified_plane.ahead_cells`), so that a press finds them checked.
        self.plane_ahead: list[tuple[GainKey, int]] = []
        self._ahead_around: tuple[GainKey, int] | None = None
        #: Patches rendered with a verified plane, and of those with the plane of a stiffness
        #: the own-response check identified other than the K_o reported.
        self.plane_patches = 0
        self.identified_plane_patches = 0
        #: Whether a rest plane a patch carries may render (the ``rest_plane`` parameter).
        self.rest_plane = bool(rest_plane)
        #: Patches rendered with their rest plane (:mod:`shared.rest_plane`).
        self.rest_plane_patches = 0
        # the tick of the last patch a verified plane rendered in this contact (None: none)
        self._plane_tick: int | None = None

    # ------------------------------------------------------------------ outgoing
    def hello(self, now_s: float | None = None) -> str:
        """The first frame to send on every (re)connection, sent at local time ``now_s`` [s].

        With ``now_s`` the ``welcome`` that answers it gives the first round-trip time, so the
        very first patch already knows the loop delay (:meth:`delay_ticks`).
        """
        self._hello_s = now_s
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
        """The ``state`` frame for the servo loop's latest sample.

        A sample with no penetration yet (None, before the first patch) is sent without
        ``penetration_m``: there is no local model to penetrate. Absent fields (that one, and
        ``rtt_ms`` before the first pong) are left out rather than sent as null, which a server
        of the same protocol version that predates optional penetration would refuse.
        """
        self._seq += 1
        return State(
            seq=self._seq,
            probe_m=sample.probe_m,
            force_n=sample.force_n,
            penetration_m=sample.penetration_m,
            in_contact=sample.in_contact,
            k_h=sample.k_h,
            i_gain=sample.i_gain,
            own_gain=sample.own_gain,
            servo_rate_hz=sample.servo_rate_hz,
            period_us_p99=sample.period_us_p99,
            rtt_ms=self.rtt_ms(),
            patch_tick=self.last_patch.tick if self.last_patch else -1,
        ).model_dump_json(exclude_none=True)

    # ------------------------------------------------------------------ incoming
    def receive(self, frame: str | bytes, now_s: float) -> LocalModelUpdate | None:
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
            if self._hello_s is not None:
                rtt = now_s - self._hello_s
                if 0.0 <= rtt < 60.0:
                    self.rtt_s.append(rtt)  # hello -> welcome: a round trip like a ping's
                self._hello_s = None
            self.welcome = msg
            self.last_patch = None  # a new session: its ticks start afresh
            self.last_update = None  # and its first patch waits for verified gains again
            self._reset_own_response()  # and the object must show its K_o again
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
            return self._patch(msg, now_s)
        return None

    @property
    def object(self) -> ObjectInfo | None:
        """The shared object's rest-state description, after ``welcome``."""
        return self.welcome.object if self.welcome else None

    @property
    def sim_rate_hz(self) -> float:
        """Simulation rate announced by the server (20 Hz before ``welcome``)."""
        return self.welcome.sim_rate_hz if self.welcome else 20.0

    @property
    def rates(self) -> Rates:
        """This client's servo rate and the server's simulation rate (:attr:`sim_rate_hz`).

        Raises
        ------
        ValueError
            The servo rate is not a whole multiple of the simulation rate (N not whole).
        """
        return Rates(self.servo_rate_hz, self.sim_rate_hz)

    def rtt_ms(self) -> float | None:
        """Median of recent round-trip times [ms], None before the first pong."""
        return float(np.median(self.rtt_s)) * 1000.0 if self.rtt_s else None

    def delay_ticks(self, now_s: float | None = None, in_contact: bool = False) -> int:
        """Extra loop delay in whole simulation ticks, from recent round trips.

        The force the server samples at tick k+1 reflects patch k only if the patch's trip down,
        the state's age (up to :attr:`state_interval_s`) and its trip up fit in one simulation
        period; every further period adds one tick (:func:`shared.gain_policy.measured_delay_ticks`:
        the 90th percentile of the last 20 round trips, 10 s of pings).

        With ``now_s`` [s] (each patch passes its arrival time, and whether the user is
        ``in_contact``) the delay the gains are designed for rises at once but falls only out of
        contact, once the lower delay has been measured for
        :data:`shared.gain_policy.DELAY_FALL_S` (:class:`shared.gain_policy.DelayHold`): every
        new delay is a new gain key whose gains must be checked before they are rendered, and
        a delay wavering by a tick or two under load kept a first contact waiting with its
        forces off, or changed the stiffness a steady hold felt. Without ``now_s``: the larger
        of the measured delay and the one held.
        """
        measured = measured_delay_ticks(list(self.rtt_s), self.state_interval_s, self.sim_rate_hz)
        held = self._delay.held
        if now_s is None:
            return measured if held is None else max(measured, held)
        return self._delay.update(measured, now_s, in_contact)

    @property
    def state_interval_s(self) -> float:
        """Interval [s] at which the link sends ``state``: half a simulation period."""
        return 0.5 / self.sim_rate_hz

    def gain_key(
        self,
        b_o: float,
        delay_ticks: int,
        stiff_ratio: float = 1.0,
    ) -> GainKey:
        """What the gain design depends on besides K_o, for this user now.

        B_o is quantized *down* to 1 N/m steps (a design for less object damping).
        ``stiff_ratio`` is the class of ``K_o_stiff / K_o_eff`` of a contact coupled to other
        users (1 uncoupled; :func:`shared.gain_key.stiff_ratio_class`).
        """
        return make_gain_key(
            servo_rate_hz=self.servo_rate_hz,
            sim_rate_hz=self.sim_rate_hz,
            delay_ticks=delay_ticks,
            mode=self.mode,
            margin=self.margin,
            k_h_max=self.device.max_stiffness_n_per_m,
            b_h_max=self.b_h_max,
            b_o=b_o,
            stiff_ratio=stiff_ratio,
        )

    def _stiff_class(self, surface: SurfacePatch) -> float:
        """The ratio class to design for, from the patch's ``k_o_eff`` and ``k_o_stiff``.

        Rises to a new class at once and falls only when the measured class is a quarter of the
        one in use (:func:`shared.gain_key.held_stiff_ratio`, the server's advisor's rule too).
        """
        self.stiff_ratio = held_stiff_ratio(self.stiff_ratio, surface.k_o_eff, surface.k_o_stiff)
        return self.stiff_ratio

    def store_plane(
        self, key: GainKey, cell: int, design: GainDesign | None, design_cell: int | None = None
    ) -> None:
        """Keep the verified plane of (key, cell) checked against the design of ``design_cell``
        (default: ``cell``'s own), or None: none passed its check."""
        self.planes[(key, cell, cell if design_cell is None else design_cell)] = design

    def _plan_ahead(self, key: GainKey, cell: int) -> None:
        """Have the planes around ``cell`` (the cell of the K_o reported) checked alone in the
        background, nearest first (:attr:`plane_ahead`; :meth:`next_plane_ahead` skips those
        checked or asked already)."""
        if self._ahead_around == (key, cell):
            return
        self._ahead_around = (key, cell)
        self.plane_ahead = [(key, c) for c in ahead_cells(key, cell, self.gain_table.grid_ratio)]

    def next_plane_ahead(self) -> tuple[GainKey, int] | None:
        """The next plane to check ahead (:attr:`plane_ahead`), marked asked, or None."""
        while self.plane_ahead:
            key, c = self.plane_ahead.pop(0)
            alone = (key, c, PLANE_ALONE)
            if alone not in self.planes and alone not in self._plane_asked:
                self._plane_asked.add(alone)
                return key, c
        return None

    def _reset_own_response(self) -> None:
        self.own_response.reset()
        self._own_ref, self._own_tick = None, None

    def _object_as_reported(self, surface: SurfacePatch, key: GainKey) -> bool:
        """Feed the own-response check this patch and return its verdict: has the object
        yielded to this user's force as a spring of the stiffness the check holds it to, the K_o
        reported or the one it identified (``own_response.identified_ratio`` times K_o;
        :mod:`shared.own_response`)?

        Only an uncoupled contact on an object without B_o is checked (:func:`plane_applies`).
        The check reads the depth of the surface along the contact normal from the proxy it
        started at, the force the simulation applied from this user and the K_o reported, read
        as the object's tangent stiffness (so it goes on across gain-table cells as a
        stiffening object is pressed); the time between patches is their ticks'. It starts over
        after a welcome, when the contact ends (a patch without this user's force), when the
        proxy has slid :data:`shared.gain_policy.OWN_RESPONSE_SLIDE_M` along the surface from where it started (on
        a curved surface the depth would carry the curvature), and when the ticks go back.
        """
        check = self.own_response
        if not plane_applies(key):
            self._reset_own_response()
            return False
        if surface.own_force_n <= 0.0:
            self._reset_own_response()
            return False
        if self._own_tick is not None and surface.tick == self._own_tick:
            return check.verified  # the same patch again (a retried render)
        proxy = np.asarray(surface.proxy, dtype=float)
        normal = np.asarray(surface.normal, dtype=float)
        if self._own_ref is not None:
            moved = proxy - self._own_ref
            slid = moved - float(np.dot(moved, normal)) * normal
            if float(np.linalg.norm(slid)) > OWN_RESPONSE_SLIDE_M or (
                self._own_tick is not None and surface.tick < self._own_tick
            ):
                self._reset_own_response()
        if self._own_ref is None:
            self._own_ref = proxy
        dt = 0.0 if self._own_tick is None else (surface.tick - self._own_tick) / self.sim_rate_hz
        self._own_tick = surface.tick
        depth = float(np.dot(self._own_ref - proxy, normal))
        return check.update(
            dt_s=dt, surface_m=depth, force_n=surface.own_force_n, k_o=surface.k_o_eff
        )  # fmt: skip

    def store_interim(self, key: GainKey, cell: int, design: GainDesign) -> None:
        """Keep verified interim gains (from :func:`shared.interim_gains.interim_design`) for (key, cell)."""
        self.interim[(key, cell)] = design

    def interim_failed(self, key: GainKey, cell: int) -> None:
        """No interim gains were found for (key, cell): its patches wait for the design."""
        self._interim_asked.add((key, cell))

    def retry_waiting(self, now_s: float) -> LocalModelUpdate | None:
        """Render the newest patch that waited for gains, now that some may be ready.

        The link calls this when a design or interim gains arrive, so the first contact does not
        also wait for the next patch. Returns None if nothing waited or it still cannot render.
        """
        waiting, self._waiting = self._waiting, None
        return None if waiting is None else self._render(*waiting, now_s)

    def _covering(self, key: GainKey, cell: int, k_o_eff: float) -> GainDesign | None:
        """Gains designed or verified for this cell and a wider coupling class, if any: checked
        over a K_o range containing this key's (:func:`shared.gain_key.covering_classes`),
        they render at once while this key's own design is made (a second user's arrival
        otherwise meant conservative unverified gains until a check was done)."""
        table = self.gain_table
        for c in covering_classes(key.stiff_ratio):
            wider = replace(key, stiff_ratio=c)
            d = table.lookup(wider, k_o_eff)
            if d is None:
                d = self.interim.get((wider, cell))
            if d is not None:
                return d
        return None

    def _design_in_use(self, n: int) -> GainDesign | None:
        lu = self.last_update
        if lu is None:
            return None
        surface, choice = rendered(lu)
        return _known_gains(
            lu.k_h, lu.i_gain, lu.b_h, lu.proxy_hold,
            k_o_eff=surface.k_o_eff, rate_ratio=n, delay_ticks=choice.delay_ticks,
            spectral_radius=choice.spectral_radius, felt_1hz=choice.felt_stiffness_ratio_1hz,
            own_gain=lu.own_gain,
        )  # fmt: skip

    def _recommended(
        self, msg: Patch, n: int, delay_ticks: int, own: GainDesign | None
    ) -> GainDesign | None:
        """The server's recommended gains as a design, if this client may render them and has
        nothing better: interim recommendations yield to a full design of its own (``own``)."""
        rec = msg.gains
        if self.gains_source != "server" or rec is None:
            return None
        if rec.interim and own is not None:
            return None
        if (
            rec.k_h > self.device.max_stiffness_n_per_m
            or rec.b_h > self.b_h_max + 1e-9
            or (self.mode == "p" and rec.i_gain > 0.0)
            or rec.delay_ticks < delay_ticks
        ):
            return None  # designed for another device, kind or a shorter delay: design here
        return _known_gains(
            rec.k_h, rec.i_gain, rec.b_h, rec.proxy_hold,
            k_o_eff=msg.k_o_eff, rate_ratio=n, delay_ticks=rec.delay_ticks,
            own_gain=rec.own_gain,
        )  # fmt: skip

    def _patch(self, msg: Patch, now_s: float) -> LocalModelUpdate | None:
        if self.last_patch is not None and msg.tick <= self.last_patch.tick:
            return None  # stale
        # read once; a bad primitive is refused now (invalid_primitive), even if the patch is
        # to wait for gains
        return self._render(msg, SurfacePatch.from_wire(msg), now_s)

    def _render(self, msg: Patch, surface: SurfacePatch, now_s: float) -> LocalModelUpdate | None:
        """The update rendering ``surface`` (of ``msg``, for its recommended gains), or None
        while it waits for verified gains."""
        try:
            n = self.rates.ratio
        except ValueError as exc:
            raise ProtocolError("unsupported_rates", str(exc)) from None
        if self.first_patch_s is None:
            self.first_patch_s = now_s
        d = self.delay_ticks(now_s, in_contact=surface.in_contact or surface.own_force_n > 0.0)
        k_o_eff = surface.k_o_eff
        key = self.gain_key(surface.b_o, d, self._stiff_class(surface))
        table = self.gain_table
        cell = table.cell(k_o_eff)
        own = table.lookup(key, k_o_eff)
        design = self._recommended(msg, n, d, own)
        if design is not None:
            self.server_gain_patches += 1
        else:
            design = own
        self._plan_ahead(key, cell)
        # the user alone on the object: the rest plane's gains for this patch (shared.rest_plane)
        rest = (
            rest_plane_gains(
                surface.k_o,
                surface.b_o,
                self.sim_rate_hz,
                self.device.max_stiffness_n_per_m,
                self.b_h_max,
                servo_period_s=1.0 / self.servo_rate_hz,
            )  # fmt: skip
            if self.rest_plane and surface.rest_plane is not None
            else None
        )
        plane_renders = False
        if self._object_as_reported(surface, key):
            # the object yields to this user's force as a spring: of the K_o reported, or of
            # the stiffness the check identified. The plane verified for that stiffness (the
            # lightest damper, K_h = K') replaces the design made for an object off by 25 %
            # where it is felt closer than the design (checked against it once made). In a cell
            # not designed yet (a press into a stiffening object crosses a cell in a fraction of
            # a second; a design may take seconds) the plane checked alone renders meanwhile
            k_id = self.own_response.identified_ratio * k_o_eff
            plane_cell = table.cell(k_id)
            plane_key = (key, plane_cell, cell if own is not None else PLANE_ALONE)
            if plane_key in self.planes:
                plane = self.planes[plane_key]
            else:
                if own is None:
                    # the server's gains render (or the fallback): design the cell here too,
                    # the plane is then compared with that design
                    self.design_wanted = (key, k_o_eff)
                if plane_key not in self._plane_asked:
                    self._plane_asked.add(plane_key)
                    self.plane_wanted.append(plane_key)
                # a plane checked alone renders where the cell has no design; where it has one,
                # only once compared with it (milliseconds: the design renders meanwhile)
                plane = None if own is not None else self.planes.get((key, plane_cell, PLANE_ALONE))
            if plane is not None:
                design = plane.at(k_id)
                plane_renders = True
                self.plane_patches += 1
                self.identified_plane_patches += self.own_response.identified_ratio != 1.0
        if not (surface.in_contact or surface.own_force_n > 0.0):
            self._plane_tick = None
        elif plane_renders:
            self._plane_tick = surface.tick
        held_back = (
            self._plane_tick is not None
            and (surface.tick - self._plane_tick) / self.sim_rate_hz < REST_HOLD_BACK_S
        )
        if rest is not None and not (plane_renders or held_back):
            # the user alone on the object, no verified plane: the rest plane, with gains of
            # the patch alone (nothing to wait for); after a verified plane in a contact it
            # waits HOLD_BACK_S without one (crossing back at once, a press into the stiffening
            # object lost box-stability in one benchmark condition)
            if design is None:
                self.design_wanted = (key, k_o_eff)  # for when another user joins
            self.rest_plane_patches += 1
            return self._rendered(
                LocalModelUpdate.from_surface(
                    surface,
                    k_h=rest.k_h,
                    i_gain=0.0,
                    b_h=rest.b_h,
                    hold_ticks=n,
                    choice=GainChoice(
                        delay_ticks=d,
                        spectral_radius=0.0,  # its force does not go through the simulation
                        felt_stiffness_ratio_1hz=rest.k_h / surface.k_o,
                    ),
                    rest=True,
                ),
                surface,
                now_s,
            )
        fallback = design is None
        verified = True
        if design is None:
            self.design_wanted = (key, k_o_eff)
            design = self.interim.get((key, cell))
            if design is None:
                design = self._covering(key, cell, k_o_eff)
            if design is None:
                # no gains verified for this key and cell yet: have some checked (fast), and
                # meanwhile keep the nearest designed cell (no stiffer relative to K_o) or the
                # gains in use -- never for a first contact, which waits with forces off
                near = table.fallback(key, k_o_eff)
                in_use = self._design_in_use(n)
                if (key, cell) not in self._interim_asked:
                    self._interim_asked.add((key, cell))
                    self.interim_wanted = (
                        key,
                        cell,
                        tuple(c for c in (near, in_use) if c is not None),
                    )
                design = near if near is not None else in_use
                last = None if self.last_update is None else rendered(self.last_update)
                more_delay = last is not None and d > last[1].delay_ticks
                if near is None and in_use is not None and (key.stiff_ratio > 1.0 or more_delay):
                    # the gains in use were not designed for this coupled contact's stiff
                    # modes, or for this much delay (designs for fewer ticks than the loop has
                    # were unstable in every case tried): until verified gains arrive, render
                    # the unverified fallback (:data:`shared.gain_policy.FALLBACK_K_RATIO`; the integral force
                    # already built is kept, frozen)
                    scale = 1.0 if last is None else min(1.0, k_o_eff / last[0].k_o_eff)
                    k_h = min(in_use.k_h * scale, FALLBACK_K_RATIO * k_o_eff)
                    design = replace(
                        in_use,
                        k_h=k_h,
                        i_gain=0.0,
                        b_h=key.b_h_max,
                        proxy_hold="zoh",
                        mode="p",
                        own_gain=0.0,
                    )
                if design is None or self.last_update is None:
                    self._waiting = (msg, surface)
                    return None
                verified = False
                self.unverified_patches += 1
        update = LocalModelUpdate.from_surface(
            surface,
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            hold_ticks=n,
            own_gain=design.own_gain,
            choice=GainChoice(
                delay_ticks=d,
                spectral_radius=design.worst_spectral_radius,
                felt_stiffness_ratio_1hz=design.felt_stiffness_ratio_1hz,
                fallback=fallback,
                verified=verified,
            ),
        )
        return self._rendered(update, surface, now_s)

    def _rendered(
        self, update: LocalModelUpdate, surface: SurfacePatch, now_s: float
    ) -> LocalModelUpdate:
        """``update`` (of ``surface``, at ``now_s``) as the one in use."""
        self.last_update = update
        self._waiting = None
        self.last_patch = surface
        self.patches += 1
        if self.first_update_s is None:
            self.first_update_s = now_s
        return update
