"""The server recommends gains in every patch: the Python client's design, stable over the hand box.

Checked without sockets (the advisor and the room, with the jobs run as the I/O layer runs them)
and independently re-verified with :func:`shared.full_loop.spectral_radius` over every hand of
the box, every sampling tick and the K_o margin.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json

import numpy as np
import pytest

from haptic_collab.client.session import ClientSession
from haptic_collab.server.gains import GainAdvisor, GainJob, run_job
from haptic_collab.server.objects.balloon import Balloon
from haptic_collab.server.objects.mesh import default_balloon
from haptic_collab.server.room import Room
from haptic_collab.server.world import World
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, spectral_radius
from haptic_collab.shared.protocol import (
    DeviceInfo,
    Hello,
    Patch,
    PlaneModel,
    Pong,
    RecommendedGains,
    State,
    Welcome,
    encode,
)
from tests.support.sessions import WELCOME_OBJECT as OBJ

PHANTOM = DeviceInfo(
    profile="phantom-desktop",
    max_force_n=7.9,
    max_stiffness_n_per_m=1000.0,
    max_damping_n_s_per_m=10.0,
)


def hello(local_model: str = "pi", device: DeviceInfo = PHANTOM) -> Hello:
    return Hello(protocol=1, role="user", name="A", device=device, local_model=local_model)  # type: ignore[arg-type]


def run_jobs(adv: GainAdvisor) -> list[GainJob]:
    jobs = adv.take_jobs()
    for job in jobs:
        adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    return jobs


def assert_stable_over_the_box(g: RecommendedGains, k_o: float, rate_ratio: int = 50) -> None:
    for k in (k_o, 0.85 * k_o):
        rho = spectral_radius(
            hand=DEFAULT_HAND_BOX.hands(), k_o=k, k_h=g.k_h, i_gain=g.i_gain, b_h=g.b_h,
            rate_ratio=rate_ratio, delay_ticks=g.delay_ticks, proxy_hold=g.proxy_hold,
            own_gain=g.own_gain,
        )  # fmt: skip
        assert rho.max() < 1.0, (k, rho.max())


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_recommended_gains_are_the_design_and_stable_over_the_hand_box(mode: str) -> None:
    adv = GainAdvisor(20.0, shipped=False)  # the online design, not the shipped table
    h = hello(mode)
    assert adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0) is None
    jobs = run_jobs(adv)
    assert [j.kind for j in jobs] == ["interim", "design"]  # the quick check first
    g = adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    assert g is not None
    assert g.k_h <= PHANTOM.max_stiffness_n_per_m and g.b_h <= 10.0
    # here P and PI requests alike get a compensated P model, C_h K_h = 1 (closer to K_o at 1 Hz
    # and in a held press than any PI design), so no integral and no threshold
    assert g.i_gain == 0.0 and g.own_gain * g.k_h == pytest.approx(1.0) and g.delay_ticks == 0
    assert g.theta_m == 0.0
    assert_stable_over_the_box(g, 300.0)
    # exactly what the Python client designs for itself
    own = ClientSession("A", device=PHANTOM, b_h_max=10.0, mode=mode, gains="local")  # type: ignore[arg-type]
    own.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    key = own.gain_key(0.0, 0)
    d = own.gain_table.design(key, 300.0)
    assert (g.k_h, g.i_gain, g.b_h, g.proxy_hold) == (d.k_h, d.i_gain, d.b_h, d.proxy_hold)


def test_the_delay_the_user_reports_makes_the_gains_cover_it() -> None:
    adv = GainAdvisor(20.0, shipped=False)  # the online design, not the shipped table
    h = hello("pi")
    for _ in range(5):
        adv.observe_rtt("u1", 120.0)  # 120 ms round trip at 20 Hz: 2 extra ticks
    assert adv.delay_ticks("u1") == 2
    adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    run_jobs(adv)
    g = adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    assert g is not None and g.delay_ticks == 2
    assert_stable_over_the_box(g, 300.0)


def test_odd_users_get_no_recommendation_and_cost_nothing() -> None:
    adv = GainAdvisor(20.0, shipped=False)  # the online design, not the shipped table
    odd = Hello(protocol=1, role="user", name="B", servo_rate_hz=1001.0)  # N = 50.05
    assert adv.recommend("b", odd, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0) is None
    assert adv.take_jobs() == []
    # a failed job is not asked again every tick
    h = hello("pi")
    adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    jobs = adv.take_jobs()
    for job in jobs:
        adv.store(job, None)
    adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    assert adv.take_jobs() == []


def test_the_room_sends_the_recommendation_in_the_patch_and_the_client_renders_it() -> None:
    world = World(Balloon(default_balloon(subdivisions=3)))
    room = Room(world, 20.0)
    room.gains = GainAdvisor(20.0, shipped=False)  # the online design (shipped: a test below)
    room.connect("c1", 0.0)
    room.receive("c1", encode(hello("pi")), 0.0)
    top = room.object_info.top_m
    probe = (top[0], top[1], top[2] - 0.002)
    state = State(
        seq=1, probe_m=probe, force_n=(0.0, 0.0, 0.0), penetration_m=0.0, in_contact=False
    )
    room.receive("c1", encode(state), 0.01)

    def patch(k: int) -> Patch:
        outs = [o for o in room.tick(k, 0.05 * k) if o.conn_id == "c1" and o.stream == "patch"]
        assert len(outs) == 1
        return Patch.model_validate(json.loads(outs[0].data))  # type: ignore[arg-type]

    first = patch(1)
    assert first.gains is None  # nothing designed yet: the client designs its own meanwhile
    run_jobs(room.gains)
    p = patch(2)
    assert p.gains is not None
    assert_stable_over_the_box(p.gains, p.k_o_eff)
    # the Python client renders it as it is where it renders the simulation's surface (alone on
    # the object, as here, it renders the rest plane the patch carries: test_rest_plane.py)
    assert p.rest_plane is not None
    s = ClientSession("A", device=PHANTOM, b_h_max=10.0, rest_plane=False)
    s.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    up = s.receive(encode(p), 0.1)
    assert up is not None and up.choice is not None and not up.choice.fallback
    assert s.server_gain_patches == 1
    assert (up.k_h, up.i_gain, up.b_h) == (p.gains.k_h, p.gains.i_gain, p.gains.b_h)
    # ... unless it is beyond this device: a softer device designs its own
    soft = ClientSession(
        "A",
        device=DeviceInfo(max_stiffness_n_per_m=0.5 * p.gains.k_h),
        b_h_max=10.0,
        rest_plane=False,
    )
    soft.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    soft.receive(encode(p), 0.1)
    assert soft.server_gain_patches == 0 and soft.design_wanted is not None


def test_a_recommendation_for_a_shorter_delay_than_measured_is_not_used() -> None:
    rec = RecommendedGains(
        k_h=100.0, i_gain=0.0, b_h=0.0, proxy_hold="zoh", theta_m=0.0, delay_ticks=0
    )
    p = Patch(
        tick=1, primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)), proxy_m=(0, 0, 0.1),
        normal=(0, 0, 1), penetration_m=0.002, in_contact=True, k_o=300.0, k_o_eff=300.0,
        b_o=0.0, gains=rec,
    )  # fmt: skip
    s = ClientSession("A", device=PHANTOM, b_h_max=10.0)
    s.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    s.rtt_s.extend([0.2] * 10)  # this client measures 4 ticks of delay
    s.receive(encode(p), 0.1)
    assert s.server_gain_patches == 0
    assert np.isfinite(s.delay_ticks()) and s.delay_ticks() > 0


def test_the_most_urgent_job_goes_first_interim_checks_then_the_newest_cell() -> None:
    """A user sweeping over the object asks for one K_o cell after another: its forces come on
    with an interim check, and the cell it is in now is designed before the ones it left."""
    adv = GainAdvisor(20.0, shipped=False)  # the online design, not the shipped table
    h = hello("pi")
    for k_o in (200.0, 260.0, 340.0):  # three cells, in the order the user met them
        assert adv.recommend("u1", h, k_o_eff=k_o, k_o_stiff=k_o, b_o=0.0) is None
    order = []
    while (job := adv.next_job()) is not None:
        order.append((job.kind, job.cell))
    cells = [adv.table.cell(k) for k in (200.0, 260.0, 340.0)]
    assert order == [("interim", c) for c in reversed(cells)] + [
        ("design", c) for c in reversed(cells)
    ]
    assert adv.next_job() is None and adv.take_jobs() == []  # each job is handed out once


def test_a_resting_users_design_is_not_starved_by_a_sweeping_one() -> None:
    """B rests on one key; A sweeps, asking a new cell each time a design is handed out. Newest
    first alone, A's cells took every design and B waited for the whole demo (the palpation
    demo at 20 ms of latency: B on interim gains for 550 of 597 patches). B's design goes
    first, as B has waited longest, and then the two take turns."""
    adv = GainAdvisor(20.0, shipped=False)
    h = hello("pi")
    b_cell = adv.table.cell(180.0)
    assert adv.recommend("B", h, k_o_eff=180.0, k_o_stiff=180.0, b_o=0.0) is None
    handed = []
    for k_o in (230.0, 280.0, 340.0, 410.0):  # A: a new cell as each design is handed out
        assert adv.recommend("A", h, k_o_eff=k_o, k_o_stiff=k_o, b_o=0.0) is None
        assert adv.recommend("B", h, k_o_eff=180.0, k_o_stiff=180.0, b_o=0.0) is None
        job = adv.next_job("design")
        assert job is not None
        handed.append(job.cell)
    assert handed[0] == b_cell
    # then turns: A's cell now, since B's design is out; the rest of A's cells after
    assert handed[1:] == [adv.table.cell(k) for k in (280.0, 340.0, 410.0)]
    # B's design is out: what is left goes newest first
    left = []
    while (job := adv.next_job("design")) is not None:
        left.append(job.cell)
    assert left == [adv.table.cell(230.0)]


def test_a_key_without_verified_gains_costs_the_tick_no_scan_of_the_table(monkeypatch) -> None:
    """The server recommends only verified gains, yet every tick a user rendered a key without
    them it looked for the nearest designed cell, which scans the whole table (5.5 ms with the
    shipped tables' 10752 cells; 5-11 ms of a tick a user in the palpation slide). It no longer
    looks: the check and the design are asked as before, and the check's gains render on the
    first tick after it."""
    from haptic_collab.shared.gains.table import GainTable

    def scan(*args, **kwargs):
        raise AssertionError("the server scanned the table for unverified gains")

    monkeypatch.setattr(GainTable, "fallback", scan)
    adv = GainAdvisor(20.0)  # the shipped tables: this key is not in them (B_o 17 N/m, 2 ticks)
    h = hello("pi")
    adv.observe_rtt("u1", 80.0, 80.0)
    for _ in range(3):
        assert adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=17.0) is None
    kinds = []
    while (job := adv.next_job()) is not None:
        kinds.append(job.kind)
        if job.kind == "interim":
            adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    assert kinds[:2] == ["interim", "design"]
    rec = adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=17.0)
    assert rec is not None and rec.interim and rec.delay_ticks >= 1
    assert_stable_over_the_box(rec, 300.0)


def test_an_interim_recommendation_yields_to_the_clients_own_full_design() -> None:
    """The server flags interim gains; a client with its own full design for the contact renders
    that, and renders the server's interim gains only while it has nothing designed itself."""
    adv = GainAdvisor(20.0, shipped=False)  # the online design, not the shipped table
    h = hello("pi")
    assert adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0) is None
    job = adv.next_job()
    assert job is not None and job.kind == "interim"
    adv.store(job, run_job(job, adv.table.grid_ratio, adv.table.hand_box))
    rec = adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0)
    assert rec is not None and rec.interim

    def patch(tick: int) -> Patch:
        return Patch(
            tick=tick, primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)),
            proxy_m=(0, 0, 0.1), normal=(0, 0, 1), penetration_m=0.002, in_contact=True,
            k_o=300.0, k_o_eff=300.0, b_o=0.0, gains=rec,
        )  # fmt: skip

    s = ClientSession("A", device=PHANTOM, b_h_max=10.0)
    s.receive(
        encode(Welcome(user_id="u1", name="A", role="user", sim_rate_hz=20.0, object=OBJ)), 0.0
    )
    up = s.receive(encode(patch(1)), 0.1)  # nothing of its own yet: the server's interim gains
    assert up is not None and s.server_gain_patches == 1 and up.k_h == rec.k_h
    key, k_o = s.design_wanted or (s.gain_key(0.0, 0), 300.0)
    s.gain_table.design(key, k_o)  # its own full design is ready now
    up = s.receive(encode(patch(2)), 0.15)
    own = s.gain_table.lookup(key, 300.0)
    assert up is not None and own is not None and s.server_gain_patches == 1
    assert (up.k_h, up.i_gain) == (own.k_h, own.i_gain) != (rec.k_h, rec.i_gain)


