"""The server under Agones: what the SDK sidecar hears from it during a session.

The sidecar is the stand-in of tests/support/agones_sidecar.py, built from Agones' swagger files
(it validates every request body against them); the server is the real one, in this process.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import time
from collections.abc import Callable

from websockets.asyncio.client import ClientConnection, connect

from haptic_collab.server.agones import PORT_ENV, AgonesAgent, AgonesOptions, start_agones
from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import ServerOptions, build_world, room_proxy, run_server
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import LinkConditions
from tests.support.agones_sidecar import Call, Sidecar

SIM_RATE = 20.0
#: A short health period and probe timeout keep the test short; the defaults are 2 s and 1 s.
FAST = {"health_period_s": 0.5, "probe_timeout_s": 0.25, "poll_s": 0.05}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def until(predicate: Callable[[], object], timeout_s: float = 60.0) -> None:
    """Let the event loop (and the server on it) run until ``predicate()`` holds."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


def block_until(predicate: Callable[[], bool], timeout_s: float = 60.0) -> None:
    """Hold the event loop's thread (the simulation's) until ``predicate()`` holds."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out while blocking the loop"
        time.sleep(0.01)


async def start_app() -> ServerApp:
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0)
    await app.start()
    return app


class User:
    """A websocket user that joins and reads every frame (so its send buffer never fills)."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.reader = asyncio.create_task(self._drain())

    async def _drain(self) -> None:
        with contextlib.suppress(Exception):
            async for _ in self.ws:
                pass

    @classmethod
    async def join(cls, port: int, name: str, role: str = "user", path: str = "/ws") -> User:
        ws = await connect(f"ws://127.0.0.1:{port}{path}")
        await ws.send(json.dumps({"type": "hello", "protocol": 1, "role": role, "name": name}))
        assert json.loads(await asyncio.wait_for(ws.recv(), 30.0))["type"] == "welcome"
        return cls(ws)

    async def leave(self) -> None:
        await self.ws.close()
        await asyncio.wait_for(self.reader, 10.0)


def counts(sc: Sidecar) -> list[int]:
    return [int(c.body["count"]) for c in sc.of("PATCH", "/v1beta1/counters/users")]


async def test_a_session_as_the_sidecar_hears_it():
    port = free_port()  # the sidecar starts after the server, as it may in a pod
    app = await start_app()
    agent = start_agones(
        app.room_reports,
        AgonesOptions(empty_shutdown_s=1.0, labels={"object": "balloon"}, **FAST),
        environ={PORT_ENV: str(port)},
    )
    assert agent is not None
    users: list[User] = []
    try:
        await until(lambda: agent.ready_attempts >= 2)  # refused, retried
        with Sidecar(port, lists={"rooms": 4}, counters={"users": 8}) as sc:
            health = lambda: len(sc.of("POST", "/health"))  # noqa: E731
            await until(lambda: counts(sc) == [0] and health() >= 1)
            assert agent.state == "ready" and sc.state == "Ready"
            assert len(sc.of("POST", "/ready")) == 1
            assert sc.labels == {"agones.dev/sdk-object": "balloon"}
            assert sc.lists["rooms"]["values"] == []  # no room in use yet

            users.append(await User.join(app.port, "A"))
            # the first arrival: the room is in use, and the server Allocated (no scale-down);
            # the list, the counter and the allocation are three calls of one report
            await until(lambda: counts(sc)[-1] == 1 and sc.state == "Allocated")
            added = sc.of("POST", "/v1beta1/lists/rooms:addValue")
            assert [c.body for c in added] == [{"value": DEFAULT_ROOM}]
            assert sc.of("POST", "/ready")[0].seq < added[0].seq
            assert sc.lists["rooms"]["values"] == [DEFAULT_ROOM]
            users.append(await User.join(app.port, "B"))
            viewer = await User.join(app.port, "V", role="viewer")  # a viewer is no user
            await until(lambda: counts(sc)[-1] == 2)

            # the tick loop blocked: no health ping while it is, pings again after
            withheld = agent.health_withheld
            block_until(lambda: agent.health_withheld >= withheld + 1)
            pings_at_first_withheld = health()
            block_until(lambda: agent.health_withheld >= withheld + 3)
            assert health() == pings_at_first_withheld
            pings = health()
            await until(lambda: health() > pings)

            await users.pop(0).leave()
            await until(lambda: counts(sc)[-1] == 1)
            await users.pop(0).leave()
            await viewer.leave()
            await until(lambda: sc.of("POST", "/shutdown"), 30.0)
            # the agent says so once the sidecar's answer is back (a loaded CI read it first)
            await until(lambda: agent.state == "shutdown", 10.0)

            assert counts(sc) == [0, 1, 2, 1, 0]
            assert len(sc.of("POST", "/allocate")) == 1
            removed = sc.of("POST", "/v1beta1/lists/rooms:removeValue")
            assert [c.body for c in removed] == [{"value": DEFAULT_ROOM}]
            assert sc.lists["rooms"]["values"] == []
            shutdown = sc.of("POST", "/shutdown")
            last_count = sc.of("PATCH", "/v1beta1/counters/users")[-1]
            assert len(shutdown) == 1 and shutdown[0].t - last_count.t >= 1.0
            assert sc.state == "Shutdown" and agent.state == "shutdown"
            assert [c for c in sc.calls if c.errors or c.status != 200] == []
    finally:
        for u in users:
            await u.leave()
        await asyncio.to_thread(agent.stop)
        await app.stop()


