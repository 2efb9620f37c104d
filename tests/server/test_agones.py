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

from haptic_collab.server.agones import (
    PORT_ENV,
    AgonesAgent,
    AgonesOptions,
    AgonesSDK,
    start_agones,
)
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
            # every open room is listed, empty or not: the list's free capacity is the rooms
            # this server can still open
            await until(lambda: sc.lists["rooms"]["values"] == [DEFAULT_ROOM])
            added = sc.of("POST", "/v1beta1/lists/rooms:addValue")
            assert [c.body for c in added] == [{"value": DEFAULT_ROOM}]
            assert sc.of("POST", "/ready")[0].seq < added[0].seq

            users.append(await User.join(app.port, "A"))
            # the first arrival: the server Allocated (no scale-down), the counter at 1
            await until(lambda: counts(sc)[-1] == 1 and sc.state == "Allocated")
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
            # the default room stays open, so listed, once empty
            assert sc.of("POST", "/v1beta1/lists/rooms:removeValue") == []
            assert sc.lists["rooms"]["values"] == [DEFAULT_ROOM]
            assert len(sc.of("POST", "/v1beta1/lists/rooms:addValue")) == 1
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


class AnyName:
    """Rooms on demand of any name (a ``[room_templates]`` with prefix "")."""

    def allows(self, name: str) -> bool:
        return True

    def build(self, name: str) -> Room:
        return Room(build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1)), SIM_RATE)


