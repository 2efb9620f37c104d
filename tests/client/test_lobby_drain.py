"""``haptic client --lobby URL --room NAME``: the client finds its room through the lobby, and
when its server drains it asks the lobby again and joins the room where it runs now.

Two real room servers (rooms made on demand, room tokens checked with the secret they share
with the lobby) and a real lobby run in this process on loopback; the client is the real
:class:`client.link.Link` with the resolver ``haptic client`` gives it
(:func:`client.app.lobby_resolver`), over real websockets and HTTP.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor

import pytest

from haptic_collab.client.app import ask_lobby, lobby_resolver
from haptic_collab.client.link import Link
from haptic_collab.client.session import ClientSession
from haptic_collab.server.app import ServerApp
from haptic_collab.server.lobby import Lobby, LocalServers, RoomServer
from haptic_collab.server.room import Room
from haptic_collab.server.security import MIN_SECRET_BYTES, RoomTokens
from tests.support.rooms import RecordingWorld

SECRET = b"d" * MIN_SECRET_BYTES
SIM_RATE = 20.0


async def until(predicate: Callable[[], object], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


def room(name: str) -> Room:
    return Room(RecordingWorld(), SIM_RATE, auth=RoomTokens(name, None, SECRET, time.time))


class AnyName:
    def allows(self, name: str) -> bool:
        return True

    def build(self, name: str) -> Room:
        return room(name)


@contextlib.asynccontextmanager
async def site(*max_rooms: int) -> AsyncIterator[tuple[list[ServerApp], Lobby]]:
    """Room servers (each with ``max_rooms``) and a lobby in front of them."""
    apps = [
        ServerApp(room("default"), "127.0.0.1", 0, room_maker=AnyName(), max_rooms=n)
        for n in max_rooms
    ]
    for app in apps:
        await app.start()
    lobby = Lobby(
        LocalServers([RoomServer(f"http://127.0.0.1:{a.port}") for a in apps]), SECRET, port=0
    )
    await lobby.start()
    try:
        yield apps, lobby
    finally:
        await lobby.stop()
        for app in apps:
            await app.stop()


@contextlib.asynccontextmanager
async def user(lobby_url: str, room_name: str) -> AsyncIterator[tuple[Link, asyncio.Task[None]]]:
    """A user's link that finds ``room_name`` through the lobby (no servo: no state sent)."""
    pool = ThreadPoolExecutor(max_workers=1)
    link = Link(
        "",
        ClientSession("A"),
        on_patch=lambda update, now: None,
        sample=lambda: None,
        clock=time.monotonic,
        backoff_s=(0.05, 0.5),
        design_executor=pool,
        resolve=lobby_resolver(lobby_url, room_name),
    )
    stop = asyncio.Event()
    task = asyncio.create_task(link.run(stop))
    try:
        yield link, task
    finally:
        stop.set()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 10.0)
        pool.shutdown(wait=False, cancel_futures=True)


async def test_a_user_moved_by_a_drain_joins_its_room_on_the_other_server() -> None:
    async with site(4, 3) as ((a, b), lobby):
        lobby_url = f"http://127.0.0.1:{lobby.port}"
        async with user(lobby_url, "lab") as (link, _):
            await until(lambda: link.joins == 1)
            # the room was made where most slots were free, and the user is in it
            assert link.joined_urls == [f"ws://127.0.0.1:{a.port}/rooms/lab/ws"]
            assert len(a.rooms()["lab"].users) == 1 and "lab" not in b.rooms()
            first_id = link.user_ids[0]
            report = await a.drain(grace_s=5.0)  # what SIGTERM runs
            assert report.told >= 1 and report.left_open == 0  # the client left at once
            await until(lambda: link.joins == 2)
            # it asked the lobby again and joined room lab on the server that runs it now
            assert link.lobby_asks == 2
            assert link.joined_urls[1] == f"ws://127.0.0.1:{b.port}/rooms/lab/ws"
            assert len(b.rooms()["lab"].users) == 1
            # the seat could not move between servers: a new one there (its resume token was
            # offered and matched nothing), and the room's one user is this link
            assert link.resumes == 0 and b.rooms()["lab"].resume_misses == 1
            assert len(link.user_ids) == 2 and first_id
            assert link.connected.is_set()


