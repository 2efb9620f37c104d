"""Local model gains with the hand in the loop: the most transparent gains the full loop allows.

Step 2 of the paper's section 6 picks K_h and I inside the stability region of the *simulation
loop* (probe as a position source). This module picks them inside the stability region of the
*full loop* (:mod:`shared.full_loop`): the gains are accepted only if the loop is stable, with a
decay-rate margin, for

- every hand of the hand box (:class:`shared.full_loop.HandBox`),
- every servo tick j at which the simulation may sample the force (Step 3 over a network),
- every object stiffness K_o' in ``[(1 - margin) K_o, K_o]`` (the paper's advice to design for a
  lower K_o than reported), with own-force compensation down to ``K_o / (1 + stiffer_by)`` where
  that costs less than a stiffness JND (:func:`softest_k_o`), and, for the product's :class:`shared.gains.table.GainTable` designs, up
  to ``1 + stiffer_by`` times the top of the cell (:attr:`GainKey.stiffer_by`: an object stiffer
  than reported, docs/fidelity.md),

and among those the one with the best *transparency*: the felt stiffness |dF/dx| at the probe,
probe as a position source, relative to K_o. For the paper's models alone, at 1 Hz (then 8 Hz
to break ties); with own-force compensation (the product), its largest error |ln |q|| over the
band :data:`shared.gains.policy.FELT_BAND_HZ` (0.5-8 Hz), q relative to the object's own
dynamic stiffness there (eq. 9's ``K_o + B_o (1 - e^{-j w N T})``,
:func:`shared.felt_stiffness.object_stiffness`: K_o where B_o = 0, stiffer to a quick press on a
damped or massive object), and in a held press (relative to K_o), compared in steps
of :data:`DESIGN_TIE` (half a stiffness JND), then the same on objects ``1 + stiffer_by`` times
softer and stiffer than reported. A
:class:`shared.gains.table.GainTable` design serves every K_o reported in its cell, scaled to it (K_h
and I in proportion, :meth:`GainDesign.at`; ``scaled``), so its transparency is judged at the
cell's two ends and middle, the worst of them counting, then their mean (``felt_k_os``), and each
scale is checked like the design.
Besides K_h (P) and K_h, I (PI), the design may use

- a probe damper B_h on the backward difference of the probe position, in contact only, up to the
  device's ``b_h_max``;
- a first-order-hold proxy (``foh``): the proxy moves linearly to each new surface over the next
  simulation period instead of jumping (``zoh``);
- own-force compensation C_h (:mod:`shared.full_loop`; not in the paper), for a proportional
  local model: the proxy is the reported surface moved out by C_h times the force F_s the
  simulation applied from this user, ``F = K_h (x - x_o) + C_h K_h F_s``. With C_h K_h = 1 the
  force is the last applied one corrected by the coupling, and a held press settles with the
  probe on the surface at ``F = K_o x``: the object's own stiffness, whatever K_h (the simulation
  loop's static gain is ``1 - K_h / K_o``) and whatever the error in the reported K_o. At K_h =
  K_o it is rendered at the servo rate and the simulation loop carries only the model's error,
  so K_h is no longer bounded by K_o; above the device's stiffness the stiffness comes through
  the (contracting) simulation loop. In general the felt stiffness at DC is ``K_h K_o / (K_o + (1
  - C_h K_o) K_h)``. Not with an integral (it would hold the probe at the compensated surface:
  infinitely stiff at DC). Used by the product
  (:attr:`GainKey.own_force`); a ``pi`` design may then be a compensated P model (I = 0) when
  that is closer to K_o over the band and at DC than any PI one;
- for K_o above the device's stiffness, the plane at the rest surface the simulation's model
  gives, C_h = 1 / K_o with K_h at (or just below) the device's stiffness: felt as K_h at every
  frequency of the band (model-mediated teleoperation: Mitra and Niemeyer 2008), where the
  paper's P model feels ``K_h K_o / (K_h + K_o)`` and its PI creeps toward K_o at 0.5 Hz but
  falls to 0.2-0.3 K_o at 4 Hz.

The felt stiffness is computed exactly on the lifted loop (:mod:`shared.felt_stiffness`); the
decay-rate margin and the K_o' a range is checked at are :mod:`shared.stability_margin`'s. This
module owns the design: :func:`design_gains` (what the gains must satisfy and which candidate
wins) and its result :class:`GainDesign`; how candidates are found and checked is
:mod:`shared.gains.search`'s. The table of designs on a grid of K_o is :mod:`shared.gains.table`; the
interim gains rendered while a design runs, :mod:`shared.gains.interim`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from haptic_collab.shared.checks import positive as _positive
from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.full_loop import (
    DEFAULT_HAND_BOX,
    HandBox,
    ProxyHold,
)
from haptic_collab.shared.gains.key import Mode
from haptic_collab.shared.gains.policy import (
    FELT_BAND_HZ,
    MIN_DECAY_RATE_PER_S,
    SOFT_END_COST_STEPS,
)
from haptic_collab.shared.gains.search import Candidate, GainSearch, candidate_groups, scaled_gains
from haptic_collab.shared.rates import Rates


@dataclass(frozen=True)
class GainDesign:
    """Gains for one object stiffness, with their robustness and transparency (SI units).

    Attributes
    ----------
    k_h : float
        K_h [N/m].
    i_gain : float
        I [N/(m*s)] (0: proportional local model).
    b_h : float
        Probe damper B_h [N*s/m], in contact only.
    proxy_hold : {"zoh", "foh"}
    worst_spectral_radius : float
        Largest spectral radius of the full loop over the hand box, every sampling tick and the
        K_o range: below 1; every oscillating mode is below ``rho_limit``.
    rho_limit : float
        exp(-MIN_DECAY_RATE * N * T): the bound oscillating modes respect (slow creep of the
        integral, below :data:`CREEP_FREQUENCY_HZ`, need only be stable).
    felt_stiffness_ratio_1hz, felt_stiffness_ratio_8hz : float
        |dF/dx| / K_o at the probe (position source) at 1 Hz and 8 Hz.
    k_o : float
        K_o [N/m] designed for; the design holds for K_o' in ``k_o_range``.
    k_o_range : (float, float)
        Object stiffness interval [N/m] checked.
    rate_ratio, delay_ticks : int
    mode : {"p", "pi"}
    hand_box : HandBox
    design_ms : float
        Wall time the design took [ms], set by whoever ran it (:func:`haptic_collab.client.workers.timed`;
        this module reads no clock); 0 when not measured. Informative: ``haptic bench gains``
        measures properly.
    own_gain : float
        Own-force compensation C_h [m/N] (module docstring), >= 0; 0: the paper's local model.
    scale_max : float
        >= 1. Above 1 the gains scale with the reported K_o (:meth:`at`): K_h and I by s =
        K_o / ``k_o``, C_h by 1 / s, B_h unchanged, for s in [1, ``scale_max``], checked like the
        design itself at s = 1, its middle and top (:func:`design_gains`, ``scaled``). 1: the
        same gains for every K_o reported (the paper's models, interim and fallback gains,
        :func:`design_gains` without ``scaled``).
    """

    k_h: float
    i_gain: float
    b_h: float
    proxy_hold: ProxyHold
    worst_spectral_radius: float
    rho_limit: float
    felt_stiffness_ratio_1hz: float
    felt_stiffness_ratio_8hz: float
    k_o: float
    k_o_range: tuple[float, float]
    rate_ratio: int
    delay_ticks: int
    mode: Mode
    hand_box: HandBox = field(default=DEFAULT_HAND_BOX, repr=False)
    design_ms: float = 0.0
    own_gain: float = 0.0
    scale_max: float = 1.0

    def at(self, k_o: float) -> GainDesign:
        """The gains to render for a reported K_o [N/m] (``scale_max``), s clamped to
        [1, ``scale_max``]: K_h, I times s, C_h over s, B_h as designed; ``k_o`` times s and
        the lower end of ``k_o_range`` times s (what those gains were checked over), and
        ``scale_max`` over s, so ``d.at(k).at(k) == d.at(k)``. A design with ``scale_max == 1``
        is returned as is.

        Raises
        ------
        ValueError
            A K_o that is not finite and > 0.
        """
        _positive("k_o", k_o)
        if self.scale_max <= 1.0:
            return self
        s = min(max(k_o / self.k_o, 1.0), self.scale_max)
        if s <= 1.0 + 1e-12:  # (rounding: the design scaled to k_o is at k_o already)
            return self
        k_h, i_gain, own_gain = scaled_gains(self.k_h, self.i_gain, self.own_gain, s)
        lo, hi = self.k_o_range
        return replace(
            self,
            k_h=k_h,
            i_gain=i_gain,
            own_gain=own_gain,
            k_o=self.k_o * s,
            k_o_range=(lo * s, hi),
            scale_max=self.scale_max / s,
        )

    def to_json(self) -> dict[str, object]:
        """The ``haptic gains --json`` object."""
        return {
            "k_h": self.k_h,
            "i_gain": self.i_gain,
            "b_h": self.b_h,
            "proxy_hold": self.proxy_hold,
            "worst_spectral_radius": self.worst_spectral_radius,
            "rho_limit": self.rho_limit,
            "hand_box": self.hand_box.as_dict(),
            "felt_stiffness_ratio_1hz": self.felt_stiffness_ratio_1hz,
            "felt_stiffness_ratio_8hz": self.felt_stiffness_ratio_8hz,
            "k_o": self.k_o,
            "k_o_range": list(self.k_o_range),
            "rate_ratio": self.rate_ratio,
            "delay_ticks": self.delay_ticks,
            "local_model": self.mode,
            "own_gain": self.own_gain,
            "scale_max": self.scale_max,
            "design_ms": self.design_ms,
        }


def softest_k_o(k_o: float, margin: float, stiffer_by: float) -> float:
    """The softest object [N/m] a compensated design for ``k_o`` [N/m] may be checked on: ``k_o /
    (1 + stiffer_by)`` where that is softer than ``(1 - margin) k_o``, else the latter.

    Why. A design with own-force compensation judges how it feels on objects ``1 + stiffer_by``
    times softer and stiffer than reported (a model error of that ratio either way; a stiffness
    estimate's error is a ratio), and is checked for stability up to ``1 + stiffer_by`` times
    its cell's top (:func:`shared.gains.table.cell_k_o_range`), but by the paper's margin only
    down to ``(1 - margin) k_o``. :func:`design_gains_modes` checks down to this softer end
    wherever that costs at most :data:`shared.gains.policy.SOFT_END_COST_STEPS` of the design's
    objective (less than a stiffness JND), and keeps the margin's end where it would cost more.

    Raises
    ------
    ValueError
        ``margin`` not in [0, 1) or ``stiffer_by`` negative or not finite.
    """
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin must be in [0, 1), got {margin!r}")
    if not (math.isfinite(stiffer_by) and stiffer_by >= 0.0):
        raise ValueError(f"stiffer_by must be finite and >= 0, got {stiffer_by!r}")
    return k_o * min(1.0 - margin, 1.0 / (1.0 + stiffer_by))


def design_gains(
    k_o: float,
    *,
    b_o: float = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    mode: Mode = "pi",
    margin: float = 0.15,
    k_o_hi: float | None = None,
    k_h_max: float = math.inf,
    b_h_max: float = 0.0,
    holds: Sequence[ProxyHold] = ("zoh", "foh"),
    hand_box: HandBox = DEFAULT_HAND_BOX,
    min_decay_rate_per_s: float = MIN_DECAY_RATE_PER_S,
    own_force: bool = False,
    felt_k_os: Sequence[float] | None = None,
    scaled: bool = False,
    stiffer_by: float = 0.0,
) -> GainDesign:
    """The most transparent gains stable over the hand box (module docstring).

    Parameters
    ----------
    k_o : float
        Reported (coupling-aware) object stiffness K_o_eff [N/m], > 0.
    b_o : float
        B_o [N/m] (eq. 9), >= 0.
    servo_rate_hz, sim_rate_hz : float
        1/T and 1/(N*T); N must be a whole number.
    delay_ticks : int
        Extra whole simulation ticks of delay, >= 0.
    mode : {"p", "pi"}
        Proportional or proportional-integral local model.
    margin : float
        Fraction in [0, 1) by which K_o may be overestimated: stability is checked down to
        ``(1 - margin) K_o``; with ``own_force``, down to ``K_o / (1 + stiffer_by)`` where that
        is softer and costs at most :data:`shared.gains.policy.SOFT_END_COST_STEPS` of the
        objective (:func:`softest_k_o`; the design's ``k_o_range`` says which).
    k_o_hi : float, optional
        Upper end of the K_o range checked (default ``k_o``; :class:`shared.gains.table.GainTable`
        passes the next grid point so a design covers its whole cell).
    k_h_max : float
        The device's maximum stable stiffness [N/m].
    b_h_max : float
        The device's maximum virtual damping [N*s/m] (0: no probe damper).
    holds : sequence of {"zoh", "foh"}
        Proxy holds the design may use.
    hand_box : HandBox
        Hands the gains must be stable for.
    min_decay_rate_per_s : float
        Decay-rate margin [1/s] (:data:`shared.gains.policy.MIN_DECAY_RATE_PER_S`).
    own_force : bool
        Also consider own-force compensation C_h = r / K_h, r in
        :data:`shared.gains.policy.OWN_FORCE_RATIOS` (module docstring), proportional only, and,
        for K_o above ``k_h_max``, the plane at the rest surface (C_h = 1 / K_o, K_h up to
        ``k_h_max``: model-mediated teleoperation's plane). The objective is then the felt
        response closest to the object's own over the band (eq. 9 with ``b_o``; K_o itself where
        B_o = 0: compensation can overshoot and lag it):
        the largest over :data:`shared.gains.policy.FELT_BAND_HZ` of |ln |q|| and the active
        share -Im q (:mod:`shared.gains.search`) and the held press's |ln q|, in steps of
        :data:`shared.gains.policy.DESIGN_TIE`; then the same on the objects of ``stiffer_by``;
        instead of the elastic part at 1 Hz capped at K_o.
    felt_k_os : sequence of float, optional
        Object stiffnesses [N/m] the transparency is also judged at, with ``own_force``: the
        worst of them and ``k_o`` counts, then their mean (default: ``k_o`` alone).
        :func:`shared.gains.table.design_cell` passes its cell's ends and middle, ``g_i``,
        ``sqrt(g_i g_(i+1))`` and ``g_(i+1)``: every reported K_o in the cell gets the design, and
        with a delay the felt response depends on ``K_h / K_o`` (fixed gains fitted to ``g_i``
        alone felt 0.78-0.82 K_o at 1 Hz at the top of the 300 and 1000 N/m cells at 20 Hz with 8
        ticks of delay; judged across the cell, 0.86-0.91; scaled, 1.005 across the 300 N/m cell
        and 0.92-0.95 across the 1000 N/m one, where K_h reaches the device's 1000 N/m).
    stiffer_by : float
        With ``own_force``, >= 0: the transparency is also judged on objects ``1 + stiffer_by``
        times softer and stiffer than ``k_o`` (the gains made for ``k_o`` rendering them; a
        model error), the worst counting. Stability over the stiffer object is the caller's
        range (``k_o_hi``; :func:`shared.gains.table.cell_k_o_range` widens it by
        :attr:`GainKey.stiffer_by`).
    scaled : bool
        Compensated gains are rendered scaled to the reported K_o (:meth:`GainDesign.at`) over
        ``[k_o, max(felt_k_os)]``, as far as K_h stays within ``k_h_max``: transparency at each
        of ``felt_k_os`` is judged with the gains scaled to it, and a candidate is accepted only
        if it passes at the scales s = 1, the geometric middle and its top, each over K_o' in
        ``[(1 - margin) s k_o, k_o_hi]`` (the margin below the reported K_o, and up to the top of
        the range as for fixed gains, at least ``s k_o``). With own-force compensation the felt
        response then depends on K_h / K_o alone and K_h = K_o feels the object's own stiffness
        across the cell (fixed gains: within 10 % of it at 1 Hz with long delays; the 1-D
        benchmark's 100 and 300 N/m cells 0.97 K_o median).

    Returns
    -------
    GainDesign
        For ``pi``, a proportional design (``mode == "p"``, I = 0) when no integral is stable
        over the box (long delays without a probe damper).

    Raises
    ------
    ValueError
        Out-of-range input, or no candidate is stable over the box (then the box or the rates are
        beyond what any local model can render).
    """
    return design_gains_modes(
        k_o,
        modes=(mode,),
        b_o=b_o,
        servo_rate_hz=servo_rate_hz,
        sim_rate_hz=sim_rate_hz,
        delay_ticks=delay_ticks,
        margin=margin,
        k_o_hi=k_o_hi,
        k_h_max=k_h_max,
        b_h_max=b_h_max,
        holds=holds,
        hand_box=hand_box,
        min_decay_rate_per_s=min_decay_rate_per_s,
        own_force=own_force,
        felt_k_os=felt_k_os,
        scaled=scaled,
        stiffer_by=stiffer_by,
    )[mode]


def design_gains_modes(
    k_o: float,
    *,
    modes: Sequence[Mode] = ("p", "pi"),
    b_o: float = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    margin: float = 0.15,
    k_o_hi: float | None = None,
    k_h_max: float = math.inf,
    b_h_max: float = 0.0,
    holds: Sequence[ProxyHold] = ("zoh", "foh"),
    hand_box: HandBox = DEFAULT_HAND_BOX,
    min_decay_rate_per_s: float = MIN_DECAY_RATE_PER_S,
    own_force: bool = False,
    felt_k_os: Sequence[float] | None = None,
    scaled: bool = False,
    stiffer_by: float = 0.0,
) -> dict[Mode, GainDesign]:
    """:func:`design_gains` for each local model of ``modes`` at once, ``{mode: design}``, each
    design the one :func:`design_gains` gives with that ``mode`` and the other arguments.

    The candidates with own-force compensation are proportional models, the same for P and PI
    (:func:`shared.gains.search.candidate_groups`): they are searched once for all ``modes``
    (pruned only below the least transparent of the modes' best so far, so that each mode's
    search finds what it finds alone), which spares a P and PI pair 15-30 % of the time of its
    two designs (the fidelity benchmark designs both for every key).

    Raises
    ------
    ValueError
        As :func:`design_gains`, or ``modes`` empty or naming another local model.
    """

    params = dict(locals())  # the arguments, for the fallback of PI to P below
    rates = Rates(servo_rate_hz, sim_rate_hz)
    N, T = rates.ratio, rates.servo_period_s
    if not (math.isfinite(k_o) and k_o > 0.0):
        raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
    if not (math.isfinite(b_o) and b_o >= 0.0):
        raise ValueError(f"b_o must be finite and >= 0, got {b_o!r}")
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin must be in [0, 1), got {margin!r}")
    if not (math.isfinite(stiffer_by) and stiffer_by >= 0.0):
        raise ValueError(f"stiffer_by must be finite and >= 0, got {stiffer_by!r}")
    _whole("delay_ticks", delay_ticks, 0)
    if not modes or any(m not in ("p", "pi") for m in modes):
        raise ValueError(f"mode must be 'p' or 'pi', got {tuple(modes)!r}")
    if not k_h_max > 0.0:
        raise ValueError(f"k_h_max must be > 0, got {k_h_max!r}")
    if not (math.isfinite(b_h_max) and b_h_max >= 0.0):
        raise ValueError(f"b_h_max must be finite and >= 0, got {b_h_max!r}")
    if not holds or any(h not in ("zoh", "foh") for h in holds):
        raise ValueError(f"holds must name 'zoh' and/or 'foh', got {holds!r}")
    hi = float(k_o if k_o_hi is None else max(k_o, k_o_hi))
    felt_at = [float(k_o)] if felt_k_os is None else [float(v) for v in felt_k_os]
    if not felt_at or not all(math.isfinite(v) and v > 0.0 for v in felt_at):
        raise ValueError(f"felt_k_os must be finite stiffnesses > 0 N/m, got {felt_k_os!r}")
    rho_limit = math.exp(-min_decay_rate_per_s * N * T)
    delay = int(delay_ticks)
    band = list(FELT_BAND_HZ) if own_force else [1.0]
    model_error_k_os = (
        [k_o / (1.0 + stiffer_by), k_o * (1.0 + stiffer_by)] if own_force and stiffer_by > 0 else []
    )

    def search_from(lo: float, floors: dict[Mode, float | None]) -> dict[Mode, Candidate | None]:
        """Each mode's most transparent candidate checked down to ``lo`` [N/m], None where none
        passes or none ranks at or above its mode's ``floors`` (``rank[0]``)."""
        # each mode's paper model, then the compensated groups (proportional: the same for every
        # mode; candidate_groups builds them whatever ``integral``)
        by_mode = {
            m: candidate_groups(
                k_o,
                lo,
                hi,
                rate_ratio=N,
                servo_period_s=T,
                integral=m == "pi",
                k_h_max=k_h_max,
                b_h_max=b_h_max,
                own_force=own_force,
                scaled=scaled,
                felt_at=felt_at,
            )
            for m in dict.fromkeys(modes)
        }
        groups = next(iter(by_mode.values()))
        search = GainSearch(
            k_o,
            lo,
            hi,
            b_o=b_o,
            rate_ratio=N,
            servo_period_s=T,
            delay_ticks=delay,
            rho_limit=rho_limit,
            band=band,
            felt_at=felt_at,
            model_error_k_os=model_error_k_os,
            own_force=own_force,
            scaled=scaled,
            hand_box=hand_box,
        )

        # the largest scale of each candidate's gains (``scaled``): to the top of felt_at, K_h
        # within the device's stiffness; compensated candidates only. The paper's models keep
        # one set of gains per cell: they win only above the device's stiffness, where K_h is at
        # or near its limit, and checking them scaled dropped PI designs that felt 8 % stiffer
        # (3000 N/m, 100 Hz, 40 ticks: 0.42 against 0.46 K_o at 1 Hz)
        top = max(felt_at) / k_o if scaled else 1.0
        smax = [np.clip(k_h_max / base["k_h"], 1.0, max(top, 1.0)) for base, _ in groups[1:]]

        best: dict[Mode, Candidate | None] = dict.fromkeys(by_mode)

        def keep(m: Mode, found: Candidate | None) -> None:
            old = best[m]
            if found is not None and (old is None or found.rank > old.rank):
                best[m] = found

        def bound_of(m: Mode) -> float | None:
            """What a candidate must reach to matter to mode ``m``: its best so far, or its
            floor."""
            b_m, f_m = best[m], floors.get(m)
            marks = [v for v in (None if b_m is None else b_m.rank[0], f_m) if v is not None]
            return max(marks) if marks else None

        for m, mode_groups in by_mode.items():
            paper, with_i = mode_groups[0]
            for hold in holds:
                keep(
                    m,
                    search.best_in_group(
                        paper, with_i, hold, np.ones_like(paper["k_h"]), bound_of(m)
                    ),
                )
        for ((base, with_i), s_max), hold in itertools.product(
            zip(groups[1:], smax, strict=True), holds
        ):
            # pruned below the least transparent best so far: no mode's best can lie there
            bounds = [bound_of(m) for m in best]
            bound = (
                None if any(b is None for b in bounds) else min(b for b in bounds if b is not None)
            )
            found = search.best_in_group(base, with_i, hold, s_max, bound)
            for m in best:
                keep(m, found)
        for m, f_m in floors.items():  # a floor is a requirement, not only a pruning bound
            b_m = best.get(m)
            if f_m is not None and b_m is not None and b_m.rank[0] < f_m - 1e-9:
                best[m] = None
        return best

    # checked down to the margin; then, with own-force compensation, down to the softer object
    # of the model error where that costs at most SOFT_END_COST_STEPS (softest_k_o)
    lo = (1.0 - margin) * k_o
    best = search_from(lo, dict.fromkeys(modes))
    lo_of: dict[Mode, float] = dict.fromkeys(best, lo)  # type: ignore[arg-type]
    soft = softest_k_o(k_o, margin, stiffer_by)
    if own_force and soft < lo * (1.0 - 1e-12):
        floors: dict[Mode, float | None] = {
            m: None if c is None else c.rank[0] - SOFT_END_COST_STEPS for m, c in best.items()
        }
        wide = search_from(soft, floors)
        for m, c in wide.items():
            if c is not None:
                best[m], lo_of[m] = c, soft

    out: dict[Mode, GainDesign] = {}
    for m in ("p", "pi"):
        if m not in best:
            continue
        found = best[m]
        if found is None and m == "pi":
            # no integral is stable here: render the best proportional local model instead
            out[m] = (
                out["p"] if "p" in out else design_gains_modes(**{**params, "modes": ("p",)})["p"]
            )
            continue
        if found is None:
            raise ValueError(
                f"no {m} local model is stable over the hand box at K_o = {k_o:g} N/m, "
                f"{sim_rate_hz:g} Hz, {delay} tick(s) of delay"
            )
        out[m] = GainDesign(
            k_h=found.k_h,
            i_gain=found.i_gain,
            b_h=found.b_h,
            proxy_hold=found.proxy_hold,
            worst_spectral_radius=found.worst_spectral_radius,
            rho_limit=rho_limit,
            felt_stiffness_ratio_1hz=found.felt_stiffness_ratio_1hz,
            felt_stiffness_ratio_8hz=found.felt_stiffness_ratio_8hz,
            k_o=float(k_o),
            k_o_range=(lo_of[m], hi),
            rate_ratio=N,
            delay_ticks=delay,
            mode=m,
            hand_box=hand_box,
            own_gain=found.own_gain,
            scale_max=found.scale_max,
        )
    return out
