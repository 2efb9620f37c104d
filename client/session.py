"""A haptic user's side of the protocol, sans-I/O: server frames and times in, frames and patches out.

The asyncio link (:mod:`client.link`) pumps bytes; this class keeps the protocol's state and the
contact's past, and asks :func:`shared.gains.choose.choose` which gains render each ``patch``
(the gain policy has that one home; its sources, in order: the rest plane of a user alone, a
verified plane, the server's recommended gains, the cell's design (or, for a damped object, the
undamped cell's design where it was checked on the damped loop), checked interim gains,
covering gains, and unverified gains for the moment a check runs). The choice comes with jobs
(a design, a check, a plane to verify) that this session hands to the link through
:attr:`ClientSession.design_wanted`, :attr:`ClientSession.interim_wanted` and
:attr:`ClientSession.plane_wanted`, each check and plane once; the link runs them off its event
loop and stores the results where the next choice finds them (the gain table,
:attr:`ClientSession.interim`, :attr:`ClientSession.planes`).

What the session keeps for the policy: the loop delay the gains are designed for, measured from
the round trips and held through a contact (:class:`shared.gains.delay.DelayHold`); the coupling
class with its hysteresis (:func:`shared.gains.key.held_stiff_ratio`); the own-response check of
the contact (:mod:`shared.gains.own_response`), which it feeds each patch; the update in use; and
the tick of the last verified plane in this contact. A patch that cannot render yet (a first
contact with no verified gains) waits with forces off and is retried when gains arrive
(:meth:`ClientSession.retry_waiting`).

The designs themselves come from the shipped tables of the built-in device profiles and this
client's cache of designs (:mod:`client.gain_store`); a key outside them is designed by the link.

The patch is read once into a :class:`shared.local_model_update.SurfacePatch`; it goes to the servo
loop inside one :class:`shared.local_model_update.LocalModelUpdate` with the gains and how they
were chosen (:class:`shared.local_model_update.GainChoice`, with its ``source``; zero-order hold:
it replaces the old one between servo ticks).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from haptic_collab.shared.full_loop import monodromy
from haptic_collab.shared.gains.choose import (
    PLANE_ALONE,
    CheckJob,
    Contact,
    DesignJob,
    Job,
    Known,
    Options,
    cell_has_gains,
    choose,
    likely_next,
)
from haptic_collab.shared.gains.delay import DelayHold, delay_rtt_s, measured_delay_ticks
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, held_stiff_ratio, make_gain_key
from haptic_collab.shared.gains.own_response import OwnResponse
from haptic_collab.shared.gains.policy import OWN_RESPONSE_SLIDE_M
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.verified_plane import ahead_cells, plane_applies
from haptic_collab.shared.local_model_update import GainChoice, LocalModelUpdate, SurfacePatch
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

if TYPE_CHECKING:
    from haptic_collab.client.servo import ServoSnapshot


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
        :mod:`shared.gains.rest_plane`) where no verified plane renders
        (default True; after a verified plane in a contact, only once none has rendered for
        :data:`shared.gains.policy.HOLD_BACK_S`); False: the designs through the simulation loop
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
        #: (key, cell, candidates) of interim gains to verify (:func:`shared.gains.interim.interim_design`); the link
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
        #: The own-response check of the contact (:mod:`shared.gains.own_response`), the proxy it
        #: measures depth from [m] and its last patch's tick.
        self.own_response = OwnResponse()
        self._own_ref: np.ndarray | None = None
        self._own_tick: int | None = None
        #: Verified planes per (key, plane cell, design cell): the plane of the cell holding the
        #: stiffness the own-response check holds the object to, checked against the design of
        #: the cell of the K_o reported (:func:`shared.gains.verified_plane.verified_plane`; None:
        #: none passed), or alone while that cell has no design (design cell
        #: :data:`PLANE_ALONE`), and the one the link is to check off the event loop.
        self.planes: dict[tuple[GainKey, int, int], GainDesign | None] = {}
        #: (key, plane cell, design cell) whose verified plane the link is to check, in the
        #: order asked (the link takes the newest first).
        self.plane_wanted: list[tuple[GainKey, int, int]] = []
        self._plane_asked: set[tuple[GainKey, int, int]] = set()
        #: (key, cell) whose plane the link is to check alone in the background once nothing
        #: above is asked, in this order: the cells around the K_o the patches report
        #: (:func:`shared.gains.verified_plane.ahead_cells`), so that a press finds them checked.
        self.plane_ahead: list[tuple[GainKey, int]] = []
        self._ahead_around: tuple[GainKey, int] | None = None
        #: (key, cell, candidates) the link is to check ahead of need: where a contact that
        #: renders designed gains no job came with (a shipped design, one the damping coverage
        #: reaches, the server's) is likely to go next (:func:`shared.gains.choose.likely_next`),
        #: as the link does after a design or a needed check of its own. Without it a second
        #: user's arrival on a FEM solid met an unchecked coupled class, and on a busy machine
        #: the resting user rendered the quarter-K_o fallback while that check ran.
        self.checks_ahead: list[tuple[GainKey, int, tuple[GainDesign, ...]]] = []
        self._checks_ahead_of: tuple[GainKey, int] | None = None
        #: Patches rendered with a verified plane, and of those with the plane of a stiffness
        #: the own-response check identified other than the K_o reported.
        self.plane_patches = 0
        self.identified_plane_patches = 0
        #: Whether a rest plane a patch carries may render (the ``rest_plane`` parameter).
        self.rest_plane = bool(rest_plane)
        #: Patches rendered with their rest plane (:mod:`shared.gains.rest_plane`).
        self.rest_plane_patches = 0
        # the tick of the last patch a verified plane rendered in this contact (None: none)
        self._plane_tick: int | None = None
        # the key and K_o cell the gains in use were chosen for
        self._in_use_key: tuple[GainKey, int] | None = None
        #: Patches that kept the checked gains in use through a contact rather than step the
        #: felt stiffness to a design that arrived (:func:`shared.gains.choose.choose`).
        self.held_patches = 0
        #: The resume token of the last ``welcome`` (users; None before one, or from a server
        #: without rejoin): the next ``hello`` sends it back, so that after a dropped link the
        #: server gives back the same seat (docs/protocol.md, "Rejoin"). Never logged.
        self.resume_token: str | None = None
        #: Welcomes that gave back the seat of the session before (``welcome.resumed``).
        self.resumes = 0

    # ------------------------------------------------------------------ outgoing
    def hello(self, now_s: float | None = None) -> str:
        """The first frame to send on every (re)connection, sent at local time ``now_s`` [s].

        With ``now_s`` the ``welcome`` that answers it gives the first round-trip time, so the
        very first patch already knows the loop delay (:meth:`delay_ticks`). After a welcome
        with a resume token it carries that token (``resume``): a rejoin within the server's
        hold time gets the same seat back. The field is left out when there is none.
        """
        self._hello_s = now_s
        return Hello(
            protocol=PROTOCOL_VERSION,
            role=self.role,
            name=self.name,
            device=self.device,
            servo_rate_hz=self.servo_rate_hz,
            local_model=self.mode,
            resume=self.resume_token if self.role == "user" else None,
        ).model_dump_json(exclude_none=True)

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
            delay_rtt_ms=self.delay_rtt_ms(),
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
            # each token is used once: keep the new one for the next drop (none: no seat kept)
            self.resume_token = msg.resume_token
            if msg.resumed:
                self.resumes += 1
            self.last_patch = None  # a new session: its ticks start afresh
            self.last_update = None  # and its first patch waits for verified gains again
            self._in_use_key = None
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

    def delay_rtt_ms(self) -> float | None:
        """The round trip [ms] the loop delay is measured from (:func:`delay_rtt_s`), None
        before the first round trip; sent in ``state`` for the server's advisor."""
        rtt = delay_rtt_s(list(self.rtt_s))
        return None if rtt is None else rtt * 1000.0

    def delay_ticks(self, now_s: float | None = None, in_contact: bool = False) -> int:
        """Extra loop delay in whole simulation ticks, from recent round trips.

        The force the server samples at tick k+1 reflects patch k only if the patch's trip down,
        the state's age (up to :attr:`state_interval_s`) and its trip up fit in one simulation
        period; every further period adds one tick (:func:`shared.gains.delay.measured_delay_ticks`:
        the 90th percentile of the last 20 round trips, 10 s of pings).

        With ``now_s`` [s] (each patch passes its arrival time, and whether the user is
        ``in_contact``) the delay the gains are designed for rises at once but falls only out of
        contact, once the lower delay has been measured for
        :data:`shared.gains.policy.DELAY_FALL_S` (:class:`shared.gains.delay.DelayHold`): every
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
        users (1 uncoupled; :func:`shared.gains.key.stiff_ratio_class`).
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
        one in use (:func:`shared.gains.key.held_stiff_ratio`, the server's advisor's rule too).
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

    def _ask_ahead(self, key: GainKey, cell: int, gains: GainDesign) -> None:
        """Ask the link to check ahead of need the (key, cell) :func:`likely_next` names that the
        table has no design for (:func:`table_design`) nor a check, once per (key, cell) of a
        contact, with ``gains`` (those rendering) as the first candidate (:attr:`checks_ahead`)."""
        if self._checks_ahead_of == (key, cell):
            return
        self._checks_ahead_of = (key, cell)
        for nk, nc in likely_next(key, cell):
            if not cell_has_gains(self.gain_table, self.interim, nk, nc):
                self.checks_ahead.append((nk, nc, (gains,)))

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
        :mod:`shared.gains.own_response`)?

        Only an uncoupled contact on an object without B_o is checked (:func:`plane_applies`).
        The check reads the depth of the surface along the contact normal from the proxy it
        started at, the force the simulation applied from this user and the K_o reported, read
        as the object's tangent stiffness (so it goes on across gain-table cells as a
        stiffening object is pressed); the time between patches is their ticks'. It starts over
        after a welcome, when the contact ends (a patch without this user's force), when the
        proxy has slid :data:`shared.gains.policy.OWN_RESPONSE_SLIDE_M` along the surface from where it started (on
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
        """Keep verified interim gains (from :func:`shared.gains.interim.interim_design`) for (key, cell)."""
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

    def _patch(self, msg: Patch, now_s: float) -> LocalModelUpdate | None:
        if self.last_patch is not None and msg.tick <= self.last_patch.tick:
            return None  # stale
        # read once; a bad primitive is refused now (invalid_primitive), even if the patch is
        # to wait for gains
        return self._render(msg, SurfacePatch.from_wire(msg), now_s)

    def _render(self, msg: Patch, surface: SurfacePatch, now_s: float) -> LocalModelUpdate | None:
        """The update rendering ``surface`` (of ``msg``, for its recommended gains), or None
        while it waits for verified gains: :func:`shared.gains.choose.choose` decides, this
        keeps the contact's past for it and hands its jobs to the link."""
        try:
            n = self.rates.ratio
        except ValueError as exc:
            raise ProtocolError("unsupported_rates", str(exc)) from None
        if self.first_patch_s is None:
            self.first_patch_s = now_s
        d = self.delay_ticks(now_s, in_contact=surface.in_contact or surface.own_force_n > 0.0)
        key = self.gain_key(surface.b_o, d, self._stiff_class(surface))
        cell = self.gain_table.cell(surface.k_o_eff)
        self._plan_ahead(key, cell)
        contact = Contact(
            key=key,
            own_response=self._object_as_reported(surface, key),
            identified_ratio=self.own_response.identified_ratio,
            in_use=self.last_update,
            plane_tick=self._plane_tick,
            in_use_key=self._in_use_key,
        )
        known = Known(self.gain_table, self.interim, self.planes)
        choice = choose(surface, msg.gains, contact, known, self._options())
        self._plane_tick = choice.plane_tick
        self._take_jobs(choice.jobs)
        if choice.source is None:
            self._waiting = (msg, surface)
            return None
        self._in_use_key = (key, cell)
        if choice.source in ("design", "design-b_o", "server") and choice.gains is not None:
            self._ask_ahead(key, cell, choice.gains)
        self.held_patches += choice.held
        self.server_gain_patches += choice.source in ("server", "server-interim")
        self.plane_patches += choice.source == "plane"
        self.identified_plane_patches += choice.identified
        self.unverified_patches += not choice.verified
        if choice.rest is not None:
            self.rest_plane_patches += 1
            update = LocalModelUpdate.from_surface(
                surface,
                k_h=choice.rest.k_h,
                i_gain=0.0,
                b_h=choice.rest.b_h,
                hold_ticks=n,
                choice=GainChoice(
                    delay_ticks=d,
                    spectral_radius=0.0,  # its force does not go through the simulation
                    felt_stiffness_ratio_1hz=choice.rest.k_h / surface.k_o,
                    source="rest",
                ),
                rest=True,
            )
            return self._rendered(update, surface, now_s)
        design = choice.gains
        assert design is not None  # a source other than the rest plane names its gains
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
                fallback=choice.fallback,
                verified=choice.verified,
                source=choice.source,
            ),
        )
        return self._rendered(update, surface, now_s)

    def _options(self) -> Options:
        return Options(
            servo_rate_hz=self.servo_rate_hz,
            sim_rate_hz=self.sim_rate_hz,
            k_h_max=self.device.max_stiffness_n_per_m,
            b_h_max=self.b_h_max,
            mode=self.mode,
            gains=self.gains_source,
            rest_plane=self.rest_plane,
        )

    def _take_jobs(self, jobs: tuple[Job, ...]) -> None:
        """Hand ``jobs`` to the link (:attr:`design_wanted`, :attr:`interim_wanted`,
        :attr:`plane_wanted`), each check and plane once."""
        for job in jobs:
            if isinstance(job, DesignJob):
                self.design_wanted = (job.key, job.k_o)
            elif isinstance(job, CheckJob):
                if (job.key, job.cell) not in self._interim_asked:
                    self._interim_asked.add((job.key, job.cell))
                    self.interim_wanted = (job.key, job.cell, job.candidates)
            else:
                plane_key = (job.key, job.cell, job.design_cell)
                if plane_key not in self._plane_asked:
                    self._plane_asked.add(plane_key)
                    self.plane_wanted.append(plane_key)

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
