"""Drain and persistence: what users and operators notice when a server is stopped (SIGTERM).

Every client connected gets ``error`` ``server_draining`` and then close code 1012 (service
restart); a connection opened during the drain gets the same; each room's object state is saved
(``--snapshot-dir``), and a room made again from it shows the same surface; a snapshot of another
object, a corrupt one or one of another format version is refused and the room starts from rest.
Real websockets on loopback, the server in this process (through :meth:`ServerApp.drain`, what
the signal handler calls) and once as a process of its own, stopped by a real SIGTERM.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from haptic_collab.server import snapshots
from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import RoomTemplates, ServerOptions, build_room, build_world
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import LinkConditions

SIM_RATE = 20.0
ROOT = Path(__file__).resolve().parents[2]


async def until(predicate: Callable[[], object], timeout_s: float = 60.0) -> None:
    """Let the event loop (and the server on it) run until ``predicate()`` holds."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.02)


def options(**changes: object) -> ServerOptions:
    keys: dict[str, object] = {"sim_rate_hz": SIM_RATE, "subdivisions": 2, **changes}
    return ServerOptions(**keys)  # type: ignore[arg-type]


async def start_app(
    snapshot_dir: Path, opts: ServerOptions | None = None, **kw: object
) -> ServerApp:
    world = build_world(opts or options())
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0, snapshot_dir=snapshot_dir, **kw)  # type: ignore[arg-type]
    await app.start()
    return app


