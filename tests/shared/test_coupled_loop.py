"""Several PI users coupled through the object's compliance (docs/coupled-users.md).

The time-domain reference below is written independently of shared.coupled_loop and
shared.full_loop: its own hand integrator (semi-implicit Euler with fine sub-steps), its own local
models, decimators, object (x_o = C F at the simulation rate), delay line and proxy holds, stepped
tick by tick for every user.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections import deque
from collections.abc import Sequence

import numpy as np
import pytest

from haptic_collab.server.contact_stiffness import effective_stiffness
from haptic_collab.shared.coupled_compliance import compliance_matrix, modal_stiffness
from haptic_collab.shared.coupled_loop import (
    UserGains,
    coupled_monodromy,
    coupled_spectral_radius,
    verification_hands,
    verify_coupled,
)
from haptic_collab.shared.full_loop import DEFAULT_HAND, DEFAULT_HAND_BOX, Hand, spectral_radius
from haptic_collab.shared.gains.coupled_design import CoupledDesign, design_coupled
from haptic_collab.shared.gains.design import GainDesign, design_gains
from haptic_collab.shared.gains.key import (
    K_O_RIGID,
    coupled_k_o_hi,
    covering_classes,
    stiff_ratio_class,
)

#: The simulated Phantom Desktop's limits (client.devices.profiles "phantom-desktop"): the gains
#: the product renders for it.
K_H_MAX, B_H_MAX = 1000.0, 10.0

HEAVY = Hand(mass_kg=0.6, damping_n_s_per_m=2.0, stiffness_n_per_m=20.0)  # the box's worst
LIGHT_STIFF = Hand(mass_kg=0.1, damping_n_s_per_m=10.0, stiffness_n_per_m=1000.0)


@functools.cache
def _single(k_o: float, delay: int) -> GainDesign:
    """The product's per-user design for a reported stiffness (client.session via GainTable)."""
    return design_gains(k_o, delay_ticks=delay, k_h_max=K_H_MAX, b_h_max=B_H_MAX)


@functools.cache
def _coupled(k_o: float, coupling: float, users: int, delay: int) -> CoupledDesign:
    return design_coupled(
        compliance_matrix(k_o, coupling, users),
        delay_ticks=delay,
        k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
    )


# ------------------------------------------------------------------------------------------
# the model


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("delay", [0, 2])
@pytest.mark.parametrize("b_o", [0.0, 150.0])
@pytest.mark.parametrize("own", [0.0, 1.0 / 700.0])
def test_one_user_reproduces_the_full_loop(hold: str, delay: int, b_o: float, own: float) -> None:
    hands = [*DEFAULT_HAND_BOX.corners(), DEFAULT_HAND]
    i_gain = 0.0 if own else 3000.0  # compensation goes with a proportional model
    g = UserGains(k_h=400.0, i_gain=i_gain, b_h=3.0, proxy_hold=hold, own_gain=own)  # type: ignore[arg-type]
    rho = coupled_spectral_radius(
        compliance=[[1.0 / 700.0]],
        gains=[g],
        hands=[[h] for h in hands],
        b_o=b_o,
        delay_ticks=delay,
    )
    ref = spectral_radius(
        hand=hands,
        k_o=700.0,
        k_h=400.0,
        i_gain=i_gain,
        b_h=3.0,
        b_o=b_o,
        own_gain=own,
        delay_ticks=delay,
        proxy_hold=hold,  # type: ignore[arg-type]
    )
    assert rho.shape == (len(hands), 50)
    np.testing.assert_allclose(rho, ref, rtol=0.0, atol=1e-9)


def test_one_rigid_probe_reproduces_the_paper_loop() -> None:
    g = UserGains(k_h=250.0, i_gain=2000.0)
    rho = coupled_spectral_radius(compliance=[[1.0 / 300.0]], gains=[g], hands=[[None]])
    ref = spectral_radius(hand=None, k_o=300.0, k_h=250.0, i_gain=2000.0)
    np.testing.assert_allclose(rho, ref, atol=1e-9)