async def test_the_rooms_list_holds_every_open_room_and_the_counter_every_user():
    """The list is what the server runs, empty rooms too, until they close; its free capacity
    is the rooms the server can still open."""
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1))
    app = ServerApp(
        Room(build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1)), SIM_RATE),
        "127.0.0.1",
        0,
        rooms={"lab": Room(world, SIM_RATE)},
        room_maker=AnyName(),
        room_idle_s=0.5,
        max_rooms=4,
    )
    await app.start()
    users: list[User] = []
    with Sidecar(lists={"rooms": 4}, counters={"users": 8}) as sc:
        options = AgonesOptions(empty_shutdown_s=None, **FAST)
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert isinstance(agent, AgonesAgent)
        app.room_gate = lambda name: asyncio.to_thread(agent.claim_room, name)
        listed = lambda: sorted(sc.lists["rooms"]["values"])  # noqa: E731
        try:
            await until(lambda: sc.state == "Ready")
            # nobody in them: both open rooms listed
            await until(lambda: listed() == sorted([DEFAULT_ROOM, "lab"]))
            users.append(await User.join(app.port, "A", path="/rooms/lab/ws"))
            users.append(await User.join(app.port, "B", path="/rooms/made/ws"))
            await until(lambda: counts(sc)[-1:] == [2])
            assert listed() == sorted([DEFAULT_ROOM, "lab", "made"])
            # the room made on demand was listed before it was built (claimed); the agent's
            # own add after it is answered "already exists" (HTTP 500), taken as done
            made = [
                c
                for c in sc.of("POST", "/v1beta1/lists/rooms:addValue")
                if c.body["value"] == "made"
            ]
            assert [c.status for c in made] == [200, 500]
            await users.pop(0).leave()  # lab empty: still open, still listed
            await until(lambda: counts(sc)[-1] == 1)
            assert listed() == sorted([DEFAULT_ROOM, "lab", "made"])
            await users.pop(0).leave()  # made empty: closed after room_idle_s, then unlisted
            await until(lambda: listed() == sorted([DEFAULT_ROOM, "lab"]))
            assert "made" not in app.rooms()
            assert [c for c in sc.calls if c.errors or c.status != 200] == made[1:]
        finally:
            for u in users:
                await u.leave()
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_a_full_rooms_list_refuses_the_new_room_once_and_never_loops(caplog):
    """The lobby's allocation listed a name (the user is on its way), the list is full: the
    listed name's room opens, another name is refused 503 with one log line, and the agent
    does not retry; the real sidecar's refusals (HTTP 500 and its text) are read as meant."""
    app = ServerApp(
        Room(build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=1)), SIM_RATE),
        "127.0.0.1",
        0,
        room_maker=AnyName(),
        max_rooms=3,  # one more than the list holds: the list decides here
    )
    await app.start()
    users: list[User] = []
    with Sidecar(lists={"rooms": 2}, counters={"users": 8}) as sc:
        options = AgonesOptions(empty_shutdown_s=None, list_check_s=0.1, **FAST)
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert isinstance(agent, AgonesAgent)
        app.room_gate = lambda name: asyncio.to_thread(agent.claim_room, name)
        adds = lambda: sc.of("POST", "/v1beta1/lists/rooms:addValue")  # noqa: E731
        try:
            await until(lambda: sc.lists["rooms"]["values"] == [DEFAULT_ROOM])
            sc.allocate({"rooms": ["anatomy"]})  # full now: [default, anatomy]
            users.append(await User.join(app.port, "A", path="/rooms/anatomy/ws"))
            try:
                await User.join(app.port, "B", path="/rooms/other/ws")
            except Exception as exc:  # refused at the handshake
                assert "503" in str(exc), exc
            else:
                raise AssertionError("a room opened past the rooms list's capacity")
            assert sorted(app.rooms()) == sorted([DEFAULT_ROOM, "anatomy"])
            # the agent goes on (many list checks), and never asks for either name again
            reads = len(sc.of("GET", "/gameserver"))
            await until(lambda: len(sc.of("GET", "/gameserver")) >= reads + 10)
            values = [c.body["value"] for c in adds()]
            assert values.count("other") == 1 and values.count("anatomy") <= 2
            assert {c.status for c in adds() if c.status != 200} <= {500}
            assert sorted(sc.lists["rooms"]["values"]) == sorted([DEFAULT_ROOM, "anatomy"])
            refusals = [r for r in caplog.records if "room 'other' refused" in r.getMessage()]
            assert len(refusals) == 1 and "list is full" in refusals[0].getMessage()
            assert (
                agent.refused_rooms == 1 and sc.of("POST", "/v1beta1/lists/rooms:removeValue") == []
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
            assert [c.status for c in patches] == [500]  # "counter not found: users"
            assert sum("declares no 'users'" in r.getMessage() for r in caplog.records) == 1
            added = sc.of("POST", "/v1beta1/lists/rooms:addValue")  # the list still works
            assert [(c.body, c.status) for c in added] == [({"value": DEFAULT_ROOM}, 200)]
        finally:
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_a_hung_room_process_is_restarted_and_health_goes_on_meanwhile(caplog):
    """A room in a process of its own whose process is stopped (alive, its loop going nowhere):
    the front kills and restarts it while the other room ticks on, and the health pings go on
    throughout (one room's trouble must not have Agones delete the GameServer and every room
    with it); the log says which room was late."""
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
            await until(lambda: health() >= 2 and agent.state == "ready")
            os.kill(pid, signal.SIGSTOP)
            late = lambda: any("rooms b late" in r.getMessage() for r in caplog.records)  # noqa: E731
            await until(late)
            pings = health()
            await until(lambda: hung.hangs == 1)  # found hung and killed
            await until(lambda: health() >= pings + 2)  # pings while b is down
            default_ticks = app.status()["rooms"][DEFAULT_ROOM]["tick"]
            await until(lambda: hung.running and hung.pid != pid)
            # the other room ticks on (on a loaded machine b may be back before its next report)
            await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["tick"] > default_ticks)
            assert hung.restarts == 1 and agent.health_withheld == 0
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_a_name_the_allocation_listed_that_nobody_joined_leaves_the_list():
    """The lobby's allocation lists a room's name before its user arrives; a name whose user
    never came (no room of that name opened) is removed after the grace, open rooms stay."""
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
            # the open rooms stay listed past the grace
            reads_then = len(reads())
            await until(lambda: len(reads()) >= reads_then + 1.5 * grace_s / check_s)
            assert sorted(sc.lists["rooms"]["values"]) == sorted([DEFAULT_ROOM, "lab"])
            assert removed() == ["ghost"]
            # an open room stays listed once empty: it is still a room of this server
            await users.pop(0).leave()
            reads_then = len(reads())
            await until(lambda: len(reads()) >= reads_then + 1.5 * grace_s / check_s)
            assert sorted(sc.lists["rooms"]["values"]) == sorted([DEFAULT_ROOM, "lab"])
            assert removed() == ["ghost"] and agent.stale_removed == 1
        finally:
            for u in users:
                await u.leave()
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_health_pings_start_before_ready_while_the_server_is_still_starting():
    """A server building its rooms (a FEM solid took 30 s on a loaded machine) is not Ready yet
    but pings from the start: Agones checks health from ``initialDelaySeconds`` on."""
    loop = asyncio.get_running_loop()
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        agent = AgonesAgent(
            AgonesSDK(sc.port, "127.0.0.1"), loop, lambda: [], AgonesOptions(**FAST)
        )
        agent.start()  # no room yet: what run_server's probe says before its app exists
        try:
            await until(lambda: len(sc.of("POST", "/health")) >= 3)
            assert sc.of("POST", "/ready") == [] and agent.state == "starting"
        finally:
            await asyncio.to_thread(agent.stop)
    # past the start grace without Ready: no more pings (Agones replaces the server)
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        options = AgonesOptions(start_grace_s=0.0, **FAST)
        agent = AgonesAgent(AgonesSDK(sc.port, "127.0.0.1"), loop, lambda: [], options)
        agent.start()
        try:
            await until(lambda: agent.health_withheld >= 3)
            assert sc.of("POST", "/health") == []
        finally:
            await asyncio.to_thread(agent.stop)


