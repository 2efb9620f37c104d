"""A lattice of hands finer than the design's hand box, and the full loop's worst spectral radius
over it: the independent re-check the gain design and gain table tests apply to designed gains.

The design (shared.gains.design) checks its candidates on the hands of ``HandBox.hands()`` (the
box's corners, face centres and centre); :data:`FINE_HANDS` spans the same ranges with 4 x 4 x 4
points plus the simulated hand, and :func:`worst_on_lattice` checks every force-sampling tick.
"""

from __future__ import annotations

import numpy as np

from haptic_collab.shared.full_loop import (
    DEFAULT_HAND,
    DEFAULT_HAND_BOX,
    Hand,
    spectral_radius,
)
from haptic_collab.shared.gains.design import GainDesign

SERVO_HZ = 1000.0
T = 1.0 / SERVO_HZ


def lattice(n: int = 4) -> list[Hand]:
    box = DEFAULT_HAND_BOX
    ms, bs, ks = (
        [float(v) for v in np.linspace(lo, hi, n)]
        for lo, hi in (box.mass_kg, box.damping_n_s_per_m, box.stiffness_n_per_m)
    )
    return [Hand(m, b, k) for m in ms for b in bs for k in ks] + [DEFAULT_HAND]


FINE_HANDS = lattice(4)


def worst_on_lattice(
    d: GainDesign,
    k_os: list[float],
    *,
    sim_rate_hz: float,
    delay_ticks: int,
    hands: list[Hand] = FINE_HANDS,
    b_o: float = 0.0,
) -> tuple[float, str]:
    """Largest full-loop spectral radius over hands x K_o' x every sampling tick, and where (on
    an object of B_o ``b_o`` [N/m], eq. 9: :mod:`shared.full_loop`)."""
    n = round(SERVO_HZ / sim_rate_hz)
    hs = [h for h in hands for _ in k_os]
    ko = np.tile(np.asarray(k_os, float), len(hands))
    rho = spectral_radius(
        hand=hs,
        k_o=ko,
        k_h=d.k_h,
        i_gain=d.i_gain,
        b_h=d.b_h,
        own_gain=d.own_gain,
        servo_period_s=T,
        rate_ratio=n,
        delay_ticks=delay_ticks,
        proxy_hold=d.proxy_hold,
        integral=d.i_gain > 0.0,
        b_o=b_o,
    )
    b, j = np.unravel_index(int(np.argmax(rho)), rho.shape)
    where = (
        f"hand {hs[b]}, K_o' = {ko[b]:g} N/m, sampling tick {j}; gains K_h = {d.k_h:g}, "
        f"I = {d.i_gain:g}, B_h = {d.b_h:g}, C_h = {d.own_gain:g}, {d.proxy_hold}"
    )
    return float(rho[b, j]), where
