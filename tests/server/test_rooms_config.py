"""``[rooms.NAME]`` and ``[room_templates.NAME]`` in a server configuration file, and the rooms
``haptic server`` builds from them."""

from __future__ import annotations

import argparse
import asyncio
import json
import urllib.request
from pathlib import Path

import pytest

from haptic_collab.cli import build_parser
from haptic_collab.cli.run import _server_options
from haptic_collab.server.config import ConfigError, apply_server_config, load_server_config
from haptic_collab.server.main import (
    RoomTemplates,
    ServerOptions,
    build_link,
    build_room,
    run_server,
)
from haptic_collab.server.security import MIN_SECRET_BYTES, RoomTokens

ROOMS = """\
sim_rate = 20.0
subdivisions = 1

[rooms.lab]
sim_rate = 25.0
max_users = 2
mesh = "part.stl"

[room_templates.any]
max_viewers = 3

[room_templates.class]
prefix = "class-"
subdivisions = 2
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "server.toml"
    path.write_text(text)
    return path


def test_rooms_and_templates_load_with_their_keys_and_paths(tmp_path: Path) -> None:
    config = load_server_config(write(tmp_path, ROOMS))
    assert config["rooms"] == {
        "lab": {"sim_rate": 25.0, "max_users": 2, "mesh": str(tmp_path / "part.stl")}
    }
    assert config["room_templates"] == {
        "any": {"max_viewers": 3},
        "class": {"prefix": "class-", "subdivisions": 2},
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[rooms."Lab!"]\nsim_rate = 20.0\n', "a name is 1-32 of a-z"),
        ("[rooms.lab]\nport = 1\n", "unknown key 'rooms.lab.port'"),
        ("[rooms.lab]\nsim_rte = 20.0\n", "did you mean 'sim_rate'"),
        ("[rooms.lab]\nmax_users = 0\n", "rooms.lab.max_users must be >= 1"),
        ('[rooms.lab]\nobject = "jelly"\n', "rooms.lab.object must be one of"),
        ("rooms = 3\n", "must be tables [rooms.NAME]"),
        ('[room_templates.a]\nprefix = "x"\n[room_templates.b]\nprefix = "x"\n', "same prefix"),
        ("max_rooms = 0\n", "max_rooms must be >= 1"),
    ],
)
def test_a_bad_room_table_is_refused_naming_it(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace(".", r"\.")):
        load_server_config(write(tmp_path, text))


def test_the_file_reaches_the_server_options_and_flags_still_win(tmp_path: Path) -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    path = write(tmp_path, "max_rooms = 5\n" + ROOMS)
    apply_server_config(sub.choices["server"], path)
    opts = _server_options(parser.parse_args(["server", "--config", str(path), "--max-rooms", "9"]))
    assert set(opts.rooms) == {"lab"} and set(opts.room_templates) == {"any", "class"}
    assert opts.max_rooms == 9
    plain = _server_options(build_parser().parse_args(["server"]))
    assert plain.rooms == {} and plain.room_templates == {} and plain.max_rooms == 16


def test_a_room_is_the_top_level_options_with_its_keys_on_top() -> None:
    opts = ServerOptions(sim_rate_hz=20.0, subdivisions=1)
    secret = b"z" * MIN_SECRET_BYTES
    room = build_room(
        opts, "lab", {"sim_rate": 25.0, "max_users": 2}, build_link(opts), None, secret
    )
    assert room.sim_rate_hz == 25.0 and room.limits.max_users == 2
    assert room.limits.max_viewers == 64 and len(room.world.vertices) == 42
    assert isinstance(room.auth, RoomTokens) and room.auth.room == "lab"
    plain = build_room(opts, "lab", {}, build_link(opts), None, None)
    assert plain.sim_rate_hz == 20.0 and plain.auth is None


def test_max_users_caps_every_room_that_does_not_set_its_own(tmp_path: Path) -> None:
    """``--max-users`` (``max_users`` at the top of the file): each room's cap of users unless
    its table sets one, the default room's too, so a server admits at most max_rooms x it."""
    config = tmp_path / "rooms.toml"
    config.write_text("max_users = 8\nmax_rooms = 4\n[room_templates.any]\n")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    apply_server_config(sub.choices["server"], config)
    opts = _server_options(parser.parse_args(["server", "--subdivisions", "1"]))
    assert opts.max_users == 8
    link = build_link(opts)
    assert build_room(opts, "default", {}, link, None, None).limits.max_users == 8
    made = RoomTemplates(opts, opts.room_templates, link, None, None).build("anatomy")
    assert made.limits.max_users == 8
    assert build_room(opts, "lab", {"max_users": 2}, link, None, None).limits.max_users == 2
    flag = _server_options(parser.parse_args(["server", "--max-users", "3"]))
    assert flag.max_users == 3  # the flag beats the file


def test_the_longest_matching_template_prefix_builds_a_room() -> None:
    opts = ServerOptions(sim_rate_hz=20.0, subdivisions=1)
    templates = RoomTemplates(
        opts,
        {"any": {"max_viewers": 3}, "class": {"prefix": "class-", "subdivisions": 2}},
        build_link(opts),
        None,
        None,
    )
    assert templates.template("class-1") == "class" and templates.template("x") == "any"
    assert not templates.allows("Bad!")
    assert len(templates.build("class-1").world.vertices) == 162  # subdivisions 2
    assert templates.build("x").limits.max_viewers == 3
    only = RoomTemplates(opts, {"class": {"prefix": "class-"}}, build_link(opts), None, None)
    assert only.allows("class-2") and not only.allows("lab")


def test_haptic_server_refuses_a_room_named_default_or_more_rooms_than_allowed() -> None:
    with pytest.raises(ValueError, match=r"\[rooms.default\]"):
        asyncio.run(run_server(ServerOptions(port=0, rooms={"default": {}})))
    with pytest.raises(ValueError, match="max_rooms is 1"):
        asyncio.run(run_server(ServerOptions(port=0, rooms={"lab": {}}, max_rooms=1)))
    with pytest.raises(ValueError, match=r"\[room_templates.t\]: --sim-rate"):
        asyncio.run(run_server(ServerOptions(port=0, room_templates={"t": {"sim_rate": 33.0}})))


async def test_haptic_server_serves_its_configured_rooms() -> None:
    opts = ServerOptions(port=0, subdivisions=1, rooms={"lab": {"sim_rate": 25.0}}, duration_s=30)
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(run_server(opts, on_ready=ready.set_result))
    try:
        port = await asyncio.wait_for(asyncio.shield(ready), 60.0)

        def status() -> dict[str, object]:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as res:
                return json.loads(res.read())  # type: ignore[no-any-return]

        rooms = (await asyncio.to_thread(status))["rooms"]
        assert isinstance(rooms, dict) and set(rooms) == {"default", "lab"}
        assert rooms["lab"]["sim_rate_hz"] == 25.0 and rooms["default"]["sim_rate_hz"] == 20.0
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
