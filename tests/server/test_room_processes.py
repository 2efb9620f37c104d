"""Rooms in processes of their own (``haptic server --room-processes``), as their users notice it.

A user of a room whose simulation runs in its own process feels the object and moves it; when
that process is killed (``kill -9``) its users get ``room_restarting`` and close code 1012, the
room can be joined again, and the users of another room keep getting their patches meanwhile; a
drain saves the room's state from its process. The real server in this process (ServerApp on a
free loopback port) with real room processes, and scripted websocket peers; every wait is
bounded, nothing is timed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from haptic_collab.server import snapshots
from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import (
    ProcessRoomTemplates,
    RoomTemplates,
    ServerOptions,
    build_world,
    room_proxy,
)
from haptic_collab.server.viewer_decoder import ViewerStreamDecoder
from haptic_collab.shared.protocol import PROTOCOL_VERSION, LinkConditions

SIM_RATE = 20.0


async def until(predicate: Callable[[], object], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def server(snapshot_dir: Path | None = None, **kw: Any) -> AsyncIterator[ServerApp]:
    """A server whose default room and room ``b`` each run in a process of their own."""
    opts = ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2, room_processes=True)
    link = LinkConditions()
    app = ServerApp(
        room_proxy(opts, DEFAULT_ROOM, {}, link, None, None),
        "127.0.0.1",
        0,
        rooms={"b": room_proxy(opts, "b", {}, link, None, None)},
        snapshot_dir=snapshot_dir,
        **kw,
    )
    await app.start()
    try:
        yield app
    finally:
        await app.stop()


class User:
    """A websocket user that keeps every text frame it gets and how its connection closed."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.texts: list[dict[str, Any]] = []
        self.reader = asyncio.create_task(self._read())
        self.seq = 0
        #: How far [m] below the top of the object its hand is (negative: above, no contact).
        self.depth_m = -0.005
        self.hand: asyncio.Task[None] | None = None

    async def _read(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            async for frame in self.ws:
                if isinstance(frame, str):
                    self.texts.append(json.loads(frame))

    @classmethod
    async def join(
        cls,
        port: int,
        name: str,
        path: str = "/ws",
        source: str = "127.0.0.1",
        resume: str | None = None,
    ) -> User:
        ws = await connect(f"ws://127.0.0.1:{port}{path}", local_addr=(source, 0))
        user = cls(ws)
        hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": "user", "name": name}
        if resume is not None:
            hello["resume"] = resume
        await ws.send(json.dumps(hello))
        await until(lambda: user.welcome is not None or user.errors(), 60.0)
        if user.welcome is not None:  # its hand reports a state every 25 ms, as a client's
            user.hand = asyncio.create_task(user._hand())
        return user

    async def _hand(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            while True:
                await self.push(self.depth_m)
                await asyncio.sleep(0.025)

    async def leave(self) -> None:
        if self.hand is not None:
            self.hand.cancel()
        await self.ws.close()

    @property
    def welcome(self) -> dict[str, Any] | None:
        return next((t for t in self.texts if t["type"] == "welcome"), None)

    def patches(self) -> list[dict[str, Any]]:
        return [t for t in self.texts if t["type"] == "patch"]

    def errors(self) -> list[dict[str, Any]]:
        return [t for t in self.texts if t["type"] == "error"]

    async def push(self, depth_m: float) -> None:
        """One ``state``: the hand ``depth_m`` below the top of the object, pushing down."""
        assert self.welcome is not None
        top = float(self.welcome["object"]["bounds_max_m"][2])
        self.seq += 1
        touching = depth_m > 0.0
        state = {
            "type": "state",
            "seq": self.seq,
            "probe_m": [0.0, 0.0, top - depth_m],
            "force_n": [0.0, 0.0, 2.0 if touching else 0.0],
            "penetration_m": max(0.0, depth_m),
            "in_contact": touching,
            "k_h": 400.0,
        }
        await self.ws.send(json.dumps(state))


def patch_top_z(patch: dict[str, Any]) -> float:
    """Where the patch's plane crosses the vertical axis [m] (the surface under the hand)."""
    prim = patch["primitive"]
    assert prim["kind"] == "plane"
    (px, py, pz), (nx, ny, nz) = prim["point"], prim["normal"]
    return float(pz + (nx * px + ny * py) / nz)


def room_pid(app: ServerApp, name: str) -> int:
    pid = app.status()["rooms"][name]["process"]["pid"]
    assert isinstance(pid, int) and pid != os.getpid()
    return pid


async def test_a_user_of_a_room_in_its_own_process_feels_and_moves_the_object() -> None:
    async with server() as app:
        assert room_pid(app, DEFAULT_ROOM) != room_pid(app, "b")
        user = await User.join(app.port, "ada")
        assert user.welcome is not None, user.errors()
        top = float(user.welcome["object"]["bounds_max_m"][2])
        await until(lambda: len(user.patches()) >= 3)

        assert patch_top_z(user.patches()[-1]) > top - 1e-4  # at rest
        user.depth_m = 0.006
        await until(lambda: patch_top_z(user.patches()[-1]) < top - 1e-3)  # pushed in
        # /status reads the room's process: one user, ticking
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["users"] == 1, 10.0)
        assert app.status()["rooms"][DEFAULT_ROOM]["tick"] > 0
        await user.leave()


async def test_a_killed_room_process_tells_its_users_restarts_and_spares_the_other_room(
    tmp_path,
) -> None:
    async with server(tmp_path) as app:
        victim = await User.join(app.port, "ada")
        other = await User.join(app.port, "bob", "/rooms/b/ws")
        await until(lambda: len(victim.patches()) >= 2 and len(other.patches()) >= 2)
        # long enough for checkpoints (every 2 s) well past the start
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["tick"] >= 100)
        pid = room_pid(app, DEFAULT_ROOM)
        before = len(other.patches())
        os.kill(pid, signal.SIGKILL)
        await asyncio.wait_for(victim.reader, 30.0)
        assert [e["code"] for e in victim.errors()] == ["room_restarting"]
        assert victim.ws.close_code == 1012
        # the room is back: a new join is welcomed and gets patches, from a new process
        again = await User.join(app.port, "ada")
        assert again.welcome is not None, again.errors()
        await until(lambda: len(again.patches()) >= 2)
        assert room_pid(app, DEFAULT_ROOM) != pid
        assert app.status()["rooms"][DEFAULT_ROOM]["process"]["restarts"] == 1
        # it started again from its last checkpoint (a room from rest starts at tick 0)
        assert (tmp_path / f"default.npz{snapshots.LOADED}").exists()
        assert app.status()["rooms"][DEFAULT_ROOM]["tick"] >= 60
        # the other room's user was never interrupted
        assert len(other.patches()) > before
        assert other.errors() == [] and other.ws.close_code is None
        for user in (again, other):
            await user.leave()


