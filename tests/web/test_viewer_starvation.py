"""A viewer that reads slowly still gets ``room`` summaries (issue 61: 0 in 15 s, 34 surface frames).

The server's own queue and sender (``ServerApp._ready``, ``ServerApp._sender``) for one viewer,
fed what ``Room.tick`` makes every tick (a surface frame, stream ``vertices``, then a ``room``
summary, stream ``room``), to a socket on which each surface frame takes longer than a tick to
write (its buffer is full: a busy browser reads slowly). Latest-wins used to remove the queued
older frame of a stream and append the newer one at the end, so the summary always sat behind
the next surface frame and was replaced again while that one was written: none was ever sent.
With each newer frame taking its older one's place in the queue, summaries and surface frames
alternate.
"""

from __future__ import annotations

import asyncio

from haptic_collab.server.app import ServerApp, _Peer
from haptic_collab.server.room import Outgoing, Room
from tests.web.test_viewer import SIM_RATE_HZ, _world

TICKS = 60  # 3 s at 20 Hz
SURFACE_SEND_S = 0.1  # two ticks per surface frame written


class SlowSocket:
    """A socket on which a binary frame takes :data:`SURFACE_SEND_S` to write."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    async def send(self, data: str | bytes) -> None:
        if isinstance(data, bytes):
            await asyncio.sleep(SURFACE_SEND_S)
        self.sent.append("surface" if isinstance(data, bytes) else "room")


async def test_a_slow_viewer_still_gets_room_summaries() -> None:
    app = ServerApp(Room(_world(2), SIM_RATE_HZ), "127.0.0.1", 0)
    ws = SlowSocket()
    peer = _Peer("c1", ws, None, None)  # type: ignore[arg-type]  # no injected latency: unused
    sender = asyncio.create_task(app._sender(peer))
    try:
        for _ in range(TICKS):
            app._ready(peer, Outgoing("c1", b"DSP1" + bytes(2000), stream="vertices"))
            app._ready(peer, Outgoing("c1", '{"type": "room"}', stream="room"))
            await asyncio.sleep(1.0 / SIM_RATE_HZ)
    finally:
        sender.cancel()
    surface, room = ws.sent.count("surface"), ws.sent.count("room")
    assert surface >= 5  # the surface frames went out, at the socket's pace
    # at least one summary for every two surface frames (the fix gives one for each)
    assert room >= surface // 2, f"{room} room summaries, {surface} surface frames"
