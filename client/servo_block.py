"""The shared-memory block between the client's link process and its servo process.

It owns the block's layout and each side's reads and writes of it (:class:`SharedBlock`), used by
the link-side handle (:mod:`client.servo_process`) and by the servo process
(:mod:`client.servo_child`): int64 header words, the latest published tick (a seqlock: the writer
makes the sequence odd, writes, makes it even; a reader retries while it is odd or changed), the
period window, the patch (a pickled :class:`shared.local_model_update.LocalModelUpdate` under its
own seqlock; latest wins, as with the thread's reference swap), the status (pickled on request) and
the telemetry ring (:class:`client.recorder.TelemetryRecorder` over shared memory). Each side writes
its own words only, so no lock is taken and the servo never waits on the link.

The seqlock relies on the stores of one process being seen in order by the other (x86-64's
memory model); each store here is one aligned 8-byte write made by CPython's C code.
"""

from __future__ import annotations

import pickle
import struct
from multiprocessing.shared_memory import SharedMemory
from typing import Any

from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.servo import PUBLISHED
from haptic_collab.shared.local_model_update import LocalModelUpdate

__all__ = [
    "FLOAT_WORDS",
    "HEADER_WORDS",
    "PATCH_BYTES",
    "STATUS_BYTES",
    "ServoProcessError",
    "SharedBlock",
]

# Header words (int64, indices into SharedBlock.hdr), each written by one side only: (L) the link
# process, (S) the servo process.
HDR_PATCH_SEQ = 0  # L: seqlock of the patch region
HDR_PATCH_LEN = 1  # L: bytes of the pickled patch
HDR_PUB_SEQ = 2  # S: seqlock of the published tick
HDR_FORCES = 3  # L: 1 enable, 0 disable (applied when HDR_FORCES_SEQ changes)
HDR_FORCES_SEQ = 4  # L
HDR_STOP = 5  # L: 1 = ramp forces down and end the loop
HDR_STATUS_REQ = 6  # L: asks for a status (a new number each time)
HDR_STATUS_ACK = 7  # S: the request number whose status is in the status region
HDR_STATUS_LEN = 8  # S: bytes of the pickled status
HDR_REC_COUNT = 9  # S: telemetry rows ever appended
HDR_STATE = 10  # S: 0 starting, 1 running, 2 ended
HDR_OVERRUNS = 11  # S: deadlines missed and skipped
HEADER_WORDS = 16
# float64 words after the header (indices into SharedBlock.flt)
FLT_LINK_S = 0  # L: servo time [s] the server last spoke
FLT_PUB = 1  # S: PUBLISHED values of the newest tick
FLOAT_WORDS = 16

#: Bytes of the patch region (the largest pickled patch).
PATCH_BYTES = 1 << 16
#: Bytes of the status region.
STATUS_BYTES = 1 << 16

#: Values of the HDR_STATE word: the servo process is starting, runs its loop, has ended.
STATE_STARTING, STATE_RUNNING, STATE_ENDED = 0, 1, 2


class _SharedMemory(SharedMemory):
    """A block whose mapping may outlive its last close: views (the telemetry ring a recording
    still reads) keep it mapped until the process ends, without an error at collection."""

    def __del__(self) -> None:
        try:
            self.close()
        except BufferError:
            pass


class ServoProcessError(RuntimeError):
    """The servo process could not be started, or ended unexpectedly."""


