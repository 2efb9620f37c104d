"""Recommended gains for every user's local model: the Python client's design, run by the server.

A client in any language may render the gains the server sends in each patch
(``patch.gains``, :class:`shared.protocol.RecommendedGains`) instead of porting the full-loop
design. The server designs them exactly as :class:`client.session.ClientSession` does:
one :class:`shared.gains.table.GainTable` keyed by the user's declared device (maximum stiffness
and damping, servo rate, P or PI local model), its loop delay in whole simulation ticks (from the
round trips the user reports in ``state``), the object damping ``b_o`` and the coupling class
``K_o_stiff / K_o_eff`` (docs/coupled-users.md), with a grid cell per ``K_o_eff``.

Pure and cheap: :meth:`GainAdvisor.recommend` is a dictionary lookup, never a design. A missing
cell is queued (:meth:`GainAdvisor.next_job` hands out the most urgent first); the I/O layer runs
the jobs in a worker process (:func:`run_job`) and hands the results back with :meth:`GainAdvisor.store`. Until then the
patch carries verified interim gains (:func:`shared.gains.interim.interim_design`, a fraction of
a second) or, for the very first moment of a new key, no gains at all.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from haptic_collab.client.workers import timed
from haptic_collab.server.contact_stiffness import coupled_groups
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, HandBox
from haptic_collab.shared.gains.b_o_band import BandedGains, b_o_band, check_band
from haptic_collab.shared.gains.choose import (
    VERIFIED_SOURCES,
    DesignJob,
    Known,
    cell_has_gains,
    table_design,
    without_design,
)
from haptic_collab.shared.gains.delay import DelayHold, measured_delay_ticks
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.group import (
    PairBucket,
    PairCase,
    PairVerdict,
    check_pair,
    pair_points,
)
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.gains.key import (
    GainKey,
    held_stiff_ratio,
    loop_delay_ticks,
    make_gain_key,
    stiff_ratio_class,
)
from haptic_collab.shared.gains.modal_guard import ModalCase, ModalVerdict, guard
from haptic_collab.shared.gains.policy import (
    K_O_GRID_RATIO,
    MODAL_CHECK_MODES,
    PAIR_LOOKAHEAD_M,
    PAIR_QUEUE,
    RTT_WINDOW,
    STIFF_RATIO_CLASSES,
)
from haptic_collab.shared.gains.table import GainTable, design_cell
from haptic_collab.shared.gains.table_file import load_shipped
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.modal_loop import ContactModes
from haptic_collab.shared.protocol import Hello, RecommendedGains
from haptic_collab.shared.stability import rate_ratio

if TYPE_CHECKING:
    from haptic_collab.server.world import Coupling

log = logging.getLogger("haptic.server")

JobKind = Literal["interim", "band", "ahead", "design", "pair", "modal"]

#: Band checks (:mod:`shared.gains.b_o_band`) and checks of the cells beside a damped key's
#: (``ahead``) waiting at most, each; the oldest are dropped (a hand sliding over a damped solid
#: has left their keys).
BAND_QUEUE = 4

#: Modal verdicts (:meth:`GainAdvisor.guard_modes`) kept, the oldest dropped first: a hand that
#: slides for hours over a solid meets a new contact every few millimetres.
MODAL_VERDICTS_KEPT = 4096

#: The jobs a worker does only when it has CPU to spare (:meth:`GainAdvisor.next_job`,
#: ``idle``): checks no contact waits for.
IDLE_KINDS: tuple[JobKind, ...] = ("band", "ahead")


@dataclass(frozen=True)
class GainJob:
    """One piece of design work for the worker: ``kind`` for grid cell ``cell`` of ``key``; a
    ``pair`` job checks ``pair`` (:mod:`shared.gains.group`; ``key`` and ``cell`` are then the
    partner's); a ``band`` job checks ``design``, the interim gains found for ``key``, over the
    band of B_o around ``key.b_o`` (:func:`shared.gains.b_o_band.check_band`); an ``ahead`` job
    is an interim check of a cell beside one a damped contact needed, asked before it is
    needed; a ``modal`` job checks ``modal``, the gains recommended for a FEM contact, on the
    contact's own modes (:func:`shared.gains.modal_guard.guard`)."""

    kind: JobKind
    key: GainKey
    cell: int
    pair: PairCase | None = None
    design: GainDesign | None = None
    modal: ModalCase | None = None


@dataclass
class _User:
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=RTT_WINDOW))
    stiff_ratio: float = 1.0
    measured: int = 0
    stale: bool = False
    #: The round trip [s] the client measures its delay from (``state.delay_rtt_ms``).
    delay_rtt_s: float | None = None
    delay: DelayHold = field(default_factory=DelayHold)
    #: The key of the user's last patch, and what was recommended with it.
    key: GainKey | None = None
    rec: RecommendedGains | None = None
    #: In contact, alone on its class-1 design when its contact last coupled: it may keep that
    #: design while its pair verifies (:meth:`GainAdvisor.hold_pairs`).
    may_hold: bool = False
    #: It keeps its uncoupled design this tick (a verified pair).
    holding: bool = False
    #: The design behind ``rec``, its key and K_o cell (for the modal guard: :meth:`GainAdvisor.guard_modes`).
    design: GainDesign | None = None
    design_key: GainKey | None = None
    cell: int = 0
    #: The modal check of what this user renders now (contact, design key, gains), and whether
    #: those are interim gains (:meth:`GainAdvisor.guard_modes`).
    modal_job: tuple[int, GainKey, tuple[Any, ...]] | None = None
    modal_interim: bool = False
    #: The design this user waits for (its key has none; None: not waiting), and its turn: when
    #: it began to wait or was last given a design job, whichever is later
    #: (:meth:`GainAdvisor.next_job`).
    design_want: tuple[JobKind, GainKey, int] | None = None
    design_turn: int = 0


