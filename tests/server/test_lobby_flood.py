"""``haptic lobby`` under floods, behind proxies and with a hung allocator: who still gets served.

A real lobby on loopback with the Agones back end against the stand-in allocator
(tests/support/agones_allocator.py). Linux routes all of 127.0.0.0/8 to loopback, so each
"address" here is a real source address (127.0.0.2, 127.0.0.3, ...), and what the lobby sees is
what it would see from separate hosts. What a user notices: one address holding hundreds of idle
sockets does not shut the others out; clients behind a trusted proxy each get their own request
budget while a forged ``X-Forwarded-For`` from anyone else changes nothing; an allocator that
hangs gets every waiting user a prompt 503 with ``Retry-After``, not a queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import socket
import time
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from haptic_collab.server.lobby import MAX_PLACEMENTS, AgonesAllocator, Lobby
from haptic_collab.server.lobby_limits import ADDRESS_BURST
from haptic_collab.server.security import MIN_SECRET_BYTES
from tests.support.agones_allocator import FLEET, Allocator, GameServer
from tests.support.agones_allocator import fleet as stand_in_fleet

SECRET = b"f" * MIN_SECRET_BYTES
ASKERS = ThreadPoolExecutor(32, thread_name_prefix="asker")


def fleet(n: int, capacity: int = 8) -> list[GameServer]:
    return stand_in_fleet(n, capacity)


def get(
    port: int, path: str, source: str = "127.0.0.1", headers: dict[str, str] | None = None
) -> tuple[int, dict[str, str], dict[str, Any]]:
    """(status, headers, JSON answer) of ``GET path`` sent from ``source``."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30, source_address=(source, 0))
    try:
        conn.request("GET", path, headers=headers or {})
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), json.loads(r.read())
    finally:
        conn.close()


async def aget(*args: Any, **kw: Any) -> tuple[int, dict[str, str], dict[str, Any]]:
    return await asyncio.get_running_loop().run_in_executor(ASKERS, lambda: get(*args, **kw))


@contextlib.asynccontextmanager
async def lobby_on(url: str, timeout_s: float = 5.0, **kw: Any) -> AsyncIterator[Lobby]:
    backend = AgonesAllocator(url, namespace="labs", match_labels=FLEET, timeout_s=timeout_s)
    lobby = Lobby(backend, SECRET, port=0, **kw)
    await lobby.start()
    try:
        yield lobby
    finally:
        await lobby.stop()


@contextlib.asynccontextmanager
async def idle_sockets(port: int, n: int, source: str) -> AsyncIterator[list[socket.socket]]:
    """``n`` connections from ``source`` that send nothing (opened off the event loop)."""
    socks: list[socket.socket] = []

    def open_all() -> None:
        for _ in range(n):
            socks.append(socket.create_connection(("127.0.0.1", port), source_address=(source, 0)))

    try:
        await asyncio.get_running_loop().run_in_executor(ASKERS, open_all)
        yield socks
    finally:
        for s in socks:
            s.close()


async def test_idle_sockets_from_one_address_do_not_shut_out_the_others() -> None:
    with Allocator(fleet(2)) as alloc:
        # idle sockets are cut off after read_timeout_s: long enough to outlast the test
        async with lobby_on(alloc.url, read_timeout_s=60.0) as lobby:
            async with idle_sockets(lobby.port, 300, "127.0.0.2"):
                # another address is served while the 300 sockets are open
                status, _, answer = await aget(lobby.port, "/rooms/anatomy", "127.0.0.3")
                assert status == 200, answer
                assert answer["server"] == "haptic-collab-0"
                # the flooding address itself is told why, and when to come back
                status, headers, answer = await aget(lobby.port, "/healthz", "127.0.0.2")
                assert status == 503
                assert headers["Retry-After"] == "1"
                assert "too many connections from your address" in answer["error"]
                assert lobby.connections.open_by_address["127.0.0.2"] == 16
            assert lobby.counts["connections_refused", "address"] >= 284


