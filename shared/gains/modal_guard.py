"""Gains checked on a FEM contact's own slow modes, and softened where those modes would ring on.

The gain design (:mod:`shared.gains.design`) sees a contact as eq. 9's K_o and B_o. A FEM solid
also has slow, lightly damped modes (the liver ball rocks at 1.6-2.4 Hz and, alone, decays at
1.08/s), and the same gains closed over them (:func:`shared.modal_loop.modal_monodromy`) can
let them ring far longer or grow: at the default sphere's side the product's designs gave 0.24/s
with no delay and grew at 0.1-0.2/s with one or two ticks (docs/fem.md). The server, which has
the modes, checks each design it recommends for a FEM contact here (:func:`guard`) and, where it
misses the bar, recommends the same design with more probe damping B_h (up to the device's
damper) or the other proxy hold and, where that is not enough, K_h scaled down (I with it, C_h up, so that ``C_h K_h``
and with it the held press's static stiffness stay as designed), rung by rung
(:func:`candidates`: the stiffest K_h first, the design's hold first, the least B_h first), until the loop on the
modes meets the bar and eq. 9's own acceptance test (:func:`shared.gains.interim.verify_gains`,
the design's margin over the cell's K_o range) still passes. B_h is what the modes need most:
at the ball's top the designs' 1.5-2.5 N*s/m let a heavy, loose hand keep the ball rocking
(0.24/s, growing at one and two ticks), where 5-8 N*s/m at 0.5-0.7 of the designed K_h meet
the design's full margin, and scaling K_h alone made it worse.

The bar (:func:`modal_bar`): the design's margin :data:`shared.gains.policy.MIN_DECAY_RATE_PER_S`,
or, where the solid alone decays at less than :data:`shared.gains.policy.MODAL_RING_FACTOR` times
that, its own slowest rate over that factor. The design's margin cannot be held there by any
gain a user would feel (at the liver ball's side even an uncompensated 0.1 K_o decays at 0.97/s
over the box, against the ball's own 1.08/s), and a hand held on the solid itself never rings
longer than the solid alone (:func:`shared.modal_loop.direct_decay_rates`): the local model may
at most double how long the solid rings, and never lets it grow.

Pure: no I/O, no clock. The hands are the box's lattice (:meth:`shared.full_loop.HandBox.hands`,
as the design checks), every sampling tick, each candidate probed first (:func:`staged_rate`);
the modes the ``modes`` given (the server passes the
:data:`shared.gains.policy.MODAL_CHECK_MODES` of largest dynamic response,
:meth:`shared.modal_loop.ContactModes.reduced`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from haptic_collab.shared.felt_stiffness import felt_responses
from haptic_collab.shared.full_loop import HandBox, ProxyHold, object_impedance
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import verify_gains
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import (
    FELT_BAND_HZ,
    MIN_DECAY_RATE_PER_S,
    MODAL_GUARD_MIN_SCALE,
    MODAL_RING_FACTOR,
)
from haptic_collab.shared.gains.search import _band_miss, _felt_dc, _log_miss, scaled_gains
from haptic_collab.shared.modal_loop import ContactModes, decay_rate_per_s, modal_decay_rates
from haptic_collab.shared.types import FloatArray

#: Sampling ticks a candidate is first checked at (:func:`modal_rate`), as
#: :func:`shared.gains.interim.verify_gains` probes.
PROBE_TICKS = 2


@dataclass(frozen=True)
class ModalCase:
    """One design to check on one contact's modes (pickles to the server's check worker).

    Attributes
    ----------
    contact : int
        The object's key of the contact (:meth:`server.objects.fem.FemSolid.patch_key`).
    key : GainKey
        The design's key (rates, delay, margin, B_o).
    cell : int
        Its K_o grid cell.
    design : GainDesign
        The gains recommended there.
    modes : ContactModes
        The contact's modes, stepped at the key's simulation period.
    """

    contact: int
    key: GainKey
    cell: int
    design: GainDesign
    modes: ContactModes


@dataclass(frozen=True)
class ModalVerdict:
    """What :func:`guard` found (rates in 1/s; negative: the loop grows).

    Attributes
    ----------
    design : GainDesign or None
        The gains to recommend: the design itself, or it with more B_h and K_h scaled by
        ``scale``; None
        where no rung down to :data:`shared.gains.policy.MODAL_GUARD_MIN_SCALE` passes.
    scale : float
        K_h (and I) rendered over K_h designed: 1, a rung, or the last rung tried.
    bar_per_s : float
        The bar (:func:`modal_bar`).
    designed_rate_per_s : float
        The design's slowest decay over the box on the modes (where a probe already misses the
        bar, the probe's: :func:`staged_rate`).
    rate_per_s : float
        That of ``design`` (of the last rung tried, where none passed).
    alone_rate_per_s : float
        The solid's own slowest decay (the modes with no hand).
    """

    design: GainDesign | None
    scale: float
    bar_per_s: float
    designed_rate_per_s: float
    rate_per_s: float
    alone_rate_per_s: float

    @property
    def changed(self) -> bool:
        """Whether the gains recommended differ from the design's."""
        return self.design is not None and self.designed_rate_per_s < self.bar_per_s


