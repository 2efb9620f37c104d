"""Several rooms in one server: routing by URL, a loop per room, rooms on demand, room tokens.

The real server in this process (World -> Room -> ServerApp on a free loopback port) and
scripted websocket peers; every wait is bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from haptic_collab.server.admission import RoomLimits
from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.server.security import MIN_SECRET_BYTES, RoomTokens, make_room_token
from haptic_collab.shared.protocol import PROTOCOL_VERSION

SIM_RATE = 20.0
SECRET = b"r" * MIN_SECRET_BYTES


def new_room(sim_rate: float = SIM_RATE, **kwargs: Any) -> Room:
    world = build_world(ServerOptions(sim_rate_hz=sim_rate, subdivisions=1))
    return Room(world, sim_rate, **kwargs)


class Templates:
    """A room maker: names starting with ``t-`` are built on demand."""

    def __init__(self) -> None:
        self.built: list[str] = []

    def allows(self, name: str) -> bool:
        return name.startswith("t-")

    def build(self, name: str) -> Room:
        self.built.append(name)
        return new_room()


@contextlib.asynccontextmanager
async def server(**kwargs: Any) -> AsyncIterator[ServerApp]:
    app = ServerApp(kwargs.pop("room", None) or new_room(), "127.0.0.1", 0, **kwargs)
    await app.start()
    try:
        yield app
    finally:
        await app.stop()


async def until(predicate: Callable[[], object], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


def hello(name: str, role: str = "user", token: str | None = None) -> str:
    msg: dict[str, Any] = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": role}
    msg["name"] = name
    if token is not None:
        msg["token"] = token
    return json.dumps(msg)


async def first_text(ws: Any, kind: str, timeout_s: float = 20.0) -> dict[str, Any]:
    """The first text frame of type ``kind`` (or an ``error``) the peer receives."""
    deadline = time.monotonic() + timeout_s
    while True:
        frame = await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic()))
        if isinstance(frame, str):
            msg = json.loads(frame)
            if msg["type"] in (kind, "error"):
                return msg


async def http(app: ServerApp, path: str) -> tuple[int, str, str]:
    """GET ``path``: status, Location header, body (redirects are not followed)."""

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args: Any) -> None:
            return None

    def get() -> tuple[int, str, str]:
        opener = urllib.request.build_opener(NoRedirect)
        try:
            with opener.open(f"http://127.0.0.1:{app.port}{path}", timeout=10) as res:
                return res.status, res.headers.get("Location", ""), res.read().decode()
        except urllib.error.HTTPError as err:
            return err.code, err.headers.get("Location", ""), err.read().decode()

    return await asyncio.to_thread(get)


async def test_a_client_joins_the_room_its_url_names_and_only_that_room() -> None:
    async with server(rooms={"a": new_room(), "b": new_room()}) as app:
        url = f"ws://127.0.0.1:{app.port}"
        async with connect(f"{url}/rooms/a/ws") as wa, connect(f"{url}/ws") as wd:
            await wa.send(hello("alice"))
            await wd.send(hello("dora"))
            assert (await first_text(wa, "welcome"))["type"] == "welcome"
            assert (await first_text(wd, "welcome"))["type"] == "welcome"
            rooms = app.rooms()
            assert list(rooms) == [DEFAULT_ROOM, "a", "b"]
            assert len(rooms["a"].users) == 1 and len(rooms[DEFAULT_ROOM].users) == 1
            assert rooms["b"].users == []
            status = (await http(app, "/status"))[2]
            listed = json.loads(status)["rooms"]
            assert set(listed) == {DEFAULT_ROOM, "a", "b"}
            assert listed["a"]["users"] == 1 and listed["b"]["users"] == 0
            assert listed["a"]["ws"] == "/rooms/a/ws" and listed[DEFAULT_ROOM]["ws"] == "/ws"


async def test_each_room_ticks_on_its_own_loop_at_its_own_rate() -> None:
    """A room whose loop has died leaves the others ticking; rooms keep their own rates."""
    async with server(rooms={"fast": new_room(50.0), "slow": new_room(10.0)}) as app:
        rooms = app.rooms()
        await until(lambda: rooms["fast"].tick_count >= 10 and rooms["slow"].tick_count >= 2)
        app._slots["slow"].task.cancel()  # type: ignore[union-attr]
        with contextlib.suppress(asyncio.CancelledError):
            await app._slots["slow"].task  # type: ignore[misc]
        stopped_at = rooms["slow"].tick_count
        fast_from = rooms["fast"].tick_count
        await until(lambda: rooms["fast"].tick_count >= fast_from + 20)
        assert rooms["slow"].tick_count == stopped_at
        alive = {r.name: r.alive for r in app.room_reports()}
        assert alive == {DEFAULT_ROOM: True, "fast": True, "slow": False}


async def test_room_pages_and_refusals_over_http() -> None:
    async with server(rooms={"a": new_room()}, room_maker=Templates()) as app:
        status, _, body = await http(app, "/rooms/a/")
        assert status == 200 and "viewer.js" in body
        assert (await http(app, "/rooms/t-later/"))[0] == 200  # allowed, built on joining
        status, location, _ = await http(app, "/rooms/a")
        assert status == 301 and location == "/rooms/a/"
        status, _, body = await http(app, "/rooms/nope/")
        assert status == 404 and "no room 'nope'" in body
        status, _, body = await http(app, "/rooms/Bad!/")
        assert status == 400 and "room name" in body
        assert list(app.rooms()) == [DEFAULT_ROOM, "a"]  # pages build nothing


@pytest.mark.parametrize(("path", "code"), [("/rooms/nope/ws", 404), ("/rooms/NO/ws", 400)])
async def test_a_websocket_to_an_unknown_or_badly_named_room_is_refused(
    path: str, code: int
) -> None:
    async with server(room_maker=Templates()) as app:
        with pytest.raises(InvalidStatus) as err:
            async with connect(f"ws://127.0.0.1:{app.port}{path}"):
                pass
        assert err.value.response.status_code == code


async def test_a_template_makes_rooms_on_demand_up_to_the_cap_and_closes_them_when_idle() -> None:
    maker = Templates()
    async with server(room_maker=maker, max_rooms=2, room_idle_s=0.5) as app:
        url = f"ws://127.0.0.1:{app.port}"
        async with connect(f"{url}/rooms/t-1/ws") as ws:
            await ws.send(hello("ann"))
            assert (await first_text(ws, "welcome"))["type"] == "welcome"
            assert maker.built == ["t-1"] and list(app.rooms()) == [DEFAULT_ROOM, "t-1"]
            listed = json.loads((await http(app, "/status"))[2])["rooms"]
            assert listed["t-1"]["on_demand"] is True and listed[DEFAULT_ROOM]["on_demand"] is False
            with pytest.raises(InvalidStatus) as err:  # the third room is over the cap
                async with connect(f"{url}/rooms/t-2/ws"):
                    pass
            assert err.value.response.status_code == 503
            assert maker.built == ["t-1"]
        await until(lambda: "t-1" not in app.rooms())  # empty for room_idle_s: closed
        assert list(app.figures) == [DEFAULT_ROOM]
        async with connect(f"{url}/rooms/t-2/ws") as ws:  # room again under the cap
            await ws.send(hello("ben"))
            assert (await first_text(ws, "welcome"))["type"] == "welcome"
        assert maker.built == ["t-1", "t-2"]


async def test_a_room_token_admits_to_its_room_only_and_not_once_expired() -> None:
    now = [time.time()]

    def room(name: str) -> Room:
        return new_room(auth=RoomTokens(name, None, SECRET, lambda: now[0]))

    async with server(room=room(DEFAULT_ROOM), rooms={"a": room("a"), "b": room("b")}) as app:
        url = f"ws://127.0.0.1:{app.port}"
        for_a = make_room_token(SECRET, "a", "user", now[0] + 60.0)
        viewer_a = make_room_token(SECRET, "a", "viewer", now[0] + 60.0)

        async def join(path: str, token: str, role: str = "user") -> dict[str, Any]:
            async with connect(f"{url}{path}") as ws:
                await ws.send(hello("x", role, token))
                return await first_text(ws, "welcome")

        assert (await join("/rooms/a/ws", for_a))["type"] == "welcome"
        refused = await join("/rooms/b/ws", for_a)
        assert refused["type"] == "error" and refused["code"] == "unauthorized"
        assert (await join("/ws", for_a))["code"] == "unauthorized"
        assert (await join("/rooms/a/ws", viewer_a))["code"] == "unauthorized"  # not a user
        assert (await join("/rooms/a/ws", viewer_a, "viewer"))["type"] == "welcome"
        now[0] += 61.0
        assert (await join("/rooms/a/ws", for_a))["code"] == "unauthorized"  # expired


async def test_an_address_cannot_multiply_its_connections_by_spreading_over_rooms() -> None:
    """Each room allows an address 3 connections, the server 4 in all rooms together."""
    limits = RoomLimits(max_connections_per_address=3)
    across = RoomLimits(max_connections=1000, max_pending=1000, max_pending_per_address=1000)
    across = RoomLimits(**{**across.__dict__, "max_connections_per_address": 4})
    rooms = {"a": new_room(limits=limits), "b": new_room(limits=limits)}
    async with server(room=new_room(limits=limits), rooms=rooms, address_limits=across) as app:
        url = f"ws://127.0.0.1:{app.port}"
        async with contextlib.AsyncExitStack() as stack:
            for path in ("/rooms/a/ws", "/rooms/a/ws", "/rooms/b/ws", "/rooms/b/ws"):
                ws = await stack.enter_async_context(connect(f"{url}{path}"))
                await ws.send(hello("p"))
                assert (await first_text(ws, "welcome"))["type"] == "welcome"
            fifth = await stack.enter_async_context(connect(f"{url}/ws"))
            refused = await first_text(fifth, "welcome")
            assert refused["code"] == "too_many_connections"
            assert "in all rooms" in refused["message"]
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(fifth.recv(), 10.0)
            assert app.rooms()[DEFAULT_ROOM].users == []


async def test_an_address_flooding_two_rooms_is_cut_off_by_the_shared_budget() -> None:
    """Each room's address budget alone would admit both floods; together they exceed the
    server's, and the busiest connection is closed with ``rate_limited``."""
    across = RoomLimits(
        max_connections=1000,
        max_pending=1000,
        max_pending_per_address=1000,
        address_rate_per_s=100.0,
        address_burst=100.0,
    )
    async with server(rooms={"a": new_room(), "b": new_room()}, address_limits=across) as app:
        url = f"ws://127.0.0.1:{app.port}"
        async with connect(f"{url}/rooms/a/ws") as wa, connect(f"{url}/rooms/b/ws") as wb:
            for ws in (wa, wb):
                await ws.send(hello("p"))
                assert (await first_text(ws, "welcome"))["type"] == "welcome"
            ping = json.dumps({"type": "ping", "id": 1, "t_client_s": 0.0})
            closed: list[dict[str, Any]] = []
            for _ in range(80):  # 160 pings: within each room's 2000, beyond the shared 100
                for ws in (wa, wb):
                    with contextlib.suppress(ConnectionClosed):
                        await ws.send(ping)
            for ws in (wa, wb):
                with contextlib.suppress(ConnectionClosed, TimeoutError):
                    while True:
                        frame = await asyncio.wait_for(ws.recv(), 5.0)
                        if isinstance(frame, str) and json.loads(frame)["type"] == "error":
                            closed.append(json.loads(frame))
            assert closed, "the shared budget closed nobody"
            for err in closed:  # the server's budget, not a room's ("this address sends ...")
                assert err["code"] == "rate_limited" and "in all rooms" in err["message"]
