"""Room names, room paths and room tokens (signed, expiring, one room and one role)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from haptic_collab.server.security import (
    MIN_SECRET_BYTES,
    RoomTokens,
    TokenTable,
    check_room_token,
    load_secret,
    make_room_token,
)
from haptic_collab.server.urls import (
    DEFAULT_ROOM,
    RoomPath,
    room_page_path,
    room_path,
    room_ws_path,
    valid_room_name,
)

SECRET = b"s" * MIN_SECRET_BYTES
T0 = 1_700_000_000.0


@pytest.mark.parametrize("name", ["a", "lab", "lab-2", "x" * 32, "0", "room-a-b"])
def test_a_short_slug_is_a_room_name(name: str) -> None:
    assert valid_room_name(name)


@pytest.mark.parametrize(
    "name", ["", "Lab", "-lab", "lab-", "x" * 33, "a.b", "a/b", "..", "a b", "é", "a_b"]
)
def test_anything_else_is_not_a_room_name(name: str) -> None:
    assert not valid_room_name(name)


def test_the_paths_of_the_default_room_and_of_a_named_room() -> None:
    assert room_path("/ws") == RoomPath(DEFAULT_ROOM, "ws")
    assert room_path("/ws?x=1") == RoomPath(DEFAULT_ROOM, "ws")
    assert room_path("/rooms/lab/ws") == RoomPath("lab", "ws")
    assert room_path("/rooms/lab/") == RoomPath("lab", "")
    assert room_path("/rooms/lab") == RoomPath("lab", None)
    assert room_path("/rooms/Bad!/ws") == RoomPath("Bad!", "ws")  # checked by the caller
    assert room_path("/status") is None and room_path("/") is None
    assert room_ws_path(DEFAULT_ROOM) == "/ws" and room_page_path(DEFAULT_ROOM) == "/"
    assert room_ws_path("lab") == "/rooms/lab/ws" and room_page_path("lab") == "/rooms/lab/"


def test_a_room_token_admits_to_its_room_in_its_role_until_it_expires() -> None:
    token = make_room_token(SECRET, "a", "viewer", T0 + 60.0)
    entry = check_room_token(token, SECRET, "a", T0)
    assert entry is not None and entry.role == "viewer"
    assert check_room_token(token, SECRET, "b", T0) is None  # another room
    assert check_room_token(token, SECRET, "a", T0 + 60.0) is None  # expired
    assert check_room_token(token, b"t" * MIN_SECRET_BYTES, "a", T0) is None  # another secret


def test_a_room_token_cannot_be_edited_into_another_room_role_or_expiry() -> None:
    token = make_room_token(SECRET, "a", "viewer", T0 + 60.0)
    prefix, room, role, exp, mac = token.split(".")
    for forged in (
        f"{prefix}.b.{role}.{exp}.{mac}",
        f"{prefix}.{room}.user.{exp}.{mac}",
        f"{prefix}.{room}.{role}.{int(exp) + 3600}.{mac}",
        f"{prefix}.{room}.{role}.{exp}.{'0' * 64}",
        token[:-1],
    ):
        assert check_room_token(forged, SECRET, "b", T0) is None
        assert check_room_token(forged, SECRET, "a", T0) is None


def test_making_a_token_refuses_a_bad_room_role_expiry_or_short_secret() -> None:
    with pytest.raises(ValueError, match="room name"):
        make_room_token(SECRET, "Bad", "user", T0)
    with pytest.raises(ValueError, match="role"):
        make_room_token(SECRET, "a", "admin", T0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="expiry"):
        make_room_token(SECRET, "a", "user", float("nan"))
    with pytest.raises(ValueError, match="at least"):
        make_room_token(b"short", "a", "user", T0)


def test_a_rooms_tokens_are_the_servers_tokens_and_its_own_room_tokens() -> None:
    now = [T0]
    table = TokenTable({"w" * 20: ("user", "alice")})
    tokens_a = RoomTokens("a", table, SECRET, lambda: now[0])
    user_a = make_room_token(SECRET, "a", "user", T0 + 10.0)
    user_b = make_room_token(SECRET, "b", "user", T0 + 10.0)
    server_wide = tokens_a.check("w" * 20)
    assert server_wide is not None and server_wide.name == "alice"  # valid in every room
    assert tokens_a.bound_names == {"alice"}
    assert tokens_a.check(user_a) is not None and tokens_a.check(user_b) is None
    assert tokens_a.check(None) is None and tokens_a.check("x" * 20) is None
    now[0] = T0 + 10.0
    assert tokens_a.check(user_a) is None  # expired by the room's clock
    only_secret = RoomTokens("b", None, SECRET, lambda: T0)
    assert only_secret.check(user_b) is not None and only_secret.check("w" * 20) is None


def test_a_secret_file_must_hold_enough_bytes(tmp_path: Path) -> None:
    short = tmp_path / "short"
    short.write_text("abc\n")
    with pytest.raises(ValueError, match=f"at least {MIN_SECRET_BYTES} bytes") as err:
        load_secret(short)
    assert "abc" not in str(err.value)
    with pytest.raises(ValueError, match="cannot read"):
        load_secret(tmp_path / "missing")
    good = tmp_path / "good"
    good.write_text("k" * 40 + "\n")
    assert load_secret(good) == b"k" * 40


def test_haptic_token_prints_a_token_for_that_room_role_and_lifetime(tmp_path: Path) -> None:
    secret = tmp_path / "secret"
    secret.write_text("q" * 48 + "\n")
    before = time.time()
    out = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "token", "--room", "lab", "--role", "viewer"]
        + ["--ttl", "600", "--secret-file", str(secret)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    token = out.stdout.strip()
    key = b"q" * 48
    entry = check_room_token(token, key, "lab", before + 1.0)
    assert entry is not None and entry.role == "viewer"
    assert check_room_token(token, key, "lab", time.time() + 601.0) is None
    assert check_room_token(token, key, "other", before + 1.0) is None
    bad = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "token", "--room", "Lab!"]
        + ["--secret-file", str(secret)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "room name" in bad.stderr and "q" * 48 not in bad.stderr