def alone_rate_per_s(modes: ContactModes, sim_period_s: float) -> float:
    """The slowest decay rate [1/s] of the modes alone (no hand, no push)."""
    if modes.mode_count == 0:
        return math.inf
    return decay_rate_per_s(float(np.abs(np.linalg.eigvals(modes.a)).max()), sim_period_s)


def modal_bar(alone_per_s: float) -> float:
    """The slowest decay [1/s] a loop on the solid's modes must keep: the design's margin, or
    the solid's own slowest decay over :data:`shared.gains.policy.MODAL_RING_FACTOR` where that
    is lower (module docstring)."""
    return min(MIN_DECAY_RATE_PER_S, alone_per_s / MODAL_RING_FACTOR)


def rungs(grid_ratio: float) -> list[float]:
    """The K_h scales tried below 1: ``grid_ratio**-k`` down to
    :data:`shared.gains.policy.MODAL_GUARD_MIN_SCALE` (a K_o grid cell each; on the 1.1 grid
    the steps a user feels least)."""
    out: list[float] = []
    s = 1.0 / grid_ratio
    while s >= MODAL_GUARD_MIN_SCALE * (1.0 - 1e-9):
        out.append(s)
        s /= grid_ratio
    return out


def damper_rungs(b_h: float, b_h_max: float) -> list[float]:
    """The probe dampings [N*s/m] tried at each K_h: the design's, then the device's damper
    ``b_h_max`` in quarters above it."""
    out = [b_h]
    out += [f * b_h_max for f in (0.25, 0.5, 0.75, 1.0) if f * b_h_max > b_h * (1.0 + 1e-9)]
    return out


def scaled_design(
    design: GainDesign, s: float, b_h: float | None = None, proxy_hold: ProxyHold | None = None
) -> GainDesign:
    """``design`` with K_h and I times ``s`` and C_h over ``s``, B_h ``b_h`` and the hold
    ``proxy_hold`` (default: as designed), rendered as is for every K_o reported
    (``scale_max`` 1)."""
    k_h, i_gain, own_gain = scaled_gains(design.k_h, design.i_gain, design.own_gain, s)
    return replace(
        design, k_h=k_h, i_gain=i_gain, own_gain=own_gain, scale_max=1.0,
        b_h=design.b_h if b_h is None else b_h,
        proxy_hold=design.proxy_hold if proxy_hold is None else proxy_hold,
    )  # fmt: skip


def candidates(
    design: GainDesign, b_h_max: float, grid_ratio: float
) -> list[tuple[float, ProxyHold, float]]:
    """``(K_h scale, proxy hold, B_h)`` in the order :func:`guard` tries them: the stiffest
    K_h first (1, then :func:`rungs`), at each the design's hold before the other, at each the
    least damping (:func:`damper_rungs`); the design itself excluded."""
    other: ProxyHold = "foh" if design.proxy_hold == "zoh" else "zoh"
    out = []
    for s in [1.0, *rungs(grid_ratio)]:
        for hold in (design.proxy_hold, other):
            out += [(s, hold, b) for b in damper_rungs(design.b_h, b_h_max)]
    return out[1:]


def felt_miss(designs: list[GainDesign], k_o: float, b_o: float, key: GainKey) -> FloatArray:
    """The design's own transparency objective for each of ``designs`` on the contact's K_o and
    B_o (:mod:`shared.gains.search`): the larger of how far the felt response over
    :data:`shared.gains.policy.FELT_BAND_HZ` is from the object's own dynamic stiffness (|ln| of
    the ratio, or its active share) and how far a held press is from K_o; smaller is closer to
    the object. A damper is felt as a stiffer object at the top of the band; a softer K_h, where
    own-force compensation holds the press, only as the first touch's softness."""
    out = np.empty(len(designs))
    rates = key.rates
    own = np.abs(
        object_impedance(
            np.asarray(FELT_BAND_HZ)[:, None], k_o, b_o, rates.ratio * rates.servo_period_s
        )
    )
    for hold in ("zoh", "foh"):
        idx = [i for i, d in enumerate(designs) if d.proxy_hold == hold]
        if not idx:
            continue
        cand = {
            name: np.array([getattr(designs[i], name) for i in idx])
            for name in ("k_h", "i_gain", "b_h", "own_gain")
        }
        resp = felt_responses(
            FELT_BAND_HZ, k_o=k_o, b_o=b_o, servo_period_s=rates.servo_period_s,
            rate_ratio=rates.ratio, delay_ticks=key.delay_ticks, proxy_hold=hold,
            k_h=cand["k_h"], i_gain=cand["i_gain"], b_h=cand["b_h"], own_gain=cand["own_gain"],
        )  # fmt: skip
        out[idx] = np.maximum(_band_miss(resp / own), _log_miss(_felt_dc(cand, k_o)))
    return out


