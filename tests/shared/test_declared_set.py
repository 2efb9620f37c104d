"""The declared set (shared/declared_set.py): draws stay inside it and a seed draws the same
conditions again, so a run of ``haptic bench drawn`` can be repeated from its printed seed."""

from __future__ import annotations

import numpy as np

from haptic_collab.shared.declared_set import (
    FAMILIES,
    HAND_DAMPING_N_S_PER_M,
    HAND_MASS_KG,
    HAND_STIFFNESS_N_PER_M,
    K_HI,
    K_LO,
    MAX_JITTER_S,
    MAX_ONE_WAY_DELAY_S,
    SIM_RATES_HZ,
    draw_conditions,
    draw_hand,
)


def test_a_seed_draws_the_same_conditions_and_another_seed_others():
    assert draw_conditions(7, 20) == draw_conditions(7, 20)
    assert draw_conditions(7, 20) != draw_conditions(8, 20)


def test_every_draw_lies_in_the_declared_set():
    conds = draw_conditions(123, 400)
    for c in conds:
        assert K_LO <= c.obj.k_ratio <= K_HI
        assert c.sim_rate_hz in SIM_RATES_HZ and 1000.0 % c.sim_rate_hz == 0.0
        assert 0.0 <= c.one_way_delay_s <= MAX_ONE_WAY_DELAY_S
        assert 0.0 <= c.jitter_s <= MAX_JITTER_S
        assert 0.0 <= c.coupling < 1.0
        assert (c.users == 1) == (c.coupling == 0.0)
        if c.obj.family == "drift":  # the wandering stiffness stays in the band
            assert K_LO <= c.obj.k_ratio * np.exp(-c.obj.drift) - 1e-12
            assert c.obj.k_ratio * np.exp(c.obj.drift) <= K_HI + 1e-12
    # the draw reaches every family, both B_o cases, several users and both ends of the delays
    assert {c.obj.family for c in conds if c.users == 1} == set(FAMILIES)
    assert {c.obj.b_o_reported for c in conds} == {True, False}
    assert {c.users for c in conds} == {1, 2, 3}
    delays = [c.one_way_delay_s for c in conds]
    assert min(delays) < 0.02 and max(delays) > 0.18


def test_hands_come_from_the_box_corners_included():
    rng = np.random.default_rng(5)
    hands = [draw_hand(rng) for _ in range(400)]
    for h in hands:
        assert HAND_MASS_KG[0] <= h.mass_kg <= HAND_MASS_KG[1]
        assert HAND_DAMPING_N_S_PER_M[0] <= h.damping_n_s_per_m <= HAND_DAMPING_N_S_PER_M[1]
        assert HAND_STIFFNESS_N_PER_M[0] <= h.stiffness_n_per_m <= HAND_STIFFNESS_N_PER_M[1]
    corners = {(h.mass_kg, h.damping_n_s_per_m, h.stiffness_n_per_m) for h in hands}
    assert (0.6, 2.0, 1000.0) in corners and (0.1, 10.0, 20.0) in corners