def test_the_advisor_holds_the_delay_through_a_contact_as_the_client_does() -> None:
    # the advisor's recommendation changes key only as the client's own would: a steady hold
    # whose round trips waver under load keeps one key (shared.gains.delay.DelayHold)
    adv = GainAdvisor(20.0, shipped=False)
    h = hello("pi")
    for _ in range(20):
        adv.observe_rtt("u1", 320.0)  # 6 ticks at 20 Hz
    keys = [adv.key("u1", h, 0.0, 300.0, 300.0, tick=0, in_contact=True).delay_ticks]
    for i in range(1, 400):  # 20 s of patches while the round trip falls to 20 ms
        adv.observe_rtt("u1", 20.0)
        keys.append(adv.key("u1", h, 0.0, 300.0, 300.0, tick=i, in_contact=True).delay_ticks)
    assert set(keys) == {6}
    # released: the lower delay is designed for once it has lasted 5 s (100 ticks)
    after = [
        adv.key("u1", h, 0.0, 300.0, 300.0, tick=400 + i, in_contact=False).delay_ticks
        for i in range(101)
    ]
    assert after[0] == 6 and after[99] == 6 and after[100] == 0


def test_with_the_shipped_table_the_first_patch_carries_the_sessions_own_design() -> None:
    # a covered key (the Phantom Desktop, 20 Hz, no delay, the balloon's stiffness): a design
    # from the first patch, the one the client would make itself, with no job for the worker
    adv = GainAdvisor(20.0)
    assert adv.shipped and all(isinstance(n, int) and n > 0 for n in adv.shipped.values())
    h = hello("pi")
    rec = adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0, tick=0)
    assert rec is not None and not rec.interim and adv.take_jobs() == []
    key = adv.key("u1", h, 0.0, 300.0, 300.0)
    own = GainAdvisor(20.0, shipped=False).table.design(key, 300.0)
    assert (rec.k_h, rec.i_gain, rec.b_h, rec.own_gain) == (
        own.k_h,
        own.i_gain,
        own.b_h,
        own.own_gain,
    )