def modal_rate(
    case: ModalCase,
    design: GainDesign,
    hand_box: HandBox,
    probe_ticks: int | None = None,
    screen: bool = False,
) -> float:
    """The slowest decay [1/s] of ``design``'s loop on the case's modes over the box's lattice
    of hands (:meth:`shared.full_loop.HandBox.hands`, as the design checks) and every sampling
    tick; a probe with ``probe_ticks`` (that many ticks spread over the period) or ``screen``
    (the box's corners, centre and extra hands only): no slower than the whole, and a candidate
    that misses the bar mostly misses it there, at a fraction of the cost."""
    rates = case.key.rates
    n = rates.ratio
    ticks = None if probe_ticks is None else list(range(0, n, max(1, n // probe_ticks)))
    return float(
        modal_decay_rates(
            hands=hand_box.screen_hands() if screen else hand_box.hands(),
            modes=case.modes,
            servo_period_s=rates.servo_period_s,
            rate_ratio=n,
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            own_gain=design.own_gain,
            delay_ticks=case.key.delay_ticks,
            proxy_hold=design.proxy_hold,
            sample_ticks=ticks,
        ).min()
    )


def staged_rate(case: ModalCase, design: GainDesign, hand_box: HandBox, bar: float) -> float:
    """:func:`modal_rate` in stages, each only where the one before keeps ``bar``: the box's
    screen at :data:`PROBE_TICKS` ticks, its lattice at those ticks and at five times as many,
    the lattice at every tick (on the liver sphere with the server's 6 modes about 2 ms, 10 ms,
    40 ms and 0.2 s).
    The whole check's rate where every stage keeps the bar, else the first stage's that does
    not (no slower than the whole)."""
    stages = ((PROBE_TICKS, True), (PROBE_TICKS, False), (5 * PROBE_TICKS, False), (None, False))
    for ticks, screen in stages:
        rate = modal_rate(case, design, hand_box, ticks, screen)
        if rate < bar:
            break
    return rate


def guard(case: ModalCase, grid_ratio: float, hand_box: HandBox) -> ModalVerdict:
    """Check ``case.design`` on the contact's modes and soften it where it misses the bar
    (module docstring).

    Returns
    -------
    ModalVerdict
        The design as is where it keeps the bar; else, of :func:`candidates` taken in the
        order of the design's own objective (:func:`felt_miss`: the closest felt first), the
        first whose loop on the modes keeps it and whose gains pass eq. 9's acceptance test for
        the case's key and cell; else no design.

    Raises
    ------
    ValueError
        Gains or rates :func:`shared.full_loop.monodromy` refuses.
    """
    period = case.key.rates.servo_period_s * case.key.rates.ratio
    alone = alone_rate_per_s(case.modes, period)
    bar = modal_bar(alone)
    designed = staged_rate(case, case.design, hand_box, bar)
    if designed >= bar:
        return ModalVerdict(case.design, 1.0, bar, designed, designed, alone)
    rate, scale = designed, 1.0
    cands = [
        scaled_design(case.design, s, b_h, hold)
        for s, hold, b_h in candidates(case.design, case.key.b_h_max, grid_ratio)
    ]
    miss = felt_miss(cands, case.design.k_o, case.key.b_o, case.key)
    for i in sorted(range(len(cands)), key=lambda i: (miss[i], i)):
        cand, s = cands[i], cands[i].k_h / case.design.k_h
        rate, scale = staged_rate(case, cand, hand_box, bar), s
        if rate < bar:
            continue
        passed, _ = verify_gains(
            case.key, case.cell, grid_ratio, hand_box,
            k_h=cand.k_h, i_gain=cand.i_gain, b_h=cand.b_h, proxy_hold=cand.proxy_hold,
            own_gain=cand.own_gain,
        )  # fmt: skip
        if passed:
            return ModalVerdict(cand, s, bar, designed, rate, alone)
    return ModalVerdict(None, scale, bar, designed, rate, alone)
