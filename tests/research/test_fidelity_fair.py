"""The fidelity benchmark compares like with like (issue 58): what each peer is given and how it
renders, as a user of that scheme would notice it: mmt-id identifies the object as the product
does, force-jacobian and the virtual coupling push only once the probe touches, the tool has mass
and damping, the stale sampling phase is the client's, and a second user's press moves the
surface under a user held still."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.bench.fidelity import _follow_errors
from haptic_collab.research.fidelity_1d import simulate
from haptic_collab.research.fidelity_cases import (
    IMPACT,
    OTHER_USER_FOLLOW,
    SPRING,
    SPRING_SOFTER,
    Cell,
    OtherUser,
    felt_depth_m,
    felt_trajectory,
    follow_depth_m,
    follow_trajectory,
    stale_ticks,
)
from haptic_collab.research.fidelity_metrics import cell_metrics, felt_response
from haptic_collab.research.fidelity_ranking import Outcome, choose_variant, follow_error
from haptic_collab.research.fidelity_schemes import (
    TOOL_MASSES_KG,
    DeviceModel,
    Rendering,
    peer_renderings,
    plane_dampers,
    tool_damping,
)
from haptic_collab.shared.full_loop import DEFAULT_HAND
from haptic_collab.shared.gains.policy import PLANE_DAMPERS

DEV = DeviceModel()


def _peer(scheme: str, variant: str, k_o: float = 300.0, *, alone: bool = True) -> Rendering:
    rs = peer_renderings(scheme, k_o=k_o, sim_rate_hz=20.0, alone=alone)
    return next(r for r in rs if r.variant == variant)


def test_the_plane_peers_get_the_products_damper_and_hold_grid() -> None:
    grid = tuple(f * DEV.max_damping_n_s_per_m for f in PLANE_DAMPERS)
    assert plane_dampers(DEV) == grid
    for s in ("mmt", "mmt-id", "static-local"):
        alone = peer_renderings(s, k_o=300.0, sim_rate_hz=20.0)
        assert tuple(r.b_h for r in alone) == grid
        assert all(r.k_h == min(300.0, DEV.max_stiffness_n_per_m) or r.kind == "mmt" for r in alone)
    # with another user the plane follows the patch: both proxy holds
    two = peer_renderings("mmt-id", k_o=300.0, sim_rate_hz=20.0, alone=False)
    assert {(r.b_h, r.proxy_hold) for r in two} == {(b, h) for b in grid for h in ("zoh", "foh")}
    assert all(r.identifies for r in two)


def test_mmt_id_feels_the_object_where_the_k_o_reported_is_off() -> None:
    # the spring 20 % softer than reported: a plane of the K_o reported is felt 1/0.8 = 1.25
    # times the object; mmt-id's plane, with the stiffness the product's own-response check
    # identifies, as the object itself (read on the longer probe, after the identification)
    k = 300.0
    depth = felt_depth_m(k, DEV.max_force_n, SPRING_SOFTER)
    mmt, mmt_id = _peer("mmt", "B=0"), _peer("mmt-id", "B=0")
    cells = [
        Cell(r, k, 20.0, 50.0, None, felt_trajectory(1.0, depth, longer=True), SPRING_SOFTER)
        for r in (mmt, mmt_id)
    ]
    q_mmt, q_id = felt_response(simulate(cells), cells)
    assert q_mmt is not None and q_id is not None
    assert abs(q_mmt) == pytest.approx(1.25, rel=0.02)
    assert abs(q_id) == pytest.approx(1.0, abs=0.03)


@pytest.mark.parametrize("scheme", ["force-jacobian", "virtual-coupling"])
def test_nothing_pushes_before_the_probe_touches(scheme: str) -> None:
    # an impact at 0.3 m/s through 100 ms each way: the probe is outside the object (depth < 0)
    # for the first 67 ms; no force may reach the hand there (the force-jacobian's stiffness
    # about a probe received outside pushed up to 4.4 N before)
    r = peer_renderings(scheme, k_o=1000.0, sim_rate_hz=20.0)[0]
    cell = Cell(r, 1000.0, 20.0, 100.0, DEFAULT_HAND, IMPACT, SPRING)
    run = simulate([cell])
    outside = run.x[0] < 0.0
    assert outside[:50].all()
    before_touch = np.cumsum(~outside) == 0
    assert np.max(np.abs(run.f[0, before_touch])) == 0.0
    # and it does push once the object is reached
    assert run.f[0].max() > 1.0


def test_the_virtual_tool_has_mass_and_damping_and_is_felt_through_them() -> None:
    vcs = peer_renderings("virtual-coupling", k_o=300.0, sim_rate_hz=20.0)
    assert [r.tool_mass_kg for r in vcs] == list(TOOL_MASSES_KG)
    for r in vcs:
        # the coupling at the device's Z-width corner, the tool critically damped on it
        assert (r.k_h, r.b_h) == (DEV.max_stiffness_n_per_m, DEV.max_damping_n_s_per_m)
        assert r.tool_damping_n_s_per_m == tool_damping(r.k_h, r.b_h, r.tool_mass_kg)
        assert r.tool_damping_n_s_per_m == max(0.0, 2.0 * math.sqrt(r.k_h * r.tool_mass_kg) - r.b_h)
    # the tool's mass and damping are felt: at 8 Hz the two tools differ by more than the
    # stiffness JND (the heavier one's inertia and damping against the object)
    k = 300.0
    depth = felt_depth_m(k, DEV.max_force_n)
    cells = [Cell(r, k, 100.0, 0.0, None, felt_trajectory(8.0, depth)) for r in vcs]
    light, heavy = felt_response(simulate(cells), cells)
    assert light is not None and heavy is not None
    assert abs(math.log(abs(heavy) / abs(light))) > math.log(1.1)


def test_the_stale_phase_is_half_a_simulation_period() -> None:
    # the client sends its state every half simulation period: at most N/2 servo ticks old
    assert [stale_ticks(n) for n in (10, 20, 50, 100)] == [5, 10, 25, 50]


def test_another_users_press_moves_the_surface_under_a_user_held_still() -> None:
    # the follow probe held 5 mm into a 300 N/m spring: the other's 1 mm bulge raises the
    # object's force by 0.3 N. A plane at the rest surface the patch implies (mmt) follows it;
    # static-local's plane, never updated, feels nothing of it
    k = 300.0
    other = OTHER_USER_FOLLOW
    depth = follow_depth_m(k, DEV.max_force_n, SPRING, other.bulge_m)
    assert depth == pytest.approx(5e-3)
    traj = follow_trajectory(depth)
    mmt = _peer("mmt", "B=0, zoh", k, alone=False)
    wall = _peer("static-local", "B=0", k, alone=False)
    cells = [Cell(r, k, 20.0, 50.0, None, traj, SPRING, other=other) for r in (mmt, wall)]
    err_mmt, err_wall = _follow_errors(simulate(cells), cells)
    assert err_mmt < 0.05
    assert math.isinf(err_wall)
    # the rest surface's motion: out by the bulge while the other holds, back after
    t = np.array([0.5, 2.6, 4.4])
    assert other.rest_depth_m(t) == pytest.approx([0.0, -other.bulge_m, 0.0])


def test_with_another_user_no_rest_plane_is_sent() -> None:
    # alone, mmt's plane stays at the server's rest surface and is felt as the spring whatever
    # the delay; with another user it is placed from the patch, the simulation's estimate
    k = 300.0
    r = _peer("mmt", "B=0", k)
    depth = felt_depth_m(k, DEV.max_force_n)
    alone = Cell(r, k, 20.0, 200.0, None, felt_trajectory(4.0, depth))
    q = felt_response(simulate([alone]), [alone])[0]
    assert q is not None and abs(q) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="other user"):
        OtherUser(bulge_m=0.0)


def test_follow_error_and_the_rule_that_picks_a_tuning() -> None:
    assert follow_error(1.0, 1.3, 1.0, 0.3, 0.0) == pytest.approx(0.0, abs=1e-12)
    assert follow_error(1.0, 1.15, 1.0, 0.3, 0.0) == pytest.approx(math.log(2.0))
    assert math.isinf(follow_error(1.0, 1.0, 1.0, 0.3, 0.0))  # felt nothing of it
    assert math.isinf(follow_error(1.0, 1.3, 1.0, 0.3, 0.1))  # ringing while held
    # the tuning a peer ships: stable with every hand, then the least error (here the follow
    # error of the two-user grid)
    r = Rendering("mmt", "mmt")
    outs = [
        Outcome(r, [True, False], follow_error=0.0),
        Outcome(r, [True, True], follow_error=0.3),
        Outcome(r, [True, True], follow_error=0.1),
    ]
    assert choose_variant(outs) == 2
    # box-stable with the other user: the hand cells run with it
    cells = [Cell(r, 300.0, 20.0, 0.0, DEFAULT_HAND, IMPACT, SPRING, other=OTHER_USER_FOLLOW)]
    assert cell_metrics(simulate(cells), cells)[0].stable