async def test_a_sidecar_slow_to_answer_a_list_call_does_not_delay_health():
    """The list update waits in the sidecar (held, as a slow sidecar's would); the health
    pings go on meanwhile, from their own thread."""
    app = await start_app()
    with Sidecar(lists={"rooms": 1}, counters={"users": 8}) as sc:
        path = "/v1beta1/lists/rooms:addValue"
        gate = sc.hold(path)
        agent = start_agones(app.room_reports, AgonesOptions(**FAST), {PORT_ENV: str(sc.port)})
        assert agent is not None
        try:
            await until(lambda: sc.held.get(path, 0) == 1)  # the agent's addValue is waiting
            pings = len(sc.of("POST", "/health"))
            await until(lambda: len(sc.of("POST", "/health")) >= pings + 3)
            assert sc.of("POST", path) == []  # still not answered
            gate.set()
            await until(lambda: sc.lists["rooms"]["values"] == [DEFAULT_ROOM])
        finally:
            gate.set()
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_capacities_that_are_not_the_servers_are_said_once_and_a_full_counter_not_retried(
    caplog,
):
    """A Fleet whose list or counter capacity is not what the server takes is said at Ready;
    users past the counter's capacity are said once, and the count is not sent again until it
    changes (the real sidecar refuses it: "out of range", HTTP 500)."""
    app = await start_app()
    with Sidecar(lists={"rooms": 4}, counters={"users": 1}) as sc:
        options = AgonesOptions(empty_shutdown_s=None, max_rooms=3, max_users=1, **FAST)
        agent = start_agones(app.room_reports, options, {PORT_ENV: str(sc.port)})
        assert agent is not None
        users: list[User] = []
        try:
            await until(lambda: agent.state == "ready" and counts(sc) == [0])
            said = [r.getMessage() for r in caplog.records if "one number" in r.getMessage()]
            assert (
                len(said) == 1 and "'rooms' list has capacity 4 but this server takes 3" in said[0]
            )
            users.append(await User.join(app.port, "A"))
            users.append(await User.join(app.port, "B"))
            await until(lambda: counts(sc)[-1] == 2)  # asked once, refused
            health = len(sc.of("POST", "/health"))
            await until(lambda: len(sc.of("POST", "/health")) >= health + 4)
            patches = sc.of("PATCH", "/v1beta1/counters/users")
            assert [(int(c.body["count"]), c.status) for c in patches] == [(0, 200), (2, 500)]
            full = [r for r in caplog.records if "cannot hold 2 users" in r.getMessage()]
            assert len(full) == 1
            await users.pop().leave()  # one user: the count changed, it is sent and taken
            await until(lambda: counts(sc)[-1] == 1 and sc.counters["users"]["count"] == 1)
        finally:
            for u in users:
                await u.leave()
            await asyncio.to_thread(agent.stop)
            await app.stop()


async def test_haptic_server_under_agones_refuses_a_room_its_rooms_list_has_no_slot_for(
    monkeypatch, caplog
):
    """``haptic server`` (run_server) wires the agent's claim in before a room is built: a
    Fleet whose list holds fewer rooms than --max-rooms gets its own number, not the server's."""
    with Sidecar(lists={"rooms": 1}, counters={"users": 64}) as sc:
        monkeypatch.setenv(PORT_ENV, str(sc.port))
        opts = ServerOptions(
            port=0,
            sim_rate_hz=SIM_RATE,
            subdivisions=1,
            room_templates={"any": {}},
            max_rooms=2,
            tick_priority="off",
        )
        started: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        server = asyncio.create_task(run_server(opts, on_ready=started.set_result))
        try:
            port = await asyncio.wait_for(asyncio.shield(started), 60.0)
            await until(lambda: sc.lists["rooms"]["values"] == [DEFAULT_ROOM])
            try:
                await User.join(port, "A", path="/rooms/lab/ws")
            except Exception as exc:
                assert "503" in str(exc), exc
            else:
                raise AssertionError("a room opened that the rooms list has no slot for")
            assert sc.lists["rooms"]["values"] == [DEFAULT_ROOM]
            assert any("room 'lab' refused" in r.getMessage() for r in caplog.records)
            assert any(
                "capacity 1 but this server takes 2" in r.getMessage() for r in caplog.records
            )
        finally:
            server.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await server