def test_the_advisor_designs_for_the_delay_the_client_measures_from_its_state() -> None:
    """The client's delay is the 90th percentile of its last 20 pings; its ``state`` carries
    that round trip (``delay_rtt_ms``), so the advisor's key has the client's delay on a trace
    that wavers under load, where a window of the states' median round trips did not."""
    from haptic_collab.client.session import ServoSample
    from tests.support.sessions import welcomed_session

    sample = ServoSample(
        probe_m=(0.0, 0.0, 0.2), force_n=(0.0, 0.0, 0.0), penetration_m=None, in_contact=False,
        k_h=0.0, i_gain=0.0, servo_rate_hz=1000.0, period_us_p99=0.0,
    )  # fmt: skip
    rng = np.random.default_rng(59)
    s = welcomed_session("A", "u1")
    adv = GainAdvisor(20.0, shipped=False)
    median_only = GainAdvisor(20.0, shipped=False)
    differ = 0
    for i in range(200):  # pings every 0.5 s: a loaded loopback, mostly quick, stalls now and then
        rtt = float(rng.choice([0.02, 0.03, 0.05, 0.4]))
        t = 0.5 * i
        s.receive(encode(Pong(id=i + 1, t_client_s=t, tick=i)), t + rtt)
        st = State.model_validate_json(s.state(sample))
        adv.observe_rtt("u1", st.rtt_ms, st.delay_rtt_ms)
        median_only.observe_rtt("u1", st.rtt_ms)
        assert adv.delay_ticks("u1") == s.delay_ticks()
        differ += median_only.delay_ticks("u1") != s.delay_ticks()
    assert differ > 0  # the states' medians alone give another delay on this trace


