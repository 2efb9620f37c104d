"""``haptic lobby``'s ``/metrics``: what an operator's Prometheus reads, and who may read it.

A real lobby on loopback with the Agones back end against the stand-in allocator; the scrape is
parsed with prometheus_client's own parser. What an operator notices: the answers by status, a
room refused because no GameServer is free (the allocator's 429 counted as such), placement
times, and the process's own ``process_*`` figures; a scrape without the metrics token is
refused.
"""

from __future__ import annotations

import asyncio
import http.client
from concurrent.futures import ThreadPoolExecutor

from prometheus_client.parser import text_string_to_metric_families

from haptic_collab.server.lobby import AgonesAllocator, Lobby
from haptic_collab.server.security import MIN_SECRET_BYTES, TokenTable
from tests.support.agones_allocator import Allocator, GameServer

SECRET = b"m" * MIN_SECRET_BYTES
METRICS_TOKEN = "lobby-metrics-token-0123456789"
ASKERS = ThreadPoolExecutor(8, thread_name_prefix="asker")


def get(port: int, path: str, token: str = "") -> tuple[int, str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request("GET", path, headers={"Authorization": f"Bearer {token}"} if token else {})
        r = conn.getresponse()
        return r.status, r.read().decode()
    finally:
        conn.close()


async def aget(port: int, path: str, token: str = "") -> tuple[int, str]:
    return await asyncio.get_running_loop().run_in_executor(ASKERS, lambda: get(port, path, token))


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


async def test_metrics_count_answers_refused_rooms_allocator_429s_and_the_process() -> None:
    token = TokenTable.single(METRICS_TOKEN)
    one = [
        GameServer("gs-0", port=7000, lists={"rooms": {"capacity": 1, "values": []}}),
    ]
    with Allocator(one) as alloc:
        backend = AgonesAllocator(alloc.url, namespace="labs")
        lobby = Lobby(backend, SECRET, port=0, metrics_token=token)
        await lobby.start()
        try:
            assert (await aget(lobby.port, "/rooms/first"))[0] == 200
            # the only server's one room slot is taken: the allocator answers 429
            assert (await aget(lobby.port, "/rooms/second"))[0] == 503
            assert (await aget(lobby.port, "/rooms/Bad_Name"))[0] == 400
            # without the token, or with another, no figures
            assert (await aget(lobby.port, "/metrics"))[0] == 401
            assert (await aget(lobby.port, "/metrics", "wrong-token-0123456789abc"))[0] == 401
            status, text = await aget(lobby.port, "/metrics", METRICS_TOKEN)
            assert status == 200
            got = samples(text)
        finally:
            await lobby.stop()
    assert got["haptic_lobby_requests_total", (("status", "200"),)] == 2  # the room, this scrape
    assert got["haptic_lobby_requests_total", (("status", "503"),)] == 1
    assert got["haptic_lobby_requests_total", (("status", "400"),)] == 1
    assert got["haptic_lobby_requests_total", (("status", "401"),)] == 2
    assert got["haptic_lobby_allocator_answers_total", (("code", "200"),)] == 1
    assert got["haptic_lobby_allocator_answers_total", (("code", "429"),)] == 1
    assert got["haptic_lobby_rooms_refused_total", (("reason", "503"),)] == 1
    assert got["haptic_lobby_placement_seconds_count", ()] == 2
    assert got["haptic_lobby_connections", ()] >= 1  # the scrape's own
    # prometheus_client's process collector: what an operator's dashboards expect by name
    assert got["process_resident_memory_bytes", ()] > 10e6
    assert 0 < got["process_open_fds", ()] < got["process_max_fds", ()]
    assert got["process_start_time_seconds", ()] > 1.7e9
