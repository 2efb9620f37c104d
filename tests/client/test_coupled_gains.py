"""Two PI users coupled through the object: the gains the product picks meet the coupled margin.

The server sends each coupled contact ``k_o_stiff`` (its group's stiffest modal stiffness) beside
``k_o_eff``; the client designs its cell over ``[(1 - margin) g_i, k_o_hi]`` widened by the ratio
class (docs/coupled-users.md). Checked here end to end: the server's own stiffness functions on a
two-user compliance, the patch through the wire, the session's design request run as the link
runs it, and the coupled lifted loop of both users (:func:`shared.coupled_loop.verify_coupled`)
with those gains, every hand of the verification set and every sampling-tick combination.
"""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

from haptic_collab.client.link import Link
from haptic_collab.client.session import ClientSession
from haptic_collab.server.contact_stiffness import effective_stiffness, stiff_stiffness
from haptic_collab.shared.coupled_compliance import compliance_matrix
from haptic_collab.shared.coupled_loop import UserGains, verify_coupled
from haptic_collab.shared.felt_stiffness import felt_stiffness
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.local_model_update import LocalModelUpdate
from tests.support.sessions import plane_patch, welcomed_session


def session() -> ClientSession:
    return welcomed_session("A", "u1", b_h_max=10.0)


def test_an_uncoupled_patch_keeps_todays_gain_key() -> None:
    s = session()
    s.receive(plane_patch(1, 300.0, 300.0, None), 0.1)
    assert s.design_wanted is not None and s.design_wanted[0].stiff_ratio == 1.0
    s2 = session()
    s2.receive(plane_patch(1, 300.0, 300.0, 300.0), 0.1)
    assert s2.design_wanted is not None and s2.design_wanted[0] == s.design_wanted[0]


@pytest.mark.parametrize(
    "coupling",
    [pytest.param(0.5, marks=pytest.mark.slow), 0.9],  # 0.5: a long PI design
)
def test_coupled_pi_users_get_gains_that_meet_the_margin_of_the_coupled_loop(
    coupling: float,
) -> None:
    k_o = 300.0
    c = compliance_matrix(k_o, coupling, users=2)
    k = np.full(2, k_o)
    k_eff = effective_stiffness(c, k)
    k_stiff = stiff_stiffness(c, k)
    assert k_eff[0] == pytest.approx(k_o / (1 + coupling))
    assert k_stiff[0] == pytest.approx(k_o / (1 - coupling))
    s = session()
    s.receive(plane_patch(1, k_o, float(k_eff[0]), float(k_stiff[0])), 0.1)
    assert s.design_wanted is not None
    key, k_req = s.design_wanted
    assert key.stiff_ratio >= k_stiff[0] / k_eff[0]
    s.gain_table.design(key, k_req)  # as the link's worker does
    up = s.receive(plane_patch(2, k_o, float(k_eff[0]), float(k_stiff[0])), 0.15)
    assert up is not None and not up.choice.fallback
    # (a compensated P model here: closer to K_o than any PI the design found)
    g = UserGains(up.k_h, up.i_gain, up.b_h, up.proxy_hold, up.own_gain)  # type: ignore[arg-type]
    verdict = verify_coupled(c, [g, g], delay_ticks=up.choice.delay_ticks, margin=0.15)
    assert verdict.meets_margin, verdict
    # the paper's PI designed over the modal range meets it too
    pi = s.gain_table.design(replace(key, own_force=False), k_req)
    assert pi.i_gain > 0.0
    verdict = verify_coupled(c, [UserGains.from_design(pi)] * 2, margin=0.15)
    assert verdict.meets_margin, verdict
    # what the product did before (the paper's PI for K_o_eff alone) does not meet it at 0.9
    if coupling == 0.9:
        plain = s.gain_table.design(
            replace(s.gain_key(0.0, up.choice.delay_ticks, stiff_ratio=1.0), own_force=False),
            float(k_eff[0]),
        )
        old = UserGains(plain.k_h, plain.i_gain, plain.b_h, plain.proxy_hold)
        assert not verify_coupled(c, [old, old], margin=0.15).meets_margin


def test_a_new_coupling_class_renders_a_scaled_proportional_model_until_verified() -> None:
    s = session()
    assert s.receive(plane_patch(1, 300.0, 300.0, None), 0.1) is None
    assert s.interim_wanted is not None
    key, cell, cands = s.interim_wanted
    s.interim_wanted = None
    s.store_interim(key, cell, interim_design(key, cell, 1.1, s.gain_table.hand_box, cands))
    first = s.retry_waiting(0.15)
    assert first is not None and first.choice.verified
    # another user presses nearby: strongly coupled, K_o_eff halves, K_o_stiff is 10x K_o
    up = s.receive(plane_patch(2, 300.0, 158.0, 3000.0), 0.2)
    assert up is not None and not up.choice.verified
    assert up.i_gain == 0.0
    assert up.k_h <= first.k_h * 158.0 / 300.0 + 1e-9
    # the class stays up while the coupling wavers just below it (no design per tick)
    ratio = s.stiff_ratio
    s.receive(plane_patch(3, 300.0, 160.0, 160.0 * ratio / 2.5), 0.25)
    assert s.stiff_ratio == ratio
    # and comes down once the users are apart
    s.receive(plane_patch(4, 300.0, 300.0, 300.0), 0.3)
    assert s.stiff_ratio == 1.0


