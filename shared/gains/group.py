"""A coupled pair checked as rendered: may a resting user keep its gains when another couples?

Each user of a coupled group is designed alone, over its whole modal range, as if its partner
were rigid (:mod:`shared.gains.coupled_design`): stable whatever the others render, so every
client may choose alone. That can ask more than the pair as rendered needs. On the stress torus
at 2 ticks of delay the resting user's uncoupled design (a compensated P, K_h 1000 N/m) beside
the arriving user's coupled design meets the margin on their coupled loop (radius 0.889), yet
its own coupled key's design is the paper's PI at K_h 270 N/m: a felt step of x5.45 as the press
arrives (docs/coupled-users.md, ``tools/coupled_pair_check.py``).

The server knows the contacts' compliance and both users' keys, so it can check the pair as
rendered: :class:`PairCase` is the resting user ``held`` keeping its uncoupled design, the other
user ``partner`` rendering its coupled key's design, on the coupled loop of two contacts
(:func:`shared.coupled_loop.verify_coupled`: every hand of the box per user, sampling ticks 0,
N/2 and N - 1 per user, all combinations, the K_o margin). A verdict holds for a *bucket*: the
grid cell of the held user's K_o, the cell of the partner's K_o_eff and the coupling class. The
check covers the bucket at its corners: both cells' ends and the class's coupling at its lower
end, its geometric middle and its upper end, each user's design scaled to its K_o there as the
table scales it (:meth:`shared.gains.design.GainDesign.at`), at the keys' object damping and at
none. A grid, not a proof, as the designs' own K_o points are. The sign of the coupling does not
matter: a compliance with ``-C_12`` is ``S C S`` with ``S = diag(1, -1)``, and negating every
state of the second user (hand, device, local model, proxy, force: linear, odd) carries one loop
into the other, so both have the same eigenvalues; a press that lifts the other contact (the
stress ant, ``C_12 < 0``) is checked as one that sinks it.

Pure: no clock, no I/O. :func:`pair_points` builds the loops to check (table lookups, cheap);
:func:`check_pair` verifies them (about 0.1 s each on this 2-core machine: the server runs it in
its design worker, never on the simulation tick).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from haptic_collab.shared.coupled_compliance import compliance_matrix
from haptic_collab.shared.coupled_loop import UserGains, verification_hands, verify_coupled
from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import STIFF_RATIO_CLASSES

#: A table lookup: the design a key's cell renders at a K_o [N/m], or None.
Lookup = Callable[[GainKey, float], GainDesign | None]


@dataclass(frozen=True)
class PairBucket:
    """Where a pair verdict holds: the held user's uncoupled key and the grid cell of its K_o,
    the partner's key and the cell of its K_o_eff, and the pair's measured coupling class
    (K_o_stiff / K_o_eff rounded up, :func:`shared.gains.key.stiff_ratio_class`; the partner's
    key may hold a higher one)."""

    held_key: GainKey
    held_cell: int
    partner_key: GainKey
    partner_cell: int
    ratio_class: float


@dataclass(frozen=True)
class PairPoint:
    """One coupled loop to check: the contacts' K_o [N/m], their coupling c in [0, 1) (the
    compliance ``C_ij = c / sqrt(K_o,i K_o,j)``) and the gains each user renders there."""

    k_o: tuple[float, float]
    coupling: float
    gains: tuple[UserGains, UserGains]


@dataclass(frozen=True)
class PairCase:
    """A pair check to run: the loops of a bucket (:func:`pair_points`) and the loop's facts
    (``delay_ticks``: the held user's and the partner's, each its key's)."""

    bucket: PairBucket
    points: tuple[PairPoint, ...]
    b_o: tuple[tuple[float, float], ...]
    servo_rate_hz: float
    sim_rate_hz: float
    delay_ticks: tuple[int, int]
    margin: float
    hand_box: HandBox


def coupling_of_ratio(ratio: float) -> float:
    """The coupling c of two contacts whose modal stiffnesses differ by ``ratio`` =
    K_o_stiff / K_o_eff >= 1: the eigenvalues of ``D^1/2 C D^1/2`` are ``1 +- c``, so
    ``ratio = (1 + c) / (1 - c)``."""
    return (ratio - 1.0) / (ratio + 1.0)


def class_ratios(ratio_class: float) -> tuple[float, ...]:
    """The ratios K_o_stiff / K_o_eff a class's verdict is checked at: the class below's bound
    (exclusive in the class, its limit), the geometric middle and the class itself. Empty for the
    uncoupled class 1 and the rigid class (``inf``: no finite coupling bounds it)."""
    if ratio_class <= 1.0 or not math.isfinite(ratio_class):
        return ()
    i = STIFF_RATIO_CLASSES.index(ratio_class)
    lo = STIFF_RATIO_CLASSES[i - 1]
    return (lo, math.sqrt(lo * ratio_class), ratio_class)


def pair_points(
    bucket: PairBucket, lookup: Lookup, grid_point: Callable[[int], float]
) -> tuple[PairPoint, ...] | None:
    """The coupled loops that stand for ``bucket``, or None where a design is missing or the
    class has no finite bound.

    The held user's K_o at both ends of its cell (``g_i`` and just below ``g_(i+1)``), the
    partner's K_o_eff likewise, the coupling at :func:`class_ratios`; the partner's own K_o is
    ``K_o_eff (1 + c)`` (two contacts: ``K_o_eff = K_o / (1 + c)``). Each user renders its key's
    design at its reported stiffness: the held user its uncoupled design at its K_o (what it
    rendered alone), the partner its coupled design at its K_o_eff.

    Parameters
    ----------
    bucket : PairBucket
    lookup : callable (key, k_o) -> GainDesign or None
        The table's rule (:func:`shared.gains.choose.table_design`).
    grid_point : callable (cell) -> float
        The table's grid point g_i [N/m].
    """
    ratios = class_ratios(bucket.ratio_class)
    if not ratios:
        return None
    below = 1.0 - 1e-9  # just inside the cell's upper end
    held_k = (grid_point(bucket.held_cell), grid_point(bucket.held_cell + 1) * below)
    partner_k = (grid_point(bucket.partner_cell), grid_point(bucket.partner_cell + 1) * below)
    out: list[PairPoint] = []
    for kh in held_k:
        held = lookup(bucket.held_key, kh)
        if held is None:
            return None
        for ke in partner_k:
            partner = lookup(bucket.partner_key, ke)
            if partner is None:
                return None
            for ratio in ratios:
                c = coupling_of_ratio(ratio)
                out.append(
                    PairPoint(
                        (kh, ke * (1.0 + c)),
                        c,
                        (UserGains.from_design(held), UserGains.from_design(partner)),
                    )
                )
    return tuple(out)


@dataclass(frozen=True)
class PairVerdict:
    """A pair check's answer: ``meets_margin`` at every point, and the largest margin radius
    (:class:`shared.coupled_loop.CoupledVerdict`) over them against the bound ``rho_limit``."""

    meets_margin: bool
    margin_radius: float
    rho_limit: float
    points: int


def check_pair(case: PairCase) -> PairVerdict:
    """Verify every loop of ``case`` (stops at the first that misses the margin).

    Raises
    ------
    ValueError
        As :func:`shared.coupled_loop.verify_coupled` (rates, margin, gains).
    """
    worst = 0.0
    limit = 1.0
    checked = 0
    hands = verification_hands(case.hand_box)
    for p in case.points:
        compliance = compliance_matrix(list(p.k_o), p.coupling)
        for b_o in case.b_o:
            v = verify_coupled(
                compliance,
                p.gains,
                b_o=np.asarray(b_o, dtype=float),
                servo_rate_hz=case.servo_rate_hz,
                sim_rate_hz=case.sim_rate_hz,
                delay_ticks=case.delay_ticks,
                margin=case.margin,
                hands=hands,
            )
            checked += 1
            worst, limit = max(worst, float(v.margin_radius)), float(v.rho_limit)
            if not v.meets_margin:
                return PairVerdict(False, worst, limit, checked)
    return PairVerdict(True, worst, limit, checked)
