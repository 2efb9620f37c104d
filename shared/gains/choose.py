"""Which gains render for one patch, and why: :func:`choose`, the gain policy in one function.

A patch arrives; the client session (:class:`client.session.ClientSession`) holds the contact's
past (the loop delay it designs for, the coupling class, the own-response check, the update in
use) and asks :func:`choose` what to render. The answer, :class:`Choice`, names the gains, their
source, and the work that would make a better answer possible next time (:data:`Job`: a design,
a check, a plane to verify). The session hands the jobs to its link, which only runs them (in a
worker process) and stores their results where the next call finds them (:class:`Known`). Pure:
no I/O, no clock, nothing kept between calls; the same inputs give the same choice.

The sources, in the order they are tried (docs/gains.md, "Which gains render"):

1. ``rest``: a user alone on the object, where no verified plane renders (nor has for
   :data:`shared.gains.policy.HOLD_BACK_S` in this contact): the object's rest plane with
   :func:`shared.gains.rest_plane.rest_plane_gains`; its force does not go through the simulation,
   so it needs no design.
2. ``plane``: the own-response check holds the object to a spring (:mod:`shared.gains.own_response`):
   the plane verified for that stiffness (:func:`shared.gains.verified_plane.verified_plane`), once
   checked (against the cell's design, if the cell has one).
3. ``server``: the server's recommended gains (``patch.gains``: the same design, made by the
   server), where this device may render them and they cover the delay measured here;
   ``server-interim`` while the server's are checked interim gains, which yield to a design of
   this client's own.
4. ``design``: the cell's design in the table (shipped, cached or made this session);
   ``design-b_o``: for a key with object damping B_o > 0 whose cell has none, the shipped design
   of the same key with B_o = 0, where that design was checked offline on the damped loop up to
   the key's B_o (:func:`table_design`, :mod:`shared.gains.damping_cover`): a designed, verified
   cell, no design asked for.
5. ``interim``: gains checked for this key and cell (:func:`shared.gains.interim.interim_design`).
6. ``covering``: a design or check of this cell for a wider coupling class
   (:func:`shared.gains.key.covering_classes`), checked over a range containing this key's.
7. Unverified, while a check runs (:class:`CheckJob`): ``near``, the nearest designed cell no
   stiffer relative to K_o (:meth:`shared.gains.table.GainTable.fallback`), else ``in-use``, the
   gains in use; or ``fallback``, :data:`shared.gains.policy.FALLBACK_K_RATIO` times K_o with no
   integral, where the gains in use were made for fewer delay ticks or an uncoupled contact.
   Never for a first contact: with nothing in use it waits with forces off (``source`` None).

In a contact, checked interim gains (``interim``, ``covering``, ``server-interim``) are kept for
as long as the key and the K_o cell stay those they were chosen for, rather than give way to a
design felt more than a stiffness JND stiffer or softer (:data:`shared.gains.policy.HOLD_FELT_STEP`;
``Choice.held``): the design renders from the next contact, or at once on a new key or cell.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Literal

from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey, covering_classes
from haptic_collab.shared.gains.policy import (
    COUPLED_CELLS_BELOW,
    FALLBACK_K_RATIO,
    HOLD_BACK_S,
    HOLD_FELT_STEP,
)
from haptic_collab.shared.gains.rest_plane import RestPlaneGains, rest_plane_gains
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import b_o_covered
from haptic_collab.shared.local_model_update import LocalModelUpdate, SurfacePatch
from haptic_collab.shared.protocol import RecommendedGains

#: The design cell of a verified plane checked alone (:class:`Known` ``planes``): the cell of the
#: K_o reported had no design when the own-response check verified there. The plane renders (it
#: passed its check in its cell) until that design is made and it is compared with it.
PLANE_ALONE = -1

Source = Literal[
    "rest",
    "plane",
    "server",
    "server-interim",
    "design",
    "design-b_o",
    "interim",
    "covering",
    "near",
    "in-use",
    "fallback",
]
#: The sources whose gains passed the full-loop check for the patch's key and cell (or, for the
#: rest plane, need none).
VERIFIED_SOURCES: frozenset[str] = frozenset(
    {"rest", "plane", "server", "server-interim", "design", "design-b_o", "interim", "covering"}
)


@dataclass(frozen=True)
class DesignJob:
    """Design the cell of ``k_o`` [N/m] for ``key`` (:func:`shared.gains.table.design_cell`)."""

    key: GainKey
    k_o: float


@dataclass(frozen=True)
class CheckJob:
    """Check gains for ``cell`` of ``key``: ``candidates`` first, then the generic ladder
    (:func:`shared.gains.interim.interim_design`). Asked once per (key, cell)."""

    key: GainKey
    cell: int
    candidates: tuple[GainDesign, ...]


@dataclass(frozen=True)
class PlaneJob:
    """Verify the plane of ``cell`` of ``key`` against the design of ``design_cell`` (or alone,
    :data:`PLANE_ALONE`) (:func:`shared.gains.verified_plane.verified_plane`)."""

    key: GainKey
    cell: int
    design_cell: int


Job = DesignJob | CheckJob | PlaneJob


@dataclass(frozen=True)
class Options:
    """What the user declared: its device, local model and wishes.

    Attributes
    ----------
    servo_rate_hz, sim_rate_hz : float
        The servo rate 1/T and the server's simulation rate [Hz].
    k_h_max : float
        The device's largest stable stiffness [N/m].
    b_h_max : float
        The device's largest virtual damping [N*s/m].
    mode : {"p", "pi"}
        The local model kind.
    gains : {"server", "local"}
        Whether the server's recommended gains may render.
    rest_plane : bool
        Whether a rest plane a patch carries may render.
    """

    servo_rate_hz: float
    sim_rate_hz: float
    k_h_max: float
    b_h_max: float
    mode: Literal["p", "pi"] = "pi"
    gains: Literal["server", "local"] = "server"
    rest_plane: bool = True

    @property
    def rate_ratio(self) -> int:
        """N = servo rate / simulation rate (whole: :class:`shared.rates.Rates` checks it)."""
        return round(self.servo_rate_hz / self.sim_rate_hz)


@dataclass(frozen=True)
class Contact:
    """The contact's past as the session holds it, for one patch.

    Attributes
    ----------
    key : GainKey
        The key this patch's gains are for (the delay held through the contact,
        :class:`shared.gains.delay.DelayHold`; the coupling class with its hysteresis,
        :func:`shared.gains.key.held_stiff_ratio`).
    own_response : bool
        The own-response check's verdict with this patch: the object yields to this user's force
        as a spring (:mod:`shared.gains.own_response`).
    identified_ratio : float
        The stiffness the check holds the object to, over the K_o reported (1: the K_o reported).
    in_use : LocalModelUpdate or None
        The update rendering now (None: nothing yet, forces off).
    plane_tick : int or None
        The tick of the last patch a verified plane rendered in this contact.
    in_use_key : (GainKey, int) or None
        The key and K_o cell the gains in use were chosen for.
    """

    key: GainKey
    own_response: bool = False
    identified_ratio: float = 1.0
    in_use: LocalModelUpdate | None = None
    plane_tick: int | None = None
    in_use_key: tuple[GainKey, int] | None = None


@dataclass(frozen=True)
class Known:
    """What has been designed or checked: the table of designs, the checked interim gains per
    (key, cell) and the verified planes per (key, plane cell, design cell) (None: none passed)."""

    table: GainTable
    interim: Mapping[tuple[GainKey, int], GainDesign]
    planes: Mapping[tuple[GainKey, int, int], GainDesign | None]


@dataclass(frozen=True)
class Choice:
    """What renders for one patch.

    Attributes
    ----------
    gains : GainDesign or None
        The gains (None for the rest plane, whose gains are ``rest``, and while waiting).
    source : Source or None
        Where they come from (module docstring); None: nothing may render yet (forces off).
    jobs : tuple of Job
        Work that would give better gains for this patch's key and cell.
    rest : RestPlaneGains or None
        The rest plane's gains when ``source == "rest"``.
    plane_tick : int or None
        The contact's new ``plane_tick`` (:class:`Contact`).
    identified : bool
        A verified plane of a stiffness the own-response check identified renders.
    held : bool
        The gains in use are kept through the contact rather than step what the hand feels
        (:func:`_held_in_hold`).
    """

    gains: GainDesign | None
    source: Source | None
    jobs: tuple[Job, ...] = ()
    rest: RestPlaneGains | None = None
    plane_tick: int | None = None
    identified: bool = False
    held: bool = False

    @property
    def verified(self) -> bool:
        """The gains passed the full-loop check for this patch's key and cell."""
        return self.source in VERIFIED_SOURCES

    @property
    def fallback(self) -> bool:
        """No design (of this client's or the server's) nor verified plane renders."""
        return self.source not in ("rest", "plane", "server", "design", "design-b_o")