class SharedBlock:
    """The shared-memory block between the link process and the servo process (module doc).

    Parameters
    ----------
    capacity : int
        Telemetry rows of the ring, >= 1.
    period_window : int
        Periods kept for the period statistics, >= 2.
    name : str, optional
        Attach to the block of this name (the servo process); default: create a new one.

    Attributes
    ----------
    shm : SharedMemory
        The block.
    hdr : memoryview
        The int64 header words.
    flt : memoryview
        The float64 words (link time, published tick).
    periods : memoryview
        The period window [s] (bytes; :class:`client.servo.ServoCore` casts it).
    """

    def __init__(self, capacity: int, period_window: int, name: str | None = None) -> None:
        self.capacity = int(capacity)
        self.period_window = int(period_window)
        ring = TelemetryRecorder.nbytes(self.capacity)
        off = 0
        self._hdr = (off, 8 * HEADER_WORDS)
        off += 8 * HEADER_WORDS
        self._flt = (off, 8 * FLOAT_WORDS)
        off += 8 * FLOAT_WORDS
        self._per = (off, 8 * self.period_window)
        off += 8 * self.period_window
        self._patch = (off, PATCH_BYTES)
        off += PATCH_BYTES
        self._status = (off, STATUS_BYTES)
        off += STATUS_BYTES
        self._ring = (off, ring)
        off += ring
        if name is None:
            self.shm: SharedMemory = _SharedMemory(create=True, size=off)
        else:
            self.shm = _SharedMemory(name=name)
            if self.shm.size < off:
                raise ServoProcessError(f"shared block {name} is {self.shm.size} bytes, not {off}")
        buf = self.shm.buf
        assert buf is not None
        self._buf = buf
        self.hdr = buf[self._hdr[0] : sum(self._hdr)].cast("q")
        self.flt = buf[self._flt[0] : sum(self._flt)].cast("d")
        self.periods = buf[self._per[0] : sum(self._per)]
        self.patch = buf[self._patch[0] : sum(self._patch)]
        self.status = buf[self._status[0] : sum(self._status)]
        self.ring = buf[self._ring[0] : sum(self._ring)]
        self._pub = struct.Struct(f"{PUBLISHED}d")
        self._pub_off = self._flt[0] + 8 * FLT_PUB

    @property
    def name(self) -> str:
        """The block's name (to attach from another process)."""
        return self.shm.name

    def recorder(self) -> TelemetryRecorder:
        """A :class:`TelemetryRecorder` over the shared ring (both sides see the same rows)."""
        return TelemetryRecorder(
            self.capacity, buffer=self.ring, counter=self.hdr[HDR_REC_COUNT : HDR_REC_COUNT + 1]
        )

    # -- the published tick (servo writes, link reads) --------------------------------------------
    def publish(self, pub: tuple[Any, ...]) -> None:
        """Write the newest tick's :data:`client.servo.PUBLISHED` values (servo side)."""
        hdr = self.hdr
        seq = hdr[HDR_PUB_SEQ] + 1
        hdr[HDR_PUB_SEQ] = seq
        self._pub.pack_into(self._buf, self._pub_off, *pub)
        hdr[HDR_PUB_SEQ] = seq + 1

    def published(self, tries: int = 1000) -> tuple[float, ...] | None:
        """The newest whole published tick (link side); None before the first."""
        hdr = self.hdr
        for _ in range(tries):
            seq = hdr[HDR_PUB_SEQ]
            if seq == 0:
                return None
            if seq & 1:
                continue
            values: tuple[float, ...] = self._pub.unpack_from(self._buf, self._pub_off)
            if hdr[HDR_PUB_SEQ] == seq:
                return values
        return None

    # -- the patch (link writes, servo reads) ---------------------------------------------------
    def write_patch(self, update: LocalModelUpdate) -> None:
        """Hand ``update`` to the servo process (link side; latest wins).

        Raises
        ------
        ServoProcessError
            The pickled patch does not fit the region (:data:`PATCH_BYTES`).
        """
        data = pickle.dumps(update, protocol=pickle.HIGHEST_PROTOCOL)
        if len(data) > PATCH_BYTES:
            raise ServoProcessError(f"patch of {len(data)} bytes exceeds {PATCH_BYTES}")
        hdr = self.hdr
        seq = hdr[HDR_PATCH_SEQ] + 1
        hdr[HDR_PATCH_SEQ] = seq
        self.patch[: len(data)] = data
        hdr[HDR_PATCH_LEN] = len(data)
        hdr[HDR_PATCH_SEQ] = seq + 1

    def read_patch(self, seen: int) -> tuple[int, LocalModelUpdate | None]:
        """The patch written since sequence ``seen``, if one is whole now (servo side).

        Returns ``(sequence, update)``; ``update`` is None when there is nothing new (or it is
        being written: the next tick takes it).
        """
        hdr = self.hdr
        seq = hdr[HDR_PATCH_SEQ]
        if seq == seen or seq & 1:
            return seen, None
        data = bytes(self.patch[: hdr[HDR_PATCH_LEN]])
        if hdr[HDR_PATCH_SEQ] != seq:
            return seen, None
        update: LocalModelUpdate = pickle.loads(data)
        return seq, update

    # -- status (servo writes on request) ---------------------------------------------------------
    def write_status(self, payload: object, request: int) -> None:
        """Store the pickled ``payload`` as the answer to ``request`` (servo side)."""
        data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)[:STATUS_BYTES]
        self.status[: len(data)] = data
        self.hdr[HDR_STATUS_LEN] = len(data)
        self.hdr[HDR_STATUS_ACK] = request

    def read_status(self) -> Any:
        """The last status the servo process stored (link side); None if none."""
        n = self.hdr[HDR_STATUS_LEN]
        if n <= 0:
            return None
        return pickle.loads(bytes(self.status[:n]))

    def release(self) -> None:
        """Drop this side's views and mapping (views still held elsewhere keep it mapped)."""
        for v in (self.hdr, self.flt, self.periods, self.patch, self.status, self.ring):
            try:
                v.release()
            except (BufferError, ValueError):
                pass
        try:
            self.shm.close()
        except BufferError:  # a recorder view is still in use: the mapping ends with the process
            pass