def test_next_job_of_one_kind_leaves_the_others_queued() -> None:
    adv = GainAdvisor(20.0, shipped=False)
    h = hello("pi")
    assert adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0) is None
    assert adv.next_job("design") is not None  # the design, though the check is more urgent
    job = adv.next_job("interim")
    assert job is not None and job.kind == "interim"
    assert adv.next_job("interim") is None and adv.next_job() is None


async def test_the_servers_interim_check_never_waits_behind_a_running_design(monkeypatch) -> None:
    """The server runs its interim checks in a worker of their own: a new key's check (a fraction
    of a second) comes back while the design worker is still busy with a design (seconds; tens of
    seconds on a loaded machine), and the user's forces come on with it."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from haptic_collab.server import app as app_module
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.main import ServerOptions, build_world

    release = threading.Event()
    ran: list[str] = []

    def fake_run_job(job: GainJob, grid_ratio: float, hand_box: object) -> tuple[object, float]:
        ran.append(job.kind)
        if job.kind == "design":
            release.wait(30.0)  # a design that takes long
            return None, 0.0
        return run_job(job, grid_ratio, hand_box), 0.0  # type: ignore[arg-type]

    monkeypatch.setattr(app_module, "run_job_measured", fake_run_job)
    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=2))
    room = Room(world, 20.0)
    pool = ThreadPoolExecutor(max_workers=2)  # one for the designs, one for the checks
    app = ServerApp(room, "127.0.0.1", 0, gain_executor=pool)
    adv = room.gains
    odd = {"profile": "odd", "max_stiffness_n_per_m": 730.0, "max_damping_n_s_per_m": 7.0}
    h = hello("pi", PHANTOM.model_copy(update=odd))  # no shipped table's device: designed here
    try:
        # a first key: its check and design are handed out; the design blocks the design worker
        assert adv.recommend("u1", h, k_o_eff=300.0, k_o_stiff=300.0, b_o=0.0) is None
        app._start_designs()
        for _ in range(200):
            if "design" in ran:
                break
            await asyncio.sleep(0.05)
        assert "design" in ran and not release.is_set()
        # a second user's key arrives while that design runs: its check comes back at once
        assert adv.recommend("u2", h, k_o_eff=900.0, k_o_stiff=900.0, b_o=0.0) is None
        app._start_designs()
        for _ in range(400):
            if adv.recommend("u2", h, k_o_eff=900.0, k_o_stiff=900.0, b_o=0.0) is not None:
                break
            await asyncio.sleep(0.05)
        rec = adv.recommend("u2", h, k_o_eff=900.0, k_o_stiff=900.0, b_o=0.0)
        assert rec is not None and rec.interim  # checked gains, the design still running
        assert not release.is_set()
    finally:
        release.set()
        await app.stop()
        pool.shutdown(wait=True)


@pytest.fixture(scope="module")
def liver_side(tmp_path_factory):
    """A FEM ball in liver: its side contact's key, K_o, B_o and modes."""
    from tests.support.fem_contact import contact_key, liver_ball

    solid = liver_ball(str(tmp_path_factory.mktemp("volumes")))
    key = contact_key(solid, "side")
    k_o = float(solid.contact_stiffness([key])[0])
    b_o = float(solid.contact_damping([key])[0])
    return key, k_o, b_o, solid.contact_modes(key)