@pytest.mark.parametrize("users", [2, 3])
def test_identical_users_split_into_single_user_loops_at_the_modal_stiffnesses(users: int) -> None:
    """Modal decomposition: same hand, gains and tick for everyone -> max over 1/lambda_i(C)."""
    c = compliance_matrix(500.0, 0.7, users)
    modal = modal_stiffness(c)
    g = UserGains(k_h=400.0, i_gain=3000.0, b_h=3.0, proxy_hold="foh")
    for hand in (HEAVY, LIGHT_STIFF, DEFAULT_HAND):
        rho = coupled_spectral_radius(
            compliance=c,
            gains=[g] * users,
            hands=[[hand] * users],
            sample_ticks=[[5] * users, [49] * users],
            b_o=100.0,
            delay_ticks=1,
        )[0]
        for col, j in enumerate((5, 49)):
            single = [
                spectral_radius(
                    hand=hand,
                    k_o=k,
                    k_h=400.0,
                    i_gain=3000.0,
                    b_h=3.0,
                    b_o=100.0,
                    delay_ticks=1,
                    sample_ticks=[j],
                    proxy_hold="foh",
                )[0, 0]
                for k in (modal.k_o_eff[0], modal.k_o_stiff[0])
            ]
            assert rho[col] == pytest.approx(max(single), abs=1e-9)


def test_compliance_and_modal_stiffnesses() -> None:
    c = compliance_matrix(300.0, 0.9, 3)
    assert c.shape == (3, 3)
    np.testing.assert_allclose(np.diag(c), 1.0 / 300.0)
    assert c[0, 1] == pytest.approx(0.9 / 300.0)
    m = modal_stiffness(c)
    np.testing.assert_allclose(m.k_o, 300.0)
    np.testing.assert_allclose(m.k_o_eff, 300.0 / (1.0 + 2 * 0.9))  # common mode
    np.testing.assert_allclose(m.k_o_stiff, 300.0 / (1.0 - 0.9))  # differential mode
    # K_o_eff is what the server reports today
    np.testing.assert_allclose(m.k_o_eff, effective_stiffness(c, m.k_o))
    # unequal contacts
    c2 = compliance_matrix([300.0, 1000.0], 0.5)
    assert c2[0, 1] == pytest.approx(0.5 / math.sqrt(300.0 * 1000.0))
    m2 = modal_stiffness(c2)
    np.testing.assert_allclose(m2.k_o_eff, [200.0, 2000.0 / 3.0])
    np.testing.assert_allclose(m2.k_o_stiff, [600.0, 2000.0])
    # uncoupled: every mode is K_o; singular (c -> 1): the stiff mode is rigid
    m0 = modal_stiffness(compliance_matrix(300.0, 0.0, 2))
    np.testing.assert_allclose([m0.k_o_eff, m0.k_o_stiff], 300.0)
    ones = np.full((2, 2), 1.0 / 300.0)
    np.testing.assert_allclose(modal_stiffness(ones).k_o_stiff, K_O_RIGID)


def test_bad_input_is_refused() -> None:
    g = UserGains(100.0)
    with pytest.raises(ValueError, match="coupling"):
        compliance_matrix(300.0, 1.0)
    with pytest.raises(ValueError, match="k_o"):
        compliance_matrix(-1.0, 0.5)
    with pytest.raises(ValueError, match="symmetric"):
        modal_stiffness([[1e-3, 1e-4], [0.0, 1e-3]])
    with pytest.raises(ValueError, match="semi-definite"):
        modal_stiffness([[1e-3, 2e-3], [2e-3, 1e-3]])
    with pytest.raises(ValueError, match="positive diagonal"):
        modal_stiffness([[0.0, 0.0], [0.0, 1e-3]])
    with pytest.raises(ValueError, match="gains"):
        coupled_monodromy(compliance=np.eye(2) * 1e-3, gains=[g], hands=[[None, None]])
    with pytest.raises(ValueError, match="sample ticks"):
        coupled_monodromy(
            compliance=np.eye(2) * 1e-3, gains=[g, g], hands=[[None, None]], sample_ticks=[[0, 50]]
        )
    with pytest.raises(ValueError, match="k_h"):
        UserGains(0.0)
    with pytest.raises(ValueError, match="proxy_hold"):
        UserGains(1.0, proxy_hold="cubic")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="margin"):
        verify_coupled(np.eye(2) * 1e-3, [g, g], margin=1.0)


