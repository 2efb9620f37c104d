"""The server's side of own-force compensation: the force it applied, sent back, and bounded.

A compensating client renders against its patch moved out by C_h F_s, F_s the force the server
applied from it (``own_force_n``); the server must report F_s truthfully, accept the honest force
of such a client resting on its own deformation, and still bound what a lying client can push.
"""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from haptic_collab.research.fidelity_users_3d import top_contact
from haptic_collab.server.force_bound import ForceBoundParams, bound_force
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.server.world import ContactInput
from haptic_collab.shared.primitives import make_plane
from tests.support.rooms import RecordingWorld, hello, prime, state, texts


def test_the_world_reports_the_normal_force_it_applied_from_each_user():
    world = build_world(ServerOptions(sim_rate_hz=20.0))
    out0, top, n = top_contact(world)
    assert out0.own_force_n == 0.0
    out = world.tick({"user": ContactInput(probe=top - 0.002 * n, force=1.5 * n)})["user"]
    assert out.own_force_n == pytest.approx(1.5)
    # a force pulling the surface out is not applied, and none is reported
    out = world.tick({"user": ContactInput(probe=top, force=-1.0 * n)})["user"]
    assert out.own_force_n == 0.0


K_O = 400.0
REST = 0.1  # the rest surface's height; outward normal +z


def _surface(f_s: float):
    """The plane the server sends after applying F_s: the surface pushed in by F_s / K_o."""
    return make_plane((0, 0, REST - f_s / K_O), (0, 0, 1))


def test_an_honest_compensated_force_resting_on_its_own_deformation_passes():
    # probe 5 mm past the rest surface, resting on the surface its own 2 N pushed in: e = 0,
    # the client renders K_h (e + C_h F_s) = 2 N
    probe = (0, 0, REST - 0.005)
    patch = [(_surface(2.0), K_O, 2.0)]
    r = bound_force((0, 0, 2.0), probe, patch, k_h=K_O, i_gain=0, own_gain=1 / K_O,
                    integral_limit_n=7.9)  # fmt: skip
    assert r.reason is None
    # the same report from a client that says it does not compensate is past its model
    r = bound_force((0, 0, 2.0), probe, patch, k_h=K_O, i_gain=0, integral_limit_n=7.9)
    assert r.reason == "too_large"


def test_a_claimed_compensation_cannot_ratchet_the_force_up():
    # a hostile client at a fixed probe 5 mm past the rest surface claims the largest C_h, a huge
    # K_h and 49 N every tick; the server applies what it bounds and the surface follows
    p = ForceBoundParams()
    f_s = 0.0
    for _ in range(100):
        r = bound_force((0, 0, 49.0), (0, 0, REST - 0.005), [(_surface(f_s), K_O, f_s)],
                        k_h=1e6, i_gain=0, own_gain=100.0, integral_limit_n=50.0)  # fmt: skip
        f_s = r.force_n[2]
    ceiling = p.stiffness_factor * K_O * (0.005 + p.penetration_tol_m)
    assert f_s <= ceiling / (1.0 - p.compensation_factor) + 1e-6
    assert f_s < 49.0 / 2
    # and at the rest surface (outside the tolerance) nothing at all
    r = bound_force((0, 0, 49.0), (0, 0, REST + 0.002), [(_surface(0.0), K_O, 0.0)],
                    k_h=1e6, i_gain=0, own_gain=100.0, integral_limit_n=50.0)  # fmt: skip
    assert r.force_n == (0.0, 0.0, 0.0)


class _PushedWorld(RecordingWorld):
    """The recording world, reporting the normal force each user applied as ``own_force_n``."""

    def tick(self, inputs, tick=None):
        out = super().tick(inputs, tick)
        return {
            k: replace(o, own_force_n=max(0.0, float(inputs[k].force[2]))) for k, o in out.items()
        }


