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

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

from haptic_collab.client.workers import timed
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, HandBox
from haptic_collab.shared.gains.choose import (
    VERIFIED_SOURCES,
    DesignJob,
    Known,
    table_design,
    without_design,
)
from haptic_collab.shared.gains.delay import DelayHold, measured_delay_ticks
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.gains.key import (
    GainKey,
    held_stiff_ratio,
    loop_delay_ticks,
    make_gain_key,
)
from haptic_collab.shared.gains.policy import K_O_GRID_RATIO, RTT_WINDOW
from haptic_collab.shared.gains.table import GainTable, design_cell
from haptic_collab.shared.gains.table_file import load_shipped
from haptic_collab.shared.protocol import Hello, RecommendedGains
from haptic_collab.shared.stability import rate_ratio

JobKind = Literal["interim", "design"]


@dataclass(frozen=True)
class GainJob:
    """One piece of design work for the worker: ``kind`` for grid cell ``cell`` of ``key``."""

    kind: JobKind
    key: GainKey
    cell: int


@dataclass
class _User:
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=RTT_WINDOW))
    stiff_ratio: float = 1.0
    measured: int = 0
    stale: bool = False
    #: The round trip [s] the client measures its delay from (``state.delay_rtt_ms``).
    delay_rtt_s: float | None = None
    delay: DelayHold = field(default_factory=DelayHold)


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
        self._queued: dict[tuple[JobKind, GainKey, int], None] = {}
        self._asked: set[tuple[JobKind, GainKey, int]] = set()
        self._users: dict[str, _User] = {}
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
            design, source, jobs = without_design(key, k_o_eff, known, None, n)
            for job in jobs:
                self._want("design" if isinstance(job, DesignJob) else "interim", key, cell)
            if source not in VERIFIED_SOURCES:
                design = None
        if design is None:
            self.misses += 1
            return None
        self.hits += 1
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

    # ---------------------------------------------------------------- work for the worker
    def _want(self, kind: JobKind, key: GainKey, cell: int) -> None:
        job = (kind, key, cell)
        if job not in self._asked:
            self._asked.add(job)
            self._queued[job] = None

    def next_job(self) -> GainJob | None:
        """The most urgent queued job, removed from the queue; None when there is none.

        Interim checks come first (they let a user's forces come on within a fraction of a
        second), then designs; within a kind the most recently asked first: a user moving over
        the object asks for one K_o cell after another, and the cell it is in now matters more
        than the ones it has left (those are still designed later, when nothing newer waits).
        """
        if not self._queued:
            return None
        jobs = list(self._queued)
        interim = [j for j in jobs if j[0] == "interim"]
        kind, key, cell = (interim or jobs)[-1]
        del self._queued[(kind, key, cell)]
        return GainJob(kind, key, cell)

    def take_jobs(self) -> list[GainJob]:
        """The design work queued since the last call (interim checks first), oldest first."""
        jobs = [GainJob(k, key, cell) for (k, key, cell) in self._queued]
        self._queued.clear()
        jobs.sort(key=lambda j: j.kind != "interim")
        return jobs

    def store(self, job: GainJob, design: GainDesign | None) -> None:
        """Hand back a job's result (None: no gains pass for it; it is not asked again)."""
        if design is None:
            return
        if job.kind == "design":
            self.table.store(job.key, job.cell, design)
        else:
            self.interim[(job.key, job.cell)] = design


def run_job(job: GainJob, grid_ratio: float, hand_box: HandBox) -> GainDesign | None:
    """Run one :class:`GainJob` (in a worker process: arguments and result pickle).

    Returns None when no gains pass (the key is beyond what any local model renders).
    """
    try:
        if job.kind == "design":
            return timed(design_cell, job.key, job.cell, grid_ratio, hand_box)
        return timed(interim_design, job.key, job.cell, grid_ratio, hand_box, design_fallback=False)
    except ValueError:
        return None