def test_users_sample_at_their_own_ticks() -> None:
    """Unsynchronised servo loops: per-user ticks matter, and relabelling users changes nothing."""
    c = compliance_matrix(300.0, 0.9, 2)
    g = UserGains(k_h=80.0, i_gain=1500.0, b_h=10.0, proxy_hold="foh")
    rho = coupled_spectral_radius(
        compliance=c,
        gains=[g, g],
        hands=[[HEAVY, LIGHT_STIFF], [LIGHT_STIFF, HEAVY]],
        sample_ticks=[[0, 49], [49, 0], [0, 0], [49, 49]],
    )
    assert rho[0, 0] == pytest.approx(rho[1, 1], abs=1e-9)
    assert rho[0, 1] == pytest.approx(rho[1, 0], abs=1e-9)
    assert abs(rho[0, 0] - rho[0, 2]) > 1e-4  # the phase between users shows


def test_symmetry_reduction_is_exact() -> None:
    """verify_coupled's one-combination-per-multiset equals the full product of combinations."""
    c = compliance_matrix(300.0, 0.99, 3)
    g = UserGains(k_h=70.0, i_gain=1100.0, b_h=10.0, proxy_hold="foh")
    hands = [HEAVY, LIGHT_STIFF, DEFAULT_HAND]
    ticks = [0, 49]
    reduced = verify_coupled(c, [g] * 3, hands=hands, sample_ticks=ticks)
    full = verify_coupled(
        c,
        [g] * 3,
        hand_combos=list(itertools.product(hands, repeat=3)),
        tick_combos=list(itertools.product(ticks, repeat=3)),
    )
    assert reduced.cases < full.cases
    assert reduced.margin_radius == pytest.approx(full.margin_radius, abs=1e-9)
    assert reduced.spectral_radius == pytest.approx(full.spectral_radius, abs=1e-9)


# ------------------------------------------------------------------------------------------
# the design


def test_reported_k_o_eff_is_not_enough_for_pi_users() -> None:
    """The product today: each PI user designs for the server's K_o_eff -> the coupled loop of two
    users 99 % coupled is unstable (the differential mode is 100x stiffer than K_o_eff)."""
    c = compliance_matrix(300.0, 0.99, 2)
    k_eff = float(modal_stiffness(c).k_o_eff[0])
    d = _single(k_eff, 0)
    assert d.worst_spectral_radius < d.rho_limit  # fine for one user on a K_o_eff object
    v = verify_coupled(c, [UserGains.from_design(d)] * 2)
    assert not v.stable
    assert v.spectral_radius > 1.05


def test_coupled_design_meets_the_single_user_margin() -> None:
    cd = _coupled(300.0, 0.99, 2, 0)
    v = cd.verdict
    assert v.meets_margin
    assert v.margin_radius < v.rho_limit == pytest.approx(math.exp(-0.05))
    assert cd.designs[0].k_o_range[1] == pytest.approx(cd.modal.k_o_stiff[0])
    assert cd.gains[0] == cd.gains[1]
    # a 4 x 4 x 4 hand lattice (all but its corners outside the verification hands), mixed per user
    lattice = [
        Hand(float(m), float(b), float(k))
        for m in np.linspace(0.1, 0.6, 4)
        for b in np.linspace(2.0, 10.0, 4)
        for k in np.linspace(20.0, 1000.0, 4)
    ]
    rng = np.random.default_rng(7)
    combos = [tuple(lattice[i] for i in rng.choice(len(lattice), 2)) for _ in range(60)]
    rho = coupled_spectral_radius(
        compliance=compliance_matrix(300.0, 0.99, 2),
        gains=list(cd.gains),
        hands=combos,
        sample_ticks=[[0, 49], [49, 0], [25, 25], [10, 40]],
    )
    assert rho.max() < 1.0


# ------------------------------------------------------------------------------------------
# a run in time


