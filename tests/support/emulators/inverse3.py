"""An emulated Haply Inverse3 on a pseudo-terminal, for driving the real HaplyHardwareAPI binding.

The emulator is our own code, written from the wire protocol the binding speaks (probed against
HaplyHardwareAPI 0.1.13 on a pty; /tmp/vendor-research/REPORT.md): one command byte, then a
little-endian float32 payload, no length, checksum or terminator.

=========  ============================  =========================================================
command    payload                       reply
=========  ============================  =========================================================
``0x0A``   none (wake-up)                ``0x0B`` + u16 device id + u8 model + u8 hardware version
                                         + u8 firmware version + 16-byte UUID (22 bytes)
``0x2A``   fx, fy, fz [N]                ``0x2B`` + position x, y, z [m] + velocity [m/s] (25 bytes)
``0x2C``   position setpoint x, y, z     ``0x2B`` state, as above
``0xAC``   none (power status)           ``0xAC`` + u8 (1: powered)
``0xAA``   none (temperature)            ``0xAA`` + float32 [deg C]
=========  ============================  =========================================================

The pty's master side is served by a separate *process* (multiprocessing, ``spawn``): an
emulator thread in the test's own process starves (the binding busy-polls the port), see the
research report. The child opens the pty itself and sends the slave's path back; it keeps a slave
descriptor of its own open, so the binding can close and reopen the port while the emulator
lives. The test talks to the child through shared memory: the state to report (device frame),
whether to answer at all (:meth:`Inverse3Emulator.set_silent`), and what it received (every force,
in newtons, device frame, in :meth:`Inverse3Emulator.forces`; the number of wake-ups).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import select
import struct
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from types import TracebackType
from typing import Any

#: Forces remembered (a ring buffer; :meth:`Inverse3Emulator.forces` returns the newest).
FORCE_HISTORY = 4096

WAKEUP = 0x0A
WAKEUP_REPLY = 0x0B
FORCE = 0x2A
POSITION = 0x2C
STATE_REPLY = 0x2B
POWER = 0xAC
TEMPERATURE = 0xAA

_F3 = struct.Struct("<3f")
_F6 = struct.Struct("<6f")
_INFO = struct.Struct("<HBBB")


def _serve(
    reply_path: Connection,
    stop: Any,
    silent: Any,
    state: Any,
    forces: Any,
    counters: Any,
    identity: tuple[int, int, int, int, bytes],
) -> None:
    """The child process: open a pty, send its slave path, answer the binding until ``stop``.

    ``state``: 6 doubles (position [m], velocity [m/s], device frame) to report. ``forces``: ring
    buffer of 3 x FORCE_HISTORY doubles. ``counters``: [forces received, wake-ups received, bytes
    of unknown commands].
    """
    import pty
    import tty

    parent = os.getppid()
    master, slave = pty.openpty()
    tty.setraw(slave)
    reply_path.send(os.ttyname(slave))
    reply_path.close()
    dev_id, model, hw, fw, uuid = identity
    wake_reply = bytes([WAKEUP_REPLY]) + _INFO.pack(dev_id, model, hw, fw) + uuid
    buf = bytearray()

    def state_reply() -> bytes:
        with state.get_lock():
            values = tuple(state[:])
        return bytes([STATE_REPLY]) + _F6.pack(*values)

    def answer(data: bytes) -> None:
        if not silent.value:
            os.write(master, data)

    try:
        while not stop.is_set() and os.getppid() == parent:  # end with the test's process
            ready, _, _ = select.select([master], [], [], 0.02)
            if not ready:
                continue
            try:
                chunk = os.read(master, 4096)
            except OSError:  # every slave descriptor closed for a moment: keep serving
                time.sleep(0.001)
                continue
            buf += chunk
            while buf:
                cmd = buf[0]
                if cmd in (FORCE, POSITION):
                    if len(buf) < 1 + _F3.size:
                        break  # wait for the rest of the payload
                    payload = _F3.unpack_from(buf, 1)
                    del buf[: 1 + _F3.size]
                    if cmd == FORCE:
                        with counters.get_lock():
                            i = counters[0] % FORCE_HISTORY
                            forces[3 * i : 3 * i + 3] = list(payload)
                            counters[0] += 1
                    answer(state_reply())
                    continue
                del buf[0]
                if cmd == WAKEUP:
                    with counters.get_lock():
                        counters[1] += 1
                    answer(wake_reply)
                elif cmd == POWER:
                    answer(bytes([POWER, 1]))
                elif cmd == TEMPERATURE:
                    answer(bytes([TEMPERATURE]) + struct.pack("<f", 31.5))
                else:
                    with counters.get_lock():
                        counters[2] += 1
    finally:
        os.close(master)
        os.close(slave)


class Inverse3Emulator:
    """An emulated Inverse3 served on a pty by a child process (a context manager).

    Parameters
    ----------
    position : (3,) float
        Position [m] it reports at first, device frame.
    device_id : int
        Device id in the wake-up reply.
    uuid : bytes
        16-byte UUID in the wake-up reply (all zeros is what the binding returns on a timeout).

    Attributes
    ----------
    path : str
        The pty slave to open (``/dev/pts/N``), what ``--device haply:PATH`` names.
    """

    def __init__(
        self,
        position: Sequence[float] = (0.0, -0.14, 0.20),
        *,
        device_id: int = 0x049D,
        uuid: bytes = bytes(range(1, 17)),
    ) -> None:
        if len(uuid) != 16:
            raise ValueError("uuid must be 16 bytes")
        ctx = mp.get_context("spawn")
        self._stop = ctx.Event()
        self._silent = ctx.Value("b", 0)
        self._state = ctx.Array("d", [*map(float, position), 0.0, 0.0, 0.0])
        self._forces = ctx.Array("d", 3 * FORCE_HISTORY)
        self._counters = ctx.Array("q", 3)
        parent, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(
            target=_serve,
            args=(
                child,
                self._stop,
                self._silent,
                self._state,
                self._forces,
                self._counters,
                (device_id, 4, 7, 1, bytes(uuid)),
            ),
            name="inverse3-emulator",
            daemon=True,
        )
        self._proc.start()
        child.close()
        if not parent.poll(20.0):
            self.close()
            raise RuntimeError("the Inverse3 emulator did not start")
        self.path: str = parent.recv()
        parent.close()

    # -- what the test sets ----------------------------------------------------------------------

    def set_state(
        self, position: Sequence[float], velocity: Sequence[float] = (0.0, 0.0, 0.0)
    ) -> None:
        """Report this position [m] and velocity [m/s] (device frame) from now on."""
        with self._state.get_lock():
            self._state[:] = [*map(float, position), *map(float, velocity)]

    def set_silent(self, silent: bool) -> None:
        """Stop answering (still reading and recording forces), or answer again."""
        self._silent.value = 1 if silent else 0

    def unplug(self) -> None:
        """End the child process: the pty's master side closes, as when the USB cable is pulled."""
        self._stop.set()
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)

    # -- what the test reads ---------------------------------------------------------------------

    @property
    def alive(self) -> bool:
        return self._proc.is_alive()

    @property
    def force_count(self) -> int:
        """How many force commands (``0x2A``) arrived so far."""
        return int(self._counters[0])

    @property
    def wakeups(self) -> int:
        """How many wake-up commands (``0x0A``) arrived so far."""
        return int(self._counters[1])

    @property
    def unknown_bytes(self) -> int:
        """Bytes of commands the emulator does not know (a protocol mismatch)."""
        return int(self._counters[2])

    def forces(self) -> list[tuple[float, float, float]]:
        """Every force [N] received (device frame), oldest first (at most FORCE_HISTORY)."""
        with self._counters.get_lock():
            n = int(self._counters[0])
            flat = list(self._forces[:])
        first = max(0, n - FORCE_HISTORY)
        out = []
        for k in range(first, n):
            i = k % FORCE_HISTORY
            out.append((flat[3 * i], flat[3 * i + 1], flat[3 * i + 2]))
        return out

    def last_force(self) -> tuple[float, float, float] | None:
        """The newest force [N] received, or None."""
        got = self.forces()
        return got[-1] if got else None

    def wait_for_forces(self, count: int, timeout_s: float = 5.0) -> bool:
        """Wait until ``count`` force commands arrived in all; False on timeout."""
        end = time.monotonic() + timeout_s
        while self.force_count < count:
            if time.monotonic() > end:
                return False
            time.sleep(0.001)
        return True

    # -- lifetime ----------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the child process (idempotent)."""
        self.unplug()

    def __enter__(self) -> Inverse3Emulator:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
