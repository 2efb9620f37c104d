"""``haptic client --url ws://HOST:PORT/rooms/NAME/ws`` joins room NAME of a ``haptic server``
whose configuration file declares it: both as separate processes on loopback, as users run them."""

from __future__ import annotations

import time
from pathlib import Path

from tests.support.processes import finish_client, server_process, start_client

CONFIG = """\
sim_rate = 20.0
subdivisions = 2

[rooms.lab]
sim_rate = 25.0
subdivisions = 2
max_users = 2
"""


def test_the_python_client_joins_a_named_room_by_its_url(tmp_path: Path) -> None:
    config = tmp_path / "server.toml"
    config.write_text(CONFIG)
    with server_process(tmp_path / "server.log", 0, "--config", str(config)) as server:
        url = f"ws://127.0.0.1:{server.port}/rooms/lab/ws"
        client = start_client(tmp_path, "A", url, "--device", "sim:rest", "--duration", "5")
        seen: list[dict[str, dict[str, int]]] = []
        deadline = time.monotonic() + 60.0
        while client.poll() is None and time.monotonic() < deadline:
            rooms = server.status()["rooms"]
            seen.append({name: {"users": r["users"]} for name, r in rooms.items()})
            if rooms["lab"]["users"]:
                break
            time.sleep(0.1)
        status = server.status()
        summary, _ = finish_client(client, tmp_path, "A")
    assert seen and seen[-1]["lab"]["users"] == 1, seen  # in room lab ...
    assert all(s["default"]["users"] == 0 for s in seen)  # ... never in the default room
    assert status["rooms"]["lab"]["sim_rate_hz"] == 25.0 and status["sim_rate_hz"] == 20.0
    assert summary["joins"] == 1 and summary["patches"] > 0
    assert summary["server_errors"] == []
