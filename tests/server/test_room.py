"""The room's protocol handling, sans-I/O: joins, patches, and hostile input from one connection.

A small recording world stands in for the physics here so that the tests can see exactly what
reached the simulation; the real world is exercised in test_world.py and the loopback tests.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.object_info import object_info
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import decode_binary
from tests.support.rooms import RecordingWorld, hello, prime, state, texts


@pytest.fixture
def room():
    r = Room(RecordingWorld(), 20.0)
    for c in ("a", "b"):
        r.connect(c, 0.0)
        (w,) = texts(r.receive(c, hello(c.upper()), 0.0), c)
        assert w["type"] == "welcome" and w["object"]["n_vertices"] == 6
    prime(r, ("a", "b"))
    return r


def test_users_get_patches_with_k_o_and_k_o_eff(room):
    room.receive("a", state(1), 0.01)
    room.receive("b", state(1, z=0.098), 0.01)
    outs = room.tick(1, 0.05)
    pa = texts(outs, "a")[0]
    assert pa["type"] == "patch" and pa["tick"] == 1
    assert pa["k_o"] == 400.0 and pa["k_o_eff"] == 380.0
    assert pa["primitive"]["kind"] == "plane"
    assert texts(outs, "b")[0]["penetration_m"] == pytest.approx(0.002)


def test_viewer_gets_faces_then_vertices_and_room_each_tick(room):
    room.connect("v", 0.0)
    outs = room.receive("v", hello("viewer", "viewer"), 0.0)
    binaries = [o.data for o in outs if isinstance(o.data, bytes)]
    assert decode_binary(binaries[0])[0] == b"FAC1" and decode_binary(binaries[1])[0] == b"VTX1"
    room.receive("a", state(1), 0.01)
    outs = room.tick(2, 0.05)
    (summary,) = texts(outs, "v")
    assert summary["type"] == "room" and [u["name"] for u in summary["users"]] == ["A", "B"]
    assert summary["users"][0]["k_o_eff"] == 380.0
    assert summary["users"][0]["force_n"] == [0, 0, 1.0]
    assert any(isinstance(o.data, bytes) and o.conn_id == "v" for o in outs)


@pytest.mark.parametrize(
    "frame,code",
    [
        ("{not json", "malformed_json"),
        ('{"type":"state","seq":5,"probe_m":[0,0,NaN],"force_n":[0,0,1]}', "non_finite"),
        ('{"type":"teleport"}', "unknown_type"),
        ('{"type":"state","seq":5,"probe_m":[0,0,0.09],"force_n":[0,0,1e6]}', "force_limit"),
        ('{"type":"state","seq":5,"probe_m":[90,90,0],"force_n":[0,0,1]}', "probe_out_of_range"),
        (hello("again"), "duplicate_hello"),
    ],
)
def test_hostile_frame_gets_an_error_and_the_others_are_unaffected(room, frame, code):
    room.receive("a", state(1), 0.01)
    room.receive("b", state(1, z=0.097, force=0.5), 0.01)
    outs = room.receive("a", frame, 0.02)
    (err,) = texts(outs, "a")
    assert err["type"] == "error" and err["code"] == code and not err["fatal"]
    assert not any(o.close for o in outs)
    outs = room.tick(1, 0.05)
    world = room.world
    # the world got A's last good state and B's, nothing from the bad frame
    last = world.inputs[-1]
    assert set(last) == {"a", "b"}
    assert last["a"].force[2] == pytest.approx(1.0) and last["b"].force[2] == pytest.approx(0.5)
    assert texts(outs, "b")[0]["type"] == "patch"


def test_wrong_protocol_version_and_missing_hello_close_only_that_connection(room):
    room.connect("x", 0.0)
    outs = room.receive(
        "x", json.dumps({"type": "hello", "protocol": 99, "role": "user", "name": "X"}), 0.0
    )
    assert texts(outs, "x")[0]["code"] == "protocol_version" and outs[0].close
    room.connect("y", 0.0)
    outs = room.receive("y", state(1), 0.0)
    assert texts(outs, "y")[0]["code"] == "expected_hello" and outs[0].close
    assert sorted(room.users) == ["a", "b"]


def test_oversized_frame_closes_that_connection(room):
    outs = room.receive("a", "x" * 20000, 0.01)
    assert texts(outs, "a")[0]["code"] == "frame_too_large" and outs[0].close
    assert room.users == ["b"]


def test_flood_is_cut_off_and_the_other_user_keeps_working():
    r = Room(RecordingWorld(), 20.0, limits=RoomLimits(rate_per_s=100.0, burst=50.0))
    for c in ("a", "b"):
        r.connect(c, 0.0)
        r.receive(c, hello(c.upper()), 0.0)
    prime(r, ("a", "b"))
    closed = False
    for i in range(200):  # 200 frames within 10 ms
        outs = r.receive("a", state(i + 1), 0.00005 * i)
        if any(o.close for o in outs):
            assert texts(outs, "a")[0]["code"] == "rate_limited"
            closed = True
            break
    assert closed
    r.receive("b", state(1, force=0.7), 0.02)
    outs = r.tick(1, 0.05)
    assert set(r.world.inputs[-1]) == {"b"} and texts(outs, "b")[0]["type"] == "patch"


def test_too_many_errors_closes_the_connection():
    r = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_errors=5))
    r.connect("a", 0.0)
    r.receive("a", hello("A"), 0.0)
    codes = []
    for i in range(8):
        outs = r.receive("a", "garbage", 0.1 * i)
        codes += [(m["code"], o.close) for m, o in zip(texts(outs, "a"), outs, strict=True)]
    assert codes[:5] == [("malformed_json", False)] * 5
    assert codes[5] == ("too_many_errors", True) and len(codes) == 6  # then nothing: closed


def test_silent_user_stops_loading_the_object(room):
    room.receive("a", state(1, force=2.0), 0.0)
    room.tick(1, 0.05)
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(2.0)
    room.tick(20, 1.0)  # nothing from A for a second
    assert np.allclose(room.world.inputs[-1]["a"].force, 0.0)


def test_older_state_does_not_replace_newer(room):
    room.receive("a", state(5, force=1.5), 0.0)
    room.receive("a", state(4, force=3.0), 0.001)
    room.tick(1, 0.05)
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(1.5)


def test_names_are_made_unique_and_room_limits_hold():
    r = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_users=2))
    names = []
    for c in ("a", "b", "c"):
        r.connect(c, 0.0)
        outs = r.receive(c, hello("same"), 0.0)
        names.append(texts(outs, c)[0])
    assert names[0]["name"] == "same" and names[1]["name"] == "same-2"
    assert names[2]["code"] == "room_full"


def test_silent_connections_are_closed_and_cannot_lock_users_out():
    r = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_pending=4, hello_timeout_s=5.0))
    for i in range(4):
        r.connect(f"idle{i}", 0.0)
    # too many pending (all from one address): named as such, not "room_full"
    assert texts(r.connect("late", 0.1), "late")[0]["code"] == "too_many_pending"
    outs = r.tick(1, 6.0)  # the idle ones never said hello
    codes = {o.conn_id: json.loads(o.data)["code"] for o in outs if o.close}
    assert codes == {f"idle{i}": "hello_timeout" for i in range(4)}
    r.connect("user", 6.1)
    assert texts(r.receive("user", hello("U"), 6.1), "user")[0]["type"] == "welcome"


def test_users_resting_on_a_side_get_four_distinct_side_anchors(room):
    info = room.object_info
    assert len(info.sides) == 4
    assert info.sides[0].point_m == info.side_m and info.sides[0].normal == info.side_normal
    points = np.array([s.point_m for s in info.sides])
    normals = np.array([s.normal for s in info.sides])
    # +x, +y, -x, -y of the balloon: four points about a diameter apart, normals pointing out
    center = np.array(info.center_m)
    assert np.allclose(np.linalg.norm(points - center, axis=1), info.radius_m, rtol=0.05)
    assert min(np.linalg.norm(points[i] - points[j]) for i in range(4) for j in range(i)) > 0.1
    for want, n in zip(([1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]), normals, strict=True):
        assert np.dot(n, want) > 0.9


def test_the_room_keeps_the_simulation_schedule_and_skips_missed_ticks():
    room = Room(RecordingWorld(), 20.0)  # a tick every 50 ms
    room.connect("a", 0.0)
    room.receive("a", hello("A"), 0.0)
    room.receive("a", state(1), 0.0)
    assert room.get_timer() == float("inf")  # not started: nothing is ever due
    assert room.handle_timer(1e9) == []
    room.start(10.0)
    assert room.get_timer() == pytest.approx(10.05)
    assert room.handle_timer(10.04) == [] and room.tick_count == 0  # early: nothing runs
    room.tick_cost(0.001)  # no tick ran: nothing to record
    assert not room.stats.window
    patches = [o for o in room.handle_timer(10.05) if o.stream == "patch"]
    assert [json.loads(o.data)["tick"] for o in patches] == [1]
    room.tick_cost(0.002)
    room.tick_cost(0.002)  # reported twice: recorded once
    assert list(room.stats.window) == [pytest.approx(2.0)] and room.stats.overruns == 0
    # the next tick runs 3.5 periods late: one tick, three skipped and counted, none piled up
    patches = [o for o in room.handle_timer(10.10 + 3.5 * 0.05) if o.stream == "patch"]
    assert [json.loads(o.data)["tick"] for o in patches] == [5]
    assert room.stats.overruns == 3
    assert room.ticks_run == 2  # the metrics' tick count: ticks run, not tick numbers
    assert room.get_timer() == pytest.approx(10.30)  # back on the drift-free schedule
    room.tick_cost(0.06)  # a tick that took longer than its period is an overrun too
    assert room.stats.overruns == 4
    room.stop()
    assert room.get_timer() == float("inf")
    room.start(20.0)  # a restarted schedule goes on numbering from the last tick
    assert room.get_timer() == pytest.approx(20.05)
    patches = [o for o in room.handle_timer(20.05) if o.stream == "patch"]
    assert [json.loads(o.data)["tick"] for o in patches] == [6]


def test_a_tick_that_raises_is_not_run_again():
    room = Room(RecordingWorld(), 20.0)
    room.start(0.0)
    calls = []

    def broken(k, now_s):
        calls.append(k)
        raise RuntimeError("physics bug")

    room.tick = broken  # type: ignore[method-assign]
    with pytest.raises(RuntimeError):
        room.handle_timer(0.05)
    assert room.get_timer() == pytest.approx(0.10)  # the schedule moved on
    with pytest.raises(RuntimeError):
        room.handle_timer(0.10)
    assert calls == [1, 2]


def test_users_are_anchored_on_the_middle_of_a_flat_top_and_side_not_a_corner():
    """A box's highest vertices are a whole face: the demo's users press its middle."""
    import trimesh

    v, f = trimesh.remesh.subdivide_to_size(
        trimesh.creation.box(extents=(0.1, 0.12, 0.08)).vertices,
        trimesh.creation.box(extents=(0.1, 0.12, 0.08)).faces,
        max_edge=0.01,
    )
    info = object_info(v, f)
    assert np.allclose(info.top_m, (0.0, 0.0, 0.04), atol=0.006)
    assert np.allclose(info.top_normal, (0.0, 0.0, 1.0), atol=1e-6)
    assert np.allclose(info.side_m, (0.05, 0.0, 0.0), atol=0.006)
    assert np.allclose(info.side_normal, (1.0, 0.0, 0.0), atol=1e-6)
    assert [round(s.normal[k]) for s, k in zip(info.sides, (0, 1, 0, 1), strict=True)] == [
        1,
        1,
        -1,
        -1,
    ]


def test_the_first_side_anchor_is_where_a_press_on_the_top_reaches():
    """On the 9 mm plate a push on the top hardly moves its +y rim: a user resting there could
    not feel it. The room lists the sides by the share of the top's push felt there, most
    first."""
    from haptic_collab.server.object_info import order_sides_by_coupling, side_coupling
    from haptic_collab.server.objects.balloon import Balloon, BalloonParams
    from haptic_collab.server.objects.shapes import stress_mesh

    mesh = stress_mesh("plate")
    obj = Balloon(mesh, BalloonParams())
    geometric = object_info(mesh.vertices, mesh.faces)
    felt = np.abs(side_coupling(geometric, obj))
    assert felt.min() < 0.05 * felt.max()  # some rim hardly moves: the reason for the order
    assert felt.max() > 0.1  # a tenth of the top's push, the force JND of a resting user
    ordered = order_sides_by_coupling(geometric, obj)
    first = np.abs(side_coupling(ordered, obj))
    assert first[0] == pytest.approx(felt.max())
    assert list(first) == sorted(first, reverse=True)
    assert {s.point_m for s in ordered.sides} == {s.point_m for s in geometric.sides}
    assert ordered.side_m == geometric.side_m