async def test_a_hung_room_process_is_killed_and_restarted_as_a_dead_one(tmp_path) -> None:
    """A room's process stopped (SIGSTOP: alive, its loop going nowhere, as in a solver that
    never returns) is found hung, killed and started again from its checkpoint; its users are
    told as for a dead one, the other room's user keeps its patches meanwhile."""
    async with server(tmp_path) as app:
        victim = await User.join(app.port, "ada")
        other = await User.join(app.port, "bob", "/rooms/b/ws")
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["tick"] >= 100)
        pid = room_pid(app, DEFAULT_ROOM)
        os.kill(pid, signal.SIGSTOP)
        try:
            # a patch the room sent before it stopped may still be on its way through the front
            await asyncio.sleep(0.5)
            before = len(other.patches())
            stopped_at = len(victim.patches())
            await asyncio.wait_for(victim.reader, 30.0)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)  # killed already, unless the test failed
        assert [e["code"] for e in victim.errors()] == ["room_restarting"]
        assert victim.ws.close_code == 1012
        assert len(victim.patches()) == stopped_at  # nothing came from the stopped room
        # the other room ticked on meanwhile: its user got patches the whole time
        assert len(other.patches()) > before + 20
        assert other.errors() == [] and other.ws.close_code is None
        await until(lambda: not _alive(pid), 10.0)  # the hung process is gone
        again = await User.join(app.port, "ada")
        assert again.welcome is not None, again.errors()
        await until(lambda: len(again.patches()) >= 2)
        process = app.status()["rooms"][DEFAULT_ROOM]["process"]
        assert process["pid"] != pid and process["restarts"] == 1 and process["hangs"] == 1
        assert app.status()["rooms"]["b"]["process"]["hangs"] == 0
        assert app.status()["rooms"][DEFAULT_ROOM]["tick"] >= 60  # from its checkpoint
        for user in (again, other):
            await user.leave()