class Client:
    """A websocket client that keeps every text frame it gets and how its connection closed."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.texts: list[dict[str, object]] = []
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            async for frame in self.ws:
                if isinstance(frame, str):
                    self.texts.append(json.loads(frame))

    @classmethod
    async def join(
        cls, port: int, name: str, role: str = "user", path: str = "/ws", hello: bool = True
    ) -> Client:
        ws = await connect(f"ws://127.0.0.1:{port}{path}")
        client = cls(ws)
        if hello:
            await ws.send(json.dumps({"type": "hello", "protocol": 1, "role": role, "name": name}))
            await until(lambda: any(t["type"] == "welcome" for t in client.texts), 30.0)
        return client

    async def closed(self) -> None:
        """Wait until the server closed the connection (bounded by the drain's own grace)."""
        await asyncio.wait_for(self.reader, 10.0)

    def errors(self) -> list[dict[str, object]]:
        return [t for t in self.texts if t["type"] == "error"]


async def press(client: Client, app: ServerApp, depth_m: float = 0.006) -> None:
    """Press into the top of the default room's object until its surface has moved 1 mm."""
    top = float(app.room.world.rest_bounds[1][2])
    seq = 0

    async def send() -> None:
        nonlocal seq
        seq += 1
        state = {
            "type": "state",
            "seq": seq,
            "probe_m": [0.0, 0.0, top - depth_m],
            "force_n": [0.0, 0.0, 2.0],
            "penetration_m": depth_m,
            "in_contact": True,
            "k_h": 400.0,
        }
        await client.ws.send(json.dumps(state))

    deadline = time.monotonic() + 30.0
    while app.room.world.obj.max_displacement_m < 1e-3:
        assert time.monotonic() < deadline, "the press never moved the surface"
        await send()
        await asyncio.sleep(0.02)


async def test_connected_clients_are_told_server_draining_then_closed_with_1012(tmp_path):
    app = await start_app(tmp_path)
    try:
        user = await Client.join(app.port, "A")
        viewer = await Client.join(app.port, "V", role="viewer")
        waiting = await Client.join(app.port, "W", hello=False)  # no hello yet
        await press(user, app)
        report = await app.drain()
        for client in (user, viewer, waiting):
            await client.closed()
            assert client.ws.close_code == 1012  # service restart
            last = client.texts[-1]  # the last thing it heard before the close
            assert last["type"] == "error" and last["code"] == "server_draining"
            assert last["fatal"] is True and "shutting down" in str(last["message"])
        assert report.told == 3 and report.left_open == 0  # they all closed within the grace
        assert app.status()["draining"] is True
    finally:
        await app.stop()


async def test_a_connection_during_the_drain_is_refused_and_no_room_is_made(tmp_path):
    opts = options()
    templates = RoomTemplates(opts, {"lab": {"prefix": "lab-"}}, LinkConditions(), None, None)
    app = await start_app(tmp_path, opts, room_maker=templates)
    try:
        await app.drain()
        for path in ("/ws", "/rooms/lab-new/ws"):
            late = await Client.join(app.port, "late", path=path, hello=False)
            hello = {"type": "hello", "protocol": 1, "role": "user", "name": "L"}
            with contextlib.suppress(ConnectionClosed):  # it may be closed already
                await late.ws.send(json.dumps(hello))
            await late.closed()
            assert late.ws.close_code == 1012
            assert [t["code"] for t in late.texts] == ["server_draining"]  # never welcomed
        assert list(app.rooms()) == [DEFAULT_ROOM]  # the on-demand room was never built
    finally:
        await app.stop()


async def test_a_room_made_again_from_its_snapshot_shows_the_same_surface(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="haptic.server")
    app = await start_app(tmp_path)
    try:
        user = await Client.join(app.port, "A")
        await press(user, app)
        report = await app.drain()
        pressed = np.array(app.room.world.vertices)  # the surface when the server stopped
        tick = app.room.tick_count
    finally:
        await app.stop()
    assert report.snapshots == (tmp_path / "default.npz",)
    rest = np.array(build_world(options()).vertices)
    assert np.max(np.abs(pressed - rest)) > 1e-3  # the press had moved it

    again = await start_app(tmp_path)
    try:
        shown = np.array(again.room.world.vertices)
        assert np.max(np.abs(shown - pressed)) == 0.0  # the same surface, to the bit
        assert again.room.tick_count == tick  # the tick numbers go on
    finally:
        await again.stop()
    assert any("started from snapshot" in r.getMessage() for r in caplog.records)
    # consumed: a third start does not bring the old state back
    assert sorted(p.name for p in tmp_path.iterdir()) == ["default.npz.loaded"]
    third = await start_app(tmp_path)
    try:
        assert np.max(np.abs(np.array(third.room.world.vertices) - rest)) == 0.0
    finally:
        await third.stop()


def test_a_fem_solid_resumes_its_displacement_and_velocity(tmp_path):
    opts = options(object="fem", volume_cache=str(tmp_path / "volumes"))
    room = build_room(opts, "liver", {}, LinkConditions(), None, None)
    world = room.world
    top = world.rest_bounds[1]
    key = world.obj.patch_key([0.0, 0.0, top[2]], normal=[0.0, 0.0, 1.0])
    for _ in range(3):  # pushed for three ticks: the solid is moving when it is saved
        world.obj.step([key], [2.0])
    room.restored(3)
    snap = snapshots.capture("liver", room)
    snapshots.write(tmp_path, snap)
    assert np.max(np.abs(snap.state["modal_v"])) > 1e-4  # moving: a velocity to keep [m/s]

    other = build_room(opts, "liver", {}, LinkConditions(), None, None)
    assert snapshots.restore(tmp_path, "liver", other)
    assert np.max(np.abs(other.world.vertices - world.vertices)) == 0.0
    # and it goes on as the solid it was taken from: the next ticks are the same
    for solid in (world.obj, other.world.obj):
        solid.step([], [])
        solid.step([], [])
    # to rounding: the modes of a solid built again may have other signs (module docstring)
    assert np.max(np.abs(other.world.obj.vertices - world.obj.vertices)) < 1e-12
    assert np.max(np.abs(world.obj.vertices - world.obj.rest_vertices)) > 1e-4  # still moving


def _other_version(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["format_version"] = np.array(99)
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]


def _another_rooms(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["room"] = np.array("other")
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]


def _state_off_its_surface(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["state_w"] = arrays["state_w"] * 0.5  # not the state that made the recorded surface
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]


def _pickled(path: Path) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["state_w"] = np.array([{"w": 1}], dtype=object)
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("case", "spoil", "why"),
    [
        ("another mesh", None, "another object: n_vertices"),
        ("another material", None, "another object: params_sha256"),
        ("corrupt", lambda p: p.write_bytes(p.read_bytes()[:200]), "not a readable snapshot"),
        ("not a zip", lambda p: p.write_bytes(b"hello"), "not a readable snapshot"),
        ("other version", _other_version, "format version 99"),
        ("another room's", _another_rooms, "room 'other'"),
        ("a state off its surface", _state_off_its_surface, "surface"),
        ("a pickle inside", _pickled, "not a readable snapshot"),
    ],
)
def test_a_snapshot_that_does_not_fit_is_refused_and_the_room_starts_from_rest(
    tmp_path, caplog, case, spoil, why
):
    caplog.set_level(logging.INFO, logger="haptic.server")
    saved_opts = options()
    if case == "another mesh":
        saved_opts = options(subdivisions=3)
    elif case == "another material":
        saved_opts = options(stiffness_scale=2.0)
    saved = build_room(saved_opts, DEFAULT_ROOM, {}, LinkConditions(), None, None)
    key = saved.world.obj.patch_key([0.0, 0.0, 0.1], normal=[0.0, 0.0, 1.0])
    saved.world.obj.step([key], [3.0])
    saved.restored(7)
    path = snapshots.write(tmp_path, snapshots.capture(DEFAULT_ROOM, saved))
    if spoil is not None:
        spoil(path)

    room = build_room(options(), DEFAULT_ROOM, {}, LinkConditions(), None, None)
    assert not snapshots.restore(tmp_path, DEFAULT_ROOM, room)
    rest = room.world.obj.rest_vertices
    assert np.max(np.abs(room.world.vertices - rest)) == 0.0  # from rest
    assert room.tick_count == 0
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refused) == 1 and why in refused[0] and "starts from rest" in refused[0], refused
    # kept aside for a person to look at, never offered again
    assert sorted(p.name for p in tmp_path.iterdir()) == ["default.npz.refused"]