async def test_no_health_once_the_simulation_loop_is_dead():
    app = await start_app()
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        agent = start_agones(app.room_reports, AgonesOptions(**FAST), {PORT_ENV: str(sc.port)})
        assert agent is not None
        try:
            await until(lambda: len(sc.of("POST", "/health")) >= 2)
            assert app._sim_task is not None
            app._sim_task.cancel()  # the loop dies; the event loop and the agent go on
            withheld = agent.health_withheld
            await until(lambda: agent.health_withheld >= withheld + 1)
            pings = len(sc.of("POST", "/health"))
            await until(lambda: agent.health_withheld >= withheld + 3)
            assert len(sc.of("POST", "/health")) == pings
        finally:
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_the_rooms_list_and_users_counter_cover_every_room():
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1))
    app = ServerApp(
        Room(build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1)), SIM_RATE),
        "127.0.0.1",
        0,
        rooms={"lab": Room(world, SIM_RATE)},
    )
    await app.start()
    users: list[User] = []
    with Sidecar(lists={"rooms": 4}, counters={"users": 8}) as sc:
        options = AgonesOptions(empty_shutdown_s=None, **FAST)
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert isinstance(agent, AgonesAgent)
        try:
            await until(lambda: sc.state == "Ready")
            users.append(await User.join(app.port, "A", path="/rooms/lab/ws"))
            await until(lambda: sc.lists["rooms"]["values"] == ["lab"] and counts(sc)[-1:] == [1])
            users.append(await User.join(app.port, "B"))
            await until(lambda: counts(sc)[-1:] == [2])
            assert sorted(sc.lists["rooms"]["values"]) == sorted([DEFAULT_ROOM, "lab"])
            await users.pop(0).leave()  # lab empty: off the list, one user left
            # the list and the counter are two calls: wait for both
            await until(
                lambda: sc.lists["rooms"]["values"] == [DEFAULT_ROOM] and counts(sc)[-1] == 1
            )
        finally:
            for u in users:
                await u.leave()
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_a_ready_server_nobody_joined_waits_until_it_is_allocated():
    app = await start_app()
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        options = AgonesOptions(empty_shutdown_s=0.2, **FAST)
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert isinstance(agent, AgonesAgent)
        try:
            # it asks whether it was allocated, and stays up while it was not
            await until(lambda: len(sc.of("GET", "/gameserver")) >= 3)
            assert sc.of("POST", "/shutdown") == []
            sc.allocate()
            await until(lambda: sc.of("POST", "/shutdown"))
            assert sc.state == "Shutdown"
        finally:
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_haptic_server_reports_to_the_sidecar_named_by_the_environment(monkeypatch):
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        monkeypatch.setenv(PORT_ENV, str(sc.port))
        opts = ServerOptions(port=0, sim_rate_hz=SIM_RATE, subdivisions=2)
        server = asyncio.create_task(run_server(opts))
        try:
            await until(lambda: sc.of("POST", "/health") and len(sc.labels) == 2)
            assert sc.of("POST", "/ready") and sc.state == "Ready"
            assert sc.labels == {"agones.dev/sdk-object": "balloon", "agones.dev/sdk-protocol": "1"}
        finally:
            server.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await server
        assert [c for c in sc.calls if c.errors or c.status != 200] == []


async def test_a_port_that_is_not_a_number_stops_the_server_before_it_listens(monkeypatch):
    monkeypatch.setenv(PORT_ENV, "sidecar")
    opts = ServerOptions(port=0, sim_rate_hz=SIM_RATE, subdivisions=2)
    try:
        await run_server(opts)
    except ValueError as exc:
        assert PORT_ENV in str(exc)
    else:
        raise AssertionError("the server started with a bad sidecar port")


