"""Server and clients as separate processes, the way users run them (``haptic server``,
``haptic client``): for the loopback tests.

The server is :class:`server.bench_load.ServerProcess` (started with ``--port 0`` it prints its
viewer URL once it listens, and the port is read from that line). Every process runs ``python -m haptic_collab.cli`` from the repository
root, so the tests exercise the command line a user types.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from haptic_collab.server.bench_load import ServerProcess

ROOT = Path(__file__).resolve().parents[1]


def haptic(*args: str) -> list[str]:
    """The command line of ``haptic ARGS``."""
    return [sys.executable, "-m", "haptic_collab.cli", *args]


def server_process(log: Path, port: int = 0, *args: str) -> ServerProcess:
    """``haptic server --port PORT ARGS`` on loopback, logging to ``log``
    (:class:`server.bench_load.ServerProcess`, the load bench's own)."""
    return ServerProcess(*args, port=port, log=log)


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
