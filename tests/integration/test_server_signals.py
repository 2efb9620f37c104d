"""Ctrl-C and SIGTERM stop `haptic server` cleanly, also when it was started with SIGINT ignored
(in the background by a non-interactive shell, as scripts and CI runners start it)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest

LAUNCH = (
    "import signal, sys\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN)  # what a background job inherits\n"
    "from haptic_collab.cli import main\n"
    "sys.argv = ['haptic', '--log-level', 'info', 'server', '--host', '127.0.0.1', '--port', '0',"
    " '--subdivisions', '2']\n"
    "sys.exit(main())\n"
)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_server_stops_cleanly_on_a_signal_even_with_sigint_ignored(tmp_path, sig):
    log = open(tmp_path / "server.log", "w+")  # noqa: SIM115 (closed below)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-c", LAUNCH], stdout=subprocess.PIPE, stderr=log, text=True, env=env
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if re.search(r"viewer: http://127\.0\.0\.1:\d+/", line):
                break
        proc.send_signal(sig)
        # a clean stop: the server closes its connections and exits 0 (it was killed by the
        # default SIGTERM handler, and a SIGINT it inherited as ignored did nothing at all)
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.seek(0)
        text = log.read()
        log.close()
    assert f"{sig.name}: stopping" in text and "haptic.server INFO server closed" in text, text[
        -2000:
    ]
