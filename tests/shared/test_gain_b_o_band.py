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


def test_the_server_renders_checked_gains_at_every_b_o_of_a_band_after_its_band_check():
    """A sliding hand's B_o goes 20, 22, 25, 30 N/m: the first key's own check gives it gains,
    then a band check (behind every interim check) gives them to the others, so the server
    recommends checked interim gains at each of them with no check of their own (a check asked
    meanwhile is dropped), where each new key waited for its own before."""
    adv = GainAdvisor(20.0, shipped=False)  # no shipped table: every key is checked here
    h = Hello(protocol=1, role="user", name="A", device=PHANTOM, local_model="pi")
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=20.0) is None
    job = adv.next_job("interim")
    assert isinstance(job, GainJob) and job.key.b_o == 20.0
    found = run_job(job, adv.table.grid_ratio, adv.table.hand_box)
    assert found is not None and not isinstance(found, BandedGains)
    adv.store(job, found)  # the key's own check: its gains at once ...
    rec = adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=20.0)
    assert (
        rec is not None
        and rec.interim
        and (rec.k_h, rec.own_gain)
        == (
            found.k_h,
            found.own_gain,
        )
    )
    # ... and the hand moves on: the next key asks a check of its own, which comes first
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=21.0) is None
    first = adv.next_job()
    assert first is not None and first.kind == "interim" and first.key.b_o == 21.0
    assert adv.next_job("interim") is None
    design = adv.next_job()  # the design worker: designs before band checks
    assert design is not None and design.kind == "design"
    band_job = adv.next_job("band")  # the check worker, with no check waiting
    assert band_job is not None and band_job.kind == "band" and band_job.design is found
    # meanwhile the hand is at 24 N/m: a check is asked, and the band answers it
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=24.0) is None
    result = run_job(band_job, adv.table.grid_ratio, adv.table.hand_box)
    assert isinstance(result, BandedGains) and result.band == (16.0, 32.0)
    adv.store(band_job, result)
    for b_o in (22.0, 24.0, 25.0, 30.0):
        rec = adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=b_o)
        assert rec is not None and rec.interim and rec.own_gain > 0.0, b_o
        assert (rec.k_h, rec.own_gain) == (found.k_h, found.own_gain)
    assert adv.band_keys == 16  # 16-32 N/m but 20, its own (21's check is still running)
    assert adv.next_job("interim") is None  # none of them asks a check; 24's is dropped
    # beyond the band the key is new again
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=33.0) is None
    nxt = adv.next_job("interim")
    assert nxt is not None and nxt.key.b_o == 33.0


def test_a_damped_contacts_check_asks_the_cells_beside_it_ahead_and_those_ask_no_further():
    """Over a lump K_o crosses a cell every 10 %: the check a damped contact needed queues the
    cells beside its own, after its band check; what a check ahead finds renders at once when
    the contact gets there, and it asks no further cells itself."""
    adv = GainAdvisor(20.0, shipped=False)
    h = Hello(protocol=1, role="user", name="A", device=PHANTOM, local_model="pi")
    assert adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=20.0) is None
    job = adv.next_job("interim")
    assert job is not None
    adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    assert adv.next_job("ahead", idle=False) is None  # no CPU to spare: none handed out
    band = adv.next_job("band")
    assert band is not None and band.key == job.key
    ahead = [adv.next_job("ahead"), adv.next_job("ahead")]
    assert all(a is not None and a.key == job.key for a in ahead)
    assert sorted(a.cell for a in ahead if a is not None) == [job.cell - 1, job.cell + 1]
    up = next(a for a in ahead if a is not None and a.cell == job.cell + 1)
    adv.store(up, run_job(up, adv.table.grid_ratio, adv.table.hand_box))
    assert adv.next_job("ahead") is None  # a check ahead asks no further cells
    k_up = adv.table.grid_point(job.cell + 1) * 1.05
    rec = adv.recommend("u1", h, k_o_eff=k_up, k_o_stiff=k_up, b_o=20.0)
    assert rec is not None and rec.interim  # the next cell up renders checked gains at once


def test_band_checks_wait_for_every_interim_check_and_for_cpu_to_spare():
    """A band check is never handed out before a check a contact waits for, nor with
    ``idle`` False (the server's workers without CPU to spare)."""
    adv = GainAdvisor(20.0, shipped=False)
    h = Hello(protocol=1, role="user", name="A", device=PHANTOM, local_model="pi")
    adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=20.0)
    job = adv.next_job("interim")
    assert job is not None
    adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    adv.recommend("u1", h, k_o_eff=240.0, k_o_stiff=240.0, b_o=40.0)  # another band: a check
    assert adv.next_job("band", idle=False) is None
    nxt = adv.next_job(None, idle=False)
    assert nxt is not None and nxt.kind == "interim" and nxt.key.b_o == 40.0
    while (other := adv.next_job(None, idle=False)) is not None:
        assert other.kind not in ("band", "ahead")
    band = adv.next_job(None)  # with CPU to spare, once nothing else waits
    assert band is not None and band.kind == "band" and band.key.b_o == 20.0


def test_the_server_does_checks_no_contact_waits_for_only_with_cpu_to_spare():
    """The server's gain workers take band checks and checks ahead only while its check worker
    had at least half a core in its last jobs (beside two spinning processes it has 10-30 %)."""
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.main import ServerOptions, build_world
    from haptic_collab.server.room import Room

    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=1))
    app = ServerApp(Room(world, 20.0), "127.0.0.1", 0)
    assert not app.idle_work_ok()  # nothing measured yet
    app.check_cpu_share.extend([0.9, 0.2, 0.15, 0.3, 0.8])
    assert not app.idle_work_ok()  # the median job had 0.3 of a core
    app.check_cpu_share.extend([0.9, 0.95, 1.0])
    assert app.idle_work_ok()