def _simulate(
    compliance: np.ndarray,
    gains: Sequence[UserGains],
    hands: Sequence[Hand],
    ticks: Sequence[int],
    *,
    delay: int | Sequence[int] = 0,
    n: int = 50,
    blocks: int = 120,
    substeps: int = 40,
    push_m: float = 1e-3,
) -> np.ndarray:
    """Every user's probe depth [m] at every servo tick (blocks * n, M): user 0 starts pushed in.

    Linear bilateral contact at 1 kHz; the object steps every n ticks, x_o = C F with F each
    user's force at its own tick; the proxy reaches each servo after ``delay`` more steps (one
    number for all, or one per user).
    """
    T = 1e-3
    m = len(gains)
    delays = [int(delay)] * m if isinstance(delay, int) else [int(d) for d in delay]
    a_u = T / (T + 0.005)  # the servo's 5 ms filter on the damper's probe velocity
    x = [0.0] * m
    x[0] = push_m
    v = [0.0] * m
    x_prev = list(x)
    u = [0.0] * m
    s = [0.0] * m
    line: deque[list[float]] = deque([[0.0] * m for _ in range(max(delays) + 1)])
    p_new = [0.0] * m
    p_old = [0.0] * m
    f_sample = [0.0] * m
    h = T / substeps
    out = np.zeros((blocks * n, m))
    for blk in range(blocks):
        if blk > 0:
            line.append([float(z) for z in compliance @ np.array(f_sample)])
            line.popleft()
            p_old, p_new = p_new, [line[-1 - delays[k]][k] for k in range(m)]
        for i in range(n):
            for k in range(m):
                g, hk = gains[k], hands[k]
                w = (i + 1) / n if g.proxy_hold == "foh" else 1.0
                p = p_old[k] + (p_new[k] - p_old[k]) * w
                e = x[k] - p
                u[k] += a_u * ((x[k] - x_prev[k]) / T - u[k])
                f = g.k_h * e + s[k] + g.b_h * u[k]
                if i == ticks[k]:
                    f_sample[k] = f
                s[k] += T * g.i_gain * e
                x_prev[k] = x[k]
                xk, vk = x[k], v[k]
                mk, bk, kk = hk.mass_kg, hk.damping_n_s_per_m, hk.stiffness_n_per_m
                for _ in range(substeps):
                    vk += h * (-kk * xk - bk * vk - f) / mk
                    xk += h * vk
                x[k], v[k] = xk, vk
            out[blk * n + i] = x
    return out


def _envelope(trace: np.ndarray, n: int = 50) -> np.ndarray:
    """Largest |probe depth| over all users in each simulation period."""
    return np.abs(trace).reshape(-1, n, trace.shape[1]).max(axis=(1, 2))


def _rate(env: np.ndarray, first: int, last: int) -> float:
    """Envelope ratio per simulation period, least squares on log over blocks [first, last)."""
    k = np.arange(first, last)
    return float(np.exp(np.polyfit(k, np.log(env[first:last]), 1)[0]))


def test_two_users_99_percent_coupled_settle_with_the_coupled_design() -> None:
    c = compliance_matrix(300.0, 0.99, 2)
    naive = [UserGains.from_design(_single(float(modal_stiffness(c).k_o_eff[0]), 0))] * 2
    coupled = list(_coupled(300.0, 0.99, 2, 0).gains)
    # the naive design's worst case (from the coupled analysis), run in time for both designs
    worst = verify_coupled(c, naive)
    hands = [h for h in worst.worst_hands if h is not None]
    ticks = list(worst.worst_sample_ticks)
    runs = {}
    for name, g in (("naive", naive), ("coupled", coupled)):
        rho = float(
            coupled_spectral_radius(compliance=c, gains=g, hands=[hands], sample_ticks=[ticks])[
                0, 0
            ]
        )
        env = _envelope(_simulate(c, g, hands, ticks))
        runs[name] = (rho, env, _rate(env, 60, 120))
    rho_n, env_n, rate_n = runs["naive"]
    rho_c, env_c, rate_c = runs["coupled"]
    assert rho_n > 1.05 and rho_c < math.exp(-0.05)
    # the time-domain envelope decays (grows) per period as the spectral radius says
    assert rate_c == pytest.approx(rho_c, abs=0.01)
    assert rate_n == pytest.approx(rho_n, abs=0.01)
    # coupled: the 1 mm push dies out; the last second of the hold is still to 10 um
    assert env_c[-20:].max() < 0.01e-3
    # naive: the contact oscillates and grows
    assert env_n[-20:].max() > 1e-3


# ------------------------------------------------------------------------------------------
# exhaustive checks


