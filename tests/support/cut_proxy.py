"""A TCP relay on loopback whose link can be cut for a while, as a network cut does.

During a cut nothing crosses in either direction, and nothing is closed: bytes and closes wait
and cross when the cut ends (TCP retransmits them), and a connection opened during the cut is
accepted here but reaches the server only when it ends (a SYN retransmitted). So a client sees
a silent link, not a closed one, and the server sees the old connection open until the client's
close crosses after the cut.
"""

from __future__ import annotations

import asyncio
import contextlib


class CutProxy:
    """Relays ``127.0.0.1:PORT`` (:attr:`port`, chosen by the system) to ``127.0.0.1:target_port``.

    Parameters
    ----------
    target_port : int
        The server's port on 127.0.0.1.
    """

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = 0
        self._cut_until = 0.0
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        #: Connections accepted so far.
        self.connections = 0

    async def start(self) -> CutProxy:
        """Listen on an ephemeral loopback port."""
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def stop(self) -> None:
        """Stop listening and drop every relayed connection."""
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await task

    def cut(self, seconds: float) -> None:
        """Cut the link for ``seconds`` [s] from now."""
        self._cut_until = asyncio.get_running_loop().time() + float(seconds)

    @property
    def is_cut(self) -> bool:
        """Whether the link is cut now."""
        return asyncio.get_running_loop().time() < self._cut_until

    async def _through(self) -> None:
        """Return once the link is not cut."""
        loop = asyncio.get_running_loop()
        while (left := self._cut_until - loop.time()) > 0.0:
            await asyncio.sleep(left)

    async def _accept(self, c_reader: asyncio.StreamReader, c_writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            await self._through()
            try:
                s_reader, s_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
            except OSError:
                c_writer.transport.abort()
                return
            await asyncio.gather(self._pipe(c_reader, s_writer), self._pipe(s_reader, c_writer))
        finally:
            self._tasks.discard(task)

    async def _pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Copy one direction; bytes and the end of the stream wait out any cut."""
        try:
            while data := await reader.read(65536):
                await self._through()
                writer.write(data)
                await writer.drain()
        except OSError:
            pass
        await self._through()
        writer.transport.abort()  # the other side's close (or reset) crosses now
