"""Prometheus metrics of the server's rooms, gathered when scraped (``GET /metrics``).

The simulation tick never touches a Prometheus object: the I/O layer (:mod:`server.app`) keeps
plain counters per room (:class:`RoomFigures`: two integer histograms it adds one tick to, the
patches and viewer bytes its senders wrote), the room keeps its own (ticks, overruns, users,
viewers, clamped forces), and :class:`ServerCollector` reads them all on each scrape and turns
them into metric families (prometheus_client's custom-collector pattern).

Every per-room family has a ``room`` label; the rooms are the server's
(:meth:`server.app.ServerApp.rooms`: today one, ``default``).

=========================================  =========  =============================================
metric                                     type       what
=========================================  =========  =============================================
haptic_room_tick_seconds                   histogram  wall time of each simulation tick [s]
haptic_room_tick_lateness_seconds          histogram  how late each tick started after it was due [s]
haptic_room_ticks_total                    counter    simulation ticks run (skipped: in overruns)
haptic_room_overruns_total                 counter    ticks longer than a period, and ticks skipped
haptic_room_users / _viewers               gauge      connections welcomed as users / viewers
haptic_room_patches_sent_total             counter    local-model patches written to users (rate():
                                                      the patch rate; users x sim rate when on time)
haptic_room_viewer_bytes_sent_total        counter    surface-stream bytes written to viewers (the
                                                      binary frames: faces, normals, keyframe, then
                                                      the displacement frames)
haptic_room_force_clamps_total             counter    user forces the server bounded
haptic_room_sim_rate_hertz                 gauge      the room's simulation rate [Hz]
haptic_send_timeouts_total                 counter    consumers dropped for a full send buffer
haptic_origins_refused_total               counter    browser handshakes refused for their Origin
=========================================  =========  =============================================

Who may scrape (docs/security.md): :func:`scrape_allowed`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from haptic_collab.server.security import TokenTable

if TYPE_CHECKING:
    from haptic_collab.server.app import ServerApp

#: Upper bounds [s] of the tick-time histogram's buckets (a 20 Hz period is 0.05 s).
TICK_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.5, 1.0)
#: Upper bounds [s] of the lateness histogram's buckets.
LATENESS_BUCKETS_S = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 5.0)


class Buckets:
    """A histogram kept as plain integers: one :meth:`add` per observation (a bisection and
    two additions), read by the collector as Prometheus' cumulative buckets.

    Parameters
    ----------
    bounds : tuple of float
        Increasing upper bounds [s] (a value equal to a bound falls in that bound's bucket);
        a last bucket, ``+Inf``, takes the rest.
    """

    def __init__(self, bounds: tuple[float, ...]) -> None:
        if list(bounds) != sorted(set(bounds)) or not all(math.isfinite(b) for b in bounds):
            raise ValueError("bounds must be finite and strictly increasing")
        self.bounds = tuple(float(b) for b in bounds)
        self.counts = [0] * (len(bounds) + 1)
        self.total = 0.0

    def add(self, value: float) -> None:
        """Count one observation ``value`` [s]."""
        self.counts[bisect.bisect_left(self.bounds, value)] += 1
        self.total += value

    def cumulative(self) -> list[tuple[str, float]]:
        """``[(le, count of observations <= le), ..., ("+Inf", all)]``."""
        out, running = [], 0
        for bound, n in zip((*map(repr, self.bounds), "+Inf"), self.counts, strict=True):
            running += n
            out.append((bound, float(running)))
        return out


@dataclass
class RoomFigures:
    """What the I/O layer counts for one room (kept by :class:`server.app.ServerApp`)."""

    tick_s: Buckets = field(default_factory=lambda: Buckets(TICK_BUCKETS_S))
    lateness_s: Buckets = field(default_factory=lambda: Buckets(LATENESS_BUCKETS_S))
    patches_sent: int = 0
    viewer_bytes_sent: int = 0


class ServerCollector(Collector):
    """Reads a :class:`server.app.ServerApp`'s rooms and figures when scraped.

    Call :meth:`collect` on the event loop's thread (the app serves ``/metrics`` there).
    """

    def __init__(self, app: ServerApp) -> None:
        self.app = app

    def collect(self) -> Iterator[Metric]:
        app = self.app
        tick = HistogramMetricFamily(
            "haptic_room_tick_seconds", "Wall time of each simulation tick.", labels=["room"]
        )
        late = HistogramMetricFamily(
            "haptic_room_tick_lateness_seconds",
            "How late each simulation tick started after it was due.",
            labels=["room"],
        )

        def counter(name: str, doc: str) -> CounterMetricFamily:
            return CounterMetricFamily(name, doc, labels=["room"])

        def gauge(name: str, doc: str) -> GaugeMetricFamily:
            return GaugeMetricFamily(name, doc, labels=["room"])

        ticks = counter("haptic_room_ticks", "Simulation ticks run.")
        overruns = counter(
            "haptic_room_overruns", "Ticks longer than a period, and ticks skipped behind."
        )
        patches = counter("haptic_room_patches_sent", "Local-model patches written to users.")
        vbytes = counter("haptic_room_viewer_bytes_sent", "Surface-stream bytes sent to viewers.")
        clamps = counter("haptic_room_force_clamps", "User forces the server bounded.")
        users = gauge("haptic_room_users", "Connections welcomed as users.")
        viewers = gauge("haptic_room_viewers", "Connections welcomed as viewers.")
        rate = gauge("haptic_room_sim_rate_hertz", "The room's simulation rate.")
        for name, room in app.rooms().items():
            fig = app.figures.get(name)
            if fig is not None:
                tick.add_metric([name], fig.tick_s.cumulative(), fig.tick_s.total)
                late.add_metric([name], fig.lateness_s.cumulative(), fig.lateness_s.total)
                patches.add_metric([name], fig.patches_sent)
                vbytes.add_metric([name], fig.viewer_bytes_sent)
            ticks.add_metric([name], room.ticks_run)
            overruns.add_metric([name], room.stats.overruns)
            clamps.add_metric([name], sum(room.clamp_counts.values()))
            users.add_metric([name], len(room.users))
            viewers.add_metric([name], len(room.viewers))
            rate.add_metric([name], room.sim_rate_hz)
        yield from (tick, late, ticks, overruns, patches, vbytes, clamps, users, viewers, rate)
        yield CounterMetricFamily(
            "haptic_send_timeouts",
            "Consumers dropped because their send buffer stayed full.",
            value=app.send_timeouts,
        )
        yield CounterMetricFamily(
            "haptic_origins_refused",
            "Browser handshakes refused for their Origin.",
            value=app.origins_refused,
        )


def scrape_allowed(
    server_on_loopback: bool, authorization: str | None, token: TokenTable | None
) -> bool:
    """Whether a scrape of ``/metrics`` may be answered.

    With a metrics token (``token``), only a request carrying ``Authorization: Bearer TOKEN``
    (compared in constant time, :meth:`server.security.TokenTable.check`), wherever the server
    listens. Without one, only a server listening on loopback answers (only local processes can
    reach it), as a server off loopback refuses to admit anyone without tokens.

    Parameters
    ----------
    server_on_loopback : bool
        The server listens on a loopback address only.
    authorization : str or None
        The request's ``Authorization`` header.
    token : TokenTable or None
        The metrics token (``--metrics-token-file``), None without one.
    """
    if token is None:
        return server_on_loopback
    scheme, _, presented = (authorization or "").strip().partition(" ")
    return scheme.lower() == "bearer" and token.check(presented.strip()) is not None
