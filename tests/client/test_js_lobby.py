"""The Node.js client (client/js) finds its room through ``haptic lobby``: ``--lobby URL --room
NAME``, as the Python client does (tests/client/test_lobby_drain.py).

Two real room servers (rooms of any name made on demand, room tokens checked with the secret
they share with the lobby) and a real lobby run in this process on loopback; the client is
``node client/js/haptic-client.mjs``, a process of its own. What a user sees:

- it joins the room the lobby names, with the lobby's room token (the servers accept no
  other), and the room's patches reach its servo;
- when that server drains (what SIGTERM runs), it asks the lobby again and joins the room on the
  server that runs it now, without restarting;
- a lobby that refuses (a bad room name, a missing lobby token) ends it with the lobby's reason;
  the lobby token from ``$HAPTIC_LOBBY_TOKEN`` is sent.

Skipped only when ``node`` is not on PATH.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.server.app import ServerApp
from haptic_collab.server.lobby import Lobby, LocalServers, RoomServer
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.server.security import MIN_SECRET_BYTES, RoomTokens, TokenTable

ROOT = Path(__file__).resolve().parents[2]
JS_DIR = ROOT / "client" / "js"
CLIENT = JS_DIR / "haptic-client.mjs"
NODE = shutil.which("node")
SECRET = b"j" * MIN_SECRET_BYTES
SIM_RATE = 20.0
LOBBY_TOKEN = "js-lobby-user-token-0123456789"

pytestmark = pytest.mark.skipif(
    NODE is None, reason="node is not on PATH: the JS reference client needs it"
)


def room(name: str) -> Room:
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1))
    return Room(world, SIM_RATE, auth=RoomTokens(name, None, SECRET, time.time))


class AnyName:
    """Rooms of any name on demand (a server's ``[room_templates.any]`` of prefix "")."""

    def allows(self, name: str) -> bool:
        return True

    def build(self, name: str) -> Room:
        return room(name)


async def until(predicate: Callable[[], object], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.05)


@contextlib.asynccontextmanager
async def site(
    *max_rooms: int, auth: TokenTable | None = None
) -> AsyncIterator[tuple[list[ServerApp], str]]:
    """Room servers (each with ``max_rooms``) and a lobby in front of them; yields the lobby's
    URL."""
    apps = [
        ServerApp(room("default"), "127.0.0.1", 0, room_maker=AnyName(), max_rooms=n)
        for n in max_rooms
    ]
    for app in apps:
        await app.start()
    backend = LocalServers([RoomServer(f"http://127.0.0.1:{a.port}") for a in apps])
    lobby = Lobby(backend, SECRET, port=0, auth=auth)
    await lobby.start()
    try:
        yield apps, f"http://127.0.0.1:{lobby.port}"
    finally:
        await lobby.stop()
        for app in apps:
            await app.stop()


@contextlib.asynccontextmanager
async def js_user(
    tmp: Path, *args: str, env: dict[str, str] | None = None
) -> AsyncIterator[asyncio.subprocess.Process]:
    """``node haptic-client.mjs ARGS`` (quiet, resting on the top); killed if left running."""
    assert NODE is not None
    assert (JS_DIR / "node_modules" / "ws").is_dir(), "run `make js-install` (npm ci in client/js)"
    base = {k: v for k, v in os.environ.items() if k not in ("HAPTIC_TOKEN", "HAPTIC_LOBBY_TOKEN")}
    proc = await asyncio.create_subprocess_exec(
        NODE, str(CLIENT), "--name", "J", "--quiet", "--duration", "120",
        "--summary", str(tmp / "J.json"), *args,
        cwd=ROOT, env=base | (env or {}),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def ended(proc: asyncio.subprocess.Process) -> tuple[int, dict[str, Any], str]:
    """Wait for the client's exit: its code, summary and stderr."""
    out, err = await asyncio.wait_for(proc.communicate(), 60.0)
    assert proc.returncode is not None
    return proc.returncode, json.loads(out) if out.strip() else {}, err.decode(errors="replace")


def users_in(app: ServerApp, name: str) -> int:
    rooms = app.rooms()
    return len(rooms[name].users) if name in rooms else 0


async def test_the_js_client_joins_through_the_lobby_and_follows_its_room_after_a_drain(
    tmp_path: Path,
) -> None:
    async with (
        site(4, 3) as ((a, b), lobby_url),
        js_user(tmp_path, "--lobby", lobby_url, "--room", "lab") as proc,
    ):
        # the room is made where most slots are free, and the JS user is in it
        await until(lambda: users_in(a, "lab") == 1)
        assert "lab" not in b.rooms()
        report = await a.drain(grace_s=5.0)  # what SIGTERM runs
        assert report.told >= 1
        # it asked the lobby again, and joined room lab where it runs now
        await until(lambda: users_in(b, "lab") == 1)
        proc.send_signal(signal.SIGINT)
        code, summary, stderr = await ended(proc)
    assert code == 0, stderr
    assert summary["joins"] == 2 and summary["fatal_error"] is None
    lobby = summary["lobby"]
    assert lobby["room"] == "lab" and lobby["asks"] >= 2
    assert [j["url"] for j in lobby["joined"]] == [
        f"ws://127.0.0.1:{a.port}/rooms/lab/ws",
        f"ws://127.0.0.1:{b.port}/rooms/lab/ws",
    ]
    assert summary["url"] == f"ws://127.0.0.1:{b.port}/rooms/lab/ws"
    assert summary["patches"] > 0


async def test_a_lobby_that_refuses_ends_the_js_client_with_its_reason(tmp_path: Path) -> None:
    table = TokenTable({LOBBY_TOKEN: ("user", None)})
    async with site(2, auth=table) as ((a,), lobby_url):
        # no lobby token: 401, said on stderr, exit 1, nothing joined
        async with js_user(tmp_path, "--lobby", lobby_url, "--room", "lab") as proc:
            code, summary, stderr = await ended(proc)
        assert code == 1 and "refused room" in stderr and "(401)" in stderr
        assert summary["joins"] == 0 and summary["fatal_error"]["code"] == "lobby_refused"
        # a name no room may have: 400
        async with js_user(
            tmp_path, "--lobby", lobby_url, "--room", "Not-A-Room",
            env={"HAPTIC_LOBBY_TOKEN": LOBBY_TOKEN},
        ) as proc:  # fmt: skip
            code, summary, stderr = await ended(proc)
        assert code == 1 and "(400)" in stderr and summary["joins"] == 0
        assert "lab" not in a.rooms()
        # the lobby token from the environment: it joins
        async with js_user(
            tmp_path, "--lobby", lobby_url, "--room", "lab",
            env={"HAPTIC_LOBBY_TOKEN": LOBBY_TOKEN},
        ) as proc:  # fmt: skip
            await until(lambda: users_in(a, "lab") == 1)
            proc.send_signal(signal.SIGINT)
            code, summary, stderr = await ended(proc)
        assert code == 0 and summary["joins"] == 1, stderr


def test_lobby_options_that_do_not_fit_are_refused(tmp_path: Path) -> None:
    import subprocess

    assert NODE is not None
    for args, says in (
        (["--lobby", "http://127.0.0.1:1"], "go together"),
        (["--room", "lab"], "go together"),
        (["--lobby", "http://127.0.0.1:1", "--room", "lab", "--url", "ws://x/ws"], "not both"),
        (["--lobby", "ws://127.0.0.1:1", "--room", "lab"], "http(s)://HOST:PORT"),
    ):
        done = subprocess.run(
            [NODE, str(CLIENT), *args], capture_output=True, text=True, timeout=60, cwd=ROOT
        )
        assert done.returncode == 2 and says in done.stderr, (args, done.stderr)
