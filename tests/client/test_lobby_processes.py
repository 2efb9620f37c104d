"""``haptic lobby`` and ``haptic client --lobby`` as users run them: two ``haptic server``
processes, a lobby process and a client process on loopback. The client finds room ``lab``
through the lobby; its server is stopped with SIGTERM (it drains: ``server_draining``, close
1012); the client asks the lobby again and goes on in room ``lab`` on the other server, and its
summary says where it was.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.server_process import ServerProcess
from tests.support.processes import ROOT, haptic

pytestmark = pytest.mark.slow


def wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def lab_users(server: ServerProcess) -> int:
    try:
        return int(server.status()["rooms"].get("lab", {}).get("users", 0))
    except (OSError, ValueError):
        return 0


def lab_tick(server: ServerProcess) -> int:
    try:
        return int(server.status()["rooms"].get("lab", {}).get("tick", 0))
    except (OSError, ValueError):
        return 0


def test_a_client_follows_its_room_through_the_lobby_when_its_server_drains(tmp_path: Path):
    secret = tmp_path / "secret"
    secret.write_text("s" * 48)
    config = tmp_path / "server.toml"
    config.write_text('[room_templates.any]\nprefix = ""\nsubdivisions = 2\n')
    common = ("--config", str(config), "--token-secret-file", str(secret), "--subdivisions", "2")
    a = ServerProcess(*common, log=tmp_path / "a.log")
    b = ServerProcess(*common, log=tmp_path / "b.log")
    lobby_log = open(tmp_path / "lobby.log", "w+")  # noqa: SIM115 (closed below)
    cmd = haptic(
        "lobby", "--port", "0", "--token-secret-file", str(secret),
        "--server", f"http://127.0.0.1:{a.port}", "--server", f"http://127.0.0.1:{b.port}",
    )  # fmt: skip
    lobby = subprocess.Popen(cmd, cwd=ROOT, stdout=lobby_log, stderr=subprocess.STDOUT, text=True)
    client: subprocess.Popen[str] | None = None
    try:
        found: list[str] = []

        def listening() -> bool:
            lobby_log.seek(0)
            found[:] = re.findall(r"lobby listening on (http://\S+):(\d+)", lobby_log.read())
            return bool(found) or lobby.poll() is not None

        wait_for(listening, 30.0, "the lobby")
        assert found, (tmp_path / "lobby.log").read_text()
        lobby_url = f"{found[0][0]}:{found[0][1]}"
        summary = tmp_path / "A.json"
        client_log = open(tmp_path / "A.log", "w")  # noqa: SIM115 (the child holds it)
        client = subprocess.Popen(
            haptic(
                "client",
                "--lobby",
                lobby_url,
                "--room",
                "lab",
                "--name",
                "A",
                "--device",
                "sim:rest",
                "--duration",
                "30",
                "--summary",
                str(summary),
            ),  # fmt: skip
            cwd=ROOT,
            stdout=client_log,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        client_log.close()

        def servo_running() -> bool:
            """The client's servo runs (its "joined as" line: the servo starts at the first
            welcome and patches are rendered from then on; on a loaded machine that comes a
            while after the server counts the user)."""
            return " joined as " in (tmp_path / "A.log").read_text()

        wait_for(lambda: lab_users(a) == 1, 60.0, "the client in room lab on server a")
        wait_for(servo_running, 60.0, "the client's servo on server a")
        assert "lab" not in b.status()["rooms"]
        a.proc.send_signal(signal.SIGTERM)  # a drains
        assert a.proc.wait(20.0) == 0
        wait_for(lambda: lab_users(b) == 1, 30.0, "the client in room lab on server b")
        # a second of ticks with the client in the room: patches sent (on a loaded clean-clone
        # run the client was stopped before its first one, and counted none)
        t0 = lab_tick(b)
        wait_for(lambda: lab_tick(b) >= t0 + 20, 30.0, "room lab's ticks on server b")
        client.send_signal(signal.SIGINT)
        assert client.wait(30.0) == 0, (tmp_path / "A.log").read_text()[-2000:]
        got = json.loads(summary.read_text())
        assert got["lobby"]["joined"] == [
            f"ws://127.0.0.1:{a.port}/rooms/lab/ws",
            f"ws://127.0.0.1:{b.port}/rooms/lab/ws",
        ]
        assert got["lobby"]["asks"] == 2
        assert got["patches"] > 0
    finally:
        if client is not None and client.poll() is None:
            client.kill()
        lobby.send_signal(signal.SIGINT)
        try:
            lobby.wait(10.0)
        except subprocess.TimeoutExpired:
            lobby.kill()
        lobby_log.close()
        a.stop()
        b.stop()
