"""Rejoin, sans-I/O: a user whose connection drops gets its seat back with its resume token.

The room's clock is an input (``now_s``), so the 30 s hold is crossed without waiting. A small
recording world stands in for the physics: the tests see which seat loaded the object with what.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.room import RESUME_HOLD_S, Room, is_bye
from haptic_collab.server.security import TokenTable
from haptic_collab.shared.protocol import PROTOCOL_VERSION
from tests.support.rooms import RecordingWorld, hello, prime, state, texts


def resume_hello(name: str, token: str | None, access: str | None = None) -> str:
    msg: dict[str, object] = {
        "type": "hello",
        "protocol": PROTOCOL_VERSION,
        "role": "user",
        "name": name,
    }
    if token is not None:
        msg["resume"] = token
    if access is not None:
        msg["token"] = access
    return json.dumps(msg)


def join(room: Room, conn: str, frame: str, now_s: float) -> dict:
    room.connect(conn, now_s)
    (welcome,) = texts(room.receive(conn, frame, now_s), conn)
    assert welcome["type"] == "welcome", welcome
    return welcome


@pytest.fixture
def room_ab():
    """A room with users A (conn a) and B (conn b), both resting, A pressing 2 N; a viewer v."""
    room = Room(RecordingWorld(), 20.0)
    welcomes = {c: join(room, c, hello(c.upper()), 0.0) for c in ("a", "b")}
    join(room, "v", hello("viewer", "viewer"), 0.0)
    prime(room, ("a", "b"))
    room.receive("a", state(1, force=2.0), 0.01)
    room.receive("b", state(1, z=0.098, force=0.5), 0.01)
    room.tick(1, 0.05)
    return room, welcomes


def viewer_users(outs) -> list[tuple[str, str]]:
    (summary,) = [m for m in texts(outs, "v") if m["type"] == "room"]
    return sorted((u["user_id"], u["name"]) for u in summary["users"])


def test_a_dropped_user_comes_back_to_its_seat_within_the_hold(room_ab):
    room, welcomes = room_ab
    a = welcomes["a"]
    assert a["resume_token"] and not a["resumed"]
    assert len(a["resume_token"]) >= 22  # at least 128 bits in URL-safe base64
    assert a["resume_token"] != welcomes["b"]["resume_token"]
    seat_inputs_before = set(room.world.inputs[-1])
    room.disconnect("a", 1.0)  # the socket closed without bye
    assert room.users == ["b"] and room.held_seats == [a["user_id"]]
    room.receive("b", state(2, z=0.098, force=0.5), 1.0)
    outs = room.tick(2, 1.05)
    # the object keeps A's contact, released: zero force from A, B's push as before
    last = room.world.inputs[-1]
    assert set(last) == seat_inputs_before
    assert np.allclose(last["a"].force, 0.0) and last["b"].force[2] == pytest.approx(0.5)
    assert texts(outs, "a") == []  # nobody to send A's patch to
    assert viewer_users(outs) == [("u1", "A"), ("u2", "B")]

    back = join(room, "a2", resume_hello("A", a["resume_token"]), 20.0)
    assert back["resumed"] and back["user_id"] == a["user_id"] and back["name"] == "A"
    assert back["resume_token"] and back["resume_token"] != a["resume_token"]
    assert room.held_seats == [] and sorted(room.users) == ["a2", "b"]
    # its new connection may start its sequence again; the contact is the same seat's
    room.receive("a2", state(0, force=1.0), 20.01)
    outs = room.tick(400, 20.05)
    assert set(room.world.inputs[-1]) == seat_inputs_before
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(1.0)
    assert texts(outs, "a2")[0]["type"] == "patch"
    assert viewer_users(outs) == [("u1", "A"), ("u2", "B")]  # one A, not two
    assert room.resumes == 1


def test_after_the_hold_the_user_joins_as_a_new_one(room_ab):
    room, welcomes = room_ab
    a = welcomes["a"]
    room.disconnect("a", 1.0)
    room.tick(2, 1.0 + RESUME_HOLD_S - 0.1)
    assert room.held_seats == [a["user_id"]]  # still held just before the end
    outs = room.tick(3, 1.0 + RESUME_HOLD_S + 0.01)
    assert room.held_seats == [] and set(room.world.inputs[-1]) == {"b"}
    assert viewer_users(outs) == [("u2", "B")]
    late = join(room, "a2", resume_hello("A", a["resume_token"]), 1.0 + RESUME_HOLD_S + 0.1)
    assert not late["resumed"] and late["user_id"] not in ("u1", "u2") and late["name"] == "A"
    assert room.resume_misses == 1


def test_a_token_presented_after_the_hold_but_before_a_tick_is_expired(room_ab):
    room, welcomes = room_ab
    room.disconnect("a", 1.0)
    late = join(room, "a2", resume_hello("A", welcomes["a"]["resume_token"]), 31.5)
    assert not late["resumed"] and late["user_id"] == "u4"  # u3 is the viewer


@pytest.mark.parametrize("case", ["used", "garbage", "other_room", "viewer_hello"])
def test_a_token_that_matches_no_seat_joins_a_new_user_and_breaks_nothing(room_ab, case):
    room, welcomes = room_ab
    token = welcomes["a"]["resume_token"]
    room.disconnect("a", 1.0)
    if case == "used":
        first = join(room, "a2", resume_hello("A", token), 2.0)
        assert first["resumed"] and first["user_id"] == "u1"
        room.disconnect("a2", 3.0)  # dropped again: the seat is held under the new token
    elif case == "garbage":
        token = "not-a-token-at-all"
    elif case == "other_room":
        other = Room(RecordingWorld(), 20.0)
        token = join(other, "x", hello("A"), 0.0)["resume_token"]
    frame = (
        resume_hello("A", token)
        if case != "viewer_hello"
        else json.dumps(
            {"type": "hello", "protocol": 1, "role": "viewer", "name": "A", "resume": token}
        )
    )
    room.connect("n", 3.5)
    outs = room.receive("n", frame, 3.5)
    (welcome,) = texts(outs, "n")
    assert welcome["type"] == "welcome" and not welcome["resumed"]
    assert welcome["user_id"] != "u1" and welcome["name"] == "A-2"  # A's name is held
    assert not any(o.close for o in outs)
    assert room.held_seats == ["u1"]  # A's seat is still there for A
    # the room goes on: B keeps getting patches and loading the object
    room.receive("b", state(2, z=0.098, force=0.6), 3.6)
    outs = room.tick(80, 4.0)
    assert texts(outs, "b")[0]["type"] == "patch"
    assert room.world.inputs[-1]["b"].force[2] == pytest.approx(0.6)


def test_a_token_is_used_up_once_resumed(room_ab):
    room, welcomes = room_ab
    token = welcomes["a"]["resume_token"]
    room.disconnect("a", 1.0)
    assert join(room, "a2", resume_hello("A", token), 2.0)["resumed"]
    again = join(room, "a3", resume_hello("A", token), 2.5)  # a copy of the old token
    assert not again["resumed"] and again["user_id"] != "u1"
    assert sorted(room.users) == ["a2", "a3", "b"]  # a2 keeps its seat


def test_bye_drops_the_seat_at_once(room_ab):
    room, welcomes = room_ab
    outs = room.receive("a", '{"type":"bye"}', 1.0)
    assert outs[0].close and outs[0].close_code == 1000
    room.disconnect("a", 1.0)  # the socket closes after the bye
    assert room.held_seats == [] and room.users == ["b"]
    room.tick(2, 1.05)
    assert set(room.world.inputs[-1]) == {"b"}
    back = join(room, "a2", resume_hello("A", welcomes["a"]["resume_token"]), 2.0)
    assert not back["resumed"] and back["user_id"] != "u1"


def test_a_held_seat_counts_against_the_user_cap():
    room = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_users=2))
    a = join(room, "a", hello("A"), 0.0)
    join(room, "b", hello("B"), 0.0)
    room.disconnect("a", 1.0)
    room.connect("c", 2.0)
    (err,) = texts(room.receive("c", hello("C"), 2.0), "c")
    assert err["code"] == "room_full" and err["fatal"]
    back = join(room, "a2", resume_hello("A", a["resume_token"]), 3.0)
    assert back["resumed"] and back["user_id"] == a["user_id"]


def test_a_seat_whose_link_died_unseen_is_taken_over_by_its_token(room_ab):
    """A network cut: the server still holds A's old connection when A comes back."""
    room, welcomes = room_ab
    a = welcomes["a"]
    room.connect("a2", 5.0)
    outs = room.receive("a2", resume_hello("A", a["resume_token"]), 5.0)
    (old,) = texts(outs, "a")
    assert old["code"] == "seat_resumed" and old["fatal"]
    assert any(o.conn_id == "a" and o.close for o in outs)
    (back,) = texts(outs, "a2")
    assert back["resumed"] and back["user_id"] == "u1" and back["name"] == "A"
    room.disconnect("a", 5.1)  # the old socket closes at last: nothing is held for it
    assert room.held_seats == [] and sorted(room.users) == ["a2", "b"]
    room.receive("a2", state(0, force=0.8), 5.2)
    outs = room.tick(110, 5.5)
    assert viewer_users(outs) == [("u1", "A"), ("u2", "B")]
    assert room.world.inputs[-1]["a"].force[2] == pytest.approx(0.8)


