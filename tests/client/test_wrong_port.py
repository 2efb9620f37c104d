"""A client pointed at a port where nothing listens says so, with what to check, and stops within
its --duration (issue 61: nine lines of retries, then "could not join" with no hint after 20 s
of an 8 s run)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again when the block ends: nothing listens


def test_nothing_listening_is_said_with_a_hint_and_the_run_keeps_its_duration(tmp_path):
    port = _closed_port()
    res = subprocess.run(
        [
            sys.executable, "-m", "haptic_collab.cli", "client", "--url",
            f"ws://127.0.0.1:{port}/ws", "--device", "sim:rest", "--duration", "2",
            "--summary", str(tmp_path / "A.json"), "--no-gain-cache",
        ],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env=dict(os.environ, OPENBLAS_NUM_THREADS="1"),
    )  # fmt: skip
    assert res.returncode == 2, res.stderr[-2000:]
    last = res.stderr.strip().splitlines()[-1]
    # the run waited its 2 s, not the 20 s join timeout, and says what to check
    assert f"could not join ws://127.0.0.1:{port}/ws within 2 s: nothing listens there" in last
    assert "is `haptic server` running" in last and "--url" in last
    # the first refusal already said it, once, before the retries
    assert res.stderr.count("nothing listens at") == 1