@pytest.mark.slow
@pytest.mark.parametrize("k_o", [300.0, 1000.0])
@pytest.mark.parametrize("delay", [0, 2])
@pytest.mark.parametrize("users", [2, 3])
@pytest.mark.parametrize("coupling", [0.0, 0.5, 0.9, 0.99])
def test_coupled_design_meets_the_margin_everywhere(
    k_o: float, delay: int, users: int, coupling: float
) -> None:
    cd = _coupled(k_o, coupling, users, delay)
    assert cd.verdict.meets_margin, cd.verdict.to_json()
    if coupling == 0.0:
        single = _single(k_o, delay)
        assert cd.gains[0].k_h == pytest.approx(single.k_h, rel=1e-9)
        assert cd.gains[0].i_gain == pytest.approx(single.i_gain, rel=1e-9)


@pytest.mark.slow
def test_two_users_every_tick_pair() -> None:
    """All N x N sampling-tick pairs for every pair of box corners."""
    cd = _coupled(300.0, 0.99, 2, 0)
    v = verify_coupled(
        compliance_matrix(300.0, 0.99, 2),
        list(cd.gains),
        hands=DEFAULT_HAND_BOX.corners(),
        sample_ticks=range(50),
    )
    assert v.meets_margin, v.to_json()


@pytest.mark.slow
def test_three_users_time_domain_decay_matches_the_spectral_radius() -> None:
    c = compliance_matrix(1000.0, 0.99, 3)
    cd = _coupled(1000.0, 0.99, 3, 2)
    hands = [HEAVY, LIGHT_STIFF, DEFAULT_HAND]
    ticks = [0, 25, 49]
    rho = float(
        coupled_spectral_radius(
            compliance=c, gains=list(cd.gains), hands=[hands], sample_ticks=[ticks], delay_ticks=2
        )[0, 0]
    )
    env = _envelope(_simulate(c, list(cd.gains), hands, ticks, delay=2, blocks=160))
    assert _rate(env, 80, 160) == pytest.approx(rho, abs=0.01)
    assert env[-20:].max() < 0.01e-3


def test_users_with_their_own_delays_decay_as_the_spectral_radius_says() -> None:
    """Each user's proxy its own delay late (B's round trip 2 ticks, A's none): the monodromy
    against the independent time-domain loop, and uncoupled users against their own loops."""
    c = compliance_matrix([1000.0, 400.0], 0.6)
    gains = [UserGains(k_h=300.0, i_gain=2500.0, b_h=5.0, proxy_hold="foh"),
             UserGains(k_h=350.0, i_gain=1500.0, b_h=8.0)]  # fmt: skip
    hands, ticks = [HEAVY, LIGHT_STIFF], [0, 49]
    rho = float(
        coupled_spectral_radius(
            compliance=c, gains=gains, hands=[hands], sample_ticks=[ticks], delay_ticks=(0, 2)
        )[0, 0]
    )
    equal = float(
        coupled_spectral_radius(
            compliance=c, gains=gains, hands=[hands], sample_ticks=[ticks], delay_ticks=2
        )[0, 0]
    )
    assert rho < 1.0 < equal  # stable as A's delay is none; B's 2 ticks for both would ring
    env = _envelope(_simulate(c, gains, hands, ticks, delay=(0, 2), blocks=160))
    assert _rate(env, 80, 160) == pytest.approx(rho, abs=0.01)
    # uncoupled: each user alone at its own delay
    apart = np.diag([1.0 / 1000.0, 1.0 / 400.0])
    both = coupled_spectral_radius(
        compliance=apart, gains=gains, hands=[hands], sample_ticks=[ticks], delay_ticks=(0, 2)
    )[0, 0]
    alone = [
        spectral_radius(
            hand=h, k_o=k, k_h=g.k_h, i_gain=g.i_gain, b_h=g.b_h, delay_ticks=d, sample_ticks=[j], proxy_hold=g.proxy_hold,
        )[0, 0]
        for h, k, g, d, j in zip(hands, (1000.0, 400.0), gains, (0, 2), ticks, strict=True)
    ]  # fmt: skip
    assert both == pytest.approx(max(alone), abs=1e-9)
    with pytest.raises(ValueError, match="delays"):
        verify_coupled(c, gains, delay_ticks=(0, 1, 2))