async def test_users_keep_their_seats_across_a_restart_of_their_rooms_process() -> None:
    """After their room's process was killed, its users who join again with their resume
    tokens get their user ids and names (the viewers' colours) back; a newcomer gets a new id,
    and a token from before the last welcome is used up."""
    async with server() as app:
        ada = await User.join(app.port, "ada")
        bob = await User.join(app.port, "bob")
        first_ada = ada.welcome
        assert first_ada is not None and bob.welcome is not None
        # ada's link drops and she resumes once before the crash: her token rotates
        await ada.leave()
        ada = await User.join(app.port, "ada", resume=first_ada["resume_token"])
        assert ada.welcome is not None and ada.welcome["resumed"]
        await until(lambda: len(ada.patches()) >= 2 and len(bob.patches()) >= 2)
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["resumes"] == 1, 10.0)
        os.kill(room_pid(app, DEFAULT_ROOM), signal.SIGKILL)
        for user in (ada, bob):
            await asyncio.wait_for(user.reader, 30.0)
            assert [e["code"] for e in user.errors()] == ["room_restarting"]

        old = await User.join(app.port, "ada", resume=first_ada["resume_token"])
        assert old.welcome is not None and not old.welcome["resumed"]  # used up before
        assert old.welcome["name"] == "ada-2"  # ada's seat is still held for her
        ada2 = await User.join(app.port, "ada", resume=ada.welcome["resume_token"])
        bob2 = await User.join(app.port, "bob", resume=bob.welcome["resume_token"])
        for before, after in ((ada, ada2), (bob, bob2)):
            assert before.welcome is not None and after.welcome is not None
            assert after.welcome["resumed"], after.errors()
            assert after.welcome["user_id"] == before.welcome["user_id"]
            assert after.welcome["name"] == before.welcome["name"]
            await until(lambda u=after: len(u.patches()) >= 2)  # type: ignore[misc]
        ids = {first_ada["user_id"], bob.welcome["user_id"], old.welcome["user_id"]}
        assert len(ids) == 3  # the newcomer's id is none of the seats'
        # /status counts the resumes of both processes (one before the kill, two after)
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["resumes"] == 3, 10.0)
        for user in (old, ada2, bob2):
            await user.leave()


async def test_a_drain_saves_each_room_from_its_process_and_it_resumes_there(tmp_path) -> None:
    async with server(tmp_path) as app:
        user = await User.join(app.port, "ada")
        assert user.welcome is not None
        top = float(user.welcome["object"]["bounds_max_m"][2])
        await until(lambda: len(user.patches()) >= 2)
        user.depth_m = 0.006
        await until(lambda: patch_top_z(user.patches()[-1]) < top - 1e-3)
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["tick"] >= 40)
        report = await app.drain(5.0)
        await asyncio.wait_for(user.reader, 10.0)
        assert [e["code"] for e in user.errors()] == ["server_draining"]
        assert user.ws.close_code == 1012
        assert sorted(p.name for p in report.snapshots) == ["b.npz", "default.npz"]
        snap = snapshots.read(tmp_path / "default.npz")
        assert snap.tick >= 40
    # a server started again resumes the pressed room in the room's new process: its tick goes
    # on from the snapshot's (a room from rest starts at 0) and the file is consumed
    async with server(tmp_path) as app:
        await until(lambda: app.status()["rooms"][DEFAULT_ROOM]["tick"] > 0, 30.0)
        assert app.status()["rooms"][DEFAULT_ROOM]["tick"] >= snap.tick
        assert (tmp_path / f"default.npz{snapshots.LOADED}").exists()


