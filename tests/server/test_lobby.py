"""``haptic lobby`` with local room servers: what a user asking for a room by name gets.

Two real room servers run in this process on loopback (``ServerApp``, rooms made on demand from
a template, room tokens checked with the secret they share with the lobby) and a real lobby in
front of them; requests are real HTTP. A user asking for a room gets the server already running
it, else a server with a free room slot where the room now runs, else a clear "no capacity";
the token it gets joins that room on that server and no other; hostile requests get a clear
4xx and the lobby goes on serving everybody else.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import ssl
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import connect

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.app import ServerApp
from haptic_collab.server.lobby import Lobby, LocalServers, RoomServer, load_servers
from haptic_collab.server.room import Room
from haptic_collab.server.security import MIN_SECRET_BYTES, RoomTokens, TokenTable
from tests.support.rooms import RecordingWorld, hello

SECRET = b"q" * MIN_SECRET_BYTES
SIM_RATE = 20.0
ASKERS = ThreadPoolExecutor(16, thread_name_prefix="asker")
USER_TOKEN = "lobby-user-token-0123456789"
VIEWER_TOKEN = "lobby-viewer-token-0123456789"


def room(name: str) -> Room:
    # a room named "solo-..." seats one user
    limits = RoomLimits(max_users=1) if name.startswith("solo-") else None
    auth = RoomTokens(name, None, SECRET, time.time)
    return Room(RecordingWorld(), SIM_RATE, limits=limits, auth=auth)


class Templates:
    """Rooms on demand whose names start with ``prefix`` (a server's ``[room_templates]``)."""

    def __init__(self, prefix: str = "") -> None:
        self.prefix = prefix

    def allows(self, name: str) -> bool:
        return name.startswith(self.prefix)

    def build(self, name: str) -> Room:
        return room(name)


@contextlib.asynccontextmanager
async def servers(*specs: tuple[int, str | None]) -> AsyncIterator[list[ServerApp]]:
    """Room servers, each (max_rooms, template prefix or None: no rooms on demand)."""
    apps = [
        ServerApp(
            room("default"),
            "127.0.0.1",
            0,
            room_maker=None if prefix is None else Templates(prefix),
            max_rooms=max_rooms,
        )
        for max_rooms, prefix in specs
    ]
    for app in apps:
        await app.start()
    try:
        yield apps
    finally:
        for app in apps:
            await app.stop()


@contextlib.asynccontextmanager
async def lobby_of(apps: list[ServerApp], **kw: Any) -> AsyncIterator[Lobby]:
    backend = LocalServers([RoomServer(f"http://127.0.0.1:{a.port}") for a in apps])
    lobby = Lobby(backend, SECRET, port=0, **kw)
    await lobby.start()
    try:
        yield lobby
    finally:
        await lobby.stop()


async def ask(lobby: Lobby, path: str, *, token: str = "") -> tuple[int, dict[str, Any]]:
    def go() -> tuple[int, dict[str, Any]]:
        req = urllib.request.Request(f"http://127.0.0.1:{lobby.port}{path}")
        if token:
            req.add_header("Authorization", f"Bearer {token}")
        try:
            with urllib.request.urlopen(req, timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    # threads of the test's own: the servers build rooms in the default executor
    return await asyncio.get_running_loop().run_in_executor(ASKERS, go)


async def welcome(url: str, token: str | None, role: str = "user") -> dict[str, Any]:
    """The first frame a client gets after its hello with ``token`` (welcome or error)."""
    async with connect(url) as ws:
        msg = json.loads(hello("A", role))
        if token is not None:
            msg["token"] = token
        await ws.send(json.dumps(msg))
        return json.loads(await asyncio.wait_for(ws.recv(), 10.0))


def port_of(url: str) -> int:
    return int(url.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1])


async def test_a_new_room_goes_where_slots_are_free_and_is_found_there_again() -> None:
    async with servers((2, ""), (4, "")) as (a, b), lobby_of([a, b]) as lobby:
        status, answer = await ask(lobby, "/rooms/lab-1")
        assert status == 200, answer
        # b has three free slots, a one: the room is made on b, and b runs it now
        assert answer["url"] == f"ws://127.0.0.1:{b.port}/rooms/lab-1/ws"
        assert "lab-1" in b.status()["rooms"] and "lab-1" not in a.status()["rooms"]
        # the token joins that room as a user; without it, or in another room, it does not
        got = await welcome(answer["url"], answer["token"])
        assert got["type"] == "welcome"
        assert (await welcome(answer["url"], None))["code"] == "unauthorized"
        other = f"ws://127.0.0.1:{b.port}/rooms/lab-2/ws"
        assert (await welcome(other, answer["token"]))["code"] == "unauthorized"
        # asked again, by anyone: the same server (it runs the room), not a new room elsewhere
        for _ in range(2):
            assert (await ask(lobby, "/rooms/lab-1"))[1]["url"] == answer["url"]
        assert "lab-1" not in a.status()["rooms"]
        # a viewer's token watches, and the viewer page opens from the URL the lobby gives
        status, view = await ask(lobby, "/rooms/lab-1?role=viewer")
        assert status == 200 and view["role"] == "viewer"
        assert (await welcome(view["url"], view["token"], role="user"))["code"] == "unauthorized"
        assert (await welcome(view["url"], view["token"], role="viewer"))["type"] == "welcome"
        page = view["viewer"].split("#", 1)[0]
        assert page == f"http://127.0.0.1:{b.port}/rooms/lab-1/"

        def fetch() -> tuple[int, bytes]:
            with urllib.request.urlopen(page, timeout=10) as r:
                return r.status, r.read()

        code, html = await asyncio.to_thread(fetch)  # the server runs on this event loop
        assert code == 200 and b"<html" in html.lower()


async def test_many_users_asking_at_once_for_a_new_room_make_it_once() -> None:
    async with servers((3, ""), (3, "")) as (a, b), lobby_of([a, b]) as lobby:
        answers = await asyncio.gather(*(ask(lobby, "/rooms/seminar") for _ in range(6)))
        assert [s for s, _ in answers] == [200] * 6
        assert len({x["url"] for _, x in answers}) == 1
        holders = [app for app in (a, b) if "seminar" in app.status()["rooms"]]
        assert len(holders) == 1
        assert list(lobby.backend.made) == [(f"http://127.0.0.1:{holders[0].port}", "seminar")]  # type: ignore[attr-defined]


async def test_full_servers_say_no_capacity_and_templates_decide_which_names() -> None:
    # a: only "lab-" names on demand, one free slot; b: no rooms on demand at all
    async with servers((2, "lab-"), (4, None)) as (a, b), lobby_of([a, b]) as lobby:
        status, answer = await ask(lobby, "/rooms/ward-1")
        assert status == 404 and "none may make a room of that name" in answer["error"]
        assert (await ask(lobby, "/rooms/lab-1"))[0] == 200
        status, answer = await ask(lobby, "/rooms/lab-2")  # a's last slot is taken
        assert status == 503 and "no room server has a free room slot" in answer["error"]
        # the default room runs everywhere: the first server that is not draining
        status, answer = await ask(lobby, "/rooms/default")
        assert status == 200 and answer["url"] == f"ws://127.0.0.1:{a.port}/ws"
        await a.drain(grace_s=2.0)
        status, answer = await ask(lobby, "/rooms/default")
        assert status == 200 and answer["url"] == f"ws://127.0.0.1:{b.port}/ws"
        status, answer = await ask(lobby, "/rooms/lab-1")  # its server drains, none makes it
        assert status == 404
    async with lobby_of([a]) as lobby:  # nobody answers
        status, answer = await ask(lobby, "/rooms/lab-1")
        assert status == 503 and "no room server answers" in answer["error"]


async def test_a_full_room_is_refused_to_users_and_open_to_viewers() -> None:
    async with servers((4, "")) as (a,), lobby_of([a]) as lobby:
        status, answer = await ask(lobby, "/rooms/solo-1")
        assert status == 200
        async with connect(answer["url"]) as ws:  # its one user stays in
            await ws.send(json.dumps({**json.loads(hello("A")), "token": answer["token"]}))
            assert json.loads(await asyncio.wait_for(ws.recv(), 10.0))["type"] == "welcome"
            status, refused = await ask(lobby, "/rooms/solo-1")
            assert status == 503 and "is full" in refused["error"]
            status, view = await ask(lobby, "/rooms/solo-1?role=viewer")
            assert status == 200 and view["url"] == answer["url"]


async def test_a_server_slow_to_make_a_room_is_not_doubled_by_another() -> None:
    """A server that has not answered the room's handshake may still be making the room: the
    lobby says so (503) and does not make the room on another server too."""
    hung: list[asyncio.StreamWriter] = []

    async def slow_server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        line = await reader.readline()
        if line.startswith(b"GET /status "):
            body = json.dumps(
                {"rooms": {"default": {}}, "max_rooms": 16, "rooms_on_demand": True,
                 "draining": False}
            ).encode()  # fmt: skip
            head = f"HTTP/1.1 200 OK\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n"
            writer.write(head.encode() + body)
            await writer.drain()
            writer.close()
        else:
            hung.append(writer)  # a websocket handshake: no answer while it builds

    slow = await asyncio.start_server(slow_server, "127.0.0.1", 0)
    slow_port = slow.sockets[0].getsockname()[1]
    try:
        async with servers((4, "")) as (b,):
            backend = LocalServers(
                [
                    RoomServer(f"http://127.0.0.1:{slow_port}"),
                    RoomServer(f"http://127.0.0.1:{b.port}"),
                ],
                build_timeout_s=0.5,
            )
            lobby = Lobby(backend, SECRET, port=0)
            await lobby.start()
            try:
                status, answer = await ask(lobby, "/rooms/big-solid")
            finally:
                await lobby.stop()
            assert status == 503 and "still being made" in answer["error"]
            assert hung  # it was asked, and had not answered
            assert "big-solid" not in b.status()["rooms"]  # not made a second time
    finally:
        for w in hung:
            w.close()
        slow.close()


async def raw(lobby: Lobby, data: bytes, source: str = "127.0.0.1") -> bytes:
    """Send ``data`` on a connection from ``source``; the lobby's whole answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", lobby.port, local_addr=(source, 0))
    writer.write(data)
    with contextlib.suppress(ConnectionError):
        await writer.drain()
    try:
        return await asyncio.wait_for(reader.read(), 20.0)
    finally:
        writer.close()


def status_of(answer: bytes) -> int:
    return int(answer.split(b" ", 2)[1])


async def test_hostile_requests_get_a_clear_4xx_and_the_lobby_keeps_serving() -> None:
    async with servers((4, "")) as (a,), lobby_of([a], read_timeout_s=0.5) as lobby:
        answered = {
            b"GET /rooms/Bad..Name HTTP/1.1\r\nHost: x\r\n\r\n": 400,
            b"GET /rooms/" + b"a" * 40 + b" HTTP/1.1\r\n\r\n": 400,
            b"GET /rooms/lab?role=admin HTTP/1.1\r\n\r\n": 400,
            b"GET /rooms/lab?role=user&role=viewer HTTP/1.1\r\n\r\n": 400,
            b"GET /etc/passwd HTTP/1.1\r\n\r\n": 404,
            b"DELETE /rooms/lab HTTP/1.1\r\n\r\n": 405,
            b"POST /rooms/lab HTTP/1.1\r\n\r\n": 405,  # the form is GET now
        }
        for data, want in answered.items():
            answer = await raw(lobby, data)
            assert status_of(answer) == want, (data[:40], answer[:200])
            assert b'"error"' in answer
        # what websockets' parser refuses itself: a line over its 8192 bytes gets a status
        too_long = {
            b"GET /rooms/lab HTTP/1.1\r\nX: " + b"y" * 20000 + b"\r\n\r\n": 431,
            b"GET /rooms/" + b"a" * 9000 + b" HTTP/1.1\r\n\r\n": 414,
        }
        for data, want in too_long.items():
            assert status_of(await raw(lobby, data)) == want, data[:40]
        # a method, body or framing it does not take, bytes that are not HTTP, a request never
        # finished or larger than the lobby's bound: the connection closes without an answer
        dropped = [
            b'POST /rooms/lab HTTP/1.1\r\nContent-Length: 17\r\n\r\n{"role": "owner"}',
            b"GET /rooms/lab HTTP/1.1\r\nContent-Length: 99999999\r\n\r\n",
            b"GET /rooms/lab HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n",
            b"\x16\x03\x01 garbage \r\n\r\n",
            b"GET /rooms/lab HTTP/1.1\r\nHost: x\r\n",  # never finishes its headers
            b"GET /rooms/lab HTTP/1.1\r\n" + (b"X: " + b"y" * 8000 + b"\r\n") * 10,  # 80 kB
        ]
        for data in dropped:
            assert await raw(lobby, data) == b"", data[:40]
        assert lobby.dropped == 2  # the slow one and the large one; websockets closed the rest
        assert "lab" not in a.status()["rooms"]  # nothing above made a room
        # a flood from one address is cut off at its budget; another address is still served
        codes = [status_of(await raw(lobby, b"GET /healthz HTTP/1.1\r\n\r\n", "127.0.0.2"))
                 for _ in range(30)]  # fmt: skip
        assert 200 in codes and codes[-1] == 429 and codes.count(429) >= 5
        status, answer = await ask(lobby, "/rooms/lab")
        assert status == 200 and answer["url"].endswith("/rooms/lab/ws")


async def test_a_lobby_with_tokens_gives_a_viewer_token_only_viewer_rooms(tmp_path: Path) -> None:
    table = TokenTable({USER_TOKEN: ("user", None), VIEWER_TOKEN: ("viewer", None)})
    async with servers((4, "")) as (a,), lobby_of([a], auth=table) as lobby:
        assert (await ask(lobby, "/rooms/lab"))[0] == 401
        assert (await ask(lobby, "/rooms/lab", token="not-a-token-at-all-000"))[0] == 401
        status, answer = await ask(lobby, "/rooms/lab", token=VIEWER_TOKEN)
        assert status == 403 and "only watch" in answer["error"]
        status, answer = await ask(lobby, "/rooms/lab?role=viewer", token=VIEWER_TOKEN)
        assert status == 200 and answer["role"] == "viewer"
        assert (await ask(lobby, "/rooms/lab", token=USER_TOKEN))[0] == 200


def test_off_loopback_the_lobby_wants_tokens_and_reads_its_servers_file(tmp_path: Path) -> None:
    backend = LocalServers([RoomServer("http://127.0.0.1:1")])
    with pytest.raises(ValueError, match="token-file"):
        Lobby(backend, SECRET, host="0.0.0.0")
    Lobby(backend, SECRET, host="0.0.0.0", insecure=True)  # said on purpose
    with pytest.raises(ValueError, match="at least"):
        Lobby(backend, b"short", port=0)
    f = tmp_path / "servers.toml"
    f.write_text(
        '[[servers]]\nurl = "http://room-a:8765"\npublic = "ws://localhost:8765"\n'
        '[[servers]]\nurl = "https://room-b:8765"\n'
    )
    a, b = load_servers(f)
    assert a.bases == ("ws://localhost:8765", "http://localhost:8765")
    assert b.bases == ("wss://room-b:8765", "https://room-b:8765")
    assert RoomServer.parse("http://x:1=wss://lab.example:443").bases[0] == "wss://lab.example:443"
    for bad in ("ftp://x", "x:8765", "http://x:1=nope"):
        with pytest.raises(ValueError):
            RoomServer.parse(bad)
    f.write_text("servers = 3\n")
    with pytest.raises(ValueError, match=r"\[\[servers\]\]"):
        load_servers(f)


async def test_a_lobby_serves_https_and_cuts_off_a_silent_tls_client() -> None:
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    server_ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server_ctx)
    client_ctx = ssl.create_default_context()
    ca.configure_trust(client_ctx)
    async with (
        servers((4, "")) as (a,),
        lobby_of([a], ssl_context=server_ctx, read_timeout_s=0.5) as lobby,
    ):

        def get(path: str) -> tuple[int, dict[str, Any]]:
            url = f"https://127.0.0.1:{lobby.port}{path}"
            with urllib.request.urlopen(url, timeout=10, context=client_ctx) as r:
                return r.status, json.loads(r.read())

        status, answer = await asyncio.get_running_loop().run_in_executor(
            ASKERS, get, "/rooms/lab?role=viewer"
        )
        assert status == 200 and answer["role"] == "viewer"
        assert (await welcome(answer["url"], answer["token"], role="viewer"))["type"] == "welcome"
        # a client that opens TCP and never starts TLS is closed, and the lobby goes on
        reader, writer = await asyncio.open_connection("127.0.0.1", lobby.port)
        assert await asyncio.wait_for(reader.read(), 20.0) == b""
        writer.close()
        assert (await asyncio.get_running_loop().run_in_executor(ASKERS, get, "/healthz"))[0] == 200