def test_the_sign_of_the_coupling_does_not_change_the_loop() -> None:
    """A press that lifts the other contact (C_12 < 0) rings as one that sinks it: negating the
    second user's states carries one loop into the other (shared.gains.group)."""
    gains = [UserGains(k_h=300.0, i_gain=2500.0, b_h=5.0, proxy_hold="foh"),
             UserGains(k_h=700.0, b_h=8.0, own_gain=1.0 / 900.0)]  # fmt: skip
    c = compliance_matrix([1000.0, 400.0], 0.6)
    flipped = c * np.array([[1.0, -1.0], [-1.0, 1.0]])
    hands = [[HEAVY, LIGHT_STIFF], [DEFAULT_HAND, HEAVY]]
    kw = dict(gains=gains, hands=hands, sample_ticks=[[0, 49], [25, 3]], delay_ticks=(1, 2))
    np.testing.assert_allclose(
        coupled_spectral_radius(compliance=flipped, **kw),  # type: ignore[arg-type]
        coupled_spectral_radius(compliance=c, **kw),  # type: ignore[arg-type]
        rtol=1e-9,
    )


@pytest.mark.slow
def test_unequal_contacts_meet_the_margin() -> None:
    """Contacts of different stiffness (300 and 1000 N/m) 90 % coupled: different gains."""
    cd = design_coupled(compliance_matrix([300.0, 1000.0], 0.9), k_h_max=K_H_MAX, b_h_max=B_H_MAX)
    assert cd.gains[0] != cd.gains[1]
    assert cd.verdict.meets_margin, cd.verdict.to_json()


def test_verification_hands_are_the_corners_centre_and_the_simulated_user() -> None:
    hands = verification_hands()
    assert len(hands) == 10
    assert set(DEFAULT_HAND_BOX.corners()) <= set(hands)
    assert DEFAULT_HAND in hands


def test_gain_table_rule_classes() -> None:
    assert stiff_ratio_class(300.0, 300.0) == 1.0  # uncoupled: the table's rows of today
    assert stiff_ratio_class(250.0, 375.0) == 2.0
    assert stiff_ratio_class(150.0, 30000.0) == 256.0
    assert stiff_ratio_class(101.0, 30000.0) == math.inf
    assert stiff_ratio_class(100.0, 400.0) == 4.0  # exact powers stay
    assert stiff_ratio_class(162.0, 333.0) == pytest.approx(2.0**1.5)  # half powers up to 4
    assert stiff_ratio_class(100.0, 141.0) == pytest.approx(2.0**0.5)
    assert stiff_ratio_class(100.0, 500.0) == 8.0  # whole powers above
    assert covering_classes(2.0)[:3] == (pytest.approx(2.0**1.5), 4.0, 8.0)
    assert covering_classes(256.0) == (math.inf,) and covering_classes(math.inf) == ()
    assert coupled_k_o_hi(330.0, 1.0) == 330.0
    assert coupled_k_o_hi(330.0, 4.0) == 1320.0
    assert coupled_k_o_hi(330.0, math.inf) == K_O_RIGID
    with pytest.raises(ValueError, match="k_o_stiff"):
        stiff_ratio_class(300.0, 200.0)
    with pytest.raises(ValueError, match="k_o_eff"):
        stiff_ratio_class(0.0, 200.0)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("k_o", "delay", "users", "coupling"),
    [
        (300.0, 0, 2, 0.2),
        (300.0, 0, 3, 0.99),
        (1000.0, 2, 2, 0.9),
        (300.0, 2, 3, 0.5),
        (300.0, 3, 2, 0.35),  # ratio 2.08: class 2 sqrt(2)
        (300.0, 0, 2, 0.15),  # ratio 1.35: class sqrt(2)
    ],
)
def test_gain_table_rule_meets_the_margin(
    k_o: float, delay: int, users: int, coupling: float
) -> None:
    """The rule for the product's GainTable: the cell of K_o_eff (grid ratio 1.1), checked up to
    the next grid point times the stiffness-ratio class."""
    c = compliance_matrix(k_o, coupling, users)
    modal = modal_stiffness(c)
    k_eff, k_stiff = float(modal.k_o_eff[0]), float(modal.k_o_stiff[0])
    cell = math.floor(math.log(k_eff) / math.log(1.1) + 1e-12)
    hi = coupled_k_o_hi(1.1 ** (cell + 1), stiff_ratio_class(k_eff, k_stiff))
    d = design_gains(1.1**cell, k_o_hi=hi, delay_ticks=delay, k_h_max=K_H_MAX, b_h_max=B_H_MAX)
    v = verify_coupled(c, [UserGains.from_design(d)] * users, delay_ticks=delay)
    assert v.meets_margin, v.to_json()