def test_a_fem_contacts_gains_are_checked_on_its_modes_and_replaced_where_they_ring_on(
    liver_side,
) -> None:
    """The shipped design for the ball's side lets the ball's rocking ring on under a resting
    hand; once the modal check is back the patch carries gains that keep the bar, a second
    contact of the same design renders that verdict at once while its own check runs, and an
    object without modes is left alone."""
    contact, k_o, b_o, modes = liver_side
    adv = GainAdvisor(20.0)
    h = hello("p")
    rec = adv.recommend("u1", h, k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o)
    assert rec is not None and not rec.interim  # the shipped table's design
    asked: list[str] = []

    def modes_of(name: str):
        asked.append(name)
        return modes

    out = adv.guard_modes({"u1": rec}, lambda name: contact, modes_of)
    assert out["u1"] == rec and asked == ["u1"]  # not checked yet: the design renders
    job = adv.next_job()
    assert job is not None and job.kind == "modal" and job.modal is not None
    assert adv.next_job(only="modal") is None  # asked once
    verdict = run_job(job, adv.table.grid_ratio, adv.table.hand_box)
    adv.store(job, verdict)
    assert verdict is not None and verdict.designed_rate_per_s < verdict.bar_per_s
    guarded = adv.guard_modes({"u1": rec}, lambda name: contact, modes_of)["u1"]
    assert guarded is not None and guarded != rec and adv.modal_changed == 1
    assert verdict.design is not None and guarded.k_h == pytest.approx(verdict.design.k_h)
    assert guarded.b_h <= PHANTOM.max_damping_n_s_per_m
    assert guarded.own_gain * guarded.k_h == pytest.approx(rec.own_gain * rec.k_h)
    assert guarded.delay_ticks == rec.delay_ticks and not guarded.interim
    assert len(asked) == 1  # its own check is known: not asked again
    # another contact with the same design: the verdict found at the first, its own queued
    other = adv.guard_modes({"u1": rec}, lambda name: contact + 1, modes_of)["u1"]
    assert other == guarded and len(asked) == 2
    nxt = adv.next_job()
    assert nxt is not None and nxt.kind == "modal" and nxt.modal.contact == contact + 1
    # no modes (a mass-spring balloon, a static solid): nothing is checked or changed
    plain = adv.guard_modes({"u1": rec}, lambda name: None, modes_of)
    assert plain["u1"] == rec and len(asked) == 2


