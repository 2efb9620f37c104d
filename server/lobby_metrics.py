"""Prometheus metrics of the lobby, gathered when scraped (``GET /metrics`` of ``haptic lobby``).

The lobby keeps plain counters (:class:`server.lobby.Lobby`: answers by status, events by kind
and reason, placement times; :class:`server.lobby_backends.AgonesAllocator`: the allocator's
answers); :class:`LobbyCollector` turns them into metric families on each scrape
(prometheus_client's custom-collector pattern, as :mod:`server.metrics` does for rooms).
:func:`lobby_registry` adds prometheus_client's own ``process_*`` (CPU seconds, resident
memory, open file descriptors against their limit, start time: Linux ``/proc``) and
``python_*`` collectors.

=============================================  =========  ============================================
metric                                         type       what
=============================================  =========  ============================================
haptic_lobby_requests_total{status}            counter    answers given, by HTTP status
haptic_lobby_connections                       gauge      connections open and counted now
haptic_lobby_connections_refused_total{reason} counter    connections over a cap (address, total)
haptic_lobby_connections_dropped_total         counter    cut off before their request was read
haptic_lobby_rooms_refused_total{reason}       counter    room requests refused: full (a user in a
                                                          full room), busy (no placement slot), or
                                                          the back end's status (404, 502, 503)
haptic_lobby_placement_seconds                 histogram  time to place a name (here or by its owner)
haptic_lobby_allocator_answers_total{code}     counter    the Agones allocator's answers: HTTP status,
                                                          timeout, unreachable
haptic_lobby_peer_requests_total{direction}    counter    placements asked of the owner replica
                                                          (asked) and done for another (served)
=============================================  =========  ============================================
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import GC_COLLECTOR, PLATFORM_COLLECTOR, PROCESS_COLLECTOR
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector, CollectorRegistry

if TYPE_CHECKING:
    from haptic_collab.server.lobby import Lobby

#: Upper bounds [s] of the placement-time histogram's buckets (a room's build takes seconds).
PLACEMENT_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class PlacementTimes:
    """A histogram of placement times kept as plain integers (read by :class:`LobbyCollector`).

    Attributes
    ----------
    counts : list of int, (len(PLACEMENT_BUCKETS_S) + 1,)
        Placements per bucket (not cumulative); the last is over the largest bound.
    total_s : float
        Sum of all placement times [s].
    """

    def __init__(self) -> None:
        self.counts = [0] * (len(PLACEMENT_BUCKETS_S) + 1)
        self.total_s = 0.0

    def add(self, seconds: float) -> None:
        """Count one placement that took ``seconds`` [s]."""
        i = next((i for i, b in enumerate(PLACEMENT_BUCKETS_S) if seconds <= b), -1)
        self.counts[i] += 1
        self.total_s += seconds


class LobbyCollector(Collector):
    """The lobby's metric families, read from ``lobby`` when scraped (on its event loop)."""

    def __init__(self, lobby: Lobby) -> None:
        self.lobby = lobby

    def collect(self) -> Iterator[Metric]:
        lobby = self.lobby
        requests = CounterMetricFamily(
            "haptic_lobby_requests", "Answers the lobby gave, by HTTP status.", labels=["status"]
        )
        for status, n in sorted(lobby.answered.items()):
            requests.add_metric([str(status)], n)
        yield requests
        yield GaugeMetricFamily(
            "haptic_lobby_connections",
            "Connections open and counted against the caps.",
            value=lobby.connections.open_total,
        )

        def by_reason(name: str, doc: str, kind: str, label: str = "reason") -> Metric:
            family = CounterMetricFamily(name, doc, labels=[label])
            for (k, reason), n in sorted(lobby.counts.items()):
                if k == kind:
                    family.add_metric([reason], n)
            return family

        yield by_reason(
            "haptic_lobby_connections_refused",
            "Connections over a cap: per address, or in all.",
            "connections_refused",
        )
        yield CounterMetricFamily(
            "haptic_lobby_connections_dropped",
            "Connections cut off before their request was read (too slow, too large).",
            value=lobby.dropped,
        )
        yield by_reason(
            "haptic_lobby_rooms_refused",
            "Room requests refused: full, busy, or the back end's HTTP status.",
            "rooms_refused",
        )
        times = lobby.placement_times
        buckets, running = [], 0
        for bound, n in zip(PLACEMENT_BUCKETS_S, times.counts, strict=False):
            running += n
            buckets.append((repr(bound), running))
        buckets.append(("+Inf", running + times.counts[-1]))
        yield HistogramMetricFamily(
            "haptic_lobby_placement_seconds",
            "Time to place a room name, here or by the replica that owns it [s].",
            buckets=buckets,
            sum_value=times.total_s,
        )
        answers = CounterMetricFamily(
            "haptic_lobby_allocator_answers",
            "The Agones allocator's answers: HTTP status, timeout or unreachable.",
            labels=["code"],
        )
        for code, n in sorted(getattr(lobby.backend, "answers", {}).items()):
            answers.add_metric([code], n)
        yield answers
        peers = CounterMetricFamily(
            "haptic_lobby_peer_requests",
            "Placements asked of the owner replica, and done for another replica.",
            labels=["direction"],
        )
        peers.add_metric(["asked"], lobby.counts.get(("peer_asked", ""), 0))
        peers.add_metric(["served"], lobby.counts.get(("peer_requests", ""), 0))
        yield peers


def lobby_registry(lobby: Lobby) -> CollectorRegistry:
    """A registry of the lobby's metrics and the process's (``process_*``, ``python_*``).

    The process and platform collectors are prometheus_client's; they describe the whole
    process, so one registry per process serves them (a second lobby in a test process shares
    the numbers).
    """
    registry = CollectorRegistry()
    registry.register(LobbyCollector(lobby))
    for collector in (PROCESS_COLLECTOR, PLATFORM_COLLECTOR, GC_COLLECTOR):
        registry.register(collector)
    return registry
