"""The stability margin every local model's gains are held to on the full loop.

A design (:func:`shared.gain_design.design_gains`), interim gains
(:func:`shared.interim_gains.verify_gains`) and coupled users' gains
(:func:`shared.coupled_loop.verify_coupled`) are accepted only if every *oscillating* mode of the
full loop (:mod:`shared.full_loop`) decays at :data:`MIN_DECAY_RATE_PER_S` or faster, while creep
(modes slower than :data:`CREEP_FREQUENCY_HZ`) need only be stable. This module owns that margin,
the eigenvalue measure of it (:func:`mode_radii`) and the object stiffnesses K_o' a range of K_o is
checked at (:func:`k_o_points`).
"""

from __future__ import annotations

import math

import numpy as np

from haptic_collab.shared.types import FloatArray

#: Slowest accepted decay of any *oscillating* mode of the full loop [1/s]: its eigenvalue over
#: one simulation period must have magnitude at most exp(-MIN_DECAY_RATE * N * T). 1/s: a
#: vibration falls to a third within a second; the box's least damped hand (0.6 kg, 2 N*s/m) alone
#: decays at 1.7/s.
MIN_DECAY_RATE_PER_S = 1.0

#: Modes slower than this [Hz] are creep, not vibration (the integral slowly pushing a stiff hand
#: out): they need only be stable (|eigenvalue| < 1), not decay at MIN_DECAY_RATE_PER_S.
CREEP_FREQUENCY_HZ = 0.5

#: Largest ratio between neighbouring K_o points a design is checked at (:func:`k_o_points`).
K_O_CHECK_RATIO = 4.0


def mode_radii(
    M: FloatArray, rho_limit: float, rate_ratio: int, servo_period_s: float
) -> tuple[FloatArray, FloatArray]:
    """``(margin_radius, radius)`` of each monodromy matrix of ``M`` (..., n, n), each shape (...).

    ``radius`` is the spectral radius; ``margin_radius`` the largest eigenvalue magnitude with
    creep eigenvalues (slower than :data:`CREEP_FREQUENCY_HZ`: angle below
    ``2 pi CREEP_FREQUENCY_HZ N T`` per simulation period) counted as ``|lambda| * rho_limit``.
    """
    creep_angle = 2.0 * math.pi * CREEP_FREQUENCY_HZ * rate_ratio * servo_period_s
    ev = np.linalg.eigvals(M)
    mag = np.abs(ev)
    slow = np.abs(np.angle(ev)) < creep_angle
    return np.max(np.where(slow, mag * rho_limit, mag), axis=-1), np.max(mag, axis=-1)


def k_o_points(lo: float, hi: float) -> list[float]:
    """The K_o values [N/m] a design over ``[lo, hi]`` is checked at.

    ``lo``, the geometric middle and ``hi`` for a range up to :data:`K_O_CHECK_RATIO` wide; a
    geometric grid with a ratio of at most :data:`K_O_CHECK_RATIO` between neighbours beyond
    (a coupled contact's range reaches ``K_O_RIGID`` = 1e6 N/m: about 8 points from 150 N/m).
    """
    if hi <= lo:
        return [float(lo)]
    n = max(3, 1 + math.ceil(math.log(hi / lo) / math.log(K_O_CHECK_RATIO) - 1e-9))
    return [float(v) for v in np.geomspace(lo, hi, n)]