class GainAdvisor:
    """Recommended gains per user, from designs computed off the simulation tick.

    Parameters
    ----------
    sim_rate_hz : float
        The room's simulation rate [Hz].
    margin : float
        K_o margin of every design (the Python client's default, 0.15).
    theta_m : float
        The integration threshold theta [m] recommended with every PI design (eq. 17; the
        Python client's default 1 mm, which it also uses as the scale of eq. 18).
    hand_box : HandBox
        Hands every design is stable for.
    grid_ratio : float
        K_o grid ratio of the gain table.
    shipped : bool
        Start the table with the shipped tables (:func:`shared.gains.table_file.load_shipped`:
        the built-in device profiles' designs, made offline); their files are read here, once.
    """

    def __init__(
        self,
        sim_rate_hz: float,
        *,
        margin: float = 0.15,
        theta_m: float = 0.001,
        hand_box: HandBox = DEFAULT_HAND_BOX,
        grid_ratio: float = K_O_GRID_RATIO,
        shipped: bool = True,
    ) -> None:
        self.sim_rate_hz = float(sim_rate_hz)
        self.margin = float(margin)
        self.theta_m = float(theta_m)
        self.table = GainTable(hand_box, grid_ratio)
        #: The shipped tables loaded into it ({file: cells, or why it was refused}).
        self.shipped = load_shipped(self.table) if shipped else {}
        self.interim: dict[tuple[GainKey, int], GainDesign] = {}
        #: Pair verdicts (:mod:`shared.gains.group`) by bucket; None: no check is possible there.
        self.pairs: dict[PairBucket, PairVerdict | None] = {}
        self._pair_queue: dict[PairBucket, PairCase] = {}
        #: Patches a user rendered its uncoupled design beside a coupled partner, by a verified
        #: pair (:meth:`hold_pairs`); pair checks asked.
        self.held_patches = 0
        self.pair_checks = 0
        self._queued: dict[tuple[JobKind, GainKey, int], None] = {}
        self._asked: set[tuple[JobKind, GainKey, int]] = set()
        #: Interim gains waiting to be checked over their B_o band, the newest last.
        self._band_queue: dict[tuple[GainKey, int], GainDesign] = {}
        #: Cells beside a damped contact's to check ahead of need, the newest last.
        self._ahead_queue: dict[tuple[GainKey, int], None] = {}
        #: Keys given interim gains by a band check before their own was asked.
        self.band_keys = 0
        self._users: dict[str, _User] = {}
        #: Modal verdicts (:mod:`shared.gains.modal_guard`) by (contact, design key, gains); None:
        #: asked, not back yet. And the newest verdict for (design key, gains) at any contact:
        #: what a contact not checked yet renders meanwhile.
        self.modal: dict[tuple[int, GainKey, tuple[Any, ...]], ModalVerdict | None] = {}
        self._modal_near: dict[tuple[GainKey, tuple[Any, ...]], ModalVerdict] = {}
        self._modal_queue: dict[tuple[int, GainKey, tuple[Any, ...]], ModalCase] = {}
        #: Patches whose gains the modal guard changed; patches it had no passing gains for.
        self.modal_changed = 0
        self.modal_unmet = 0
        #: A design was handed out since the last modal check: a waiting check goes next.
        self._modal_turn = False
        #: Numbers the users' waits for a design, so the longest wait is served first.
        self._turns = itertools.count()
        #: Lookups answered with gains / without (no design or interim yet).
        self.hits = 0
        self.misses = 0

    # ---------------------------------------------------------------- per user
    def observe_rtt(
        self, user: str, rtt_ms: float | None, delay_rtt_ms: float | None = None
    ) -> None:
        """Record the round trips [ms] the user reported in ``state``: ``delay_rtt_ms``, the one
        the client measures its loop delay from, is used as it is (the advisor then designs for
        the delay the client does); a client that does not send it has the delay measured from
        its reported ``rtt_ms`` over the last :data:`shared.gains.policy.RTT_WINDOW` states.
        None, negative or non-finite: not recorded."""
        u = self._users.setdefault(user, _User())
        if delay_rtt_ms is not None and math.isfinite(delay_rtt_ms) and delay_rtt_ms >= 0.0:
            u.delay_rtt_s = min(delay_rtt_ms, 10_000.0) / 1e3
            u.stale = True
        if rtt_ms is None or not math.isfinite(rtt_ms) or rtt_ms < 0.0:
            return
        u.rtt_s.append(min(rtt_ms, 10_000.0) / 1e3)
        u.stale = True  # the delay is recomputed when the next patch asks for it

    def forget(self, user: str) -> None:
        """The user left."""
        self._users.pop(user, None)

    def delay_ticks(self, user: str, tick: int | None = None, in_contact: bool = False) -> int:
        """The user's loop delay [whole simulation ticks], by the client's rule: measured as
        :func:`shared.gains.delay.measured_delay_ticks`, and with the simulation ``tick`` (its
        time) held as :class:`shared.gains.delay.DelayHold` holds it (rises at once, falls only
        out of contact, after :data:`shared.gains.policy.DELAY_FALL_S`); without ``tick``, the
        larger of the measured delay and the one held."""
        u = self._users.get(user)
        if u is None:
            return 0
        if u.stale:
            age = 0.5 / self.sim_rate_hz  # the client's state interval
            if u.delay_rtt_s is not None:
                u.measured = loop_delay_ticks(u.delay_rtt_s, age, self.sim_rate_hz)
            else:
                u.measured = measured_delay_ticks(list(u.rtt_s), age, self.sim_rate_hz)
            u.stale = False
        if tick is None:
            return u.measured if u.delay.held is None else max(u.measured, u.delay.held)
        return u.delay.update(u.measured, tick / self.sim_rate_hz, in_contact)

    def key(
        self,
        user: str,
        hello: Hello,
        b_o: float,
        k_o_eff: float,
        k_o_stiff: float,
        tick: int | None = None,
        in_contact: bool = False,
    ) -> GainKey:
        """The gain key of ``user`` for this patch at simulation ``tick`` (raises ValueError for
        unsupported rates)."""
        rate_ratio(hello.servo_rate_hz, self.sim_rate_hz)  # N must be whole
        u = self._users.setdefault(user, _User())
        u.stiff_ratio = held_stiff_ratio(u.stiff_ratio, k_o_eff, k_o_stiff)  # the client's rule
        device = hello.device
        return make_gain_key(
            servo_rate_hz=hello.servo_rate_hz,
            sim_rate_hz=self.sim_rate_hz,
            delay_ticks=self.delay_ticks(user, tick, in_contact),
            mode=hello.local_model,
            margin=self.margin,
            k_h_max=1000.0 if device is None else device.max_stiffness_n_per_m,
            b_h_max=0.0 if device is None else device.max_damping_n_s_per_m,
            b_o=b_o,
            stiff_ratio=u.stiff_ratio,
        )

    def recommend(
        self,
        user: str,
        hello: Hello,
        *,
        k_o_eff: float,
        k_o_stiff: float,
        b_o: float,
        tick: int | None = None,
        in_contact: bool = False,
    ) -> RecommendedGains | None:
        """The gains to send ``user`` with this patch of simulation ``tick`` (the user
        ``in_contact`` or not: the loop delay's hold, :meth:`delay_ticks`), or None while none
        are verified yet.

        A dictionary lookup (:func:`shared.gains.choose.table_design`: a key with object
        damping gets the shipped design for B_o = 0 where its offline check covers that B_o,
        as on the client); a missing cell queues an interim check and a design
        (:meth:`next_job`). Never raises for a hostile or odd user: unsupported rates give None.
        """
        if not (math.isfinite(k_o_eff) and k_o_eff > 0.0):
            return None
        try:
            key = self.key(user, hello, b_o, k_o_eff, k_o_stiff, tick, in_contact)
        except ValueError:
            return None
        cell = self.table.cell(k_o_eff)
        # the client's own rule for the table (a damped key gets the design for B_o = 0 its
        # offline check covers: shared.gains.choose.table_design)
        design = table_design(self.table, key, k_o_eff)[0]
        interim = design is None
        if design is None:
            # the client's own rule for a cell without a design (shared.gains.choose), of which
            # the server recommends only verified gains: checked interim or covering gains
            known = Known(self.table, self.interim, {})
            n = rate_ratio(hello.servo_rate_hz, self.sim_rate_hz)
            design, source, jobs = without_design(key, k_o_eff, known, None, n, verified_only=True)
            for job in jobs:
                self._want("design" if isinstance(job, DesignJob) else "interim", key, cell)
            if source not in VERIFIED_SOURCES:
                design = None
        u = self._users[user]
        u.key = key
        if interim:
            if u.design_want is None:  # it begins to wait
                u.design_turn = next(self._turns)
            u.design_want = ("design", key, cell)
        else:
            u.design_want = None
        if design is None:
            self.misses += 1
            u.rec = None
            return None
        self.hits += 1
        u.rec = self._rec(design, key, interim)
        u.design, u.design_key, u.cell = design, key, cell
        return u.rec

    def _rec(self, design: GainDesign, key: GainKey, interim: bool) -> RecommendedGains:
        return RecommendedGains(
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            theta_m=self.theta_m if design.i_gain > 0.0 else 0.0,
            delay_ticks=key.delay_ticks,
            interim=interim,
            own_gain=design.own_gain,
        )

    # ---------------------------------------------------------------- coupled pairs
    def hold_pairs(
        self,
        coupling: Coupling,
        patches: Mapping[str, SurfacePatch],
        recs: Mapping[str, RecommendedGains | None],
    ) -> dict[str, RecommendedGains | None]:
        """This tick's recommendations with a resting user's uncoupled design kept where its
        coupled pair, as rendered, is verified (:mod:`shared.gains.group`); call after
        :meth:`recommend` for every user of the tick.

        A user in contact whose recommendation is its class-1 design (alone on the object, or
        uncoupled) may keep that design when another user's press couples its contact: while
        the group is that pair, the partner renders its coupled key's design
        and the pair's verdict for the bucket (the held user's K_o cell, the partner's K_o_eff
        cell, the coupling class) meets the margin; alone again (the partner left), it keeps
        its class-1 design at its K_o. A verdict not known when the coupling arrives, or one
        that fails, ends the hold for the rest of the contact: the user renders its coupled
        key's design, designed for a rigid partner, as without this check (one step, never a
        return). A contact is the probe in the surface, or within the world's proximity of it
        while holding: a light touch the partner's press lifts off for a moment keeps its hold.
        Only one user of a pair holds. Ahead of need (:data:`shared.gains.policy.PAIR_LOOKAHEAD_M`),
        while a resting user is uncoupled, the pair it would make with every user within that
        distance of the surface is queued for the design worker (:meth:`next_job`), so the
        verdict is there when the press arrives.

        Parameters
        ----------
        coupling : server.world.Coupling
            The world's contacts of this tick (compliance, penetrations).
        patches : mapping user -> SurfacePatch
            This tick's patches.
        recs : mapping user -> RecommendedGains or None
            What :meth:`recommend` answered this tick.

        Returns
        -------
        dict user -> RecommendedGains or None: ``recs`` with the holding users' replaced.
        """
        out = dict(recs)
        names = list(coupling.names)
        if not names:
            return out
        c = np.asarray(coupling.compliance, dtype=np.float64)
        pen = np.asarray(coupling.penetration_m, dtype=np.float64)
        near = [i for i in range(len(names)) if pen[i] > -coupling.proximity_m]
        group_of: dict[str, list[str]] = {}
        if near:
            for g in coupled_groups(c[np.ix_(near, near)]):
                members = [names[near[int(j)]] for j in g]
                for m in members:
                    group_of[m] = members
        for i, name in enumerate(names):
            u = self._users.get(name)
            patch = patches.get(name)
            if u is None or patch is None or u.key is None:
                continue
            was_holding, u.holding = u.holding, False
            touching = patch.in_contact or patch.own_force_n > 0.0
            if not touching and not (u.may_hold and pen[i] > -coupling.proximity_m):
                # out of contact and away: a new contact starts over (a light touch that the
                # partner's press lifts off for a tick, still near, keeps its hold)
                u.may_hold = False
                continue
            rec = recs.get(name)
            if u.key.stiff_ratio == 1.0:
                if touching:
                    u.may_hold = rec is not None and not rec.interim
                if u.may_hold:
                    self._look_ahead(i, names, c, pen)
                continue
            if not u.may_hold:
                continue
            group = group_of.get(name, [name])
            held, why = self._held_design(name, u, patch, group, patches)
            if held is None:
                u.may_hold = False
                log.info(
                    "user %s: its contact coupled to %s, its coupled design renders (%s%s)",
                    name, ", ".join(g for g in group if g != name) or "nobody",
                    "after a hold: " if was_holding else "", why,
                )  # fmt: skip
                continue
            if not was_holding:
                log.info("user %s keeps its uncoupled gains (%s)", name, why)
            u.holding = True
            self.held_patches += 1
            out[name] = self._rec(held, u.key, interim=False)
            u.design, u.design_key = held, replace(u.key, stiff_ratio=1.0)
            u.cell = self.table.cell(patch.k_o)
        return out

    # ---------------------------------------------------------------- a FEM contact's modes
    def guard_modes(
        self,
        recs: Mapping[str, RecommendedGains | None],
        contact_of: Callable[[str], int | None],
        modes_of: Callable[[str], ContactModes | None],
    ) -> dict[str, RecommendedGains | None]:
        """This tick's recommendations with each FEM contact's checked on the solid's own modes
        (:mod:`shared.gains.modal_guard`); call after :meth:`hold_pairs`.

        A user whose object has modes (``contact_of(user)``: the object's key of its contact,
        None for an object without modes) renders its design where the check passed, the
        softer or more damped gains the check found where it did not, and, until its own
        contact's check is back (a job for the design worker, :meth:`next_job`), the verdict
        found last for the same design at another contact of the object: a hand sliding over
        the solid changes contact every few millimetres. ``modes_of(user)`` gives the contact's
        modes when a check is queued. Where no gains pass the check, the design renders as it
        is (counted in ``modal_unmet``).
        """
        out = dict(recs)
        for name, rec in recs.items():
            u = self._users.get(name)
            if rec is None or u is None or u.design is None or u.design_key is None:
                continue
            contact = contact_of(name)
            u.modal_job = None
            if contact is None:
                continue
            gains = _gains_of(rec)
            job = (contact, u.design_key, gains)
            u.modal_job, u.modal_interim = job, rec.interim
            verdict = self.modal.get(job)
            if job not in self.modal:
                self._want_modal(job, u, modes_of(name))
            if verdict is None:
                verdict = self._modal_near.get((u.design_key, gains))
            if verdict is None:
                continue
            if verdict.design is None:
                self.modal_unmet += 1
                continue
            if verdict.changed:
                self.modal_changed += 1
                d = verdict.design
                out[name] = rec.model_copy(
                    update={
                        "k_h": d.k_h, "i_gain": d.i_gain, "b_h": d.b_h,
                        "proxy_hold": d.proxy_hold, "own_gain": d.own_gain,
                    }
                )  # fmt: skip
        return out

    def _want_modal(
        self, job: tuple[int, GainKey, tuple[Any, ...]], u: _User, modes: ContactModes | None
    ) -> None:
        """Queue the modal check of ``job`` (what ``u`` renders now: one check waits per user, so
        a room of many users never drops a current check to ask it again every tick)."""
        assert u.design is not None and u.design_key is not None
        self.modal[job] = None
        while len(self.modal) > MODAL_VERDICTS_KEPT:
            del self.modal[next(iter(self.modal))]  # the oldest: asked again if met again
        if modes is None or modes.mode_count == 0:
            return
        case = ModalCase(job[0], u.design_key, u.cell, u.design, modes.reduced(MODAL_CHECK_MODES))
        self._modal_queue[job] = case
        self._modal_rendered()  # at most one waiting per user

    def _held_design(
        self,
        name: str,
        u: _User,
        patch: SurfacePatch,
        group: list[str],
        patches: Mapping[str, SurfacePatch],
    ) -> tuple[GainDesign | None, str]:
        """The class-1 design ``name`` keeps this tick, or None where its hold ends, and why."""
        assert u.key is not None
        held_key = replace(u.key, stiff_ratio=1.0)
        if not (math.isfinite(patch.k_o) and patch.k_o > 0.0):
            return None, "no K_o"
        design = table_design(self.table, held_key, patch.k_o)[0]
        if design is None:
            return None, "no uncoupled design at its K_o"
        if len(group) > 2:
            return None, f"a group of {len(group)}"
        if len(group) == 1:
            return design, "alone"  # alone again: its own verified design
        partner = group[0] if group[1] == name else group[1]
        p, pp = self._users.get(partner), patches.get(partner)
        if p is None or pp is None or p.key is None or p.rec is None or p.rec.interim:
            return None, "the partner has no design"
        if p.holding or p.key.stiff_ratio == 1.0:
            return None, "the partner holds"
        try:
            ratio_class = stiff_ratio_class(pp.k_o_eff, max(pp.k_o_eff, pp.k_o_stiff))
            bucket = PairBucket(
                held_key, self.table.cell(patch.k_o), p.key, self.table.cell(pp.k_o_eff),
                ratio_class,
            )  # fmt: skip
        except ValueError:
            return None, "no K_o_eff"
        if bucket not in self.pairs:
            self._want_pair(bucket)
            return None, "the pair not checked in time"  # the coupled design (one step)
        verdict = self.pairs[bucket]
        if verdict is None:
            return None, "the pair not checked in time"
        if not verdict.meets_margin:
            return None, f"the pair misses the margin: radius {verdict.margin_radius:.3f}"
        p.may_hold = False  # one user of a pair holds: the verdict is for the other's design
        self._want_near(bucket)  # where the press goes next, while this one holds
        return design, "verified"

    def _want_near(self, bucket: PairBucket) -> None:
        """Queue the buckets a press moves a verified pair to next: the partner's K_o_eff a cell
        lower or higher, and the next coupling class (a deeper press couples more)."""
        near = [replace(bucket, partner_cell=bucket.partner_cell + d) for d in (-1, 1)]
        i = STIFF_RATIO_CLASSES.index(bucket.ratio_class)
        up = STIFF_RATIO_CLASSES[min(i + 1, len(STIFF_RATIO_CLASSES) - 1)]
        if math.isfinite(up) and up != bucket.ratio_class:
            key = replace(bucket.partner_key, stiff_ratio=max(up, bucket.partner_key.stiff_ratio))
            near.append(replace(bucket, partner_key=key, ratio_class=up))
        for b in near:
            if b not in self.pairs:
                self._want_pair(b)

    def _look_ahead(self, i: int, names: list[str], c: np.ndarray, pen: np.ndarray) -> None:
        """Queue the pair checks resting user ``names[i]`` would need if a user within
        :data:`shared.gains.policy.PAIR_LOOKAHEAD_M` of the surface pressed where its probe is."""
        u = self._users[names[i]]
        assert u.key is not None
        for j, other in enumerate(names):
            p = self._users.get(other)
            if j == i or p is None or p.key is None or not pen[j] > -PAIR_LOOKAHEAD_M:
                continue
            k_i, k_j = 1.0 / c[i, i], 1.0 / c[j, j]
            if not (math.isfinite(k_i) and math.isfinite(k_j) and k_i > 0.0 and k_j > 0.0):
                continue
            # a negative coupling (a press here lifts the surface there) is the same loop: the
            # other user's states negated (shared.gains.group)
            coupling = min(abs(float(c[i, j])) * math.sqrt(k_i * k_j), 1.0 - 1e-9)
            if coupling <= 1e-9:
                continue
            ratio = (1.0 + coupling) / (1.0 - coupling)
            k_eff = k_j / (1.0 + coupling)
            ratio_class = stiff_ratio_class(1.0, ratio)
            partner_key = replace(p.key, stiff_ratio=max(ratio_class, p.key.stiff_ratio))
            bucket = PairBucket(
                replace(u.key, stiff_ratio=1.0), self.table.cell(k_i), partner_key,
                self.table.cell(k_eff), ratio_class,
            )  # fmt: skip
            if bucket not in self.pairs:
                self._want_pair(bucket)
            elif (v := self.pairs[bucket]) is not None and v.meets_margin:
                self._want_near(bucket)  # verified: then where the press may go
            # and the resting user's own coupled key, should the pair not hold: checked gains
            # for it from the press's first patch, rather than a wider class's paper PI
            self._check_ahead(replace(u.key, stiff_ratio=ratio_class), k_i / (1.0 + coupling))

    def _check_ahead(self, key: GainKey, k_o_eff: float) -> None:
        """Queue interim checks for ``key`` in the cell of ``k_o_eff`` [N/m] and the two beside
        it, where neither the table (:func:`shared.gains.choose.table_design`) nor a check has
        gains yet: a contact about to couple has its coupled key's gains verified before the
        press arrives (each check 0.05-0.5 s in the check worker)."""
        cell = self.table.cell(k_o_eff)
        for c in (cell + 1, cell - 1, cell):  # the newest is checked first: the cell itself
            if not cell_has_gains(self.table, self.interim, key, c):
                self._want("interim", key, c)

    def _want_pair(self, bucket: PairBucket) -> None:
        """Queue the check of ``bucket`` (once; the newest first, at most
        :data:`shared.gains.policy.PAIR_QUEUE` waiting)."""
        if bucket in self._pair_queue:
            return
        points = pair_points(
            bucket, lambda key, k_o: table_design(self.table, key, k_o)[0], self.table.grid_point
        )
        if points is None:
            self.pairs[bucket] = None  # a design missing or a rigid class: no hold there
            return
        held, partner = bucket.held_key, bucket.partner_key
        b_o: tuple[tuple[float, float], ...] = ((0.0, 0.0),)
        if held.b_o > 0.0 or partner.b_o > 0.0:
            b_o += ((held.b_o, partner.b_o),)
        self._pair_queue[bucket] = PairCase(
            bucket, points, b_o, held.servo_rate_hz, held.sim_rate_hz,
            (held.delay_ticks, partner.delay_ticks),
            held.margin, self.table.hand_box,
        )  # fmt: skip
        while len(self._pair_queue) > PAIR_QUEUE:
            del self._pair_queue[next(iter(self._pair_queue))]

    def _modal_rendered(self) -> dict[tuple[int, GainKey, tuple[Any, ...]], bool]:
        """The modal checks of what users render now (whether each is of interim gains), with
        every other check dropped from the queue unchecked, to be asked again should its gains
        render again."""
        now = {u.modal_job: u.modal_interim for u in self._users.values() if u.modal_job}
        for job in [j for j in self._modal_queue if j not in now]:
            del self._modal_queue[job]
            if self.modal.get(job, 0) is None:
                del self.modal[job]
        return now

    def _next_modal(self) -> ModalCase | None:
        """The modal check to run next: of the gains a user renders now, a design's before
        interim gains' (which a design replaces within seconds, often before their check is
        back), the newest first. Checks of gains nobody renders any more are dropped unchecked
        (asked again should they render again): a check takes 0.26-1.0 s of CPU on the liver
        sphere, and in the demo a resting user's check waited behind checks of gains it had
        left."""
        now = self._modal_rendered()
        if not self._modal_queue:
            return None
        designs = [j for j in self._modal_queue if not now[j]]
        job = (designs or list(self._modal_queue))[-1]  # the newest of its kind
        return self._modal_queue.pop(job)

    # ---------------------------------------------------------------- work for the worker
    def _longest_wait(
        self, jobs: list[tuple[JobKind, GainKey, int]]
    ) -> tuple[JobKind, GainKey, int] | None:
        """The queued design of the user that has waited longest for one (since it began to
        wait, or since its last design job was handed out), which then goes to the back of
        the line; None where no user waits for a queued design."""
        queued = set(jobs)
        waiting = [u for u in self._users.values() if u.design_want in queued]
        if not waiting:
            return None
        u = min(waiting, key=lambda w: w.design_turn)
        u.design_turn = next(self._turns)
        return u.design_want

    def _want(self, kind: JobKind, key: GainKey, cell: int) -> None:
        job = (kind, key, cell)
        if job not in self._asked:
            self._asked.add(job)
            self._queued[job] = None

    def next_job(self, only: JobKind | None = None, idle: bool = True) -> GainJob | None:
        """The most urgent queued job (``only`` one of that kind; with ``idle`` False no band
        check or check ahead: :data:`IDLE_KINDS`), removed from the queue; None when there is
        none.

        Interim checks come first (they let a user's forces come on within a fraction of a
        second), then designs, then band checks (a hand sliding over a damped solid changes
        key with every whole N/m of B_o: interim gains checked over a band spare the keys next
        to it their own check, :mod:`shared.gains.b_o_band`), then pair checks
        (:meth:`hold_pairs`: they spare a felt step, where a design replaces interim gains; on
        the FEM palpation demo, pair checks before designs left B on interim gains for 339 of
        400 patches against 174); within a kind the most recently asked first: a user moving
        over the object asks for one K_o cell after another, and the cell it is in now matters
        more than the ones it has left (those are still designed later, when nothing newer
        waits). Before those, though, the designs users wait for: of the keys users render now
        without a design, the key of the user that has waited longest (since it began to wait,
        or since its last design job was handed out), so users take turns: with the newest
        alone, a hand sweeping over a FEM solid asks a new key faster than designs finish, and
        a resting user's design waited behind every one of them (docs/gains.md, "Which design
        the server runs first"). Checks ahead
        come after band checks. The server's check worker takes those two
        (:data:`IDLE_KINDS`) when no interim check waits, and only while it has CPU to spare
        (``idle``; :meth:`server.app.ServerApp._start_designs`); the design worker after its
        designs: with them before designs, beside two spinning processes no design finished
        for the resting user in one run of two. Last, when nothing else waits, modal checks
        (:meth:`guard_modes`: a FEM contact's rendered gains on the solid's own modes, 0.26-1.0 s
        each on the liver sphere; before designs they kept every design from finishing in the
        firm-hand FEM demo, and before pair checks a resting user's pair did not verify in time).
        A modal check waiting when a design has been handed out since the last one takes the
        next turn before further designs: in the palpation demo designs (1 s of CPU each) kept
        the design worker busy for the whole run, and one modal check came back in 20 s (with
        the turn, 2-7 a run; docs/fem.md).
        """
        for job in [j for j in self._queued if j[0] == "interim" and j[1:] in self.interim]:
            del self._queued[job]  # answered meanwhile by a check over its B_o band
        jobs = [j for j in self._queued if only is None or j[0] == only]
        if not idle and only in IDLE_KINDS:
            return None
        interim = [j for j in jobs if j[0] == "interim"]
        if (
            not interim and self._modal_turn and self._modal_queue and only is None
            and (modal := self._next_modal())
        ):  # fmt: skip
            self._modal_turn = False
            return GainJob("modal", modal.key, modal.cell, modal=modal)
        if first := interim or jobs:
            kind, key, cell = first[-1]  # interim checks, then designs
            if not interim:
                kind, key, cell = self._longest_wait(jobs) or (kind, key, cell)
            del self._queued[(kind, key, cell)]
            self._modal_turn = self._modal_turn or kind == "design"
            return GainJob(kind, key, cell)
        if idle and self._band_queue and only in (None, "band"):
            (key, cell), design = self._band_queue.popitem()  # the newest
            return GainJob("band", key, cell, design=design)
        while idle and self._ahead_queue and only in (None, "ahead"):
            key, cell = self._ahead_queue.popitem()[0]  # the newest
            if not cell_has_gains(self.table, self.interim, key, cell):
                return GainJob("ahead", key, cell)
        if self._pair_queue and only in (None, "pair"):
            bucket, case = self._pair_queue.popitem()  # the newest
            self.pairs.setdefault(bucket, None)  # asked once (a lost job: no hold there)
            self.pair_checks += 1
            return GainJob("pair", bucket.partner_key, bucket.partner_cell, case)
        if self._modal_queue and only in (None, "modal") and (modal := self._next_modal()):
            self._modal_turn = False
            return GainJob("modal", modal.key, modal.cell, modal=modal)
        return None

    def take_jobs(self) -> list[GainJob]:
        """The design work queued since the last call (interim checks first, then designs, then
        pair checks), oldest first."""
        jobs = [GainJob(k, key, cell) for (k, key, cell) in self._queued]
        self._queued.clear()
        for bucket, case in self._pair_queue.items():
            self.pairs.setdefault(bucket, None)
            self.pair_checks += 1
            jobs.append(GainJob("pair", bucket.partner_key, bucket.partner_cell, case))
        self._pair_queue.clear()
        jobs.extend(GainJob("band", k, c, design=d) for (k, c), d in self._band_queue.items())
        jobs.extend(GainJob("ahead", k, c) for (k, c) in self._ahead_queue)
        jobs.extend(GainJob("modal", c.key, c.cell, modal=c) for c in self._modal_queue.values())
        self._band_queue.clear()
        self._ahead_queue.clear()
        self._modal_queue.clear()
        order = {"interim": 0, "design": 1, "band": 2, "ahead": 3, "modal": 5}
        jobs.sort(key=lambda j: order.get(j.kind, 4))
        return jobs

    def store(
        self, job: GainJob, design: GainDesign | BandedGains | PairVerdict | ModalVerdict | None
    ) -> None:
        """Hand back a job's result (None: no gains pass for it; it is not asked again; a pair
        job's :class:`shared.gains.group.PairVerdict`; a band job's
        :class:`shared.gains.b_o_band.BandedGains`, kept for every key of its band with no
        interim gains yet).

        Interim gains for a key whose B_o lies in a band of
        :data:`shared.gains.policy.B_O_COVER_LATTICE` queue their band check (:meth:`next_job`),
        and, where a contact needed them, checks of the cells beside theirs: over a lump K_o
        crosses a cell every 10 %, and each new cell rendered a wider class's PI until its own
        check came back.
        """
        if job.kind == "pair":
            if job.pair is not None and (design is None or isinstance(design, PairVerdict)):
                self.pairs[job.pair.bucket] = design
            return
        if job.kind == "modal":
            case = job.modal
            if case is None or not isinstance(design, ModalVerdict):
                return  # failed: the design renders unchecked, not asked again
            d = case.design
            gains = _gains_of(d)
            self.modal[(case.contact, case.key, gains)] = design
            self._modal_near[(case.key, gains)] = design
            if not design.changed and design.design is not None:
                log.info(
                    "contact %d: the design (K_h %.1f N/m, B_h %.1f N*s/m) keeps the solid's "
                    "modes at %.2f/s (bar %.2f/s)", case.contact, d.k_h, d.b_h,
                    design.rate_per_s, design.bar_per_s,
                )  # fmt: skip
            elif design.design is None:
                log.warning(
                    "no gains keep the solid's modes at %.2f/s at contact %d (the design: "
                    "%.2f/s); the design renders", design.bar_per_s, case.contact,
                    design.designed_rate_per_s,
                )  # fmt: skip
            else:
                log.info(
                    "contact %d: the design (K_h %.1f N/m, B_h %.1f N*s/m, %s) on the solid's "
                    "modes %.2f/s, under %.2f/s: K_h x %.2f, B_h %.1f N*s/m, %s (%.2f/s)",
                    case.contact, d.k_h, d.b_h, d.proxy_hold, design.designed_rate_per_s,
                    design.bar_per_s, design.scale, design.design.b_h,
                    design.design.proxy_hold, design.rate_per_s,
                )  # fmt: skip
            return
        if job.kind == "band":
            if isinstance(design, BandedGains):
                for key in design.keys(job.key):
                    if (key, job.cell) not in self.interim:
                        self.interim[(key, job.cell)] = design.design
                        self.band_keys += 1
            return
        if design is None or not isinstance(design, GainDesign):
            return
        if job.kind == "design":
            self.table.store(job.key, job.cell, design)
            return
        self.interim[(job.key, job.cell)] = design
        if b_o_band(job.key.b_o) is None:
            return
        if ("band", job.key, job.cell) not in self._asked:
            self._asked.add(("band", job.key, job.cell))
            _push_newest(self._band_queue, (job.key, job.cell), design)
        if job.kind != "interim":
            return  # a check ahead asks none further
        for c in (job.cell - 1, job.cell + 1):
            if ("ahead", job.key, c) not in self._asked:
                self._asked.add(("ahead", job.key, c))
                _push_newest(self._ahead_queue, (job.key, c), None)