async def test_a_trusted_proxy_s_clients_each_get_their_own_budget() -> None:
    with Allocator(fleet(2)) as alloc:
        async with lobby_on(alloc.url, trusted_proxies=["127.0.0.5"]) as lobby:
            burst = int(ADDRESS_BURST)

            async def statuses(source: str, forwarded: str, n: int) -> list[int]:
                hdr = {"X-Forwarded-For": forwarded}
                return [(await aget(lobby.port, "/healthz", source, hdr))[0] for _ in range(n)]

            # one client behind the proxy spends its budget ...
            # (twice the burst: the bucket refills 5 a second while the requests go out)
            spent = await statuses("127.0.0.5", "198.51.100.1", 2 * burst)
            assert spent[:burst] == [200] * burst and 429 in spent[burst:]
            # ... and the next client behind the same proxy still has all of its own
            assert await statuses("127.0.0.5", "198.51.100.2", burst) == [200] * burst
            # from an address that is not a trusted proxy the header is ignored: a new
            # "client" per request does not buy a new budget
            spoofed = []
            for i in range(2 * burst):
                forged = {"X-Forwarded-For": f"10.0.0.{i}"}
                spoofed.append((await aget(lobby.port, "/healthz", "127.0.0.6", forged))[0])
            assert 429 in spoofed[burst:]
            # a proxy that forwards garbage gets a clear 400
            status, _, answer = await aget(
                lobby.port, "/healthz", "127.0.0.5", {"X-Forwarded-For": "unknown"}
            )
            assert status == 400
            assert "not an IP address" in answer["error"]


@contextlib.contextmanager
def hung_allocator() -> Iterator[tuple[str, list[socket.socket]]]:
    """An allocator that accepts connections and never answers: (URL, connections taken)."""
    listener = socket.create_server(("127.0.0.1", 0), backlog=64)
    taken: list[socket.socket] = []
    stop = False

    def accept() -> None:
        listener.settimeout(0.1)
        while not stop:
            with contextlib.suppress(TimeoutError, OSError):
                taken.append(listener.accept()[0])

    worker = ASKERS.submit(accept)
    try:
        yield f"http://127.0.0.1:{listener.getsockname()[1]}", taken
    finally:
        stop = True
        worker.result()
        for s in taken:
            s.close()
        listener.close()


async def test_a_hung_allocator_gets_everyone_a_prompt_503_not_a_queue() -> None:
    with hung_allocator() as (url, taken):
        async with lobby_on(url, timeout_s=5.0) as lobby:
            t0 = time.monotonic()

            async def timed(
                path: str, source: str
            ) -> tuple[int, dict[str, str], dict[str, Any], float]:
                status, headers, answer = await aget(lobby.port, path, source)
                return status, headers, answer, time.monotonic() - t0

            # 20 names at once, each from its own address
            asked = [timed(f"/rooms/room-{i}", f"127.0.1.{i + 1}") for i in range(20)]
            health = asyncio.ensure_future(timed("/healthz", "127.0.1.99"))
            answers = await asyncio.gather(*asked)
            assert (await health)[0] == 200  # the lobby itself answers meanwhile
            assert [a[0] for a in answers] == [503] * 20
            assert all(a[1].get("Retry-After") for a in answers)
            reasons = sorted(a[2]["error"].split(";")[0] for a in answers)
            waited = [a for a in answers if "did not answer within 5 s" in a[2]["error"]]
            busy = [a for a in answers if "busy placing 8 other rooms" in a[2]["error"]]
            # as many as there are placement slots reached the allocator; the rest were told
            # at once that the lobby is busy, instead of queueing behind them
            assert (len(waited), len(busy)) == (MAX_PLACEMENTS, 20 - MAX_PLACEMENTS), reasons
            assert len(taken) == MAX_PLACEMENTS
            late_busy, late_wait = max(a[3] for a in busy), max(a[3] for a in waited)
            print(f"latest busy answer {late_busy:.2f} s, latest timeout answer {late_wait:.2f} s")


async def test_many_asking_for_one_name_while_the_allocator_hangs_share_one_try() -> None:
    with hung_allocator() as (url, taken):
        async with lobby_on(url, timeout_s=4.0) as lobby:
            answers = await asyncio.gather(
                *(aget(lobby.port, "/rooms/same", f"127.0.2.{i + 1}") for i in range(20))
            )
            assert [a[0] for a in answers] == [503] * 20
            assert {a[2]["error"] for a in answers} == {
                "the Agones allocator did not answer within 4 s; try again"
            }
            assert len(taken) == 1  # one request to the allocator, not one after another