async def test_a_counter_the_fleet_does_not_declare_is_asked_for_once(caplog):
    app = await start_app()
    with Sidecar(lists={"rooms": 1}) as sc:  # no "users" counter in this GameServer
        agent = start_agones(app.room_reports, AgonesOptions(**FAST), {PORT_ENV: str(sc.port)})
        assert agent is not None
        try:
            await until(lambda: len(sc.of("POST", "/health")) >= 1)
            user = await User.join(app.port, "A")
            await until(lambda: len(sc.of("POST", "/health")) >= 3)
            await user.leave()
            patches = sc.of("PATCH", "/v1beta1/counters/users")
            assert [c.status for c in patches] == [404]
            assert sum("declares no 'users'" in r.getMessage() for r in caplog.records) == 1
            added = sc.of("POST", "/v1beta1/lists/rooms:addValue")  # the list still works
            assert [(c.body, c.status) for c in added] == [({"value": DEFAULT_ROOM}, 200)]
        finally:
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_no_health_while_a_room_process_is_hung_and_again_once_it_is_restarted(caplog):
    """A room in a process of its own whose process is stopped (alive, its loop going nowhere):
    no health ping from soon after it stops until the front has killed it and its new process
    ticks; the other room ticks on meanwhile."""
    opts = ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2, room_processes=True)
    link = LinkConditions()
    hung = room_proxy(opts, "b", {}, link, None, None)
    app = ServerApp(
        room_proxy(opts, DEFAULT_ROOM, {}, link, None, None), "127.0.0.1", 0, rooms={"b": hung}
    )
    await app.start()
    with Sidecar(lists={"rooms": 2}, counters={"users": 8}) as sc:
        agent = start_agones(app.room_reports, AgonesOptions(**FAST), {PORT_ENV: str(sc.port)})
        assert agent is not None
        health = lambda: len(sc.of("POST", "/health"))  # noqa: E731
        pid = hung.pid
        assert pid is not None
        try:
            await until(lambda: health() >= 2)
            withheld = agent.health_withheld
            os.kill(pid, signal.SIGSTOP)
            await until(lambda: agent.health_withheld > withheld)
            pings = health()
            await until(lambda: hung.hangs == 1)  # found hung and killed: no ping till now
            assert health() == pings
            default_ticks = app.status()["rooms"][DEFAULT_ROOM]["tick"]
            await until(lambda: hung.running and hung.pid != pid)
            await until(lambda: health() > pings)  # its new process ticks: pings again
            assert app.status()["rooms"][DEFAULT_ROOM]["tick"] > default_ticks
            assert hung.restarts == 1
            assert any("stalled or stopped (rooms b)" in r.getMessage() for r in caplog.records)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_a_name_the_allocation_listed_that_nobody_joined_leaves_the_list():
    """The lobby's allocation lists a room's name before its user arrives; a name whose user
    never came is removed after the grace, one whose user came stays."""
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1))
    app = ServerApp(
        Room(build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1)), SIM_RATE),
        "127.0.0.1",
        0,
        rooms={"lab": Room(world, SIM_RATE)},
    )
    await app.start()
    users: list[User] = []
    with Sidecar(lists={"rooms": 4}, counters={"users": 8}) as sc:
        # the grace is long enough for the user on its way to "lab" to join on a busy machine
        grace_s, check_s = 2.0, 0.1
        options = AgonesOptions(
            empty_shutdown_s=None, stale_room_grace_s=grace_s, list_check_s=check_s, **FAST
        )
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert isinstance(agent, AgonesAgent)

        def reads() -> list[Call]:
            return sc.of("GET", "/gameserver")

        def removed() -> list[str]:
            return [c.body["value"] for c in sc.of("POST", "/v1beta1/lists/rooms:removeValue")]

        try:
            await until(lambda: sc.state == "Ready")
            # two allocations by the lobby: "lab" (a user is on the way) and "ghost" (never)
            sc.allocate({"rooms": ["lab", "ghost"]})
            seen_at = len(sc.calls)
            await until(lambda: any(c.seq >= seen_at for c in reads()))  # the agent read them
            users.append(await User.join(app.port, "A", path="/rooms/lab/ws"))
            # the sidecar's list changes before the agent's POST returns and it counts it
            await until(
                lambda: "ghost" not in sc.lists["rooms"]["values"] and agent.stale_removed == 1
            )
            assert removed() == ["ghost"]
            # not at first sight: the agent read the list more than once before removing it
            (removal,) = sc.of("POST", "/v1beta1/lists/rooms:removeValue")
            assert len([c for c in reads() if seen_at <= c.seq < removal.seq]) >= 2
            # the room its user joined stays listed, past the grace, while the user is in it
            reads_then = len(reads())
            await until(lambda: len(reads()) >= reads_then + 1.5 * grace_s / check_s)
            assert sc.lists["rooms"]["values"] == ["lab"] and removed() == ["ghost"]
            # a name listed again after its users left (the lobby sent someone) is removed too
            await users.pop(0).leave()
            await until(lambda: sc.lists["rooms"]["values"] == [])
            assert removed() == ["ghost", "lab"]  # the agent's own removal, as before
            sc.allocate({"rooms": ["lab"]})
            await until(lambda: removed() == ["ghost", "lab", "lab"] and agent.stale_removed == 2)
        finally:
            for u in users:
                await u.leave()
            await asyncio.to_thread(agent.stop)
            await app.stop()
