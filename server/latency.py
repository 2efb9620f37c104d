"""Latency injection for one direction of one connection: delay, jitter and loss, seeded.

Sans-I/O: :meth:`LinkShaper.schedule` takes the send time and returns when the frame may be
delivered, or None when it is dropped; the asyncio layer does the waiting. Time is passed in.

- delay: ``latency_ms`` plus a jitter drawn uniformly from ``[-jitter_ms, +jitter_ms]``, never
  negative; deliveries stay in order (a websocket is a TCP stream, so a late frame holds back the
  ones behind it), i.e. ``deliver_at = max(previous deliver_at + 1 us, now + delay)``: strictly
  increasing, so that timers scheduled for the deliveries fire in order.
- loss: each *droppable* frame (the latest-wins state streams: state, patch, room, vertices, ping,
  pong) is dropped with probability ``loss``; events (hello, welcome, error, bye) never are, since
  TCP would retransmit them — a lost state frame models a late one overtaken by its successor.
"""

from __future__ import annotations

import math
import random

from haptic_collab.shared.protocol import LinkConditions


class LinkShaper:
    """Schedules frames through one impaired direction. Deterministic for a given ``seed``.

    Parameters
    ----------
    config : LinkConditions
        The conditions to inject (the ones announced to clients in ``welcome.link``).
    seed : int or str, optional
        Seed of the jitter and loss draws.
    """

    def __init__(self, config: LinkConditions, seed: int | str | None = None) -> None:
        self.config = config
        self._rng = random.Random(seed)
        self._last_delivery_s = -math.inf
        self.dropped = 0
        self.sent = 0

    def schedule(self, now_s: float, droppable: bool) -> float | None:
        """Delivery time [s] of a frame sent at ``now_s`` [s], or None if it is dropped."""
        cfg = self.config
        self.sent += 1
        if droppable and cfg.loss > 0.0 and self._rng.random() < cfg.loss:
            self.dropped += 1
            return None
        delay_ms = cfg.latency_ms
        if cfg.jitter_ms > 0.0:
            delay_ms += self._rng.uniform(-cfg.jitter_ms, cfg.jitter_ms)
        at = now_s + max(0.0, delay_ms) / 1000.0
        if at <= self._last_delivery_s:  # strictly increasing: timers fire in this order
            at = self._last_delivery_s + 1e-6
        self._last_delivery_s = at
        return at
