"""Server and clients as separate processes, the way users run them (``haptic server``,
``haptic client``, any ``haptic`` command), and a scripted well-behaved user over a websocket: for
the loopback tests.

The server is :class:`haptic_collab.server_process.ServerProcess` (started with ``--port 0`` it prints its
viewer URL once it listens, and the port is read from that line). Every process runs ``python -m haptic_collab.cli`` from the repository
root, so the tests exercise the command line a user types.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.client import connect

from haptic_collab.server_process import ServerProcess

ROOT = Path(__file__).resolve().parents[2]


def haptic(*args: str) -> list[str]:
    """The command line of ``haptic ARGS``."""
    return [sys.executable, "-m", "haptic_collab.cli", *args]


def server_process(log: Path, port: int = 0, *args: str) -> ServerProcess:
    """``haptic server --port PORT ARGS`` on loopback, logging to ``log``
    (:class:`haptic_collab.server_process.ServerProcess`)."""
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


def run(
    *args: str, timeout: float = 120.0, tmpdir: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """``haptic ARGS`` in a subprocess; ``tmpdir`` becomes its temporary folder (TMPDIR)."""
    env = None if tmpdir is None else dict(os.environ, TMPDIR=str(tmpdir))
    return subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env=env,
    )


async def good_user(url: str, seconds: float) -> list[int]:
    """A scripted, well-behaved user resting 2 mm into the top; returns the patch ticks it got."""
    ticks: list[int] = []
    async with connect(url) as ws:
        await ws.send(json.dumps({"type": "hello", "protocol": 1, "role": "user", "name": "good"}))
        welcome = json.loads(await ws.recv())
        top = welcome["object"]["top_m"]
        probe = [top[0], top[1], top[2] - 0.002]
        t_end = time.monotonic() + seconds
        seq = 0

        async def send() -> None:
            nonlocal seq
            while time.monotonic() < t_end:
                seq += 1
                await ws.send(
                    json.dumps(
                        {"type": "state", "seq": seq, "probe_m": probe, "force_n": [0, 0, 0.3]}
                    )
                )
                await asyncio.sleep(0.025)

        sender = asyncio.create_task(send())
        with contextlib.suppress(TimeoutError):
            while time.monotonic() < t_end:
                msg = await asyncio.wait_for(ws.recv(), max(0.01, t_end - time.monotonic()))
                if isinstance(msg, str):
                    m = json.loads(msg)
                    assert m["type"] != "error", m
                    if m["type"] == "patch":
                        assert all(math.isfinite(x) for x in m["proxy_m"])
                        ticks.append(m["tick"])
        await sender
    return ticks