def test_sigterm_saves_every_room_from_its_process_and_leaves_no_process(tmp_path) -> None:
    """``haptic server --room-processes`` stopped by a real SIGTERM, as Kubernetes stops it."""
    snaps = tmp_path / "snapshots"
    log = tmp_path / "server.log"
    env = dict(os.environ, PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1")
    cmd = [
        sys.executable, "-m", "haptic_collab.cli", "server", "--host", "127.0.0.1",
        "--port", "0", "--subdivisions", "2", "--snapshot-dir", str(snaps),
        "--drain-grace-s", "10", "--room-processes",
    ]  # fmt: skip
    with open(log, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=env)
    try:
        assert proc.stdout is not None
        port = None
        for line in proc.stdout:
            m = re.search(r"viewer: http://127\.0\.0\.1:(\d+)/", line)
            if m:
                port = int(m.group(1))
                break
        assert port is not None, log.read_text()[-2000:]

        async def session() -> tuple[User, int]:
            user = await User.join(port, "ada")
            assert user.welcome is not None
            top = float(user.welcome["object"]["bounds_max_m"][2])
            await until(lambda: len(user.patches()) >= 2)
            user.depth_m = 0.006
            await until(lambda: patch_top_z(user.patches()[-1]) < top - 1e-3)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as res:
                pid = int(json.loads(res.read())["rooms"][DEFAULT_ROOM]["process"]["pid"])
            proc.send_signal(signal.SIGTERM)  # while the user still presses
            await asyncio.wait_for(user.reader, 10.0)
            return user, pid

        user, room_pid_ = asyncio.run(session())
        assert proc.wait(30) == 0  # a clean exit
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert user.ws.close_code == 1012
    assert [e["code"] for e in user.errors()] == ["server_draining"]
    snap = snapshots.read(snaps / "default.npz")
    rest = np.array(build_world(ServerOptions(subdivisions=2)).vertices)
    assert np.max(np.abs(snap.vertices - rest)) > 1e-3  # saved while pressed, by its process
    with pytest.raises(ProcessLookupError):  # the room's process is gone with the server
        os.kill(room_pid_, 0)


async def test_status_metrics_and_agones_reports_read_the_room_processes() -> None:
    async with server() as app:
        user = await User.join(app.port, "ada", "/rooms/b/ws")
        await until(lambda: len(user.patches()) >= 5)
        await until(lambda: app.status()["rooms"]["b"]["users"] == 1, 10.0)

        def metrics() -> dict[tuple[str, str], float]:
            url = f"http://127.0.0.1:{app.port}/metrics"
            with urllib.request.urlopen(url, timeout=10) as res:
                text = res.read().decode()
            out = {}
            for fam in text_string_to_metric_families(text):
                for s in fam.samples:
                    if "room" in s.labels and "le" not in s.labels:
                        out[(s.name, s.labels["room"])] = s.value
            return out

        seen = await asyncio.to_thread(metrics)
        assert seen[("haptic_room_users", "b")] == 1
        assert seen[("haptic_room_ticks_total", "b")] > 0
        assert seen[("haptic_room_tick_lateness_seconds_count", "b")] > 0
        assert seen[("haptic_room_patches_sent_total", "b")] >= 5
        reports = {r.name: r for r in app.room_reports()}
        assert reports["b"].alive and reports["b"].users == 1 and reports[DEFAULT_ROOM].alive
        # while a room's process is dead its report says so (no Health ping); back after
        os.kill(room_pid(app, "b"), signal.SIGKILL)
        await until(lambda: not {r.name: r for r in app.room_reports()}["b"].alive, 10.0)
        assert {r.name: r for r in app.room_reports()}[DEFAULT_ROOM].alive
        await until(lambda: {r.name: r for r in app.room_reports()}["b"].alive, 60.0)
        after = await asyncio.to_thread(metrics)  # the histograms go on across the restart
        count = "haptic_room_tick_lateness_seconds_count", "b"
        assert after[count] >= seen[count]
        assert after[("haptic_room_patches_sent_total", "b")] >= 5
        await user.leave()


async def test_a_room_made_on_demand_runs_in_its_own_process_and_closes_when_idle() -> None:
    opts = ServerOptions(
        sim_rate_hz=SIM_RATE,
        subdivisions=2,
        room_processes=True,
        room_templates={"class": {"prefix": "class-", "subdivisions": 1}},
    )
    link = LinkConditions()
    templates = ProcessRoomTemplates(RoomTemplates(opts, opts.room_templates, link, None, None))
    app = ServerApp(
        room_proxy(opts, DEFAULT_ROOM, {}, link, None, None),
        "127.0.0.1",
        0,
        room_maker=templates,
        room_idle_s=1.0,
    )
    await app.start()
    try:
        user = await User.join(app.port, "ada", "/rooms/class-3/ws")
        assert user.welcome is not None, user.errors()
        assert user.welcome["object"]["n_vertices"] == 42  # the template's: subdivisions 1
        await until(lambda: len(user.patches()) >= 2)
        pid = room_pid(app, "class-3")
        assert pid != room_pid(app, DEFAULT_ROOM)
        await user.leave()
        await until(lambda: "class-3" not in app.status()["rooms"], 30.0)
        await until(lambda: not _alive(pid), 10.0)  # its process ended with it
    finally:
        await app.stop()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with contextlib.suppress(OSError):  # a zombie not yet reaped by its parent is gone too
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    return True


async def test_a_viewer_of_a_room_in_its_own_process_sees_the_press_and_the_release() -> None:
    """The viewers' binary surface stream crosses the front too, with its acknowledgements."""
    async with server() as app:
        ws = await connect(f"ws://127.0.0.1:{app.port}/rooms/b/ws")
        decoder = ViewerStreamDecoder()
        sizes: list[int] = []
        hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": "viewer", "name": "v"}
        await ws.send(json.dumps(hello))

        async def watch() -> None:
            with contextlib.suppress(ConnectionClosed):
                async for frame in ws:
                    if isinstance(frame, bytes):
                        decoder.feed(frame)
                        sizes.append(len(frame))

        watcher = asyncio.create_task(watch())
        user = await User.join(app.port, "ada", "/rooms/b/ws")
        await until(lambda: decoder.frames >= 3 and decoder.tick > 0)
        assert float(np.max(np.abs(decoder.w))) < 1e-4  # at rest
        user.depth_m = 0.006
        await until(lambda: float(np.min(decoder.w)) < -1e-3)  # the press, seen
        user.depth_m = -0.005
        await until(lambda: float(np.max(np.abs(decoder.w))) < 1e-4)  # and the release
        # at rest again, and the server knows what the viewer holds (the front tells the room's
        # process which frames were written): its frames shrink to the bare 20-byte header
        await until(lambda: len(sizes) > 5 and set(sizes[-5:]) == {20}, 30.0)
        await user.leave()
        await ws.close()
        watcher.cancel()


async def test_a_room_whose_process_cannot_build_it_stops_the_start_and_says_why() -> None:
    opts = ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2, room_processes=True)
    link = LinkConditions()
    bad = room_proxy(opts, "b", {"mesh": "/nonexistent/mesh.obj"}, link, None, None)
    app = ServerApp(
        room_proxy(opts, DEFAULT_ROOM, {}, link, None, None), "127.0.0.1", 0, rooms={"b": bad}
    )
    with pytest.raises(RuntimeError, match="room 'b'"):
        await app.start()
    assert not bad.running and not app.room.running  # every room's process was stopped