def test_modal_checks_go_to_what_users_render_now_designs_first(liver_side) -> None:
    """The check worker spends its seconds on the gains users render now: a resting user's
    design before a sliding user's interim gains, and nothing on gains nobody renders any
    more (asked again should they render again)."""
    contact, k_o, b_o, modes = liver_side
    adv = GainAdvisor(20.0)
    h = hello("p")
    rec = adv.recommend("b", h, k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o)
    assert rec is not None and not rec.interim
    interim = rec.model_copy(update={"k_h": 0.9 * rec.k_h, "interim": True})
    adv.recommend("a", h, k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o)
    adv.guard_modes({"b": rec}, lambda name: contact, lambda name: modes)
    for c in range(1, 4):  # the sliding user's interim gains at one contact after another
        adv.guard_modes({"a": interim}, lambda name, c=c: contact + c, lambda name: modes)
    first = adv.next_job()
    assert first is not None and first.modal is not None
    assert first.modal.contact == contact  # the resting user's design first
    second = adv.next_job()
    assert second is not None and second.modal is not None
    assert second.modal.contact == contact + 3  # where the sliding user is now
    assert adv.next_job() is None  # the contacts it has left: dropped
    # back at one of them: asked again
    adv.guard_modes({"a": interim}, lambda name: contact + 1, lambda name: modes)
    again = adv.next_job()
    assert again is not None and again.modal is not None and again.modal.contact == contact + 1


