"""A resting user keeps its gains when another user's press couples its contact, where the pair
as rendered is verified (server.gains.GainAdvisor.hold_pairs, shared.gains.group).

The contacts are the stress demo's (docs/real-objects.md, tools/coupled_pair_check.py), at 2
ticks of delay with the Phantom Desktop's shipped tables:
- torus: B rests on the side (K_o 1202.9 N/m) on its uncoupled compensated P (K_h 1000 N/m);
  A's press on the top couples them (K_o_stiff / K_o_eff 2.33, class 2 sqrt 2). Designed for a
  rigid partner, B's coupled key renders the paper's PI at K_h 270 N/m, a felt step of x5;
  beside A's coupled design B's own gains meet the margin on the pair's loop, so B keeps them;
- bowl: the same pairing rings (class 8), so B takes its coupled design, as before.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from haptic_collab.server.gains import GainAdvisor, run_job
from haptic_collab.server.world import Coupling
from haptic_collab.shared.coupled_loop import UserGains, verification_hands, verify_coupled
from haptic_collab.shared.gains.group import PairVerdict, class_ratios, coupling_of_ratio
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.primitives import make_plane
from haptic_collab.shared.protocol import DeviceInfo, Hello, RecommendedGains

PHANTOM = DeviceInfo(
    profile="phantom-desktop",
    max_force_n=7.9,
    max_stiffness_n_per_m=1000.0,
    max_damping_n_s_per_m=10.0,
)
HELLO = Hello(protocol=1, role="user", name="u", device=PHANTOM, local_model="pi")
#: A round trip that makes the loop delay 2 ticks at 20 Hz (shared.gains.key.loop_delay_ticks).
RTT_MS = 110.0

#: (B's K_o, A's K_o, their coupling c) as the demo's patches reported them during A's press.
TORUS = (1202.9, 472.7, coupling_of_ratio(2003.6 / 859.4))
BOWL = (281.4, 306.1, coupling_of_ratio(1178.2 / 175.9))


@functools.cache
def shipped() -> GainAdvisor:
    """An advisor whose table holds the shipped tables (loaded once; each test gets a fresh
    advisor sharing that table)."""
    return GainAdvisor(20.0)


def advisor(rtt_ms: tuple[float, float] = (RTT_MS, RTT_MS)) -> GainAdvisor:
    """A fresh advisor on the shipped tables, A's and B's round trips ``rtt_ms`` [ms]."""
    adv = GainAdvisor(20.0, shipped=False)
    adv.table = shipped().table
    for user, rtt in zip("AB", rtt_ms, strict=True):
        adv.observe_rtt(user, rtt, rtt)
    return adv


def patch(tick: int, k_o: float, k_eff: float, k_stiff: float, pen: float) -> SurfacePatch:
    return SurfacePatch(
        tick=tick,
        primitive=make_plane((0, 0, 0), (0, 0, 1)),
        proxy=(0.0, 0.0, 0.0),
        normal=(0.0, 0.0, 1.0),
        penetration_m=pen,
        in_contact=pen > 0.0,
        k_o=k_o,
        k_o_eff=k_eff,
        k_o_stiff=k_stiff,
        b_o=0.0,
    )


def tick(
    adv: GainAdvisor,
    n: int,
    case: tuple[float, float, float],
    a_pen: float,
    b_pen: float = 0.001,
) -> dict[str, RecommendedGains | None]:
    """One simulation tick: B resting ``b_pen`` [m] in, A's probe ``a_pen`` [m] from the surface
    (coupled to B only within the world's 5 mm), as the room calls the advisor."""
    k_b, k_a, c = case
    proximity = 0.005
    cross = c / math.sqrt(k_a * k_b)
    compliance = np.array([[1.0 / k_a, cross], [cross, 1.0 / k_b]])
    near = a_pen > -proximity
    if near:
        patches = {
            "A": patch(n, k_a, k_a / (1 + c), k_a / (1 - c), a_pen),
            "B": patch(n, k_b, k_b / (1 + c), k_b / (1 - c), b_pen),
        }
    else:
        patches = {"A": patch(n, k_a, k_a, k_a, a_pen), "B": patch(n, k_b, k_b, k_b, b_pen)}
    recs = {
        u: adv.recommend(
            u,
            HELLO,
            k_o_eff=p.k_o_eff,
            k_o_stiff=p.k_o_stiff,
            b_o=0.0,
            tick=n,
            in_contact=p.in_contact,
        )  # fmt: skip
        for u, p in patches.items()
    }
    coupling = Coupling(("A", "B"), compliance, np.array([a_pen, b_pen]), proximity)
    return adv.hold_pairs(coupling, patches, recs)


def run_pair_jobs(adv: GainAdvisor) -> list[PairVerdict | None]:
    out = []
    for job in adv.take_jobs():
        result = run_job(job, adv.table.grid_ratio, adv.table.hand_box)
        adv.store(job, result)
        if job.kind == "pair":
            assert result is None or isinstance(result, PairVerdict)
            out.append(result)
    return out


def felt(g: RecommendedGains | None) -> tuple[float, float, float]:
    assert g is not None
    return (g.k_h, g.i_gain, g.own_gain)


def press(adv: GainAdvisor, case: tuple[float, float, float], *, look_ahead: bool) -> list:
    """B rests while A waits 3 cm above, then A presses and releases: B's gains each tick."""
    seen = []
    for n in range(5):
        seen.append(tick(adv, n, case, -0.03))
    if look_ahead:
        run_pair_jobs(adv)  # the design worker, between ticks
    for n in range(5, 15):
        seen.append(tick(adv, n, case, 0.004))
    for n in range(15, 20):
        seen.append(tick(adv, n, case, -0.03))
    return seen


@pytest.mark.parametrize(("rtt_ms", "delays"), [((RTT_MS, RTT_MS), (2, 2)), ((10.0, 60.0), (0, 1))])
def test_the_resting_user_keeps_its_gains_as_a_verified_press_arrives(
    rtt_ms: tuple[float, float], delays: tuple[int, int]
) -> None:
    adv = advisor(rtt_ms)
    seen = press(adv, TORUS, look_ahead=True)
    assert (seen[10]["A"].delay_ticks, seen[10]["B"].delay_ticks) == delays  # type: ignore[union-attr]
    b = [felt(r["B"]) for r in seen]
    assert b[0][0] == pytest.approx(1000.0)  # B's compensated P alone
    assert all(x == b[0] for x in b), "B's gains changed while A pressed and left"
    a_alone, a_pressing = felt(seen[0]["A"]), felt(seen[10]["A"])
    assert a_pressing != a_alone  # A renders its coupled key's design
    assert adv.held_patches >= 10
    # the pair B held is the one the check verified: B's gains beside A's on the coupled loop
    k_b, k_a, c = TORUS
    cross = c / math.sqrt(k_a * k_b)
    gb, ga = seen[10]["B"], seen[10]["A"]
    assert ga is not None and gb is not None
    v = verify_coupled(
        np.array([[1.0 / k_a, cross], [cross, 1.0 / k_b]]),
        [UserGains(k_h=g.k_h, i_gain=g.i_gain, b_h=g.b_h, proxy_hold=g.proxy_hold,
                   own_gain=g.own_gain) for g in (ga, gb)],
        delay_ticks=delays, margin=0.15, hands=verification_hands(adv.table.hand_box),
    )  # fmt: skip
    assert v.meets_margin


def test_without_a_verdict_in_time_the_resting_user_steps_once_and_stays() -> None:
    adv = advisor()
    adv_jobs = []
    seen = []
    for n in range(3):  # A far beyond the look-ahead: nothing is checked
        seen.append(tick(adv, n, TORUS, -0.2))
    assert not [j for j in adv.take_jobs() if j.kind == "pair"]
    for n in range(3, 10):
        seen.append(tick(adv, n, TORUS, 0.004))
        adv_jobs += run_pair_jobs(adv)  # the verdict arrives after the coupled patch
    assert adv_jobs and all(v is not None and v.meets_margin for v in adv_jobs)
    b = [felt(r["B"]) for r in seen]
    assert b[0][0] == pytest.approx(1000.0)
    assert b[3] != b[0]  # the coupled key's design: designed for a rigid partner
    assert all(x == b[3] for x in b[3:]), "B went back to its old gains within the contact"
    assert adv.held_patches == 0


def test_where_the_pair_rings_the_resting_user_takes_its_coupled_design() -> None:
    adv = advisor()
    seen = press(adv, BOWL, look_ahead=True)
    verdicts = [v for v in adv.pairs.values() if v is not None]
    assert verdicts and not any(v.meets_margin for v in verdicts)
    b = [felt(r["B"]) for r in seen]
    assert b[6] != b[0]
    assert adv.held_patches == 0


def test_a_pair_check_covers_its_bucket_at_its_corners() -> None:
    # class 2 sqrt 2 is checked at the coupling of class 2's bound, the middle and its own
    r = class_ratios(2 * math.sqrt(2))
    assert r == pytest.approx((2.0, 2**1.25, 2 * math.sqrt(2)))
    assert class_ratios(1.0) == () and class_ratios(math.inf) == ()
    adv = advisor()
    press(adv, TORUS, look_ahead=True)
    (bucket,) = [b for b, v in adv.pairs.items() if v is not None]
    verdict = adv.pairs[bucket]
    assert verdict is not None and verdict.points == 12  # 2 x 2 cell ends x 3 couplings


def test_a_light_touch_lifted_off_for_a_moment_keeps_its_gains() -> None:
    """On the torus A's press draws the surface under B's light touch away (0.86 mm in the
    demo): B's probe leaves the surface for a tick or two, still within the world's 5 mm."""
    adv = advisor()
    for n in range(5):
        tick(adv, n, TORUS, -0.03)
    run_pair_jobs(adv)
    rest = felt(tick(adv, 5, TORUS, 0.004)["B"])
    lifted = [felt(tick(adv, n, TORUS, 0.004, b_pen=-0.0005)["B"]) for n in range(6, 8)]
    back = [felt(tick(adv, n, TORUS, 0.004)["B"]) for n in range(8, 12)]
    assert rest[0] == pytest.approx(1000.0)
    assert all(x == rest for x in lifted + back)
    # lifted off beyond the world's proximity, a new touch starts over: its coupled design
    tick(adv, 12, TORUS, 0.004, b_pen=-0.02)
    assert felt(tick(adv, 13, TORUS, 0.004)["B"]) != rest


def test_a_resting_users_coupled_key_is_checked_before_the_press_arrives() -> None:
    """The palpation demo's B: resting on the liver's side (K_o 181 N/m, B_o 53 N/m, beyond the
    shipped designs' damping coverage) when A's press couples the contacts (K_o_eff 146.5,
    K_o_stiff 238 N/m). Without a verified pair, B's coupled key rendered a wider class's paper
    PI: a light touch (its integral idle) felt 54 N/m against the object's 181. While A is still
    on its way, the advisor has B's coupled key checked, so the press's first patch recommends
    compensated gains, felt as the object."""
    k_b, k_a, b_o = 181.3, 231.1, 53.0
    c = (238.0 - 146.5) / (238.0 + 146.5)
    adv = advisor((1.0, 1.0))  # loopback: no delay

    def step(n: int, a_pen: float) -> dict[str, RecommendedGains | None]:
        near = a_pen > -0.005
        patches = {
            "A": patch(n, k_a, k_a / (1 + c) if near else k_a, k_a / (1 - c) if near else k_a, a_pen),
            "B": patch(n, k_b, k_b / (1 + c) if near else k_b, k_b / (1 - c) if near else k_b, 0.001),
        }  # fmt: skip
        recs = {
            u: adv.recommend(
                u,
                HELLO,
                k_o_eff=p.k_o_eff,
                k_o_stiff=p.k_o_stiff,
                b_o=b_o,
                tick=n,
                in_contact=p.in_contact,
            )  # fmt: skip
            for u, p in patches.items()
        }
        cross = c / math.sqrt(k_a * k_b)
        compliance = np.array([[1.0 / k_a, cross], [cross, 1.0 / k_b]])
        return adv.hold_pairs(Coupling(("A", "B"), compliance, np.array([a_pen, 0.001]), 0.005),
                              patches, recs)  # fmt: skip

    def run_checks() -> list[tuple[float, int]]:
        done = []
        for job in adv.take_jobs():
            if job.kind == "interim":  # the checks only: the designs take seconds
                adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
                done.append((job.key.stiff_ratio, job.cell))
        return done

    recs = step(1, -0.02)  # B rests alone; A 2 cm above the surface
    assert recs["B"] is not None and recs["B"].own_gain > 0.0  # B's own compensated design
    checked = run_checks()
    step(2, -0.02)
    checked += run_checks()
    coupled = adv.table.cell(k_b / (1 + c))
    assert (2.0, coupled) in checked  # B's coupled key (class 2) in the cell A's press brings
    recs = step(3, 0.003)  # A presses: B's contact is coupled, no pair verdict yet
    rec = recs["B"]
    assert rec is not None and rec.i_gain == 0.0 and rec.own_gain * rec.k_h == pytest.approx(1.0)
