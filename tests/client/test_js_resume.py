"""The Node.js reference client (client/js) rejoins with its resume token and keeps its seat.

A real server on loopback cuts the JS user's socket off from its side; the client sees the close,
redials with backoff, and its ``hello`` carries the last welcome's ``resume_token``: the server
gives back the same user id, and the room holds one seat for it. Skipped when ``node`` is not on
PATH (as tests/client/test_js_client.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from haptic_collab.server.app import ServerApp
from haptic_collab.server.room import Room
from tests.support.rooms import RecordingWorld

ROOT = Path(__file__).resolve().parents[2]
JS_DIR = ROOT / "client" / "js"
NODE = shutil.which("node")

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        NODE is None, reason="node is not on PATH: the JS reference client needs it"
    ),
]


async def until(predicate: Callable[[], object], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.05)


async def test_the_js_client_resumes_its_seat_after_its_socket_is_cut(tmp_path):
    assert (JS_DIR / "node_modules" / "ws").is_dir(), "run `make js-install` (npm ci in client/js)"
    assert NODE is not None
    app = ServerApp(Room(RecordingWorld(), 20.0), "127.0.0.1", 0)
    await app.start()
    summary_path = tmp_path / "A.json"
    env = {k: v for k, v in os.environ.items() if k != "HAPTIC_TOKEN"}
    proc = await asyncio.create_subprocess_exec(
        NODE, str(JS_DIR / "haptic-client.mjs"), f"--url=ws://127.0.0.1:{app.port}/ws",
        "--name=A", "--on=top", "--duration=8", f"--summary={summary_path}", "--quiet",
        cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        await until(lambda: any(p.named for p in app._peers.values()))
        await asyncio.sleep(1.0)  # it sends states and gets patches
        (peer,) = [p for p in app._peers.values() if p.named]
        assert "(u1)" in peer.who
        peer.ws.transport.abort()  # the server's side of the socket is gone, no close frame
        await until(lambda: app.room.resumes == 1, 30.0)
        assert len(app.room.users) == 1 and app.room.held_seats == []
        out, err = await asyncio.wait_for(proc.communicate(), 60.0)
    finally:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
        await app.stop()
    assert proc.returncode == 0, err.decode(errors="replace")
    summary = json.loads(out)
    assert summary["joins"] == 2 and summary["resumes"] == 1, summary
    assert summary["user_ids"] == ["u1", "u1"] and summary["assigned_name"] == "A"
    assert summary["fatal_error"] is None and summary["patches"] > 0