def test_the_room_sends_the_force_applied_and_believes_a_compensating_client():
    room = Room(_PushedWorld(), 20.0)
    room.connect("a", 0.0)
    room.receive("a", hello("A"), 0.0)
    prime(room, ("a",))
    # pressing 5 mm with a plain P model: 2 N applied, and the next patch says so
    room.receive("a", state(1, z=0.095, force=2.0), 0.05)
    (patch,) = [m for m in texts(room.tick(1, 0.05), "a") if m["type"] == "patch"]
    assert patch["own_force_n"] == pytest.approx(2.0)
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(2.0)
    # resting on the patch's surface (e = 0), holding 2 N by compensation: applied unchanged
    msg = json.loads(state(2, z=0.1, force=2.0))
    msg["own_gain"] = 1.0 / 400.0
    room.receive("a", json.dumps(msg), 0.1)
    room.tick(2, 0.1)
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(2.0)
    assert room.clamp_counts.get("A", 0) == 0


def test_an_honest_client_with_a_small_k_h_keeps_the_force_its_compensation_holds():
    # interim gains K_h = K_o / 20 with C_h = 1/K_h: F = K_h (x - x_o) + F_s; resting on the
    # deformed surface (e = 0) it holds the 2 N the server applied, tick after tick
    k_h = K_O / 20.0
    f_s = 2.0
    for _ in range(40):
        r = bound_force((0, 0, f_s), (0, 0, REST - f_s / K_O), [(_surface(f_s), K_O, f_s)],
                        k_h=k_h, i_gain=0, own_gain=1.0 / k_h, integral_limit_n=7.9)  # fmt: skip
        assert r.reason is None
        f_s = r.force_n[2]
    assert f_s == pytest.approx(2.0)


def test_the_room_believes_a_user_alone_on_its_rest_plane_and_still_bounds_a_liar():
    # a user alone renders the rest plane the patch carries with K_h = K_o and no compensation
    # (shared.gains.rest_plane): its force is K_o times the depth under the rest surface, while the
    # current surface has given way by F / K_o under it. The bound must allow that force (by the
    # current surface alone it allowed K_o times the depth under it: a fraction), and no more
    world = build_world(ServerOptions(sim_rate_hz=20.0))
    room = Room(world, 20.0)
    room.connect("a", 0.0)
    room.receive("a", hello("A"), 0.0)
    info = room.object_info
    top = info.top_m
    depth = 0.004
    z = top[2] - depth

    def step(seq: int, force: float, k_h: float) -> dict:
        msg = json.loads(state(seq, z=z, force=force, k_h=k_h))
        msg["probe_m"] = [top[0], top[1], z]
        room.receive("a", json.dumps(msg), 0.05 * seq)
        (patch,) = [m for m in texts(room.tick(seq, 0.05 * seq), "a") if m["type"] == "patch"]
        return patch

    patch = step(0, 0.0, 100.0)
    force = 0.0
    for seq in range(1, 40):
        assert patch["rest_plane"] is not None
        k_o = patch["k_o"]
        force = k_o * (patch["rest_plane"]["point"][2] - z)
        patch = step(seq, force, k_o)
    assert patch["own_force_n"] == pytest.approx(force, rel=1e-6)
    assert force > 0.5 and room.clamp_counts.get("A", 0) == 0
    # the surface gave way under the push: by the surface alone the force is far off
    surface_depth = patch["primitive"]["point"][2] - z
    assert patch["k_o"] * surface_depth < 0.5 * force
    # twice that force is more than the rest plane allows: clamped to K_o times the depth
    # under it, with the bound's penetration tolerance
    k_o, rest_depth = patch["k_o"], patch["rest_plane"]["point"][2] - z
    patch = step(40, 2.0 * force, k_o)
    assert room.clamp_counts.get("A", 0) == 1
    tol = ForceBoundParams().penetration_tol_m
    assert patch["own_force_n"] <= k_o * (rest_depth + tol) + 1e-6 < 1.5 * force
