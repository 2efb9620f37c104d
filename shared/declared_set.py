"""The set of environments the product's haptic stability is declared for, and random draws from it.

A guarantee is stated over a set and argued over all of it (docs/stability.md); this module is
where the set is written down, once, for the runtime (the port's passivity guard reads its
stiffness band, :mod:`shared.passivity`), the tests and ``haptic bench drawn``. Nothing here
reads a clock or the network.

The set, for one user rendering the product's own local model on the product's own client:

- **Objects**: every passive 1-D contact (force in, surface depth out, energy out never above
  energy in) whose local stiffness at the contact lies anywhere in ``[K_LO, K_HI]`` times the
  K_o the server reports, with any damping and any mass, whether the server reports its damping
  B_o or not, and whose stiffness or rest position may drift while it is touched. Why that wide:
  K_o is a linearisation (eq. 6); soft tissue stiffens severalfold at large strain (Fung,
  *Biomechanics*, 1993, ch. 7), a partner's press changes the stiffness a user meets
  (docs/coupled-users.md), an object's damping and mass are not in K_o, and a simulation
  plugged in by someone else may report K_o loosely.
- **Simulation rates** 10-100 Hz (the rates that divide a 1 kHz servo rate), **one-way delays**
  0-200 ms each way with jitter, packets reordered or late (latest wins).
- **Partners**: any number of other users on the same object running the product's own client,
  with the keys the server really sends (K_o, K_o_eff, K_o_stiff, B_o, own force, no rest
  plane), coupled to this user through the object by any amount below rigid.
- **Hands**: the hand box of :mod:`shared.full_loop` (mass 0.1-0.6 kg, damping 2-10 N*s/m,
  stiffness 20-1000 N/m as the probe feels them; Hogan 1989, Kuchenbecker et al. 2003, Fu and
  Hashtrudi-Zaad 2009), any of which is a passive impedance about the point the user aims at.

What "stable" means over it: the energy the device port gives the hand over a contact never
exceeds what the hand put in plus what the object's spring can hold at the current force
(:mod:`shared.passivity`), so no oscillation can grow and none can be sustained: an oscillation
needs energy every cycle and the port has none to give (Hannaford and Ryu 2002; Colgate and
Hogan 1988 for why a passive port and a passive hand cannot go unstable together).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

#: Lowest true local stiffness over the K_o reported that the product's transparency and its
#: passivity guard's credit are stated for (stability holds beyond it; docs/stability.md).
K_LO = 0.5
#: Highest true local stiffness over the K_o reported in the declared set.
K_HI = 2.0
#: Simulation rates [Hz] in the declared set: those in 10-100 Hz that divide a 1 kHz servo rate.
SIM_RATES_HZ: tuple[float, ...] = (10.0, 20.0, 25.0, 40.0, 50.0, 100.0)
#: Largest one-way network delay [s] in the declared set (each way).
MAX_ONE_WAY_DELAY_S = 0.2
#: Largest jitter [s] on top of the delay (uniform, each message on its own).
MAX_JITTER_S = 0.02
#: The hand box as the probe feels it (hand plus device), SI: :data:`shared.full_loop` docs.
HAND_MASS_KG = (0.1, 0.6)
HAND_DAMPING_N_S_PER_M = (2.0, 10.0)
HAND_STIFFNESS_N_PER_M = (20.0, 1000.0)

Family = Literal["spring", "two-mass", "hunt-crossley", "creep", "drift"]
FAMILIES: tuple[Family, ...] = ("spring", "two-mass", "hunt-crossley", "creep", "drift")


@dataclass(frozen=True, slots=True)
class DrawnObject:
    """One object of the declared set along the contact normal, relative to the K_o reported.

    Attributes
    ----------
    family : str
        ``spring`` (``m x'' + b x' + k x = F``); ``two-mass`` (a surface mass on ``k_1`` to an
        inner mass on ``k_2`` to ground, each damped by ``b``); ``hunt-crossley``
        (``F = k x^n (1 + lambda x')``, Hunt and Crossley 1975); ``creep`` (Kelvin-Voigt whose
        rest position follows the surface with time constant ``creep_time_s``: plastic flow);
        ``drift`` (a spring whose stiffness wanders by ``drift`` over ``drift_period_s``).
    k_ratio : float
        True static local stiffness (for ``hunt-crossley``: the tangent at the press's depth)
        over the K_o the server reports, in [K_LO, K_HI].
    damping_n_s_per_m, mass_kg : float
        Viscous damping b [N*s/m] and surface mass [kg], >= 0.
    inner_mass_kg, inner_split : float
        ``two-mass``: the inner mass [kg] and ``k_1 / (k_1 + k_2)`` in (0, 1).
    exponent, hc_lambda_s_per_m : float
        ``hunt-crossley``: n >= 1 and lambda [s/m].
    creep_time_s : float
        ``creep``: time constant [s] of the rest position.
    drift, drift_period_s : float
        ``drift``: relative amplitude (the stiffness stays in the band) and period [s].
    b_o_reported : bool
        Whether the server reports the object's damping as B_o = b / (N T) (eq. 9).
    """

    family: Family
    k_ratio: float
    damping_n_s_per_m: float = 0.0
    mass_kg: float = 0.0
    inner_mass_kg: float = 0.0
    inner_split: float = 0.5
    exponent: float = 1.0
    hc_lambda_s_per_m: float = 0.0
    creep_time_s: float = 0.0
    drift: float = 0.0
    drift_period_s: float = 1.0
    b_o_reported: bool = False


@dataclass(frozen=True, slots=True)
class DrawnHand:
    """A hand of the box as the probe feels it (hand plus device), SI units."""

    mass_kg: float
    damping_n_s_per_m: float
    stiffness_n_per_m: float


@dataclass(frozen=True, slots=True)
class DrawnCondition:
    """One condition drawn from the declared set.

    Attributes
    ----------
    seed, index : int
        The run's seed and this condition's place in the draw (it can be drawn again alone).
    k_o : float
        K_o the server reports at the user's contact [N/m].
    sim_rate_hz : float
    one_way_delay_s, jitter_s : float
    users : int
        1 (alone) or more (partners press and let go while the user holds).
    coupling : float
        Normalised cross-compliance between any two contacts, in [0, 1) (0 with one user).
    obj : DrawnObject
    force_n : float
        Force [N] the user aims to hold.
    """

    seed: int
    index: int
    k_o: float
    sim_rate_hz: float
    one_way_delay_s: float
    jitter_s: float
    users: int
    coupling: float
    obj: DrawnObject
    force_n: float


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def draw_object(rng: np.random.Generator, family: Family | None = None) -> DrawnObject:
    """An object of the declared set, its family uniform over :data:`FAMILIES` unless given."""
    fam: Family = family if family is not None else FAMILIES[int(rng.integers(len(FAMILIES)))]
    r = _log_uniform(rng, K_LO, K_HI)
    b = float(rng.choice([0.0, _log_uniform(rng, 0.5, 50.0)]))
    m = float(rng.choice([0.0, _log_uniform(rng, 0.005, 0.5)]))
    reported = bool(rng.integers(2))
    if fam == "two-mass":
        return DrawnObject(
            fam, r, b, max(m, 0.01), _log_uniform(rng, 0.01, 1.0), float(rng.uniform(0.2, 0.8)),
            b_o_reported=reported,
        )  # fmt: skip
    if fam == "hunt-crossley":
        return DrawnObject(
            fam, r, 0.0, 0.0, exponent=float(rng.uniform(1.0, 1.5)),
            hc_lambda_s_per_m=_log_uniform(rng, 0.05, 2.0), b_o_reported=reported,
        )  # fmt: skip
    if fam == "creep":
        return DrawnObject(
            fam, r, max(b, 0.5), m, creep_time_s=_log_uniform(rng, 0.5, 20.0),
            b_o_reported=reported,
        )  # fmt: skip
    if fam == "drift":
        # the stiffness wanders inside the band: r * exp(+-a) stays in [K_LO, K_HI]
        room = min(math.log(r / K_LO), math.log(K_HI / r))
        return DrawnObject(
            fam, r, b, m, drift=float(rng.uniform(0.0, max(room, 0.0))),
            drift_period_s=_log_uniform(rng, 0.3, 5.0), b_o_reported=reported,
        )  # fmt: skip
    return DrawnObject(fam, r, b, m, b_o_reported=reported)


def draw_hand(rng: np.random.Generator) -> DrawnHand:
    """A hand of the box: a corner with probability 1/2 (stability is worst near corners), else
    anywhere inside (log-uniform in each axis)."""
    box = (HAND_MASS_KG, HAND_DAMPING_N_S_PER_M, HAND_STIFFNESS_N_PER_M)
    if rng.integers(2):
        m, b, k = (float(lim[int(rng.integers(2))]) for lim in box)
    else:
        m, b, k = (_log_uniform(rng, lo, hi) for lo, hi in box)
    return DrawnHand(m, b, k)


def draw_conditions(
    seed: int,
    n: int,
    *,
    users: tuple[int, ...] = (1, 2, 3),
    k_o_n_per_m: tuple[float, float] = (100.0, 2000.0),
) -> list[DrawnCondition]:
    """``n`` conditions drawn from the declared set with ``seed`` (the same seed, the same draw).

    Users are drawn uniformly from ``users``; with partners the object is a coupled linear
    spring-damper-mass (``family`` ``spring``, coupling uniform in [0, 0.9]), alone any family.
    K_o is log-uniform over ``k_o_n_per_m`` [N/m]; the delay uniform over 0-200 ms one way, the
    jitter up to a fifth of it (at most :data:`MAX_JITTER_S`); the rate uniform over
    :data:`SIM_RATES_HZ`; the force aimed at 0.5-2 N (below the Phantom's continuous 1.75 N
    where possible).
    """
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        u = int(users[int(rng.integers(len(users)))])
        obj = draw_object(rng, "spring" if u > 1 else None)
        delay = float(rng.uniform(0.0, MAX_ONE_WAY_DELAY_S))
        out.append(
            DrawnCondition(
                seed=seed,
                index=i,
                k_o=_log_uniform(rng, *k_o_n_per_m),
                sim_rate_hz=float(SIM_RATES_HZ[int(rng.integers(len(SIM_RATES_HZ)))]),
                one_way_delay_s=delay,
                jitter_s=float(rng.uniform(0.0, min(MAX_JITTER_S, 0.2 * delay))),
                users=u,
                coupling=float(rng.uniform(0.0, 0.9)) if u > 1 else 0.0,
                obj=obj,
                force_n=float(rng.uniform(0.5, 2.0)),
            )
        )
    return out