def _gains_of(g: RecommendedGains | GainDesign) -> tuple[Any, ...]:
    """The gains that identify a modal check: K_h, I, B_h, the hold and C_h."""
    return (g.k_h, g.i_gain, g.b_h, g.proxy_hold, g.own_gain)


def _push_newest(queue: dict[Any, Any], item: Any, value: Any) -> None:
    """Put ``item`` last in ``queue`` (the newest), dropping the oldest beyond
    :data:`BAND_QUEUE`."""
    queue[item] = value
    while len(queue) > BAND_QUEUE:
        del queue[next(iter(queue))]


def run_job_measured(
    job: GainJob, grid_ratio: float, hand_box: HandBox
) -> tuple[GainDesign | BandedGains | PairVerdict | ModalVerdict | None, float]:
    """:func:`run_job`, and the CPU time [s] the worker spent on it (``time.process_time``):
    against the wall time the server waited, the share of a core the worker had."""
    cpu0 = time.process_time()
    result = run_job(job, grid_ratio, hand_box)
    return result, time.process_time() - cpu0


def run_job(
    job: GainJob, grid_ratio: float, hand_box: HandBox
) -> GainDesign | BandedGains | PairVerdict | ModalVerdict | None:
    """Run one :class:`GainJob` (in a worker process: arguments and result pickle).

    Returns None when no gains pass (the key is beyond what any local model renders); a pair
    job's verdict (:func:`shared.gains.group.check_pair`); a modal job's
    (:func:`shared.gains.modal_guard.guard`); a band job's
    :class:`shared.gains.b_o_band.BandedGains` (with no band where an end fails).
    """
    try:
        if job.kind == "pair":
            return None if job.pair is None else check_pair(job.pair)
        if job.kind == "modal":
            return None if job.modal is None else guard(job.modal, grid_ratio, hand_box)
        if job.kind == "band":
            if job.design is None:
                return None
            return check_band(job.key, job.cell, job.design, grid_ratio, hand_box)
        if job.kind == "design":
            return timed(design_cell, job.key, job.cell, grid_ratio, hand_box)
        return timed(interim_design, job.key, job.cell, grid_ratio, hand_box, design_fallback=False)
    except ValueError:
        return None
