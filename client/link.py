"""The client's network link: websockets only. Joins the room, pumps frames, reconnects.

All protocol decisions are in :class:`client.session.ClientSession`; this module connects, sends
``hello``, sends the servo loop's latest ``state`` every half simulation period (latest wins: an old
state is never queued behind a new one) and a ``ping`` twice a second, hands each patch to the servo
loop through ``on_patch``, and reconnects with exponential backoff when the server goes away. The
servo loop never waits on any of this: when the link falls silent it ramps its forces to zero by its
own timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import Callable

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from client.session import ClientSession, PatchUpdate, ServoSample
from shared.protocol import ProtocolError, Welcome

log = logging.getLogger("haptic.client")

PING_INTERVAL_S = 0.5


class Link:
    """Runs one session over a websocket until ``stop`` is set.

    Parameters
    ----------
    url : str
        ``ws://HOST:PORT/ws``.
    session : ClientSession
        Protocol state.
    on_patch : callable(PatchUpdate, float)
        Called with each new patch and the local time [s] it arrived (hand it to the servo loop).
    sample : callable() -> ServoSample or None
        The servo loop's latest sample (None: nothing to report yet).
    clock : callable() -> float
        Monotonic clock [s], the same one the servo loop uses.
    on_welcome : callable(Welcome), optional
        Called on every (re)join.
    backoff_s : (float, float)
        First and largest reconnect delay [s].
    """

    def __init__(
        self,
        url: str,
        session: ClientSession,
        *,
        on_patch: Callable[[PatchUpdate, float], None],
        sample: Callable[[], ServoSample | None],
        clock: Callable[[], float],
        on_welcome: Callable[[Welcome], None] | None = None,
        backoff_s: tuple[float, float] = (0.2, 5.0),
    ) -> None:
        self.url = url
        self.session = session
        self.on_patch = on_patch
        self.sample = sample
        self.clock = clock
        self.on_welcome = on_welcome
        self.backoff_s = backoff_s
        self.connected = asyncio.Event()
        self.joins = 0
        self.protocol_errors = 0

    async def run(self, stop: asyncio.Event) -> None:
        """Connect, serve, reconnect with backoff until ``stop`` is set."""
        delay = self.backoff_s[0]
        while not stop.is_set():
            joins = self.joins
            try:
                async with connect(self.url, max_size=8 * 1024 * 1024, open_timeout=5.0) as ws:
                    await self._serve(ws, stop)
            except (OSError, InvalidHandshake, TimeoutError, ConnectionClosed) as exc:
                if not stop.is_set():
                    log.info("link to %s down (%s); retrying in %.1f s", self.url, exc, delay)
            except InvalidURI as exc:
                raise ValueError(f"bad server URL {self.url!r}: {exc}") from None
            finally:
                self.connected.clear()
                if self.joins > joins:
                    delay = self.backoff_s[0]  # a session that joined resets the backoff
            if stop.is_set():
                break
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), delay * (0.8 + 0.4 * random.random()))
            delay = min(self.backoff_s[1], delay * 2.0)

    async def _serve(self, ws: ClientConnection, stop: asyncio.Event) -> None:
        await ws.send(self.session.hello())
        sender = asyncio.create_task(self._send_loop(ws))
        stopper = asyncio.create_task(stop.wait())
        try:
            receiver = asyncio.create_task(self._receive_loop(ws))
            done, _ = await asyncio.wait({receiver, stopper}, return_when=asyncio.FIRST_COMPLETED)
            if stopper in done:
                with contextlib.suppress(ConnectionClosed):
                    await ws.send('{"type":"bye"}')
                receiver.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                    await receiver
            else:
                receiver.result()  # re-raise ConnectionClosed and the like
        finally:
            sender.cancel()
            stopper.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                await sender

    async def _receive_loop(self, ws: ClientConnection) -> None:
        async for frame in ws:
            now = self.clock()
            n_errors = len(self.session.errors)
            try:
                update = self.session.receive(frame, now)
            except ProtocolError as exc:
                self.protocol_errors += 1
                log.warning("ignoring a bad frame from the server: %s", exc)
                continue
            if len(self.session.errors) > n_errors:
                err = self.session.errors[-1]
                level = logging.ERROR if err.fatal else logging.WARNING
                log.log(level, "server: %s (%s)", err.message, err.code)
            if update is not None:
                self.on_patch(update, now)
            elif self.session.welcome is not None and not self.connected.is_set():
                self.joins += 1
                self.connected.set()
                if self.on_welcome:
                    self.on_welcome(self.session.welcome)

    async def _send_loop(self, ws: ClientConnection) -> None:
        await self.connected.wait()
        next_ping = self.clock()
        while True:
            interval = self.session.state_interval_s
            if self.session.role == "user":
                sample = self.sample()
                if sample is not None:
                    try:
                        frame = self.session.state(sample)
                    except ValueError as exc:  # e.g. a non-finite sample: skip it, keep the link
                        log.warning("not sending an invalid state: %s", exc)
                    else:
                        await ws.send(frame)
            now = self.clock()
            if now >= next_ping:
                await ws.send(self.session.ping(now))
                next_ping = now + PING_INTERVAL_S
            await asyncio.sleep(interval)