def _server(snapshot_dir: Path, log: Path) -> tuple[subprocess.Popen[str], int]:
    """``haptic server --snapshot-dir DIR --drain-grace-s 10`` in a process of its own; its port."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1")
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "haptic_collab.cli",
                "server",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--subdivisions",
                "2",
                "--snapshot-dir",
                str(snapshot_dir),
                "--drain-grace-s",
                "10",
            ],  # fmt: skip
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            env=env,
            cwd=ROOT,
        )
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.search(r"viewer: http://127\.0\.0\.1:(\d+)/", line)
        if m:
            return proc, int(m.group(1))
    proc.wait(10)
    raise AssertionError(f"the server did not start:\n{log.read_text()[-2000:]}")


def test_sigterm_tells_the_client_saves_the_room_and_exits_and_the_next_server_resumes(tmp_path):
    snaps = tmp_path / "snapshots"
    proc, port = _server(snaps, tmp_path / "server1.log")
    try:

        async def session() -> Client:
            client = await Client.join(port, "A")
            top = 0.1  # the default balloon's top [m]
            for seq in range(1, 40):  # press for about 2 s
                state = {
                    "type": "state",
                    "seq": seq,
                    "probe_m": [0.0, 0.0, top - 0.006],
                    "force_n": [0.0, 0.0, 2.0],
                    "penetration_m": 0.006,
                    "in_contact": True,
                    "k_h": 400.0,
                }
                await client.ws.send(json.dumps(state))
                await asyncio.sleep(0.05)
            proc.send_signal(signal.SIGTERM)  # while A still presses
            await client.closed()
            return client

        client = asyncio.run(session())
        assert proc.wait(30) == 0  # a clean exit
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert client.ws.close_code == 1012
    assert client.texts[-1]["code"] == "server_draining"
    log1 = (tmp_path / "server1.log").read_text()
    assert "SIGTERM: stopping" in log1 and "drained in" in log1, log1[-2000:]
    with np.load(snaps / "default.npz", allow_pickle=False) as z:
        assert str(z["room"]) == "default" and int(z["format_version"]) == 1
        saved = np.array(z["vertices"])
        assert int(z["tick"]) > 0
    assert np.max(np.linalg.norm(saved, axis=1)) > 0.0
    rest = np.array(build_world(options()).vertices)
    assert np.max(np.abs(saved - rest)) > 1e-3  # saved while pressed

    proc2, _ = _server(snaps, tmp_path / "server2.log")
    try:
        proc2.send_signal(signal.SIGTERM)
        assert proc2.wait(30) == 0
    finally:
        if proc2.poll() is None:
            proc2.kill()
            proc2.wait()
    log2 = (tmp_path / "server2.log").read_text()
    assert "room 'default': started from snapshot" in log2, log2[-2000:]
    assert (snaps / "default.npz.loaded").is_file()
