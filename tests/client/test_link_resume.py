"""The Python client's link rejoins by itself and gets its seat back (a real server on loopback).

Two ways a link dies: the server's side of the socket is cut off (the client sees the close at
once), and a network cut (nothing is closed, nothing crosses: the link notices the silence).
Either way the next ``hello`` carries the resume token, and the server gives back the same user
id; the room holds one seat for the user, not two.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor

import pytest
from websockets.asyncio.client import connect

from haptic_collab.client.link import Link
from haptic_collab.client.session import ClientSession
from haptic_collab.server.app import ServerApp
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import LinkConditions
from tests.support.cut_proxy import CutProxy
from tests.support.rooms import RecordingWorld, hello

SIM_RATE = 20.0


async def until(predicate: Callable[[], object], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def server() -> AsyncIterator[ServerApp]:
    app = ServerApp(Room(RecordingWorld(), SIM_RATE), "127.0.0.1", 0)
    await app.start()
    try:
        yield app
    finally:
        await app.stop()


@contextlib.asynccontextmanager
async def running_link(url: str) -> AsyncIterator[Link]:
    """A user's link (no servo: it sends no state, so only pongs come back) running until exit."""
    pool = ThreadPoolExecutor(max_workers=1)
    link = Link(
        url,
        ClientSession("A"),
        on_patch=lambda update, now: None,
        sample=lambda: None,
        clock=time.monotonic,
        backoff_s=(0.05, 0.5),
        design_executor=pool,
    )
    stop = asyncio.Event()
    task = asyncio.create_task(link.run(stop))
    try:
        yield link
    finally:
        stop.set()
        await asyncio.wait_for(task, 10.0)
        pool.shutdown(wait=False, cancel_futures=True)


def user_peer(app: ServerApp, user_id: str):  # the server's side of one user's connection
    return next(p for p in app._peers.values() if not p.closed and f"({user_id})" in p.who)


async def test_the_link_resumes_its_seat_after_the_server_side_drops_it():
    async with server() as app, running_link(f"ws://127.0.0.1:{app.port}/ws") as link:
        await until(lambda: link.joins == 1)
        (uid,) = link.user_ids
        first_token = link.session.resume_token
        assert first_token
        await until(lambda: any(p.named for p in app._peers.values()))
        user_peer(app, uid).ws.transport.abort()  # no close frame: the link just breaks
        await until(lambda: link.joins == 2)
        assert link.user_ids == [uid, uid] and link.resumes == 1 and link.session.resumes == 1
        assert link.session.resume_token not in (None, first_token)  # a fresh one
        await until(lambda: not app.room.held_seats)
        assert len(app.room.users) == 1 and app.room.resumes == 1
        assert app.status()["resumes"] == 1 and app.status()["held_seats"] == 0


async def test_the_link_notices_a_network_cut_and_resumes_after_it():
    async with server() as app:
        proxy = await CutProxy(app.port).start()
        try:
            # another user, straight to the server, sees that A keeps one seat
            async with connect(f"ws://127.0.0.1:{app.port}/ws") as b:
                await b.send(hello("B"))
                assert json.loads(await asyncio.wait_for(b.recv(), 10.0))["type"] == "welcome"
                async with running_link(f"ws://127.0.0.1:{proxy.port}/ws") as link:
                    await until(lambda: link.joins == 1)
                    (uid,) = link.user_ids
                    proxy.cut(3.0)
                    await until(lambda: link.silent_drops == 1)  # 2 s of silence
                    assert link.joins == 1 and len(app.room.users) == 2  # the server saw nothing
                    await until(lambda: link.joins == 2)  # once the cut is over
                    assert not proxy.is_cut
                    assert link.user_ids == [uid, uid] and link.resumes == 1
                    await until(lambda: len(app.room.users) == 2 and not app.room.held_seats)
                    assert app.room.resumes == 1 and app.room.resume_misses == 0
        finally:
            await proxy.stop()


@pytest.mark.parametrize("latency_ms", [0.0, 80.0])
async def test_a_bye_leaves_no_seat_behind_even_when_latency_holds_it_back(latency_ms):
    app = ServerApp(
        Room(RecordingWorld(), SIM_RATE),
        "127.0.0.1",
        0,
        link=LinkConditions(latency_ms=latency_ms),
    )
    await app.start()
    try:
        ws = await connect(f"ws://127.0.0.1:{app.port}/ws")
        await ws.send(hello("A"))
        assert json.loads(await asyncio.wait_for(ws.recv(), 10.0))["type"] == "welcome"
        await ws.send('{"type":"bye"}')
        await ws.close()  # gone at once, the bye still on its way through the latency
        await until(lambda: not app._peers)
        assert app.room.held_seats == [] and app.room.users == []
    finally:
        await app.stop()