def test_a_token_bound_to_another_name_cannot_take_the_seat():
    alice, bob = "alice-access-token-0001", "bob-access-token-000001"
    table = TokenTable({alice: ("user", "alice"), bob: ("user", "bob")})
    room = Room(RecordingWorld(), 20.0, auth=table)
    a = join(room, "a", resume_hello("x", None, alice), 0.0)
    room.disconnect("a", 1.0)
    other = join(room, "b", resume_hello("x", a["resume_token"], bob), 2.0)
    assert not other["resumed"] and other["name"] == "bob" and other["user_id"] != a["user_id"]
    own = join(room, "a2", resume_hello("x", a["resume_token"], alice), 3.0)
    assert own["resumed"] and own["user_id"] == a["user_id"] and own["name"] == "alice"


def test_viewers_get_no_resume_token_and_are_not_held(room_ab):
    room, _ = room_ab
    join_v = join(room, "v2", hello("watcher", "viewer"), 0.5)
    assert join_v["resume_token"] is None
    room.disconnect("v2", 1.0)
    assert room.held_seats == []


def test_no_hold_when_the_room_holds_none():
    room = Room(RecordingWorld(), 20.0, resume_hold_s=0.0)
    a = join(room, "a", hello("A"), 0.0)
    room.disconnect("a", 1.0)
    assert room.held_seats == []
    assert not join(room, "a2", resume_hello("A", a["resume_token"]), 1.5)["resumed"]


def test_is_bye_reads_only_bye():
    assert is_bye('{"type":"bye"}') and is_bye('{ "type" : "bye" }')
    assert not is_bye('{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0]}')
    assert not is_bye('{"type":"hello","name":"bye"}') and not is_bye(b'{"type":"bye"}')
    assert not is_bye('"bye"') and not is_bye('{"type":"bye"')