class CountingPool(ThreadPoolExecutor):
    """The front's design worker, counting the jobs it was given."""

    def __init__(self) -> None:
        super().__init__(max_workers=1)
        self.jobs = 0

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Any:
        self.jobs += 1
        return super().submit(fn, *args, **kwargs)


@pytest.mark.slow  # a room process and a design
async def test_gains_for_a_room_in_its_own_process_are_designed_by_the_front() -> None:
    pool = CountingPool()
    try:
        async with server(gain_executor=pool) as app:
            ws = await connect(f"ws://127.0.0.1:{app.port}/ws")
            user = User(ws)
            device = {  # not a shipped table's device: its gains must be designed
                "profile": "odd",
                "max_force_n": 7.9,
                "max_stiffness_n_per_m": 730.0,
                "max_damping_n_s_per_m": 7.0,
            }
            hello = {
                "type": "hello",
                "protocol": PROTOCOL_VERSION,
                "role": "user",
                "name": "ada",
                "local_model": "pi",
                "device": device,
            }
            await ws.send(json.dumps(hello))
            await until(lambda: user.welcome is not None)
            user.depth_m = 0.004
            user.hand = asyncio.create_task(user._hand())
            await until(lambda: any(p.get("gains") for p in user.patches()), 120.0)
            assert pool.jobs >= 1  # the room's process asked, the front's worker answered
            await user.leave()
    finally:
        pool.shutdown(wait=True)


