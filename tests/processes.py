"""Server and clients as separate processes, the way users run them (``haptic server``,
``haptic client``): for the loopback tests.

A server started with ``--port 0`` prints its viewer URL once it listens; :class:`ServerProcess`
reads the port from that line. Every process runs ``python -m haptic_collab.cli`` from the repository
root, so the tests exercise the command line a user types.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_PORT_LINE = re.compile(r"viewer: https?://[^\s/]+:(\d+)/")


def haptic(*args: str) -> list[str]:
    """The command line of ``haptic ARGS``."""
    return [sys.executable, "-m", "haptic_collab.cli", *args]


class ServerProcess:
    """``haptic server --host 127.0.0.1`` in its own process group; ``port`` once it listens.

    Parameters
    ----------
    log : path of the server's log (stdout and stderr).
    port : TCP port; 0 takes any free one.
    args : further ``haptic server`` options.

    Raises
    ------
    RuntimeError
        The server exited or did not print its URL within ``timeout_s``.
    """

    def __init__(self, log: Path, port: int = 0, *args: str, timeout_s: float = 60.0) -> None:
        self.log_path = log
        self._log = open(log, "w")  # noqa: SIM115 (closed in stop)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        cmd = haptic("server", "--host", "127.0.0.1", "--port", str(port), *args)
        self.proc = subprocess.Popen(
            cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=self._log, text=True,
            start_new_session=True,
        )  # fmt: skip
        self._port: list[int] = []
        self._listening = threading.Event()
        threading.Thread(target=self._drain, daemon=True).start()
        if not self._listening.wait(timeout_s) or not self._port:
            self.stop()
            raise RuntimeError(f"the server did not start:\n{log.read_text()[-3000:]}")
        self.port = self._port[0]
        self.url = f"ws://127.0.0.1:{self.port}/ws"

    def _drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._log.write(line)
            m = _PORT_LINE.search(line)
            if m and not self._port:
                self._port.append(int(m.group(1)))
                self._listening.set()
        self._listening.set()  # exited without listening

    def stop(self) -> int | None:
        """Stop it as Ctrl-C does (SIGINT), then harder; returns its exit status."""
        for sig, wait_s in ((signal.SIGINT, 15.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(wait_s)
        with contextlib.suppress(OSError):
            os.killpg(self.proc.pid, signal.SIGKILL)  # whatever worker is left of it
        self._log.flush()
        self._log.close()
        return self.proc.returncode

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_client(workdir: Path, name: str, url: str, *args: str) -> subprocess.Popen[str]:
    """``haptic client --name NAME --url URL ARGS`` recording to ``workdir/NAME.csv`` with its
    summary in ``workdir/NAME.json`` and its log in ``workdir/NAME.log``."""
    log = open(workdir / f"{name}.log", "w")  # noqa: SIM115 (the child holds it)
    cmd = haptic(
        "client", "--name", name, "--url", url, *args,
        "--record", str(workdir / f"{name}.csv"), "--summary", str(workdir / f"{name}.json"),
    )  # fmt: skip
    try:
        return subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, text=True)
    finally:
        log.close()


def finish_client(
    proc: subprocess.Popen[str], workdir: Path, name: str, timeout_s: float = 120.0
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Wait for a client started by :func:`start_client`; its summary and telemetry columns.

    Raises
    ------
    AssertionError
        The client failed (its log's tail in the message).
    """
    try:
        rc = proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    log = (workdir / f"{name}.log").read_text()
    assert rc == 0, f"client {name} exited {rc}:\n{log[-3000:]}"
    summary = json.loads((workdir / f"{name}.json").read_text())
    return summary, load_csv(workdir / f"{name}.csv")


def load_csv(path: Path) -> dict[str, np.ndarray]:
    """A telemetry CSV as one array per column."""
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {h: data[:, i] for i, h in enumerate(header)}


def wait_until(predicate: Any, timeout_s: float, poll_s: float = 0.05) -> bool:
    """Poll ``predicate()`` until it is true or ``timeout_s`` passes; whether it came true."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())
