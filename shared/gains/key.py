"""The gain key: what a local model's design depends on besides K_o, and its rules, once.

A :class:`GainKey` names one row of a :class:`shared.gains.table.GainTable`. The client session
(:class:`client.session.ClientSession`) and the server's gain advisor
(:class:`server.gains.GainAdvisor`) build theirs with the same function, :func:`make_gain_key`, from the
same rules:

- the loop delay in whole simulation ticks (:func:`loop_delay_ticks`) from the round trip;
- the object damping B_o (eq. 9: the damping over the simulation period, in N/m) quantized down
  to 1 N/m steps (a design for less object damping; on the full loop with the hand that is not
  always the safe side, so a key with B_o > 0 renders a design made for B_o = 0 only up to the
  B_o that design was checked for: :func:`shared.gains.choose.table_design`);
- the coupling class of ``K_o_stiff / K_o_eff`` (:func:`stiff_ratio_class`, docs/coupled-users.md)
  with its hysteresis (:func:`held_stiff_ratio`): it rises at once and falls only when the
  measured class is :data:`STIFF_CLASS_FALL` times lower;
- the K_o range a cell's design is checked over (:func:`coupled_k_o_hi`, :data:`STIFFER_BY`).

Pure: no clocks, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from haptic_collab.shared.gains.policy import (
    STIFF_CLASS_FALL,
    STIFF_RATIO_CLASSES,
    STIFFER_BY,
)
from haptic_collab.shared.rates import Rates

#: The local model's form: proportional (eq. 12 with I = 0) or proportional-integral.
Mode = Literal["p", "pi"]

#: Stiffness [N/m] that stands for a rigid differential mode (singular compliance, coupling -> 1),
#: the same value the server reports for a contact that cannot move (server.contact_stiffness.K_O_MAX).
K_O_RIGID = 1.0e6


def stiff_ratio_class(k_o_eff: float, k_o_stiff: float) -> float:
    """``K_o_stiff / K_o_eff`` rounded up to a class, for a gain-table key (SI, [N/m] in).

    1 for an uncoupled contact (ratio 1), else sqrt(2), 2, 2 sqrt(2), 4, 8, 16, ...,
    :data:`MAX_STIFF_RATIO_CLASS`, and ``inf`` (design against a rigid proxy) beyond
    (:data:`STIFF_RATIO_CLASSES`). A design checked up to :func:`coupled_k_o_hi` covers every
    modal stiffness of the contact's coupled group, and every lower class too (its range is a
    superset: :func:`covering_classes`).

    Half powers of 2 up to 4: on the liver FEM torus two users coupled at a ratio of 2.05 were
    designed for 4 with whole powers, and with 3 ticks of delay no compensated model passed
    there (a PI of K_h 41 N/m felt 0.72 of the object), whereas for 2.83 a compensated P of
    145 N/m passed (felt 1.02). Whole powers above 4, as checked against the coupled loop of 2
    and 3 users (docs/coupled-users.md): with half powers there, the paper's PI for a coupling
    of 0.9 (ratio 19, class 22.6) missed the coupled loop's margin by 0.001.

    Raises
    ------
    ValueError
        Non-positive or non-finite ``k_o_eff``; ``k_o_stiff`` below ``k_o_eff`` or NaN.
    """
    if not (math.isfinite(k_o_eff) and k_o_eff > 0.0):
        raise ValueError(f"k_o_eff must be a finite stiffness > 0 N/m, got {k_o_eff!r}")
    if not k_o_stiff >= k_o_eff * (1.0 - 1e-9):
        raise ValueError(f"k_o_stiff must be >= k_o_eff, got {k_o_stiff!r} < {k_o_eff!r}")
    ratio = k_o_stiff / k_o_eff
    if ratio <= 1.0 + 1e-9:
        return 1.0
    for q in STIFF_RATIO_CLASSES[1:]:
        if ratio <= q * (1.0 + 1e-9):
            return q
    return math.inf


def covering_classes(ratio_class: float) -> tuple[float, ...]:
    """The classes above ``ratio_class``, narrowest first: a design for any of them was checked
    over a K_o range that contains this class's (:func:`coupled_k_o_hi` grows with the class),
    so it may be rendered for this class without a further check."""
    return tuple(c for c in STIFF_RATIO_CLASSES if c > ratio_class)


def coupled_k_o_hi(k_o_hi: float, ratio_class: float) -> float:
    """Upper end [N/m] of the K_o range a coupled contact's design must be checked over.

    ``min(K_O_RIGID, k_o_hi * ratio_class)``: ``k_o_hi`` the upper end the single-user design
    would use (the gain table's next grid point), ``ratio_class`` from :func:`stiff_ratio_class`.
    """
    return float(min(K_O_RIGID, k_o_hi * ratio_class))


def loop_delay_ticks(round_trip_s: float, state_age_s: float, sim_rate_hz: float) -> int:
    """Extra loop delay D [whole simulation ticks] a design must cover.

    The force the server samples at tick k+1 reflects patch k only if the patch's trip down, the
    age of the client's state and its trip up fit in one simulation period; every further period
    adds one tick: ``ceil((round_trip + state_age) * rate) - 1``, at least 0.

    Parameters
    ----------
    round_trip_s : float
        Network round trip [s], >= 0.
    state_age_s : float
        Oldest age [s] of the state the server samples (the client's send interval), >= 0.
    sim_rate_hz : float
        Simulation rate [Hz], > 0.

    Raises
    ------
    ValueError
        Negative or non-finite times, or a non-positive rate.
    """
    for name, v in (("round_trip_s", round_trip_s), ("state_age_s", state_age_s)):
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{name} must be finite and >= 0 s, got {v!r}")
    if not (math.isfinite(sim_rate_hz) and sim_rate_hz > 0.0):
        raise ValueError(f"sim_rate_hz must be > 0, got {sim_rate_hz!r}")
    return max(0, math.ceil((round_trip_s + state_age_s) * sim_rate_hz - 1e-9) - 1)


@dataclass(frozen=True)
class GainKey:
    """What a design depends on besides K_o (hashable; one :class:`GainTable` row per key)."""

    servo_rate_hz: float
    sim_rate_hz: float
    delay_ticks: int
    mode: Mode
    margin: float
    k_h_max: float
    b_h_max: float
    b_o: float = 0.0
    #: ``K_o_stiff / K_o_eff`` class of the contact (:func:`stiff_ratio_class`):
    #: 1 uncoupled, 2, 4, ... 256 or inf (rigid) for users coupled through the object. A cell's
    #: design is checked up to ``coupled_k_o_hi(g_(i+1), stiff_ratio)`` (docs/coupled-users.md).
    stiff_ratio: float = 1.0
    #: Let the design use own-force compensation (:func:`design_gains`). For a coupled contact
    #: (``stiff_ratio > 1``) the design's range of K_o' covers the modal stiffnesses as for the
    #: paper's model; tests verify the result on the coupled loop of two and three users
    #: (:func:`shared.coupled_loop.verify_coupled`, docs/coupled-users.md).
    own_force: bool = True
    #: Fraction by which the object may be stiffer than the K_o reported (a model error: a
    #: viscoelastic or strain-stiffening object, a K_o estimated low): a cell's design is checked
    #: up to ``(1 + stiffer_by)`` times the top of its range, or up to that top plus ``b_o``
    #: where that is higher (:func:`cell_k_o_range`).
    stiffer_by: float = STIFFER_BY

    @property
    def rates(self) -> Rates:
        """The key's servo and simulation rates (raises ValueError when N is not whole)."""
        return Rates(self.servo_rate_hz, self.sim_rate_hz)


def held_stiff_ratio(current: float, k_o_eff: float, k_o_stiff: float) -> float:
    """The coupling class to design for: :func:`stiff_ratio_class` of the patch's ``k_o_eff`` and
    ``k_o_stiff`` [N/m] (``k_o_stiff`` below ``k_o_eff`` counts as ``k_o_eff``: uncoupled), held
    at ``current`` unless it is higher or :data:`STIFF_CLASS_FALL` times lower.

    Rising at once is the safe side (a design for a wider K_o range); falling late keeps a
    coupling that wavers around a class boundary from asking for a new design every tick.

    Raises
    ------
    ValueError
        As :func:`stiff_ratio_class`.
    """
    new = stiff_ratio_class(k_o_eff, max(k_o_eff, k_o_stiff))
    return new if new > current or new * STIFF_CLASS_FALL <= current else current


def make_gain_key(
    *,
    servo_rate_hz: float,
    sim_rate_hz: float,
    delay_ticks: int,
    mode: Mode,
    margin: float,
    k_h_max: float,
    b_h_max: float,
    b_o: float,
    stiff_ratio: float,
) -> GainKey:
    """The :class:`GainKey` of one user now: rates [Hz], loop delay [ticks], local model form,
    design margin, the device's K_h and B_h limits [N/m, N·s/m], the object damping ``b_o``
    [N/m] (eq. 9: the damping over the simulation period; quantized down to whole N/m, negative
    counts as 0) and the coupling class.
    """
    return GainKey(
        servo_rate_hz=float(servo_rate_hz),
        sim_rate_hz=float(sim_rate_hz),
        delay_ticks=int(delay_ticks),
        mode=mode,
        margin=float(margin),
        k_h_max=float(k_h_max),
        b_h_max=float(b_h_max),
        b_o=float(math.floor(max(0.0, b_o))),
        stiff_ratio=float(stiff_ratio),
    )