def test_a_second_user_arriving_is_rendered_at_once_with_gains_of_a_wider_class() -> None:
    # gains designed ahead for the contact's cell at coupling class 2 (shared.gains.choose.likely_next)
    # cover any weaker coupling: no unverified fallback, no halved force when B arrives
    s = session()
    assert s.receive(plane_patch(1, 300.0, 300.0, None), 0.1) is None
    assert s.design_wanted is not None
    s.gain_table.design(*s.design_wanted)
    assert s.receive(plane_patch(1, 300.0, 300.0, None), 0.1) is not None
    c = compliance_matrix(300.0, 0.1, users=2)  # a weak coupling: ratio 1.22, class sqrt(2)
    k_eff = float(effective_stiffness(c, np.full(2, 300.0))[0])
    k_stiff = float(stiff_stiffness(c, np.full(2, 300.0))[0])
    s.gain_table.design(replace(s.gain_key(0.0, 0), stiff_ratio=2.0), k_eff)
    up = s.receive(plane_patch(2, 300.0, k_eff, k_stiff), 0.2)
    assert up is not None and up.choice.verified and up.choice.fallback
    assert s.design_wanted is not None  # its own class's design is still made
    assert up.own_gain * up.k_h == pytest.approx(1.0)
    g = UserGains(up.k_h, up.i_gain, up.b_h, up.proxy_hold, up.own_gain)  # type: ignore[arg-type]
    assert verify_coupled(c, [g, g], delay_ticks=0, margin=0.15).meets_margin
    # a coupling beyond class 2 is not covered: the conservative path, until verified
    c = compliance_matrix(300.0, 0.5, users=2)  # ratio 3
    k_eff = float(effective_stiffness(c, np.full(2, 300.0))[0])
    k_stiff = float(stiff_stiffness(c, np.full(2, 300.0))[0])
    up = s.receive(plane_patch(3, 300.0, k_eff, k_stiff), 0.25)
    assert up is not None and not up.choice.verified


@pytest.mark.parametrize(("coupling", "k_o"), [(0.5, 300.0), (0.7, 100.0)])
def test_a_coupled_contact_keeps_feeling_the_object_with_its_interim_gains(
    coupling: float, k_o: float
) -> None:
    # until a coupled cell's design is done (seconds) the contact renders interim gains; with
    # the zero-order-hold rungs alone they were the paper's soft P here (0.14 K_o_eff at 0.1 Hz:
    # a resting user's force fell by half when the other touched) or a 2 N/m spring fed the
    # whole delayed force (2.3 K_o_eff)
    c = compliance_matrix(k_o, coupling, users=2)
    k = np.full(2, k_o)
    k_eff = float(effective_stiffness(c, k)[0])
    k_stiff = float(stiff_stiffness(c, k)[0])
    s = session()
    assert s.receive(plane_patch(1, k_o, k_eff, k_stiff), 0.1) is None
    assert s.interim_wanted is not None
    key, cell, cands = s.interim_wanted
    assert key.stiff_ratio > 2.0
    d = interim_design(key, cell, 1.1, s.gain_table.hand_box, cands)
    assert d.own_gain * d.k_h == pytest.approx(1.0)
    g = UserGains(d.k_h, d.i_gain, d.b_h, d.proxy_hold, d.own_gain)
    verdict = verify_coupled(c, [g, g], delay_ticks=key.delay_ticks, margin=0.15)
    assert verdict.meets_margin, verdict
    held = felt_stiffness(
        0.1,
        k_o=k_eff,
        k_h=d.k_h,
        b_h=d.b_h,
        own_gain=d.own_gain,
        rate_ratio=key.rates.ratio,
        proxy_hold=d.proxy_hold,
    )[0]
    assert held == pytest.approx(k_eff, rel=0.05)


def test_a_second_users_press_soon_after_the_first_contact_is_rendered_with_checked_gains() -> None:
    # In the demo B rests on the balloon and A's press couples the two contacts and lowers B's
    # K_o_eff by 12 % (two cells of the gain table). B used to render unverified gains for the
    # 0.15-0.3 s of a check (no own-force compensation: B's resting force fell from 0.28 to
    # 0.07-0.11 N just as A arrived): the coupled class's checks ahead of need waited behind the
    # design worker's full designs, seconds each. They now run in the check worker while no
    # needed check waits, for the contact's cell and the two below.
    s = session()
    gate = threading.Event()
    design_pool, check_pool = ThreadPoolExecutor(max_workers=1), ThreadPoolExecutor(max_workers=1)
    design_pool.submit(gate.wait, 60.0)  # the design worker is busy with a long design
    got: list[LocalModelUpdate] = []

    async def go() -> None:
        link = Link(
            "ws://127.0.0.1:1/ws", s, on_patch=lambda u, t: got.append(u), sample=lambda: None,
            clock=lambda: 1.0, design_executor=design_pool, check_executor=check_pool,
        )  # fmt: skip
        assert s.receive(plane_patch(1, 300.0, 300.0, None), 0.1) is None  # the first contact
        link._start_check()
        assert link._check_task is not None
        try:
            await asyncio.wait_for(link._check_task, 60.0)  # its check, then the coupled ones
        finally:
            link.close()
        assert len(link.check_wait_s) == 1  # one check was needed; the others came ahead

    try:
        asyncio.run(go())
        assert not gate.is_set()  # all of it while the design worker stayed busy
        assert len(got) == 1 and got[0].choice.verified  # the first contact, rendered once checked
        for k_eff in (300.0, 0.88 * 300.0):  # the same cell, and two cells below
            up = s.receive(plane_patch(2 if k_eff == 300.0 else 3, 300.0, k_eff, 1.33 * k_eff), 0.2)
            assert up is not None and up.choice.verified, k_eff
            assert s.gain_table.cell(k_eff) <= s.gain_table.cell(300.0)
            # own-force compensated: the surface does not give way under the user's own push
            assert up.own_gain * up.k_h == pytest.approx(1.0)
    finally:
        gate.set()
        for pool in (design_pool, check_pool):
            pool.shutdown(wait=True, cancel_futures=True)
