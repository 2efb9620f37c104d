"""No room without a token: what a stranger's handshakes cost a room server with tokens.

A server with a token secret and a template that makes rooms of any name (as the Agones
fleet's rooms-config.yaml and docs/usage.md run it), started by ``run_server`` in this process.
What an operator notices: handshakes and hellos without a token for the room leave the server
with its configured rooms only, nothing of them is kept once they are closed, and the lobby goes
on placing new names there; a client with the lobby's token gets its room.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from haptic_collab.cli import build_parser
from haptic_collab.cli.run import _lobby_backend
from haptic_collab.server.app import DEFAULT_ROOM
from haptic_collab.server.lobby import Lobby, LocalServers, RoomServer
from haptic_collab.server.main import ServerOptions, run_server
from haptic_collab.server.security import MIN_SECRET_BYTES, make_room_token
from tests.server.test_lobby import ask
from tests.support.rooms import hello

SECRET = b"r" * MIN_SECRET_BYTES
HANDSHAKES = 1000


@contextlib.asynccontextmanager
async def token_server(
    tmp_path: Path, max_rooms: int = 3, *, host: str = "127.0.0.1", metrics_token: str = ""
) -> AsyncIterator[int]:
    """``haptic server --token-secret-file F --max-rooms N`` with a template for any name (and
    ``--metrics-token-file`` holding ``metrics_token``, if given); its port."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    secret = tmp_path / "secret"
    secret.write_bytes(SECRET)
    metrics_file = tmp_path / "metrics-token"
    metrics_file.write_text(metrics_token + "\n")
    opts = ServerOptions(
        host=host,
        port=0,
        metrics_token_file=str(metrics_file) if metrics_token else None,
        sim_rate_hz=20.0,
        subdivisions=1,
        token_secret_file=str(secret),
        room_templates={"any": {"prefix": ""}},
        max_rooms=max_rooms,
        tick_priority="off",
    )
    started: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(run_server(opts, on_ready=started.set_result))
    await asyncio.wait({started, task}, return_when=asyncio.FIRST_COMPLETED)
    if task.done():
        task.result()
    try:
        yield started.result()
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def _status(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as r:
        return json.loads(r.read())  # type: ignore[no-any-return]


async def rooms_of(port: int) -> list[str]:
    """The rooms the server's ``/status`` lists (what the lobby reads)."""

    def get() -> list[str]:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as r:
            return sorted(json.loads(r.read())["rooms"])

    return await asyncio.to_thread(get)


def room_token(room: str, role: str = "user") -> str:
    return make_room_token(SECRET, room, role, time.time() + 600)  # type: ignore[arg-type]


async def first_answer(url: str, token: str | None, **kw: Any) -> dict[str, Any]:
    """The first frame after a hello with ``token`` (None: no token field)."""
    async with connect(url, **kw) as ws:
        msg = json.loads(hello("A"))
        if token is not None:
            msg["token"] = token
        await ws.send(json.dumps(msg))
        return json.loads(await asyncio.wait_for(ws.recv(), 10.0))


async def test_tokenless_handshakes_cost_no_room_and_the_lobby_still_places(tmp_path) -> None:
    async with token_server(tmp_path) as port:
        base = f"ws://127.0.0.1:{port}"
        # a handshake per name, closed without a word (what filled the servers before)
        for i in range(HANDSHAKES):
            async with connect(f"{base}/rooms/junk-{i}/ws"):
                pass
        # hellos without a token, with a token for another room, with a forged one
        wrong = [None, room_token("other"), room_token("junk-1")[:-4] + "0000"]
        for token in wrong:
            got = await first_answer(f"{base}/rooms/junk-1/ws", token)
            assert got["type"] == "error" and got["code"] == "unauthorized", got
        assert await rooms_of(port) == [DEFAULT_ROOM]
        status = await asyncio.to_thread(_status, port)
        assert status["roomless_refused"] == HANDSHAKES + len(wrong)

        # the lobby still finds a free slot here and places a new name; its token makes it
        lobby = Lobby(LocalServers([RoomServer(f"http://127.0.0.1:{port}")]), SECRET, port=0)
        await lobby.start()
        try:
            for name in ("anatomy-1", "anatomy-2"):
                status, answer = await ask(lobby, f"/rooms/{name}")
                assert status == 200, answer
                got = await first_answer(answer["url"], answer["token"])
                assert got["type"] == "welcome", got
        finally:
            await lobby.stop()
        assert await rooms_of(port) == sorted([DEFAULT_ROOM, "anatomy-1", "anatomy-2"])


async def test_a_bearer_token_for_the_room_makes_it_at_the_handshake(tmp_path) -> None:
    """What a lobby may send to have a room made before its user arrives."""
    async with token_server(tmp_path) as port:
        url = f"ws://127.0.0.1:{port}/rooms/lab/ws"
        headers = {"Authorization": f"Bearer {room_token('lab', 'viewer')}"}
        async with connect(url, additional_headers=headers):
            assert "lab" in await rooms_of(port)  # made before any hello
        try:
            async with connect(
                url.replace("/lab/", "/lab-2/"),
                additional_headers={"Authorization": f"Bearer {room_token('lab')}"},
            ):
                raise AssertionError("a token for room lab opened room lab-2")
        except InvalidStatus as exc:
            assert exc.response.status_code == 401
            assert b"not valid for room 'lab-2'" in exc.response.body
        assert "lab-2" not in await rooms_of(port)


async def test_a_silent_connection_is_closed_and_waiting_ones_are_bounded(tmp_path) -> None:
    """A connection that never says hello to a room not made yet is closed after the hello
    time; one address holds at most a few such connections at once."""
    async with token_server(tmp_path) as port:
        url = f"ws://127.0.0.1:{port}/rooms/quiet/ws"
        async with connect(url) as silent:
            got = json.loads(await asyncio.wait_for(silent.recv(), 30.0))
            assert got["code"] == "hello_timeout"
        opened = [await connect(url) for _ in range(12)]
        for ws in opened:  # each is closed by the server: at once, or after the hello time
            await asyncio.wait_for(ws.wait_closed(), 30.0)
        codes = sorted(ws.close_code for ws in opened)
        assert codes == [1008] * 8 + [1013] * 4  # 8 waited for a hello, 4 were one too many
        assert await rooms_of(port) == [DEFAULT_ROOM]


async def test_two_new_names_never_share_the_last_free_slot_of_a_server(tmp_path) -> None:
    """The lobby makes each new room with its user's token in the handshake: the room exists
    (and ``/status`` counts it) before the lobby answers, so a server with one free slot gets
    one new name and the next goes to the other server; both users are welcomed. (Before, the
    tokenless handshake made no room, both names went to the first server, and the second
    user got ``room_unavailable``.)"""
    async with (
        token_server(tmp_path / "a", max_rooms=2) as port_a,
        token_server(tmp_path / "b", max_rooms=2) as port_b,
    ):
        lobby = Lobby(
            LocalServers([RoomServer(f"http://127.0.0.1:{p}") for p in (port_a, port_b)]),
            SECRET,
            port=0,
        )
        await lobby.start()
        try:
            answers = []
            for name in ("anatomy-1", "anatomy-2"):  # one after the other, nobody joined yet
                status, answer = await ask(lobby, f"/rooms/{name}")
                assert status == 200, answer
                answers.append(answer)
            assert answers[0]["server"] != answers[1]["server"]
            for answer in answers:
                got = await first_answer(answer["url"], answer["token"])
                assert got["type"] == "welcome", got
        finally:
            await lobby.stop()
        assert await rooms_of(port_a) != await rooms_of(port_b)
        assert {"anatomy-1", "anatomy-2"} <= set(await rooms_of(port_a) + await rooms_of(port_b))


async def test_the_lobby_reads_the_status_of_a_server_off_loopback_with_its_metrics_token(
    tmp_path,
) -> None:
    """A room server listening off loopback answers ``/status`` only with its metrics token:
    a lobby without it finds no server (503), one given the same token file
    (``--status-token-file``) places the name and its user is welcomed. (The server listens on
    0.0.0.0; every request goes to 127.0.0.1.)"""
    metrics = "m" * 32
    token_file = tmp_path / "status-token"
    token_file.write_text(metrics + "\n")
    async with token_server(tmp_path / "s", host="0.0.0.0", metrics_token=metrics) as port:
        server = f"http://127.0.0.1:{port}"
        argv = ["lobby", "--token-secret-file", str(tmp_path / "s" / "secret"), "--server", server]
        without = _lobby_backend(build_parser().parse_args(argv))
        with_token = _lobby_backend(
            build_parser().parse_args([*argv, "--status-token-file", str(token_file)])
        )
        for backend, expected in ((without, 503), (with_token, 200)):
            lobby = Lobby(backend, SECRET, port=0)
            await lobby.start()
            try:
                status, answer = await ask(lobby, "/rooms/anatomy-1")
            finally:
                await lobby.stop()
            assert status == expected, answer
        got = await first_answer(answer["url"], answer["token"])
        assert got["type"] == "welcome", got


async def test_a_server_that_refuses_the_lobbys_room_token_is_a_clear_502(tmp_path) -> None:
    """A lobby whose token secret is not the servers' gets its handshake refused (401): it
    answers 502 and says why, rather than hand the user a token the server will refuse."""
    async with token_server(tmp_path) as port:
        other = b"o" * MIN_SECRET_BYTES
        lobby = Lobby(LocalServers([RoomServer(f"http://127.0.0.1:{port}")]), other, port=0)
        await lobby.start()
        try:
            status, answer = await ask(lobby, "/rooms/anatomy-1")
        finally:
            await lobby.stop()
        assert status == 502, answer
        assert "token secret is not the lobby's" in answer["error"]
        assert await rooms_of(port) == [DEFAULT_ROOM]