def known_gains(
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


def in_use_design(update: LocalModelUpdate | None, rate_ratio: int) -> GainDesign | None:
    """The gains of the update in use as a design (None if nothing renders)."""
    if update is None or update.surface is None or update.choice is None:
        return None
    return known_gains(
        update.k_h, update.i_gain, update.b_h, update.proxy_hold,
        k_o_eff=update.surface.k_o_eff, rate_ratio=rate_ratio,
        delay_ticks=update.choice.delay_ticks, spectral_radius=update.choice.spectral_radius,
        felt_1hz=update.choice.felt_stiffness_ratio_1hz, own_gain=update.own_gain,
    )  # fmt: skip


def recommended(
    rec: RecommendedGains | None,
    options: Options,
    k_o_eff: float,
    delay_ticks: int,
    own: GainDesign | None,
) -> GainDesign | None:
    """The server's recommended gains ``rec`` as a design, if this user may render them and has
    nothing better: within the device's stiffness and damping, of its local model kind, for at
    least ``delay_ticks``; an interim recommendation yields to a design of its own (``own``)."""
    if options.gains != "server" or rec is None:
        return None
    if rec.interim and own is not None:
        return None
    if (
        rec.k_h > options.k_h_max
        or rec.b_h > options.b_h_max + 1e-9
        or (options.mode == "p" and rec.i_gain > 0.0)
        or rec.delay_ticks < delay_ticks
    ):
        return None  # designed for another device, kind or a shorter delay
    return known_gains(
        rec.k_h, rec.i_gain, rec.b_h, rec.proxy_hold,
        k_o_eff=k_o_eff, rate_ratio=options.rate_ratio, delay_ticks=rec.delay_ticks,
        own_gain=rec.own_gain,
    )  # fmt: skip


def table_design(
    table: GainTable, key: GainKey, k_o: float
) -> tuple[GainDesign | None, Literal["design", "design-b_o"] | None]:
    """The table's design for ``key`` at a reported ``k_o`` [N/m] and its source: the one rule by
    which a key meets the table (the client's :func:`choose`, the server's gain advisor).

    The cell's own design (``"design"``). Else, for a key with object damping B_o > 0 (eq. 9;
    the FEM solid's), the design of the same key with B_o = 0 (``"design-b_o"``) where that
    design's coverage (:func:`shared.gains.table_file.b_o_covered`: checked offline on the loop
    with every lattice B_o up to it, :mod:`shared.gains.damping_cover`) reaches the object's own
    B_o, which is below ``key.b_o + 1`` (the key floors it to whole N/m): a
    design for less object damping, the safe side of the paper's eq. 10, verified on the damped
    loop with the hand in it. Else ``(None, None)``: the cell is designed during the session.

    Raises
    ------
    ValueError
        ``k_o`` not a finite stiffness > 0 (:meth:`GainTable.cell`).
    """
    d = table.lookup(key, k_o)
    if d is not None:
        return d, "design"
    if key.b_o > 0.0:
        undamped = replace(key, b_o=0.0)
        d = table.lookup(undamped, k_o)
        # the key's B_o is the reported one floored to whole N/m (make_gain_key): the object's
        # own is below key.b_o + 1, and the design must have passed up to that
        reach = key.b_o + 1.0
        if d is not None and reach <= b_o_covered(table, undamped, table.cell(k_o)):
            return d, "design-b_o"
    return None, None


def covering(known: Known, key: GainKey, cell: int, k_o_eff: float) -> GainDesign | None:
    """Gains designed or checked for this cell and a wider coupling class, if any: checked over a
    K_o range containing this key's (:func:`shared.gains.key.covering_classes`)."""
    for c in covering_classes(key.stiff_ratio):
        wider = replace(key, stiff_ratio=c)
        d = table_design(known.table, wider, k_o_eff)[0]
        if d is None:
            d = known.interim.get((wider, cell))
        if d is not None:
            return d
    return None


def cell_has_gains(
    table: GainTable, interim: Mapping[tuple[GainKey, int], GainDesign], key: GainKey, cell: int
) -> bool:
    """Whether grid cell ``cell`` of ``key`` has verified gains already: a check's (``interim``)
    or the table's for a K_o in the cell (:func:`table_design`, damping coverage included). What
    the client's and the server's checks ahead of need skip."""
    if (key, cell) in interim:
        return True
    return table_design(table, key, table.grid_point(cell) * 1.0001)[0] is not None


def compensated(design: GainDesign) -> bool:
    """Whether ``design`` compensates its own force (C_h > 0, no integral): a held press through
    it is felt as the object's own stiffness (docs/own-force.md)."""
    return design.own_gain > 0.0 and design.i_gain == 0.0


def likely_next(key: GainKey, cell: int) -> tuple[tuple[GainKey, int], ...]:
    """The (key, cell) a contact in ``cell`` of ``key`` most likely needs next, most likely first:
    what the link designs and checks ahead of need.

    The same cell coupled to another user, class 2 when the contact is alone, and the
    :data:`shared.gains.policy.COUPLED_CELLS_BELOW` cells below (class 2 covers every coupling up
    to K_o_stiff / K_o_eff = 2, :func:`covering`, and a second user's press lowers K_o_eff);
    then one more tick of delay, and the cells just below and above (the contact moves, K_o
    changes).
    """
    out: list[tuple[GainKey, int]] = []
    if key.stiff_ratio == 1.0:
        coupled = replace(key, stiff_ratio=2.0)
        out += [(coupled, cell - j) for j in range(COUPLED_CELLS_BELOW + 1)]
    out += [(replace(key, delay_ticks=key.delay_ticks + 1), cell), (key, cell - 1), (key, cell + 1)]
    return tuple(out)


def choose(
    surface: SurfacePatch,
    rec: RecommendedGains | None,
    contact: Contact,
    known: Known,
    options: Options,
) -> Choice:
    """The gains to render ``surface`` with, their source and the jobs that would improve them.

    Parameters
    ----------
    surface : SurfacePatch
        The patch as read from the wire.
    rec : RecommendedGains or None
        The server's recommended gains carried by the patch.
    contact : Contact
        The contact's past (the key, the own-response verdict, the update in use).
    known : Known
        The designs, checks and planes made so far.
    options : Options
        The user's device and local model.

    Returns
    -------
    Choice
        See the module docstring for the order of the sources.

    Raises
    ------
    ValueError
        ``surface.k_o_eff`` is not a finite stiffness > 0 (:meth:`GainTable.cell`).
    """
    key = contact.key
    d = key.delay_ticks
    k_o_eff = surface.k_o_eff
    table = known.table
    cell = table.cell(k_o_eff)
    own, own_source = table_design(table, key, k_o_eff)
    jobs: list[Job] = []
    gains: GainDesign | None = recommended(rec, options, k_o_eff, d, own)
    source: Source | None = (
        ("server-interim" if rec is not None and rec.interim else "server")
        if gains is not None
        else own_source
    )
    if gains is None:
        gains = own
    identified = False
    plane_renders = False
    if contact.own_response:
        # the object yields to this user's force as a spring: of the K_o reported, or of the
        # stiffness the check identified. The plane verified for that stiffness replaces the
        # design made for an object off by 25 % where it is felt closer than the design. In a
        # cell not designed yet the plane checked alone renders meanwhile
        k_id = contact.identified_ratio * k_o_eff
        plane_cell = table.cell(k_id)
        plane_key = (key, plane_cell, cell if own is not None else PLANE_ALONE)
        if plane_key in known.planes:
            plane = known.planes[plane_key]
        else:
            if own is None:
                jobs.append(DesignJob(key, k_o_eff))  # the plane is compared with it once made
            jobs.append(PlaneJob(*plane_key))
            # where the cell has a design the plane renders only once compared with it
            plane = None if own is not None else known.planes.get((key, plane_cell, PLANE_ALONE))
        if plane is not None:
            gains, source, plane_renders = plane.at(k_id), "plane", True
            identified = contact.identified_ratio != 1.0
    in_contact = surface.in_contact or surface.own_force_n > 0.0
    plane_tick = None if not in_contact else surface.tick if plane_renders else contact.plane_tick
    held_back = (
        plane_tick is not None and (surface.tick - plane_tick) / options.sim_rate_hz < HOLD_BACK_S
    )
    if options.rest_plane and surface.rest_plane is not None and not (plane_renders or held_back):
        # the user alone on the object, no verified plane (nor one for HOLD_BACK_S in this
        # contact): the rest plane, with gains of the patch alone
        if gains is None:
            jobs.append(DesignJob(key, k_o_eff))  # for when another user joins
        rest = rest_plane_gains(
            surface.k_o, surface.b_o, options.sim_rate_hz, options.k_h_max, options.b_h_max,
            servo_period_s=1.0 / options.servo_rate_hz,
        )  # fmt: skip
        return Choice(None, "rest", tuple(jobs), rest=rest, plane_tick=plane_tick)
    if gains is None:
        gains, source, more = without_design(
            key, k_o_eff, known, contact.in_use, options.rate_ratio
        )
        jobs += more
        if gains is None or (source not in VERIFIED_SOURCES and contact.in_use is None):
            # a first contact renders only verified gains: it waits with forces off
            return Choice(None, None, tuple(jobs), plane_tick=plane_tick)
    held = _held_in_hold(surface, contact, known, key, cell, gains, source)
    if held is not None:
        gains, source = held
        return Choice(gains, source, tuple(jobs), plane_tick=plane_tick, held=True)
    return Choice(gains, source, tuple(jobs), plane_tick=plane_tick, identified=identified)


def static_felt_stiffness(k_h: float, i_gain: float, own_gain: float, k_o: float) -> float:
    """The stiffness [N/m] a still hand feels through a local model of these gains on an object
    of ``k_o`` [N/m]: the coupling's steady compliance ``1/K_h - C_h`` (``-C_h`` with an integral,
    which carries the force at rest) in series with ``1/K_o``, at most ten times K_o (a
    coupling stiffer than the object). K_o itself with C_h K_h = 1; K_o / 5 for K_h = K_o / 4
    without compensation."""
    c = -own_gain if i_gain > 0.0 else 1.0 / k_h - own_gain
    return 1.0 / max(c + 1.0 / k_o, 0.1 / k_o)


def _held_in_hold(
    surface: SurfacePatch,
    contact: Contact,
    known: Known,
    key: GainKey,
    cell: int,
    gains: GainDesign | None,
    source: Source | None,
) -> tuple[GainDesign, Source] | None:
    """The gains in use, kept through a contact, where the choice would step what the hand feels.

    In contact, for the key and cell the gains in use were chosen for (their delay, coupling
    class and K_o cell unchanged: they are still verified for this patch), checked interim or
    covering gains are kept when a design (this client's or the server's) arrives whose static
    felt stiffness differs from theirs by more than :data:`shared.gains.policy.HOLD_FELT_STEP`
    (a stiffness JND): on a busy machine a design arrives seconds into a press, and the hand
    felt the object's stiffness jump fivefold under it. The design renders from the next contact
    on, or at once where the key or the cell changes. Returns the gains to keep and their source,
    or None to render the choice.
    """
    in_use = contact.in_use
    if (
        gains is None
        or source not in ("server", "design", "design-b_o")
        or in_use is None
        or in_use.choice is None
        or in_use.choice.source not in ("interim", "covering", "server-interim")
        or contact.in_use_key != (key, cell)
        or not (surface.in_contact or surface.own_force_n > 0.0)
    ):
        return None
    k_o = surface.k_o_eff
    now = static_felt_stiffness(in_use.k_h, in_use.i_gain, in_use.own_gain, k_o)
    new = static_felt_stiffness(gains.k_h, gains.i_gain, gains.own_gain, k_o)
    if max(now, new) / min(now, new) <= HOLD_FELT_STEP:
        return None
    # the same source as in use, looked up again (its gains over this cell, as verified); the
    # server's interim gains are the gains in use (checked over the cell, unscaled)
    kept = (
        known.interim.get((key, cell))
        if in_use.choice.source == "interim"
        else covering(known, key, cell, k_o)
        if in_use.choice.source == "covering"
        else in_use_design(in_use, round(in_use.hold_ticks))
    )
    return None if kept is None else (kept, in_use.choice.source)  # type: ignore[return-value]


def without_design(
    key: GainKey,
    k_o_eff: float,
    known: Known,
    in_use: LocalModelUpdate | None,
    rate_ratio: int,
    *,
    verified_only: bool = False,
) -> tuple[GainDesign | None, Source | None, tuple[Job, ...]]:
    """The gains for ``k_o_eff`` [N/m] of ``key`` while its cell has no design (steps 5-7 of the
    module docstring), their source and the jobs to ask: the cell's design always, and a check
    where nothing verified renders. The server's gain advisor (:class:`server.gains.GainAdvisor`)
    asks this too and recommends only verified gains (:data:`VERIFIED_SOURCES`): with
    ``verified_only`` the unverified ones (the nearest designed cell, the gains in use) are not
    looked for, as gains or as a check's candidates: that look scans the whole table
    (:meth:`GainTable.fallback`), and on the server it ran every tick for every user without
    verified gains, for gains it then dropped (docs/fem.md, "Under load").

    Returns ``(None, None, jobs)`` when nothing is known for the cell and nothing is in use (or
    nothing verified, with ``verified_only``).
    """
    table = known.table
    cell = table.cell(k_o_eff)
    jobs: list[Job] = [DesignJob(key, k_o_eff)]
    interim = known.interim.get((key, cell))
    if interim is not None:
        return interim, "interim", tuple(jobs)
    wider = covering(known, key, cell, k_o_eff)
    if wider is not None:
        if key.own_force and not compensated(wider):
            # a wider class's design is verified here but, without own-force compensation (the
            # wide classes' designs are mostly the paper's PI), felt softer than the object while
            # the hand moves (a slide over a lump, docs/palpation.md). It renders while a check
            # for this key is asked (a fraction of a second): the compensated gains known, then
            # the generic compensated rungs (:func:`shared.gains.interim.interim_design`)
            ahead = (
                ()
                if verified_only
                else (known.table.fallback(key, k_o_eff), in_use_design(in_use, rate_ratio))
            )
            jobs.append(
                CheckJob(key, cell, tuple(c for c in ahead if c is not None and compensated(c)))
            )
        return wider, "covering", tuple(jobs)
    if verified_only:
        return None, None, (*jobs, CheckJob(key, cell, ()))
    # nothing verified for this key and cell: have gains checked (fast) and meanwhile keep the
    # nearest designed cell (no stiffer relative to K_o) or the gains in use
    near = table.fallback(key, k_o_eff)
    current = in_use_design(in_use, rate_ratio)
    jobs.append(CheckJob(key, cell, tuple(c for c in (near, current) if c is not None)))
    if near is not None:
        return near, "near", tuple(jobs)
    if current is None:
        return None, None, tuple(jobs)
    assert in_use is not None and in_use.choice is not None and in_use.surface is not None
    if key.stiff_ratio > 1.0 or key.delay_ticks > in_use.choice.delay_ticks:
        # the gains in use were not designed for this coupled contact's stiff modes or for this
        # much delay (designs for fewer ticks than the loop has were unstable in every case
        # tried): the unverified fallback, without its integral
        scale = min(1.0, k_o_eff / in_use.surface.k_o_eff)
        fallback = replace(
            current,
            k_h=min(current.k_h * scale, FALLBACK_K_RATIO * k_o_eff),
            i_gain=0.0,
            b_h=key.b_h_max,
            proxy_hold="zoh",
            mode="p",
            own_gain=0.0,
        )
        return fallback, "fallback", tuple(jobs)
    return current, "in-use", tuple(jobs)
