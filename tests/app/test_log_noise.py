"""The server's log says what happened in its own words; the websockets library's lines (every
HTTP response, every connection opened and closed) only at --log-level debug (issue 61: a
server.log was mostly "HTTP response sent (200 OK)")."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _server_log(*extra: str) -> str:
    res = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", *extra, "server", "--port", "0",
         "--subdivisions", "1", "--duration", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env=dict(os.environ, OPENBLAS_NUM_THREADS="1"),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stderr


def test_websockets_lines_only_at_debug():
    info = _server_log()
    assert "haptic.server INFO" in info  # the server's own lines
    assert "websockets" not in info
    debug = _server_log("--log-level", "debug")
    assert "websockets.server" in debug  # "server listening on ...", for whoever asks for it