@pytest.mark.slow  # a FEM ball's ticks and several designs' modal checks: 25 s
def test_the_room_sends_a_fem_contact_the_gains_checked_on_its_modes(tmp_path) -> None:
    """End to end without sockets: a user resting on a FEM ball's side gets the table's design,
    then, once the worker's modal check is back, gains that keep the ball's modes dying out at
    the bar, in the very patch the client renders."""
    from haptic_collab.shared.gains.modal_guard import ModalCase, modal_rate
    from haptic_collab.shared.gains.policy import MODAL_CHECK_MODES
    from tests.support.fem_contact import liver_ball

    solid = liver_ball(str(tmp_path))
    room = Room(World(solid), 20.0)
    room.connect("c1", 0.0)
    room.receive("c1", encode(hello("p")), 0.0)
    probe = (0.099, 0.0, 0.0)  # 1 mm into the side, pushing in
    room.receive(
        "c1", encode(State(seq=1, probe_m=probe, force_n=(-0.2, 0.0, 0.0), k_h=170.0)), 0.01
    )

    def patch(k: int) -> Patch:
        outs = [o for o in room.tick(k, 0.05 * k) if o.conn_id == "c1" and o.stream == "patch"]
        assert len(outs) == 1
        return Patch.model_validate(json.loads(outs[0].data))  # type: ignore[arg-type]

    seen = [patch(1).gains]
    for k in range(2, 8):  # interim checks or designs first, then the modal check
        run_jobs(room.gains)
        seen.append(patch(k).gains)
    given = [g for g in seen if g is not None]
    first, later = given[0], given[-1]
    (contact,) = {c for (c, _, _) in room.gains.modal}
    verdict = next(v for v in room.gains.modal.values() if v is not None)
    assert verdict.designed_rate_per_s < verdict.bar_per_s  # the table's design rings on
    assert later != first and room.gains.modal_changed >= 1
    g = later
    # what the patch carries keeps the ball's modes at the bar over the box
    (u,) = room.gains._users.values()
    assert u.design is not None and u.design_key is not None
    checked = dataclasses.replace(
        u.design, k_h=g.k_h, b_h=g.b_h, proxy_hold=g.proxy_hold, own_gain=g.own_gain
    )
    modes = solid.contact_modes(contact).reduced(MODAL_CHECK_MODES)
    case = ModalCase(contact, u.design_key, u.cell, checked, modes)
    assert modal_rate(case, checked, room.gains.table.hand_box) >= verdict.bar_per_s - 0.05


def test_a_waiting_modal_check_takes_the_turn_after_each_design(liver_side) -> None:
    """Designs do not starve the modal check of what a user renders: after a design the check
    waiting goes next, then the designs go on; interim checks still come first."""
    contact, k_o, b_o, modes = liver_side
    adv = GainAdvisor(20.0)
    rec = adv.recommend("b", hello("p"), k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o)
    assert rec is not None and not rec.interim  # the shipped design, rendered by a resting user
    odd = PHANTOM.model_copy(update={"profile": "odd", "max_stiffness_n_per_m": 730.0})
    for k in (300.0, 600.0, 900.0):  # a sweeping user of a device no table has: three cells
        assert adv.recommend("a", hello("pi", odd), k_o_eff=k, k_o_stiff=k, b_o=0.0) is None
    adv.guard_modes({"b": rec}, lambda name: contact, lambda name: modes)
    kinds = [job.kind for job in iter(adv.next_job, None)]
    assert kinds == ["interim"] * 3 + ["design", "modal", "design", "design"]


def test_every_users_modal_check_waits_in_a_full_room(liver_side) -> None:
    """Eight users on one FEM solid: each one's check waits its turn, and none is asked again
    (rebuilding the contact's modes on the tick) while it waits."""
    contact, k_o, b_o, modes = liver_side
    adv = GainAdvisor(20.0)
    h = hello("p")
    users = [f"u{i}" for i in range(8)]
    recs = {u: adv.recommend(u, h, k_o_eff=k_o, k_o_stiff=k_o, b_o=b_o) for u in users}
    built: list[str] = []

    def modes_of(name: str):
        built.append(name)
        return modes

    for _ in range(3):  # three ticks
        adv.guard_modes(recs, lambda name: contact + users.index(name), modes_of)
    assert sorted(built) == users  # each contact's modes built once
    waiting = {j.modal.contact for j in iter(adv.next_job, None) if j.modal is not None}
    assert waiting == {contact + i for i in range(8)}