async def test_a_lobby_that_refuses_the_room_stops_the_client_with_its_reason() -> None:
    async with site(2) as (_, lobby):
        lobby_url = f"http://127.0.0.1:{lobby.port}"
        async with user(lobby_url, "Not A Room") as (link, task):
            with pytest.raises(ValueError, match="refused room 'Not A Room'.*400"):
                await asyncio.wait_for(task, 10.0)
            assert link.joins == 0


async def test_a_client_waits_for_a_lobby_that_is_not_up_yet() -> None:
    async with site(2) as ((a,), lobby):
        port = lobby.port
        await lobby.stop()
        with pytest.raises(ConnectionError, match="cannot be reached"):
            await asyncio.to_thread(ask_lobby, f"http://127.0.0.1:{port}", "lab")
        async with user(f"http://127.0.0.1:{port}", "lab") as (link, task):
            await asyncio.sleep(0.3)
            assert link.joins == 0 and not task.done()  # still trying, not failed
            lobby.port = port
            await lobby.start()
            await until(lambda: link.joins == 1)
            assert link.joined_urls == [f"ws://127.0.0.1:{a.port}/rooms/lab/ws"]


async def test_the_room_a_drain_moved_starts_from_its_snapshot_on_the_other_server(tmp_path):
    """Servers sharing a snapshot folder (docker-compose's volume): the pressed surface of a
    room drained on one server is the surface of that room where the lobby makes it next."""
    import json

    import numpy as np
    from websockets.asyncio.client import connect

    from haptic_collab.server.main import RoomTemplates, ServerOptions, build_world
    from haptic_collab.shared.protocol import LinkConditions

    opts = ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2)
    apps = []
    for max_rooms in (4, 3):
        maker = RoomTemplates(opts, {"any": {"prefix": ""}}, LinkConditions(), None, SECRET)
        apps.append(
            ServerApp(
                Room(build_world(opts), SIM_RATE),
                "127.0.0.1",
                0,
                room_maker=maker,
                max_rooms=max_rooms,
                snapshot_dir=tmp_path,
            )  # fmt: skip
        )
    a, b = apps
    for app in apps:
        await app.start()
    lobby = Lobby(
        LocalServers([RoomServer(f"http://127.0.0.1:{x.port}") for x in apps]), SECRET, port=0
    )
    await lobby.start()
    lobby_url = f"http://127.0.0.1:{lobby.port}"
    try:
        answer = await asyncio.to_thread(ask_lobby, lobby_url, "lab")
        assert answer["url"] == f"ws://127.0.0.1:{a.port}/rooms/lab/ws"
        lab = a.rooms()["lab"]
        top = float(lab.world.rest_bounds[1][2])  # type: ignore[union-attr]
        async with connect(answer["url"]) as presser, user(lobby_url, "lab") as (link, _):
            hello = {"type": "hello", "protocol": 1, "role": "user", "name": "P"}
            await presser.send(json.dumps({**hello, "token": answer["token"]}))
            seq = 0
            while lab.world.obj.max_displacement_m < 1e-3:  # type: ignore[union-attr]
                seq += 1
                state = {
                    "type": "state", "seq": seq, "probe_m": [0.0, 0.0, top - 0.006],
                    "force_n": [0.0, 0.0, 2.0], "penetration_m": 0.006, "in_contact": True,
                    "k_h": 400.0,
                }  # fmt: skip
                await presser.send(json.dumps(state))
                await asyncio.sleep(0.02)
            await until(lambda: link.joins == 1)
            report = await a.drain(grace_s=5.0)
            assert tmp_path / "lab.npz" in report.snapshots
            pressed = np.array(lab.world.vertices)  # type: ignore[union-attr]
            await until(lambda: link.joins == 2)
            assert link.joined_urls[1] == f"ws://127.0.0.1:{b.port}/rooms/lab/ws"
            shown = np.array(b.rooms()["lab"].world.vertices)  # type: ignore[union-attr]
            rest = np.array(build_world(opts).vertices)
            assert np.max(np.abs(pressed - rest)) > 1e-3  # the press had moved it
            # b's room lab started from a's snapshot: the same surface (b's own ticks since
            # may have relaxed it a little: it is a live object now)
            assert np.max(np.abs(shown - pressed)) < 0.25 * np.max(np.abs(pressed - rest))
            assert (tmp_path / "lab.npz.loaded").exists()
    finally:
        await lobby.stop()
        for app in apps:
            await app.stop()