async def test_a_room_in_its_own_process_budgets_each_clients_real_address() -> None:
    """The room's per-address budgets see each client's own address through the front: eight
    connections waiting for ``hello`` from one address fill its share, not another's."""
    async with server() as app:
        url = f"ws://127.0.0.1:{app.port}/rooms/b/ws"
        waiting = [await connect(url, local_addr=("127.0.0.1", 0)) for _ in range(8)]
        ninth = User(await connect(url, local_addr=("127.0.0.1", 0)))
        await asyncio.wait_for(ninth.reader, 30.0)
        assert [e["code"] for e in ninth.errors()] == ["too_many_pending"]
        other = await User.join(app.port, "bob", "/rooms/b/ws", source="127.0.0.2")
        assert other.welcome is not None, other.errors()
        for ws in waiting:
            await ws.close()
        await other.leave()


def test_seats_held_from_a_previous_process_run_out_after_the_hold() -> None:
    """Sans-I/O: a room given the seats of its previous process (``Room.hold_seats``) gives
    a seat back within ``RESUME_HOLD_S`` of its start, and not after; new ids go on."""
    from haptic_collab.server.room import RESUME_HOLD_S, Room
    from tests.support.rooms import RecordingWorld, hello, texts

    def welcome(room: Room, conn: str, frame: str, now_s: float) -> dict[str, Any]:
        room.connect(conn, now_s)
        (msg,) = texts(room.receive(conn, frame, now_s), conn)
        assert msg["type"] == "welcome", msg
        return msg

    def resume(name: str, token: str) -> str:
        msg = json.loads(hello(name))
        msg["resume"] = token
        return json.dumps(msg)

    old = Room(RecordingWorld(), SIM_RATE)
    ada, bob = welcome(old, "c1", hello("ada"), 0.0), welcome(old, "c2", hello("bob"), 0.0)
    records = old.seat_records()
    assert "resume_token" not in repr(records) and ada["resume_token"] not in repr(records)

    for start in (100.0, 200.0):
        new = Room(RecordingWorld(), SIM_RATE)
        new.hold_seats(*records, start)
        assert sorted(new.held_seats) == sorted([ada["user_id"], bob["user_id"]])
        late = start + (RESUME_HOLD_S + 1.0 if start == 200.0 else RESUME_HOLD_S - 1.0)
        back = welcome(new, "c9", resume("ada", ada["resume_token"]), late)
        if start == 100.0:  # within the hold: her seat
            assert back["resumed"] and back["user_id"] == ada["user_id"] and back["name"] == "ada"
        else:  # after it: a new user, with an id no seat of the old room had
            assert not back["resumed"] and back["name"] == "ada"
            assert back["user_id"] not in (ada["user_id"], bob["user_id"])
