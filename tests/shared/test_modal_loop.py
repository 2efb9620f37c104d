"""The full loop closed over an object's modes (shared.modal_loop), and the FEM contact's modes
it takes (server.objects.fem.FemSolid.contact_modes).

What a user would notice: the gain design checks a contact on eq. 9's K_o and B_o, which is
all the server reports; a FEM solid's lowest modes ring for many ticks beyond that. The check on
the solid's own modes must be the same loop as the design's wherever the object is the same
(no modes: eq. 9 without damping, to rounding), its object must move as the solid does under
the same pushes, and on the liver ball it must see what the demos saw: a resting hand's wobble
that outlasts the design's decay margin (docs/palpation.md, docs/fem.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from haptic_collab.server.objects.fem import FemParams, FemSolid
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, Hand, monodromy
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S, MODAL_CHECK_MODES
from haptic_collab.shared.modal_loop import (
    ContactModes,
    decay_rate_per_s,
    decay_rates,
    modal_decay_rates,
    modal_monodromy,
)
from tests.support.fem_contact import contact_key, liver_ball


def spectral_radius(m: np.ndarray) -> np.ndarray:
    return np.max(np.abs(np.linalg.eigvals(m)), axis=-1)


HANDS = [
    Hand(mass_kg=0.645, damping_n_s_per_m=2.5, stiffness_n_per_m=20.0),  # heavy, loosely held
    Hand(mass_kg=0.145, damping_n_s_per_m=2.5, stiffness_n_per_m=1000.0),  # light, firm
    Hand(mass_kg=0.495, damping_n_s_per_m=5.5, stiffness_n_per_m=300.0),  # the demo's
]


@pytest.fixture(scope="module")
def liver_side(tmp_path_factory):
    """The default sphere's shape in liver (a cheaper mesh), its side contact's modes."""
    solid = liver_ball(str(tmp_path_factory.mktemp("volumes")))
    key = contact_key(solid, "side")
    return solid, key, solid.contact_modes(key)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("delay", [0, 2])
def test_without_modes_it_is_the_designs_own_loop(hold, delay) -> None:
    static = ContactModes(a=np.zeros((0, 0)), b=np.zeros(0), c=np.zeros(0), d=1 / 300.0)
    for gains in (
        {"k_h": 150.0, "b_h": 3.0, "own_gain": 1 / 150.0},
        {"k_h": 80.0, "i_gain": 900.0},
    ):
        ours = spectral_radius(
            modal_monodromy(hand=HANDS, modes=static, delay_ticks=delay, proxy_hold=hold, **gains)
        )
        design = spectral_radius(
            monodromy(hand=HANDS, k_o=300.0, delay_ticks=delay, proxy_hold=hold, **gains)
        )
        assert np.allclose(ours, design, rtol=0.0, atol=1e-12)


def test_the_contacts_modes_move_as_the_solid_does(liver_side) -> None:
    solid, key, modes = liver_side
    patch = solid.patch(key)
    dofs = (3 * patch.indices[:, None] + np.arange(3)).ravel()
    b = (patch.weights[:, None] * patch.normal[None, :]).ravel()
    z = np.zeros(len(modes.b))
    solid.reset()
    pushes = np.random.default_rng(1).uniform(0.0, 1.0, 25)
    for f in pushes:
        solid.step([key], [f])
        depth = -(b @ solid.linear_displacement.ravel()[dofs])
        z = modes.a @ z + modes.b * f
        assert modes.c @ z + modes.d * f == pytest.approx(depth, rel=1e-9, abs=1e-15)
    # the first tick of a step push is the one-tick compliance B_o is defined by
    k_o = solid.contact_stiffness([key])[0]
    b_o = solid.contact_damping([key])[0]
    assert modes.step_response(1)[0] == pytest.approx(1.0 / (k_o + b_o), rel=1e-9)
    assert modes.step_response(400)[-1] == pytest.approx(modes.c_static, rel=1e-3)
    assert modes.c_static == pytest.approx(1.0 / k_o, rel=1e-9)


def test_fewer_modes_keep_the_static_compliance_and_the_verdict(liver_side) -> None:
    _, _, modes = liver_side
    few = modes.reduced(20)
    assert few.mode_count == 20 < modes.mode_count
    assert few.c_static == pytest.approx(modes.c_static, rel=1e-9)  # the rest folded in, static
    gains = {"k_h": 72.0, "b_h": 5.0, "own_gain": 1 / 72.0, "proxy_hold": "foh"}
    full = modal_decay_rates(hands=HANDS, modes=modes, **gains)
    assert np.allclose(modal_decay_rates(hands=HANDS, modes=few, **gains), full, atol=0.05)


def _mode(static_m_per_n: float, freq_hz: float, zeta: float, period_s: float = 0.05):
    """One mode, ``q'' + 2 zeta w q' + w^2 q = w^2 s F``, depth ``q``, stepped exactly over a
    period with the push held: its ``(a, b, c)``."""
    from scipy.linalg import expm

    w = 2.0 * np.pi * freq_hz
    cont = np.zeros((3, 3))
    cont[:2, :2] = [[0.0, 1.0], [-(w**2), -2.0 * zeta * w]]
    cont[1, 2] = w**2 * static_m_per_n
    step = expm(cont * period_s)
    return step[:2, :2], step[:2, 2], np.array([1.0, 0.0])


def test_fewer_modes_keep_the_one_that_rings_not_the_largest_static_share() -> None:
    """A stiff, overdamped mode that settles within a period holds most of the compliance; a
    lightly damped 2 Hz one little of it, but rings for seconds. One mode kept is the ringing
    one: the reduced contact then moves as the whole one does, and the settling one, folded
    into the static residual, costs nothing a loop would see."""
    settles = _mode(4e-3, 30.0, 1.0)
    rings = _mode(5e-4, 2.0, 0.02)
    a = np.zeros((4, 4))
    a[:2, :2], a[2:, 2:] = settles[0], rings[0]
    modes = ContactModes(
        a=a, b=np.concatenate([settles[1], rings[1]]), c=np.concatenate([settles[2], rings[2]]),
        d=1e-4,
    )  # fmt: skip
    shares = modes.static_shares()
    assert shares[0] > 5 * shares[1]  # by static share the settling mode would be kept
    one = modes.reduced(1)
    assert one.mode_count == 1 and np.allclose(one.a, rings[0])
    assert one.c_static == pytest.approx(modes.c_static, rel=1e-12)
    whole = modes.step_response(60)
    assert np.max(np.abs(one.step_response(60) - whole)) < 0.02 * modes.c_static
    by_share = ContactModes(a=settles[0], b=settles[1], c=settles[2], d=modes.d + shares[1])
    assert np.max(np.abs(by_share.step_response(60) - whole)) > 0.1 * shares[1]


def test_on_the_liver_ball_six_modes_stand_for_forty_and_err_slow(liver_side) -> None:
    """The server checks 6 modes (:data:`MODAL_CHECK_MODES`): on the liver ball's side the
    slowest decay over the box's corners and centre is within 0.02/s of 40 modes' and never
    visibly faster, so gains that keep a bar on the 6 keep it on the solid."""
    _, _, modes = liver_side
    hands = DEFAULT_HAND_BOX.screen_hands()
    for gains in (
        {"k_h": 72.0, "b_h": 5.0, "own_gain": 1 / 72.0, "proxy_hold": "foh"},  # rings on
        {"k_h": 34.0, "b_h": 7.5, "own_gain": 1 / 34.0, "proxy_hold": "foh"},  # dies out
    ):
        for delay in (0, 1):
            loop = {"hands": hands, "delay_ticks": delay, **gains}
            ref = modal_decay_rates(modes=modes.reduced(40), **loop).min()
            six = modal_decay_rates(modes=modes.reduced(MODAL_CHECK_MODES), **loop).min()
            assert ref - 0.02 <= six <= ref + 0.002


def test_on_the_liver_ball_a_hand_keeps_the_rocking_going_past_the_design_margin(liver_side):
    """Gains the design's loop passes with room to spare (eq. 9: 2-7/s) let the ball's lowest
    mode, which alone decays at about 1.1/s, die out more slowly than the 1/s margin with the
    demo's hand and the firm one: the resting hand's lingering wobble of the palpation demos."""
    solid, key, modes = liver_side
    k_o = solid.contact_stiffness([key])[0]
    b_o = solid.contact_damping([key])[0]
    gains = {"k_h": 72.0, "b_h": 5.0, "own_gain": 1 / 72.0, "proxy_hold": "foh"}
    eq9_rates = decay_rates(monodromy(hand=HANDS, k_o=k_o, b_o=b_o, **gains))
    assert min(eq9_rates) > 1.5 * MIN_DECAY_RATE_PER_S
    alone = decay_rate_per_s(float(np.abs(np.linalg.eigvals(modes.a)).max()), 0.05)
    assert MIN_DECAY_RATE_PER_S < alone < 1.3
    rates = modal_decay_rates(hands=HANDS, modes=modes.reduced(20), **gains)
    assert rates[1] < 0.5 * MIN_DECAY_RATE_PER_S  # the firm hand
    assert rates[2] < MIN_DECAY_RATE_PER_S  # the demo's hand


def test_the_direct_reference_is_the_hand_on_the_solid_itself(tmp_path) -> None:
    """direct_decay_rates' loop, tick by tick, against the solid stepped at 1 ms with the pad's
    force solved from its look-ahead (tools/landing_reference.py's coupling, never leaving the
    surface): the same probe to rounding, and the decay its eigenvalues give."""
    from haptic_collab.shared.full_loop import _hand_zoh
    from haptic_collab.shared.modal_loop import direct_decay_rates

    ball = default_balloon(0.1, 2)
    solid = FemSolid(
        ball, FemParams(rayleigh_alpha=1.11, sim_period_s=1e-3), cache_dir=str(tmp_path)
    )
    key = solid.patch_key([0.1, 0.0, 0.0], normal=[1, 0, 0])
    modes = solid.contact_modes(key)
    patch = solid.patch(key)
    dofs = (3 * patch.indices[:, None] + np.arange(3)).ravel()
    b = (patch.weights[:, None] * patch.normal[None, :]).ravel()
    hand = HANDS[1]
    k_pad, b_pad = 1000.0, 5.0
    phi, gam = _hand_zoh(
        np.array([hand.mass_kg]), np.array([hand.damping_n_s_per_m]),
        np.array([hand.stiffness_n_per_m]), 1e-3,
    )  # fmt: skip
    c_t = float(modes.c @ modes.b) + modes.d

    def depth() -> float:
        return float(-(b @ solid.linear_displacement.ravel()[dofs]))

    xv = np.array([2e-3, 0.0])  # the probe 2 mm in, still: the pad pushes it back out
    z = np.zeros(len(modes.b))
    for _ in range(300):
        mark = solid.checkpoint()
        solid.step([key], [0.0])
        free = depth()
        solid.rewind(mark)
        f = (k_pad * (xv[0] - free) + b_pad * xv[1]) / (1.0 + k_pad * c_t)
        solid.step([key], [f])
        # the matrix's own step of the same state
        f_m = (k_pad * (xv[0] - modes.c @ modes.a @ z) + b_pad * xv[1]) / (1.0 + k_pad * c_t)
        assert f_m == pytest.approx(f, rel=1e-9, abs=1e-12)
        z = modes.a @ z + modes.b * f
        assert modes.c @ z + modes.d * f == pytest.approx(depth(), rel=1e-9, abs=1e-15)
        xv = phi[0] @ xv + gam[0] * f
    rate = direct_decay_rates(
        hands=[hand], modes=modes, pad_stiffness_n_per_m=k_pad, pad_damping_n_s_per_m=b_pad,
        period_s=1e-3,
    )  # fmt: skip
    assert rate[0] > 0.0  # a passive hand on a passive solid dies out
