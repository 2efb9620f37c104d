"""Measure ``haptic lobby`` under floods on loopback: do other addresses still get answers?

Starts the stand-in Agones allocator (tests/support/agones_allocator.py) in this process and a
``haptic lobby`` process in front of it, then runs three scenarios, each while a second address
(127.0.0.3) asks for a room every 250 ms (within its budget of 5 a second) and records its
answers and their latency:

- ``idle``: 300 connections from 127.0.0.2 that send nothing, held for 5 s;
- ``flood``: 1000 requests a second from 127.0.0.2 for 5 s (each its own connection);
- ``hung``: the lobby pointed at an allocator that accepts and never answers, 20 names asked at
  once from 20 addresses (the lobby's allocator timeout is its default, 5 s).

Usage: ``PYTHONPATH=. python tools/lobby_flood.py [--out FILE.json] [--code-root DIR]``
(``--code-root``: run the lobby from another checkout, e.g. to compare with an older one).
Loopback only; Linux (127.0.0.0/8 all local).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from tests.support.agones_allocator import Allocator, GameServer

FLEET = {"agones.dev/fleet": "haptic-collab"}


def fleet(n: int) -> list[GameServer]:
    return [
        GameServer(
            f"gs-{i}",
            port=7000 + i,
            labels=dict(FLEET),
            lists={"rooms": {"capacity": 64, "values": []}},
        )
        for i in range(n)
    ]


async def request(port: int, path: str, source: str, timeout_s: float = 30.0) -> tuple[int, float]:
    """(status or 0 when cut off or refused, seconds) of one GET from ``source``."""
    t0 = time.monotonic()
    try:
        async with asyncio.timeout(timeout_s):
            reader, writer = await asyncio.open_connection(
                "127.0.0.1", port, local_addr=(source, 0)
            )
            writer.write(f"GET {path} HTTP/1.1\r\nHost: lobby\r\n\r\n".encode())
            await writer.drain()
            line = await reader.readline()
            writer.close()
        return (int(line.split()[1]) if line.startswith(b"HTTP/") else 0), time.monotonic() - t0
    except (OSError, TimeoutError, ValueError, IndexError):
        return 0, time.monotonic() - t0


def observe(port: int, duration_s: float) -> dict[str, Any]:
    """Another address asking every 250 ms for ``duration_s`` (run in a process of its own, so
    that the flood's generator does not delay it)."""
    import http.client

    statuses: Counter[int] = Counter()
    latencies = []
    end = time.monotonic() + duration_s
    i = 0
    while time.monotonic() < end:
        t0 = time.monotonic()
        try:
            conn = http.client.HTTPConnection(
                "127.0.0.1", port, timeout=30, source_address=("127.0.0.3", 0)
            )
            conn.request("GET", f"/rooms/observer-{i % 4}")
            status = conn.getresponse().status
            conn.close()
        except OSError:
            status = 0
        latencies.append(time.monotonic() - t0)
        statuses[status] += 1
        i += 1
        time.sleep(max(0.0, 0.25 - (time.monotonic() - t0)))
    latencies.sort()
    return {
        "answers": dict(statuses),
        "max_latency_s": round(latencies[-1], 3),
        "median_latency_s": round(latencies[len(latencies) // 2], 4),
    }


def observer(port: int, duration_s: float) -> asyncio.Future[dict[str, Any]]:
    """:func:`observe` in another process, as a future of this event loop."""
    pool = ProcessPoolExecutor(1)
    future = asyncio.get_running_loop().run_in_executor(pool, observe, port, duration_s)
    future.add_done_callback(lambda _: pool.shutdown(wait=False))
    return future


async def idle(port: int) -> dict[str, Any]:
    watch = observer(port, 5.5)
    socks = []
    loop = asyncio.get_running_loop()

    def open_all() -> None:
        for _ in range(300):
            with contextlib.suppress(OSError):
                s = socket.create_connection(("127.0.0.1", port), source_address=("127.0.0.2", 0))
                socks.append(s)

    await loop.run_in_executor(None, open_all)
    await asyncio.sleep(2.0)
    own, _ = await request(port, "/healthz", "127.0.0.2")  # while its sockets are open
    await asyncio.sleep(3.0)
    for s in socks:
        s.close()
    return {"sockets_opened": len(socks), "flooder_new_request": own, "other": await watch}


async def flood(port: int) -> dict[str, Any]:
    watch = observer(port, 5.0)
    await asyncio.sleep(0.3)  # the observer's process is up
    tasks = []
    t0 = time.monotonic()
    n = 0
    while time.monotonic() - t0 < 5.0:
        due = t0 + n / 1000.0
        delay = due - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        tasks.append(asyncio.ensure_future(request(port, "/rooms/flood", "127.0.0.2")))
        n += 1
    sent_s = time.monotonic() - t0
    results = await asyncio.gather(*tasks)
    return {
        "requests": n,
        "sent_in_s": round(sent_s, 2),
        "flooder_answers": dict(Counter(s for s, _ in results)),
        "other": await watch,
    }


async def hung(port: int) -> dict[str, Any]:
    t0 = time.monotonic()
    results = await asyncio.gather(
        *(request(port, f"/rooms/hung-{i}", f"127.0.1.{i + 1}") for i in range(20))
    )
    return {
        "answers": dict(Counter(s for s, _ in results)),
        "latencies_s": sorted(round(dt, 2) for _, dt in results),
        "wall_s": round(time.monotonic() - t0, 2),
    }


def start_lobby(allocator_url: str, root: Path, secret: Path) -> tuple[subprocess.Popen, int]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "haptic_collab.cli", "lobby", "--port", str(port),
           "--agones-allocator", allocator_url, "--agones-fleet", "haptic-collab",
           "--token-secret-file", str(secret)]  # fmt: skip
    proc = subprocess.Popen(  # cwd: the checkout's own haptic_collab comes first
        cmd, env=env, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    for _ in range(200):
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
            return proc, port
        time.sleep(0.05)
    proc.kill()
    raise SystemExit("the lobby did not start")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None)
    parser.add_argument("--code-root", default=str(Path(__file__).resolve().parents[1]))
    args = parser.parse_args()
    root = Path(args.code_root)
    report: dict[str, Any] = {"code_root": str(root), "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory() as tmp:
        secret = Path(tmp) / "secret"
        secret.write_text("s" * 48)
        with Allocator(fleet(4)) as alloc:
            proc, port = start_lobby(alloc.url, root, secret)
            try:
                report["idle"] = asyncio.run(idle(port))
                time.sleep(6.0)  # budgets refill, cut-off sockets gone
                report["flood"] = asyncio.run(flood(port))
            finally:
                proc.terminate()
                proc.wait(10)
        listener = socket.create_server(("127.0.0.1", 0), backlog=128)  # never answers
        proc, port = start_lobby(f"http://127.0.0.1:{listener.getsockname()[1]}", root, secret)
        try:
            report["hung"] = asyncio.run(hung(port))
        finally:
            proc.terminate()
            proc.wait(10)
            listener.close()
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
