"""Security without sockets: tokens and roles, origins, per-address budgets, the force bound.

The room is driven with a small recording world (see test_room.py) so the tests can see exactly
which force reached the simulation; the real server is attacked in test_security_loopback.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.force_bound import ForceBoundParams, bound_force
from haptic_collab.server.main import ServerOptions, build_auth
from haptic_collab.server.room import Room
from haptic_collab.server.security import TokenBucket, TokenTable, is_loopback, origin_allowed
from haptic_collab.shared.primitives import make_plane, make_sphere
from tests.support.rooms import RecordingWorld, prime, state, texts

ALICE = "alice-token-0123456789"
VIEW = "viewer-token-0123456789"
FREE = "free-user-token-0123456789"
TOKENS = f"""
# token               role    bound name
{ALICE}  user    alice
{VIEW}   viewer
{FREE}   user
"""


def hello(name: str, role: str = "user", token: str | None = None) -> str:
    msg = {"type": "hello", "protocol": 1, "role": role, "name": name}
    if token is not None:
        msg["token"] = token
    return json.dumps(msg)


def join(room: Room, conn: str, frame: str, now_s: float = 0.0, address: str = "10.0.0.1"):
    out = room.connect(conn, now_s, address)
    return out + room.receive(conn, frame, now_s)


# ----------------------------------------------------------------------------- tokens and roles
def test_token_file_format_and_its_errors_never_show_a_token():
    table = TokenTable.parse(TOKENS)
    assert len(table) == 3 and table.bound_names == {"alice"}
    assert table.check(ALICE).role == "user" and table.check(ALICE).name == "alice"
    assert table.check(VIEW).role == "viewer" and table.check(VIEW).name is None
    assert table.check(ALICE[:-1]) is None and table.check(None) is None
    assert table.check(ALICE + "x") is None
    assert "alice-token" not in repr(table.check(ALICE))
    for bad in (
        f"{ALICE} admin",  # unknown role
        f"{ALICE}",  # no role
        "short user",  # too short a token
        f"{ALICE} user a b",  # too many fields
        f"{ALICE} user a\n{FREE} user a",  # one name bound to two tokens
        f"{ALICE} user\n{ALICE} viewer",  # the same token twice
        "# only comments\n",
    ):
        with pytest.raises(ValueError) as info:
            TokenTable.parse(bad)
        assert ALICE not in str(info.value) and FREE not in str(info.value)


def test_missing_or_wrong_token_is_unauthorized_and_nothing_else_changes():
    room = Room(RecordingWorld(), 20.0, auth=TokenTable.parse(TOKENS))
    for conn, frame in (
        ("x", hello("X")),
        ("y", hello("Y", token="wrong-token-0123456789")),
        ("z", hello("Z", role="user", token=VIEW)),  # a viewer token may not push
    ):
        (err,) = texts(join(room, conn, frame), conn)
        assert err["code"] == "unauthorized" and err["fatal"]
        assert "0123456789" not in err["message"]  # the token is never echoed
    assert room.users == [] and room.viewers == []
    (w,) = texts(join(room, "v", hello("V", role="viewer", token=VIEW)), "v")
    assert w["type"] == "welcome" and w["role"] == "viewer"
    # a user token may also watch
    (w,) = texts(join(room, "w", hello("W", role="viewer", token=FREE)), "w")
    assert w["type"] == "welcome"


def test_bound_names_belong_to_their_token_even_after_it_leaves():
    room = Room(RecordingWorld(), 20.0, auth=TokenTable.parse(TOKENS))
    (w,) = texts(join(room, "a", hello("whatever", token=ALICE)), "a")
    assert w["name"] == "alice"  # the file binds the name
    (w,) = texts(join(room, "f", hello("alice", token=FREE)), "f")
    assert w["name"] == "alice-2"  # another token cannot take it
    room.receive("a", '{"type":"bye"}', 1.0)
    (w,) = texts(join(room, "g", hello("alice", token=FREE), 2.0), "g")
    assert w["name"] == "alice-3"  # nor take it after alice left
    (w,) = texts(join(room, "a2", hello("x", token=ALICE), 3.0), "a2")
    assert w["name"] == "alice"  # alice gets it back


def test_without_tokens_the_room_admits_everyone_and_ignores_a_token():
    room = Room(RecordingWorld(), 20.0)
    (w,) = texts(join(room, "a", hello("A", token="anything-at-all-here")), "a")
    assert w["type"] == "welcome"


def test_off_loopback_needs_tokens_unless_insecure(tmp_path):
    assert build_auth(ServerOptions(host="127.0.0.1")) is None
    assert build_auth(ServerOptions(host="::1")) is None
    with pytest.raises(ValueError, match="refusing to listen on 0.0.0.0 without tokens"):
        build_auth(ServerOptions(host="0.0.0.0"))
    assert build_auth(ServerOptions(host="0.0.0.0", insecure=True)) is None
    assert len(build_auth(ServerOptions(host="0.0.0.0", token=FREE))) == 1
    f = tmp_path / "tokens.txt"
    f.write_text(TOKENS)
    assert len(build_auth(ServerOptions(host="192.168.1.5", token_file=str(f)))) == 3
    with pytest.raises(ValueError, match="not both"):
        build_auth(ServerOptions(token=FREE, token_file=str(f)))
    with pytest.raises(ValueError, match="cannot read token file"):
        build_auth(ServerOptions(token_file=str(tmp_path / "missing")))


def test_loopback_names():
    assert is_loopback("127.0.0.1") and is_loopback("127.3.2.1") and is_loopback("localhost")
    assert is_loopback("[::1]")
    assert not is_loopback("0.0.0.0") and not is_loopback("10.1.2.3") and not is_loopback("::")


# ----------------------------------------------------------------------------- origins
@pytest.mark.parametrize(
    "origin,host,allowed,loopback,ok",
    [
        (None, "localhost:8765", (), True, True),  # not a browser
        ("http://localhost:8765", "localhost:8765", (), True, True),  # the server's own page
        ("http://127.0.0.1:8765", "127.0.0.1:8765", (), True, True),
        ("http://evil.example", "127.0.0.1:8765", (), True, False),  # another site
        ("http://127.0.0.1:9999", "127.0.0.1:8765", (), True, False),  # another port
        ("https://localhost:8765", "localhost:8765", (), True, True),
        ("http://evil.example:8765", "evil.example:8765", (), True, False),  # DNS rebinding
        (
            "http://lab.example:8765",
            "lab.example:8765",
            (),
            False,
            True,
        ),  # own origin, off loopback
        ("https://lab.example", "lab.example", (), False, True),  # default port
        ("https://other.example", "lab.example", ("https://other.example",), False, True),
        ("https://other.example", "lab.example", ("*",), False, True),
        ("null", "lab.example", (), False, False),
        ("file://", "lab.example", (), False, False),
    ],
)
def test_origin_allow_list(origin, host, allowed, loopback, ok):
    assert origin_allowed(origin, host, frozenset(allowed), loopback) is ok


# ----------------------------------------------------------------------------- denial of service
def test_idle_sockets_from_one_address_cannot_lock_out_another():
    room = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_pending=32))
    refused = 0
    for i in range(60):  # 60 sockets from one address that never say hello
        out = room.connect(f"idle{i}", 0.01 * i, "10.6.6.6")
        refused += any(o.close for o in out)
    assert refused == 60 - RoomLimits().max_pending_per_address
    (err,) = texts(room.connect("idle-x", 0.7, "10.6.6.6"), "idle-x")
    assert err["code"] == "too_many_pending"  # named for what it is, not room_full
    (w,) = texts(join(room, "good", hello("G"), 0.7, address="10.0.0.2"), "good")
    assert w["type"] == "welcome"


def test_many_addresses_cannot_fill_the_pending_total_against_a_newcomer():
    room = Room(RecordingWorld(), 20.0, limits=RoomLimits(max_pending=8, max_pending_per_address=4))
    for i in range(8):  # the total is full: 4 from each of two addresses
        assert room.connect(f"p{i}", 0.0, f"10.6.6.{i % 2}") == []
    out = room.connect("new", 0.1, "10.0.0.9")
    evicted = [json.loads(o.data)["code"] for o in out if o.close]
    assert evicted == ["too_many_pending"] and out[0].conn_id in ("p0", "p1")  # the oldest
    (w,) = texts(room.receive("new", hello("N"), 0.1), "new")
    assert w["type"] == "welcome"


def test_rate_budget_per_address_closes_the_heaviest_and_spares_a_light_user():
    limits = RoomLimits(address_rate_per_s=200.0, address_burst=200.0)
    room = Room(RecordingWorld(), 20.0, limits=limits)
    conns = [f"f{i}" for i in range(6)] + ["good"]
    for c in conns:
        join(room, c, hello(c), 0.0, address="10.9.9.9")  # all behind one address
    prime(room, conns)
    closed: dict[str, str] = {}
    t, seq = 0.0, 1
    for _step in range(100):  # 1 s: each flooder at 100 frames/s (below its own 400/s)
        t += 0.01
        seq += 1
        for c in conns[:-1]:
            for o in room.receive(c, '{"type":"ping","id":1,"t_client_s":0}', t):
                if o.close:
                    closed[o.conn_id] = json.loads(o.data)["code"]
        if _step % 4 == 0:  # the good user: 25 states/s
            for o in room.receive("good", state(seq, force=0.5), t):
                if o.close:  # the good user's frame may find the budget spent: a flooder goes
                    closed[o.conn_id] = json.loads(o.data)["code"]
    assert "good" not in closed and closed and set(closed.values()) == {"rate_limited"}
    assert "good" in room.users


def test_byte_budget_per_connection_counts_bytes():
    room = Room(RecordingWorld(), 20.0, limits=RoomLimits(bytes_per_s=10_000, bytes_burst=20_000))
    join(room, "a", hello("A"))
    pad = "\u00e9" * 7000  # 7000 characters, 14000 bytes
    frame = '{"type":"ping","id":1,"t_client_s":0,"pad":"' + pad + '"}'
    assert not any(o.close for o in room.receive("a", frame, 0.0))
    (err,) = texts(room.receive("a", frame, 0.01), "a")
    assert err["code"] == "rate_limited" and err["fatal"]


def test_frame_limit_is_in_bytes_not_characters():
    room = Room(RecordingWorld(), 20.0)
    join(room, "a", hello("A"))
    join(room, "b", hello("B"))
    frame = '{"type":"ping","id":1,"t_client_s":0,"pad":"' + "\u00e9" * 6000 + '"}'  # 12 KB
    big = '{"type":"ping","id":1,"t_client_s":0,"pad":"' + "\u00e9" * 9000 + '"}'
    assert len(big) < 16 * 1024 < len(big.encode())  # under in characters, over in bytes
    (err,) = texts(room.receive("b", big, 0.0), "b")
    assert err["code"] == "frame_too_large" and err["fatal"]
    assert not any(o.close for o in room.receive("a", frame, 0.0))


def test_bye_closes_the_socket_normally():
    room = Room(RecordingWorld(), 20.0)
    join(room, "a", hello("A"))
    (out,) = room.receive("a", '{"type":"bye"}', 0.1)
    assert out.close and out.close_code == 1000 and out.data is None
    assert room.users == []


def test_token_bucket():
    b = TokenBucket(10.0, 5.0, 0.0)
    assert all(b.take(1.0, 0.0) for _ in range(5)) and not b.take(1.0, 0.0)
    assert b.take(1.0, 0.1) and not b.take(1.0, 0.1)
    assert b.refill(100.0) == 5.0


# ----------------------------------------------------------------------------- the force bound
PLANE = make_plane((0, 0, 0.1), (0, 0, 1))  # the top of an object, outward +z


def test_force_out_of_contact_is_clamped_to_zero():
    r = bound_force(
        (0, 0, 49.0), (0, 0, 0.12), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9
    )
    assert r.reason == "out_of_contact" and r.force_n == (0.0, 0.0, 0.0)
    # and a 49 N push at zero penetration is bounded by the model at e = 0 (+ tolerance)
    r = bound_force(
        (0, 0, 49.0), (0, 0, 0.1), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9
    )
    assert r.reason == "too_large" and r.force_n[2] == pytest.approx(300 * 0.001)


def test_force_into_the_object_or_sideways_is_refused():
    r = bound_force(
        (0, 0, -3.0), (0, 0, 0.09), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9
    )
    assert r.reason == "wrong_direction" and r.force_n == (0.0, 0.0, 0.0)
    r = bound_force(
        (3.0, 0, 0.5), (0, 0, 0.09), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9
    )
    assert r.reason == "wrong_direction" and r.force_n == (0.0, 0.0, pytest.approx(0.5))


def test_an_honest_force_passes_unchanged():
    # P: K_h * e; PI: plus the integral up to its anti-windup bound; sphere: radial
    r = bound_force(
        (0, 0, 3.0), (0, 0, 0.09), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9
    )
    assert r.reason is None and r.force_n == (0.0, 0.0, 3.0)
    # PI held 10 mm deep for a second, sampled at 20 Hz: the integral (threshold 1 mm) winds up
    # to its anti-windup bound and the server's bound follows it
    s_true, s_max = 0.0, 0.0
    for _ in range(20):
        s_true = min(7.9, s_true + 4000 * 0.05 * (0.010 - 0.001))
        r = bound_force((0, 0, 300 * 0.01 + s_true), (0, 0, 0.09), [(PLANE, 400.0, 0.0)], k_h=300,
                        i_gain=4000, integral_limit_n=7.9, integral_bound_n=s_max, dt_s=0.05)  # fmt: skip
        assert r.reason is None, (s_true, r)
        s_max = r.integral_bound_n
    assert s_true == 7.9
    sphere = make_sphere((0, 0, 0), 0.1)
    n = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    probe, force = 0.095 * n, 1.4 * n
    r = bound_force(force, probe, [(sphere, 400.0, 0.0)], k_h=300, i_gain=0, integral_limit_n=7.9)
    assert r.reason is None


def test_latency_tolerance_and_integral_release():
    moved = make_plane((0, 0, 0.09), (0, 0, 1))  # the surface moved down 10 mm since
    # rendered against the previous patch: still within the last patches' geometry
    r = bound_force((0, 0, 2.0), (0, 0, 0.095), [(PLANE, 400.0, 0.0), (moved, 400.0, 0.0)], k_h=300,
                    i_gain=0, integral_limit_n=7.9)  # fmt: skip
    assert r.reason is None
    # the integral is ramped down after release, not dropped: a report 0.05 s later passes...
    r = bound_force((0, 0, 5.0), (0, 0, 0.2), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=4000,
                    integral_limit_n=7.9, integral_bound_n=7.9, dt_s=0.05)  # fmt: skip
    assert r.reason is None
    # ...but not forever
    r = bound_force((0, 0, 5.0), (0, 0, 0.2), [(PLANE, 400.0, 0.0)], k_h=300, i_gain=4000,
                    integral_limit_n=7.9, integral_bound_n=7.9, dt_s=0.2)  # fmt: skip
    assert r.reason == "out_of_contact"


def test_a_claimed_integral_cannot_push_at_the_surface():
    # a client claiming a PI model with a huge I and a 100 N device, at zero penetration: an
    # integral does not grow at the surface, and K_h is believed up to c_K K_o
    s_max = 0.0
    for _ in range(40):  # 2 s of 49 N reports
        r = bound_force((0, 0, 49.0), (0, 0, 0.1), [(PLANE, 400.0, 0.0)], k_h=1e6, i_gain=1e8,
                        integral_limit_n=50.0, integral_bound_n=s_max, dt_s=0.05)  # fmt: skip
        s_max = r.integral_bound_n
    assert r.reason == "too_large"
    p = ForceBoundParams()
    assert r.limit_n == pytest.approx(p.stiffness_factor * 400 * p.penetration_tol_m)  # 0.8 N
    assert r.force_n[2] == pytest.approx(0.8)


def test_a_claimed_huge_k_h_is_believed_only_up_to_the_object_stiffness():
    r = bound_force((0, 0, 20.0), (0, 0, 0.095), [(PLANE, 400.0, 0.0)], k_h=1e6, i_gain=0,
                    integral_limit_n=7.9)  # fmt: skip
    assert r.reason == "too_large"
    assert r.limit_n == pytest.approx(ForceBoundParams().stiffness_factor * 400.0 * 0.006)


def test_room_clamps_counts_and_reports_rate_limited_and_the_other_user_is_unaffected():
    room = Room(RecordingWorld(), 20.0)
    for c in ("a", "b"):
        join(room, c, hello(c.upper()))
    prime(room, ("a", "b"))
    errors = []
    for k in range(1, 41):  # 2 s: A pushes 49 N out of contact every tick, B rests honestly
        t = 0.05 * k
        room.receive("a", state(k, z=0.12, force=49.0), t)
        room.receive("b", state(k, z=0.097, force=1.0), t)
        out = room.tick(k, t)
        errors += [m for m in texts(out, "a") if m["type"] == "error"]
        assert not any(m["type"] == "error" for m in texts(out, "b"))
        inputs = room.world.inputs[-1]
        assert np.allclose(inputs["a"].force, 0.0)  # the push never reaches the object
        assert inputs["b"].force[2] == pytest.approx(1.0)  # the honest user's does
    assert room.clamp_counts == {"A": 40}
    assert [e["code"] for e in errors] == ["force_clamped"] * len(errors)
    assert 2 <= len(errors) <= 3 and not any(e["fatal"] for e in errors)  # about once a second
    assert "A" in [u.name for u in room.room_state(41).users]  # still connected
    shown = {u.name: u.force_n for u in room.room_state(41).users}
    assert shown["A"] == (0.0, 0.0, 0.0)  # viewers see the force applied, not the claim
