"""Interim gains checked over a band of object damping: a hand sliding over a damped solid,
whose B_o changes by whole N/m along the way, keeps the gains one check found for the band."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from haptic_collab.server.gains import GainAdvisor, GainJob, run_job
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains import b_o_band as band_module
from haptic_collab.shared.gains.b_o_band import BandedGains, b_o_band, check_band
from haptic_collab.shared.gains.interim import interim_design, verify_gains
from haptic_collab.shared.gains.key import make_gain_key
from haptic_collab.shared.gains.policy import K_O_GRID_RATIO
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.protocol import DeviceInfo, Hello

PHANTOM = DeviceInfo(
    profile="phantom-desktop", max_force_n=7.9, max_stiffness_n_per_m=1000.0,
    max_damping_n_s_per_m=10.0,
)  # fmt: skip


def _key(b_o: float, delay_ticks: int = 1, stiff_ratio: float = 2.0):
    """The palpation demo's A sliding over the liver's top at a tick of delay (docs/gains.md)."""
    return make_gain_key(
        servo_rate_hz=1000.0, sim_rate_hz=20.0, delay_ticks=delay_ticks, mode="pi", margin=0.15,
        k_h_max=1000.0, b_h_max=10.0, b_o=b_o, stiff_ratio=stiff_ratio,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("b_o", "band"),
    [(0.0, None), (0.5, None), (1.0, (1.0, 2.0)), (8.0, (8.0, 16.0)), (15.9, (8.0, 16.0)),
     (16.0, (16.0, 32.0)), (53.0, (32.0, 64.0)), (64.0, None), (500.0, None),
     (math.nan, None), (math.inf, None)],
)  # fmt: skip
def test_a_keys_b_o_lies_in_one_band_of_the_damping_lattice(b_o, band):
    assert b_o_band(b_o) == band


def test_the_gains_found_for_one_b_o_hold_for_every_whole_b_o_of_its_band():
    """Interim gains found at 20 N/m pass at 16 and 32 N/m, so they are kept for 16-32 N/m; each
    key in between passes its own acceptance test with them (the lattice's rule, checked here
    where the product does not check)."""
    cell = GainTable().cell(240.0)
    key = _key(20.0)
    found = interim_design(key, cell, K_O_GRID_RATIO, DEFAULT_HAND_BOX, design_fallback=False)
    assert found.own_gain > 0.0 and found.i_gain == 0.0  # compensated: felt as the object
    banded = check_band(key, cell, found, K_O_GRID_RATIO, DEFAULT_HAND_BOX)
    assert banded.band == (16.0, 32.0) and banded.design is found
    keys = banded.keys(key)
    assert [k.b_o for k in keys] == [float(b) for b in range(16, 33)]
    assert all(replace(k, b_o=key.b_o) == key for k in keys)  # only B_o differs
    for b_o in (17.0, 25.0, 31.0):
        ok, rho = verify_gains(
            _key(b_o), cell, K_O_GRID_RATIO, DEFAULT_HAND_BOX, k_h=found.k_h, i_gain=0.0,
            b_h=found.b_h, proxy_hold=found.proxy_hold, own_gain=found.own_gain,
        )  # fmt: skip
        assert ok, (b_o, rho)


def test_gains_that_fail_at_an_end_of_the_band_hold_for_their_own_key_only(monkeypatch):
    cell = GainTable().cell(240.0)
    key = _key(20.0)
    found = interim_design(key, cell, K_O_GRID_RATIO, DEFAULT_HAND_BOX, design_fallback=False)
    asked: list[float] = []

    def fails_at_32(key, *args, **kwargs):
        asked.append(key.b_o)
        return key.b_o != 32.0, 1.01

    monkeypatch.setattr(band_module, "verify_gains", fails_at_32)
    banded = check_band(key, cell, found, K_O_GRID_RATIO, DEFAULT_HAND_BOX)
    assert banded.band is None and banded.keys(key) == [key]
    assert asked == [16.0, 32.0]
    # an undamped key (the balloon, every mesh) is checked at its own B_o only
    assert check_band(_key(0.0), cell, found, K_O_GRID_RATIO, DEFAULT_HAND_BOX).band is None
    assert asked == [16.0, 32.0]


def test_the_server_renders_checked_gains_at_every_b_o_of_a_band_after_one_check():
    """A sliding hand's B_o goes 20, 22, 25, 30 N/m: after the first key's check the server
    recommends checked interim gains at each of them at once, with no check of their own (a
    check asked meanwhile is dropped), where each new key waited for its own before."""
    adv = GainAdvisor(20.0, shipped=False)  # no shipped table: every key is checked here
    h = Hello(protocol=1, role="user", name="A", device=PHANTOM, local_model="pi")
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=20.0) is None
    job = adv.next_job("interim")
    assert isinstance(job, GainJob) and job.key.b_o == 20.0
    # while the check runs the hand moves on: the next key asks a check of its own
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=21.0) is None
    result = run_job(job, adv.table.grid_ratio, adv.table.hand_box)
    assert isinstance(result, BandedGains) and result.band == (16.0, 32.0)
    adv.store(job, result)
    for b_o in (22.0, 25.0, 30.0):
        rec = adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=b_o)
        assert rec is not None and rec.interim and rec.own_gain > 0.0, b_o
        assert (rec.k_h, rec.own_gain) == (result.design.k_h, result.design.own_gain)
    assert adv.next_job("interim") is None  # none of them asks a check; 21 N/m's is dropped
    # beyond the band the key is new again
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=33.0) is None
    nxt = adv.next_job("interim")
    assert nxt is not None and nxt.key.b_o == 33.0


def test_the_client_keeps_a_bands_check_for_the_next_b_o_as_the_server_does():
    """The Python client's own choice (``haptic client --gains local``): gains found for B_o
    20 N/m and checked over 16-32 N/m render at once at 25 N/m, with no check asked."""
    from haptic_collab.client.session import ClientSession
    from haptic_collab.shared.protocol import Welcome, encode
    from tests.support.sessions import WELCOME_OBJECT, press_patch

    s = ClientSession("A", device=DeviceInfo(max_stiffness_n_per_m=1000.0), b_h_max=10.0)
    welcome = Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=WELCOME_OBJECT)
    s.receive(encode(welcome), 0.0)
    assert s.receive(press_patch(1, 0.5, 240.0, k_o=240.0, b_o=20.0), 0.10) is None
    assert s.interim_wanted is not None
    key, cell, candidates = s.interim_wanted
    s.interim_wanted = None
    table = s.gain_table
    found = interim_design(key, cell, table.grid_ratio, table.hand_box, candidates)
    s.store_interim(key, cell, found)  # what the link does, then the band after it
    s.store_interim_band(key, cell, check_band(key, cell, found, table.grid_ratio, table.hand_box))
    up = s.receive(press_patch(2, 0.5, 240.0, k_o=240.0, b_o=25.0), 0.15)
    assert up is not None and up.choice.verified and s.interim_wanted is None
    assert (up.k_h, up.own_gain) == (found.k_h, found.own_gain)
    assert up.choice.source == "interim"  # checked for its own key, by the band
    assert (s.gain_key(25.0, key.delay_ticks, key.stiff_ratio), cell) in s.interim


def test_the_clients_link_checks_the_band_after_the_waiting_patch_has_its_gains():
    """The link (``haptic client``) renders the first damped contact with its check's gains, then
    checks them over the band: the session then holds them for every B_o of the band."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    from haptic_collab.client.link import Link
    from haptic_collab.client.session import ClientSession
    from haptic_collab.shared.protocol import Welcome, encode
    from tests.support.sessions import WELCOME_OBJECT, press_patch

    s = ClientSession("A", device=DeviceInfo(max_stiffness_n_per_m=1000.0), b_h_max=10.0)
    welcome = Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=WELCOME_OBJECT)
    s.receive(encode(welcome), 0.0)
    got = []
    design_pool, check_pool = ThreadPoolExecutor(max_workers=1), ThreadPoolExecutor(max_workers=1)

    async def go() -> None:
        link = Link(
            "ws://127.0.0.1:1/ws", s, on_patch=lambda u, t: got.append(u), sample=lambda: None,
            clock=lambda: 1.0, design_executor=design_pool, check_executor=check_pool,
        )  # fmt: skip
        assert s.receive(press_patch(1, 0.5, 240.0, k_o=240.0, b_o=20.0), 0.5) is None
        link._start_check()
        assert link._check_task is not None
        try:
            await asyncio.wait_for(link._check_task, 30.0)
        finally:
            link.close()

    try:
        asyncio.run(go())
    finally:
        for pool in (design_pool, check_pool):
            pool.shutdown(wait=True, cancel_futures=True)
    assert len(got) == 1 and got[0].choice.verified  # the waiting patch, with its check's gains
    cell = s.gain_table.cell(240.0)
    key = s.gain_key(20.0, 0)
    assert s.interim[(key, cell)] is not None
    band = [b for b in range(0, 80) if (replace(key, b_o=float(b)), cell) in s.interim]
    assert band == list(range(16, 33))
