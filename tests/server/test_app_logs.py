"""The server's connection log lines say who: the peer's address, then name and role once known."""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import pytest
from websockets.asyncio.client import connect

from haptic_collab.server.app import ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room

SIM_RATE = 20.0
#: The checkout's viewer folder (installed as haptic_collab/web).
WEB = Path(__file__).resolve().parents[2] / "web"


async def test_open_and_close_lines_name_the_peer(caplog):
    caplog.set_level(logging.INFO, logger="haptic.server")
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0)
    await app.start()
    try:
        url = f"ws://127.0.0.1:{app.port}/ws"
        async with connect(url) as ws:
            port = ws.local_address[1]
            await ws.send(
                json.dumps({"type": "hello", "protocol": 1, "role": "user", "name": "Ada"})
            )
            assert json.loads(await asyncio.wait_for(ws.recv(), 10.0))["type"] == "welcome"
            await ws.send(json.dumps({"type": "bye"}))
            await asyncio.wait_for(ws.wait_closed(), 10.0)
        async with connect(url) as quiet:  # leaves before saying hello
            quiet_port = quiet.local_address[1]
        for _ in range(100):  # the server notices the close a moment later
            if sum("closed" in r.getMessage() for r in caplog.records) >= 2:
                break
            await asyncio.sleep(0.05)
    finally:
        await app.stop()
    lines = [r.getMessage() for r in caplog.records if r.name == "haptic.server"]
    mine = [ln for ln in lines if f"127.0.0.1:{port}" in ln]
    assert any("open" in ln for ln in mine), lines
    closed = [ln for ln in mine if "closed" in ln]
    assert len(closed) == 1 and "user 'Ada'" in closed[0] and "code 1000" in closed[0], mine
    quiet_closed = [ln for ln in lines if f"127.0.0.1:{quiet_port}" in ln and "closed" in ln]
    assert len(quiet_closed) == 1 and "before hello" in quiet_closed[0], lines


@pytest.mark.skipif(
    not (WEB / "node_modules" / "three").is_dir(),
    reason="web/node_modules is not installed (make web-install: npm ci in web/)",
)
def test_the_packages_own_viewer_is_complete():
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    # npm's three.js in a checkout, package data in a wheel
    assert ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0).viewer_missing() == []


def test_an_incomplete_viewer_is_named(tmp_path):
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    room = Room(world, SIM_RATE)
    # a viewer folder without three.js: the server says which files are missing
    (tmp_path / "index.html").write_text("<html></html>")
    missing = ServerApp(room, "127.0.0.1", 0, web_dir=tmp_path).viewer_missing()
    assert "node_modules/three/build/three.module.js" in missing and "index.html" not in missing
