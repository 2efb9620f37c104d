"""Several ``haptic lobby`` replicas in front of one Agones allocator: each name on one server.

Two real lobbies on loopback share one stand-in allocator (tests/support/agones_allocator.py).
The stand-in matches selectors against the GameServers as they were when a request arrived, as
the allocator's informer cache does, so two allocations for a new name that arrive together
land on two servers: the first test shows that happening to two lobbies that do not know each
other. Given each other as peers (server/lobby_peers.py), every name has one owner that places
it, and users asking through either replica at once all end up on one server. While a name's
owner is down, a request for that name is refused with ``Retry-After``, never placed elsewhere.
Two ``haptic lobby`` processes given each other with ``--peer`` do the same.
A name asked again moments after its placement, while the allocator's cache does not show it
yet, is answered from the lobby's memory instead of allocated again.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import json
import socket
import subprocess
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

from haptic_collab.server.lobby import AgonesAllocator, Lobby
from haptic_collab.server.lobby_peers import Peers
from haptic_collab.server.security import MIN_SECRET_BYTES, check_room_token
from tests.support.agones_allocator import FLEET, Allocator, GameServer, LaggingCacheAllocator
from tests.support.agones_allocator import fleet as stand_in_fleet
from tests.support.processes import ROOT, haptic

SECRET = b"r" * MIN_SECRET_BYTES
ASKERS = ThreadPoolExecutor(48, thread_name_prefix="asker")
#: The stand-in's informer lag [s]: wide enough that requests sent together fall inside it.
LAG_S = 0.4


def fleet(n: int, capacity: int = 4) -> list[GameServer]:
    return stand_in_fleet(n, capacity)


class _At:
    """What :func:`ask` needs of a lobby: its port."""

    def __init__(self, port: int) -> None:
        self.port = port


async def ask(
    lobby: Lobby | _At, path: str, source: str = "127.0.0.1"
) -> tuple[int, dict[str, str], dict[str, Any]]:
    """(status, headers, JSON answer) of ``GET path``, sent from the address ``source``."""

    def go() -> tuple[int, dict[str, str], dict[str, Any]]:
        conn = http.client.HTTPConnection(
            "127.0.0.1", lobby.port, timeout=30, source_address=(source, 0)
        )
        try:
            conn.request("GET", path)
            r = conn.getresponse()
            return r.status, dict(r.getheaders()), json.loads(r.read())
        finally:
            conn.close()

    return await asyncio.get_running_loop().run_in_executor(ASKERS, go)


@contextlib.asynccontextmanager
async def replicas(url: str, n: int, *, peers: bool) -> AsyncIterator[list[Lobby]]:
    """``n`` lobbies on the allocator at ``url``; with ``peers``, each knows all of them."""
    lobbies = [
        Lobby(AgonesAllocator(url, namespace="labs", match_labels=FLEET), SECRET, port=0)
        for _ in range(n)
    ]
    for lobby in lobbies:
        await lobby.start()
    if peers:
        urls = [f"http://127.0.0.1:{lobby.port}" for lobby in lobbies]
        for lobby, me in zip(lobbies, urls, strict=True):
            lobby.peers = Peers.of(urls, me)
    try:
        yield lobbies
    finally:
        for lobby in lobbies:
            await lobby.stop()


async def test_two_lobbies_that_do_not_know_each_other_can_place_a_name_twice() -> None:
    with Allocator(fleet(3), lag_s=LAG_S) as alloc:
        async with replicas(alloc.url, 2, peers=False) as (a, b):
            answers = await asyncio.gather(ask(a, "/rooms/anatomy"), ask(b, "/rooms/anatomy"))
            assert [s for s, _, _ in answers] == [200, 200]
            # two servers each think they run the room: its users would not meet
            assert len(alloc.holding("anatomy")) == 2
            assert len({ans["url"] for _, _, ans in answers}) == 2


async def test_replicas_that_know_each_other_place_every_name_once() -> None:
    # a server per name: the stand-in's lagging view sends new names at once to Ready servers
    with Allocator(fleet(8), lag_s=LAG_S) as alloc:
        async with replicas(alloc.url, 2, peers=True) as (a, b):
            names = owned_half_and_half(a.peers, 8)
            # every name asked 3 times through each replica, all at once, by 48 users
            asked = [(n, lobby) for n in names for lobby in (a, b, a, b, a, b)]
            answers = await asyncio.gather(
                *(
                    ask(lobby, f"/rooms/{n}", f"127.0.3.{i + 1}")
                    for i, (n, lobby) in enumerate(asked)
                )
            )
            assert [s for s, _, _ in answers] == [200] * len(asked), answers
            for name in names:
                got = {
                    ans["url"]
                    for (n, _), (_, _, ans) in zip(asked, answers, strict=True)
                    if n == name
                }
                assert len(got) == 1, (name, got)  # every user of a name: one server
                assert len(alloc.holding(name)) == 1, (name, alloc.holding(name))
            # each replica signs tokens the room's server accepts, whichever placed the name
            for (name, _), (_, _, ans) in zip(asked, answers, strict=True):
                assert check_room_token(ans["token"], SECRET, name, ans["expires"] - 1) is not None
            # both replicas owned some names (the work is shared), and each name was
            # allocated by its owner only: one request per name reached the allocator
            assert a.counts.get(("peer_asked", ""), 0) > 0
            assert b.counts.get(("peer_asked", ""), 0) > 0
            allocated = [c.body["lists"]["rooms"]["addValues"][0] for c in alloc.calls]
            assert sorted(allocated) == sorted(names)


async def test_a_name_asked_again_while_the_allocators_cache_lags_stays_on_its_server() -> None:
    # each allocator pod matches against an informer cache that lags the writes: an allocation
    # soon after another for the same name does not see its list entry
    for remember_s, servers in ((0.0, 2), (3.0, 1)):
        with LaggingCacheAllocator(fleet(3), cache_lag_s=1.0) as alloc:
            backend = AgonesAllocator(alloc.url, match_labels=FLEET, remember_s=remember_s)
            lobby = Lobby(backend, SECRET, port=0)
            await lobby.start()
            try:
                first = await ask(lobby, "/rooms/anatomy", "127.0.4.1")
                again = await ask(lobby, "/rooms/anatomy", "127.0.4.2")  # right after
            finally:
                await lobby.stop()
            assert (first[0], again[0]) == (200, 200)
            # asking the allocator every time (remember_s 0) puts the second user elsewhere;
            # the lobby's memory of the placement keeps both on one server
            assert len(alloc.holding("anatomy")) == servers, remember_s
            assert (first[2]["url"] == again[2]["url"]) == (servers == 1)


async def test_while_a_names_owner_is_down_it_is_refused_not_placed_twice() -> None:
    with Allocator(fleet(3), lag_s=0.0) as alloc:
        async with replicas(alloc.url, 2, peers=True) as (a, b):
            assert a.peers is not None
            owned_by_b = next(
                f"room-{i}" for i in range(100) if a.peers.owner(f"room-{i}") != a.peers.self_url
            )
            status, _, first = await ask(a, f"/rooms/{owned_by_b}")
            assert status == 200
            await b.stop()
            status, headers, answer = await ask(a, f"/rooms/{owned_by_b}")
            assert status == 503
            assert headers["Retry-After"] == "2"
            assert "the lobby replica that places room" in answer["error"]
            assert alloc.holding(owned_by_b) == [first["server"]]
            assert len(alloc.calls) == 1  # a never allocated it itself


async def test_a_peer_request_without_the_replicas_signature_is_not_served() -> None:
    with Allocator(fleet(1)) as alloc:
        async with replicas(alloc.url, 2, peers=True) as (a, b):
            status, _, answer = await ask(a, "/peer/place/anatomy")
            assert status == 404
            assert "GET /rooms/NAME" in answer["error"]
            assert alloc.calls == []
            # a replica with another secret: the user is told what is wrong, not "not found"
            b._secret = b"o" * MIN_SECRET_BYTES
            assert a.peers is not None
            theirs = next(
                f"n-{i}" for i in range(100) if a.peers.owner(f"n-{i}") != a.peers.self_url
            )
            status, _, answer = await ask(a, f"/rooms/{theirs}")
            assert status == 502
            assert "do they share the token secret" in answer["error"]
            assert alloc.calls == []


def owned_half_and_half(peers: Peers | None, n: int) -> list[str]:
    """``n`` room names, half owned by each of two replicas (the ports, so the owners, vary)."""
    assert peers is not None and len(peers.urls) == 2
    pool = [f"lab-{i}" for i in range(1000)]
    first = [name for name in pool if peers.owner(name) == peers.urls[0]][: n // 2]
    second = [name for name in pool if peers.owner(name) == peers.urls[1]][: n - n // 2]
    return first + second


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_two_haptic_lobby_processes_given_as_peers_place_each_name_once(
    tmp_path: Path,
) -> None:
    secret, metrics = tmp_path / "secret", tmp_path / "metrics-token"
    secret.write_text("p" * 48)
    metrics.write_text("metrics-token-0123456789\n")
    ports = [free_port(), free_port()]
    urls = [f"http://127.0.0.1:{p}" for p in ports]
    names = owned_half_and_half(Peers.of(urls, urls[0]), 6)
    with Allocator(fleet(len(names)), lag_s=LAG_S) as alloc:
        procs = []
        try:
            for port, me in zip(ports, urls, strict=True):
                cmd = haptic(
                    "lobby", "--port", str(port), "--token-secret-file", str(secret),
                    "--agones-allocator", alloc.url, "--agones-fleet", "haptic-collab",
                    "--metrics-token-file", str(metrics),
                    "--peer", urls[0], "--peer", urls[1], "--peer-self", me,
                )  # fmt: skip
                procs.append(subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.DEVNULL))
            deadline = time.monotonic() + 60.0
            while any(not _listening(p) for p in ports):
                assert time.monotonic() < deadline, "the lobbies did not start"
                assert all(p.poll() is None for p in procs)
                await asyncio.sleep(0.1)
            lobbies = [_At(p) for p in ports]
            asked = [(n, i % 2) for i, n in enumerate(names * 4)]
            answers = await asyncio.gather(
                *(
                    ask(lobbies[which], f"/rooms/{n}", f"127.0.5.{i + 1}")
                    for i, (n, which) in enumerate(asked)
                )
            )
            assert [a[0] for a in answers] == [200] * len(asked), answers
            for name in names:
                assert len(alloc.holding(name)) == 1, (name, alloc.holding(name))
            # each process says, on its /metrics, how many names it asked the other to place
            conn = http.client.HTTPConnection("127.0.0.1", ports[0], timeout=10)
            conn.request(
                "GET", "/metrics", headers={"Authorization": "Bearer metrics-token-0123456789"}
            )
            text = conn.getresponse().read().decode()
            conn.close()
            got = {
                (m.name, tuple(m.labels.items())): m.value
                for f in text_string_to_metric_families(text)
                for m in f.samples
            }
            assert got["haptic_lobby_peer_requests_total", (("direction", "asked"),)] > 0
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                p.wait(10)


def _listening(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
        return True
    return False
