"""The client's link counts a join only when the server welcomes it, rejoins included."""

from __future__ import annotations

import asyncio

from haptic_collab.client.link import Link
from haptic_collab.client.session import ClientSession
from haptic_collab.shared.protocol import DeviceInfo, ErrorMsg, ObjectInfo, Welcome, encode

OBJ = ObjectInfo(
    n_vertices=6, n_faces=8, center_m=(0, 0, 0), radius_m=0.1, bounds_min_m=(-0.1, -0.1, -0.1),
    bounds_max_m=(0.1, 0.1, 0.1), top_m=(0, 0, 0.1), top_normal=(0, 0, 1), side_m=(0.1, 0, 0),
    side_normal=(1, 0, 0),
)  # fmt: skip
WELCOME = encode(Welcome(user_id="u1", name="A", role="viewer", sim_rate_hz=20.0, object=OBJ))
ROOM_FULL = encode(ErrorMsg(code="room_full", message="the room is full", fatal=True))


class ScriptedSocket:
    """Yields the frames a server sent on one connection, then ends (the server closed)."""

    def __init__(self, *frames: str) -> None:
        self.frames = list(frames)

    def __aiter__(self) -> ScriptedSocket:
        return self

    async def __anext__(self) -> str:
        if not self.frames:
            raise StopAsyncIteration
        return self.frames.pop(0)


def test_a_refused_rejoin_is_not_taken_for_a_join() -> None:
    welcomed: list[Welcome] = []
    session = ClientSession("A", device=DeviceInfo(), role="viewer")
    link = Link(
        "ws://127.0.0.1:1/ws",
        session,
        on_patch=lambda update, now: None,
        sample=lambda: None,
        clock=lambda: 0.0,
        on_welcome=welcomed.append,
    )

    async def main() -> None:
        await link._receive_loop(ScriptedSocket(WELCOME))  # type: ignore[arg-type]
        assert link.joins == 1 and link.connected.is_set() and len(welcomed) == 1
        link.connected.clear()  # the connection dropped; the client connects again
        await link._receive_loop(ScriptedSocket(ROOM_FULL))  # type: ignore[arg-type]
        # refused: not joined, not told it joined, so the backoff keeps growing
        assert link.joins == 1 and not link.connected.is_set() and len(welcomed) == 1
        await link._receive_loop(ScriptedSocket(WELCOME))  # type: ignore[arg-type]
        assert link.joins == 2 and link.connected.is_set() and len(welcomed) == 2

    asyncio.run(main())
