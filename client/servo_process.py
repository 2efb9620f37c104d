"""The servo in its own process: device, local model, safety and telemetry off the link's GIL.

Why (issue 27): with the servo as a thread of the client, 98 % of its missed deadlines were waits
to retake the interpreter lock after its sleep, held by the link's thread (patch parsing, the
sample, the recorder) while that thread was preempted on a busy machine. A process has its own
interpreter lock; the servo process runs nothing but the loop.

What runs where:

- **servo process** (:func:`_servo_main`, spawned): opens the device (so vendor callbacks and
  HID ports live where the loop is), runs :class:`client.servo.ServoCore` on
  :class:`client.scheduler.DeadlineLoop` in its main thread, under SCHED_FIFO when allowed,
  writes the telemetry ring, and reopens a faulted device from a helper thread
  (:func:`reopen_device`, on a thread started only while the device is away, at ordinary
  priority). Before the loop it
  collects and freezes its garbage and turns the cyclic collector off: the tick makes no
  reference cycles, so its temporaries are freed by reference counting and no collection ever
  pauses a tick.
- **link process** (the client's main process, :class:`ServoProcess`): hands patches and force
  switches to the servo and reads its latest state, all through one shared-memory block.

The block (:class:`SharedBlock`): int64 header words, the latest published tick (a seqlock: the
writer makes the sequence odd, writes, makes it even; a reader retries while it is odd or
changed), the period window, the patch (a pickled :class:`shared.local_model_update.
LocalModelUpdate` under its own seqlock; latest wins, as with the thread's reference swap),
the status (pickled on request) and the telemetry ring (:class:`client.recorder.
TelemetryRecorder` over shared memory). Each side writes its own words only, so no lock is
taken and the servo never waits on the link.

Loss of the other side:

- **link process gone** (killed, crashed): the kernel sends the servo process SIGTERM
  (``PR_SET_PDEATHSIG``) and the loop also compares ``os.getppid()`` every tick; either way
  forces ramp to zero (``ServoConfig.ramp_s``), the device's forces are disabled and the
  process exits. A link that hangs but lives is caught by the link timeout as before.
- **servo process gone**: a thread of the link process waits on the process's sentinel and
  reports the death at once (:attr:`ServoProcess.died_at_s`, ``on_death``); from then on
  :meth:`ServoProcess.latest` reports the last force ramping to zero over ``ramp_s``, so the
  object the server simulates is released smoothly, and ``haptic client`` stops with an error.
  The device itself is then in its own hands: the vendor driver's or the device's own watchdog
  stops its forces once the process holding it is gone; a simulated device has none to stop.

The seqlock relies on the stores of one process being seen in order by the other (x86-64's
memory model); each store here is one aligned 8-byte write made by CPython's C code.
"""

from __future__ import annotations

import gc
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from multiprocessing.shared_memory import SharedMemory
from typing import Any

from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.devices.base import Device, DeviceLimits
from haptic_collab.client.devices.opener import DeviceOpener
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.scheduler import DeadlineLoop, ordinary_priority, try_realtime_priority
from haptic_collab.client.servo import (
    PUBLISHED,
    ServoConfig,
    ServoCore,
    ServoSnapshot,
    ServoStatus,
    clamp_to_device,
    snapshot_of,
)
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate

log = logging.getLogger("haptic.client")

__all__ = [
    "BuiltDevice",
    "SharedBlock",
    "ServoProcess",
    "ServoProcessError",
    "encoder_resolution",
    "reopen_device",
    "watch_device",
]

#: First and largest delay [s] between two attempts to reopen a faulted device.
DEVICE_REOPEN_BACKOFF_S = (0.5, 5.0)
#: How often [s] the device's fault flag is looked at.
DEVICE_WATCH_PERIOD_S = 0.05

# header words (int64), each written by one side only: (L) the link process, (S) the servo
_PATCH_SEQ = 0  # L: seqlock of the patch region
_PATCH_LEN = 1  # L: bytes of the pickled patch
_PUB_SEQ = 2  # S: seqlock of the published tick
_FORCES = 3  # L: 1 enable, 0 disable (applied when _FORCES_SEQ changes)
_FORCES_SEQ = 4  # L
_STOP = 5  # L: 1 = ramp forces down and end the loop
_STATUS_REQ = 6  # L: asks for a status (a new number each time)
_STATUS_ACK = 7  # S: the request number whose status is in the status region
_STATUS_LEN = 8  # S: bytes of the pickled status
_REC_COUNT = 9  # S: telemetry rows ever appended
_STATE = 10  # S: 0 starting, 1 running, 2 ended
_OVERRUNS = 11  # S: deadlines missed and skipped
_HEADER_WORDS = 16
# float64 words after the header
_LINK_S = 0  # L: servo time [s] the server last spoke
_PUB = 1  # S: PUBLISHED values of the newest tick
_FLOAT_WORDS = 16

#: The servo process's thread switch interval [s] (:func:`sys.setswitchinterval`), as
#: :class:`client.servo.ServoThread` sets while it runs.
SWITCH_INTERVAL_S = 2e-4

PATCH_BYTES = 1 << 16
STATUS_BYTES = 1 << 16

_STARTING, _RUNNING, _ENDED = 0, 1, 2


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


@dataclass(frozen=True)
class BuiltDevice:
    """What the link process needs to know of the device the servo process placed and opened.

    Attributes
    ----------
    name : str
        The device's name.
    limits : DeviceLimits
        Its limits (workspace on the object).
    has_buttons : bool
        It reports buttons (``--engage default`` then engages forces with the first).
    encoder_resolution_m : float
        Its position quantum [m] (0: unknown), :func:`encoder_resolution`.
    """

    name: str
    limits: DeviceLimits
    has_buttons: bool
    encoder_resolution_m: float


def encoder_resolution(device: Device) -> float:
    """Position quantum [m] of the device: a simulated profile's encoder, or the coarsest integer
    axis of an absolute-position HID profile (metres per count); 0 when unknown."""
    profile = getattr(device, "profile", None)
    res = getattr(profile, "encoder_resolution_m", None)
    if isinstance(res, int | float) and math.isfinite(res):
        return float(res)
    layout = getattr(profile, "input", None)
    if getattr(layout, "mode", None) == "absolute":
        scales = [
            abs(float(ax.scale))
            for ax in getattr(layout, "axes", ())
            if getattr(ax, "type", "float32") != "float32"
        ]
        if scales and all(math.isfinite(v) for v in scales):
            return max(scales)
    return 0.0


def built_device(device: Device) -> BuiltDevice:
    """The :class:`BuiltDevice` of an opened device."""
    return BuiltDevice(
        name=str(getattr(device, "name", "device")),
        limits=device.limits,
        has_buttons=bool(getattr(device, "has_buttons", False)),
        encoder_resolution_m=encoder_resolution(device),
    )


def reopen_device(
    device: Device,
    counters: dict[str, int],
    stop: threading.Event,
    *,
    backoff_s: tuple[float, float] = DEVICE_REOPEN_BACKOFF_S,
) -> None:
    """Handle one fault of ``device`` (it was unplugged): reopen it with backoff until the fault
    clears, the device says it cannot be reopened, or ``stop``.

    A device fault is the device's business: the servo loop ramps forces to zero while
    :attr:`Device.fault` is set and back up once it clears; the network link is not touched. A
    device that cannot be reopened (:meth:`Device.reopen` returns False, e.g. simulated) stays
    faulted, forces off, logged once. Counts ``device_faults`` and ``device_reopens`` in
    ``counters``. Runs on a thread of its own, never the servo loop's.
    """
    counters["device_faults"] += 1
    log.warning(
        "device fault: %s; forces ramp to zero, reopening the device (the server link stays)",
        device.fault,
    )
    delay = backoff_s[0]
    while device.fault is not None and not stop.wait(delay):
        try:
            ok = device.reopen()
        except OSError as exc:
            delay = min(backoff_s[1], 2.0 * delay)
            log.info("device still unavailable (%s); next try in %.1f s", exc, delay)
            continue
        if not ok:
            if device.fault is not None:
                log.error("device %s cannot be reopened; forces stay off", device.name)
                while device.fault is not None and not stop.wait(DEVICE_WATCH_PERIOD_S):
                    pass
            return
        counters["device_reopens"] += 1
        log.warning("device %s is back; forces ramp up again", device.name)
        return


def watch_device(device: Device, counters: dict[str, int], stop: threading.Event) -> None:
    """Look at ``device``'s fault flag every :data:`DEVICE_WATCH_PERIOD_S` until ``stop`` and
    handle each fault with :func:`reopen_device` (the servo thread's companion in ``--servo
    thread``; the servo process starts :func:`reopen_device` only when a fault appears, so no
    other thread ever competes with its loop for the interpreter lock)."""
    while not stop.wait(DEVICE_WATCH_PERIOD_S):
        if device.fault is not None:
            reopen_device(device, counters, stop)


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
        self._hdr = (off, 8 * _HEADER_WORDS)
        off += 8 * _HEADER_WORDS
        self._flt = (off, 8 * _FLOAT_WORDS)
        off += 8 * _FLOAT_WORDS
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
        self._pub_off = self._flt[0] + 8 * _PUB

    @property
    def name(self) -> str:
        """The block's name (to attach from another process)."""
        return self.shm.name

    def recorder(self) -> TelemetryRecorder:
        """A :class:`TelemetryRecorder` over the shared ring (both sides see the same rows)."""
        return TelemetryRecorder(
            self.capacity, buffer=self.ring, counter=self.hdr[_REC_COUNT : _REC_COUNT + 1]
        )

    # -- the published tick (servo writes, link reads) --------------------------------------------
    def publish(self, pub: tuple[Any, ...]) -> None:
        """Write the newest tick's :data:`client.servo.PUBLISHED` values (servo side)."""
        hdr = self.hdr
        seq = hdr[_PUB_SEQ] + 1
        hdr[_PUB_SEQ] = seq
        self._pub.pack_into(self._buf, self._pub_off, *pub)
        hdr[_PUB_SEQ] = seq + 1

    def published(self, tries: int = 1000) -> tuple[float, ...] | None:
        """The newest whole published tick (link side); None before the first."""
        hdr = self.hdr
        for _ in range(tries):
            seq = hdr[_PUB_SEQ]
            if seq == 0:
                return None
            if seq & 1:
                continue
            values: tuple[float, ...] = self._pub.unpack_from(self._buf, self._pub_off)
            if hdr[_PUB_SEQ] == seq:
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
        seq = hdr[_PATCH_SEQ] + 1
        hdr[_PATCH_SEQ] = seq
        self.patch[: len(data)] = data
        hdr[_PATCH_LEN] = len(data)
        hdr[_PATCH_SEQ] = seq + 1

    def read_patch(self, seen: int) -> tuple[int, LocalModelUpdate | None]:
        """The patch written since sequence ``seen``, if one is whole now (servo side).

        Returns ``(sequence, update)``; ``update`` is None when there is nothing new (or it is
        being written: the next tick takes it).
        """
        hdr = self.hdr
        seq = hdr[_PATCH_SEQ]
        if seq == seen or seq & 1:
            return seen, None
        data = bytes(self.patch[: hdr[_PATCH_LEN]])
        if hdr[_PATCH_SEQ] != seq:
            return seen, None
        update: LocalModelUpdate = pickle.loads(data)
        return seq, update

    # -- status (servo writes on request) ---------------------------------------------------------
    def write_status(self, payload: object, request: int) -> None:
        """Store the pickled ``payload`` as the answer to ``request`` (servo side)."""
        data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)[:STATUS_BYTES]
        self.status[: len(data)] = data
        self.hdr[_STATUS_LEN] = len(data)
        self.hdr[_STATUS_ACK] = request

    def read_status(self) -> Any:
        """The last status the servo process stored (link side); None if none."""
        n = self.hdr[_STATUS_LEN]
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


# -- the servo process ------------------------------------------------------------------------------
class _Bridge:
    """The servo side's per-tick exchange with the shared block (no lock, nothing waits)."""

    def __init__(self, block: SharedBlock, core: ServoCore, parent_pid: int) -> None:
        self.block = block
        self.core = core
        self.parent_pid = parent_pid
        self.patch_seen = 0
        self.forces_seen = 0
        self.stop_seen = False
        self.link_s = -math.inf
        self.status_extra: Callable[[], dict[str, Any]] = dict

    def before(self, now_s: float) -> None:
        block, core = self.block, self.core
        hdr = block.hdr
        if hdr[_PATCH_SEQ] != self.patch_seen:
            self.patch_seen, update = block.read_patch(self.patch_seen)
            if update is not None:
                core.set_patch(update)
        t = block.flt[_LINK_S]
        if t > self.link_s:
            self.link_s = t
            core.notify_link(t)
        f = hdr[_FORCES_SEQ]
        if f != self.forces_seen:
            self.forces_seen = f
            if hdr[_FORCES] == 1:
                core.enable_forces()
            else:
                core.disable_forces()
        if not self.stop_seen and (hdr[_STOP] or os.getppid() != self.parent_pid):
            self.stop_seen = True
            core.request_stop()
        r = hdr[_STATUS_REQ]
        if r != hdr[_STATUS_ACK]:
            self.write_status(r)

    def tick(self, now_s: float) -> bool:
        self.before(now_s)
        stopped = self.core.tick(now_s)
        pub = self.core.published
        if pub is not None:
            self.block.publish(pub)
        return stopped

    def write_status(self, request: int) -> None:
        self.block.write_status((self.core.status(), self.status_extra()), request)


def _reply(conn: multiprocessing.connection.Connection, *msg: Any) -> None:
    try:
        conn.send(msg)
    except (OSError, ValueError):  # the link process is gone: the loop notices it too
        pass


def _failure(exc: BaseException) -> tuple[str, str]:
    kind = "device" if isinstance(exc, DeviceError) else type(exc).__name__
    return kind, str(exc) or type(exc).__name__


def _servo_main(
    conn: multiprocessing.connection.Connection,
    block_name: str,
    capacity: int,
    period_window: int,
    opener_kwargs: Mapping[str, Any],
    clock_origin_s: float,
    parent_pid: int,
    realtime_priority: int | None,
    log_level: int,
) -> None:
    """Entry point of the servo process (started by :class:`ServoProcess`)."""
    from haptic_collab.workers import die_with_parent

    # a forked child inherits the link's heap: never scan it (a full collection of it took
    # 36 ms, and would copy every page it touched)
    gc.freeze()
    # ... and the link's asyncio signal wake-up fd: a signal here must not wake (and stop) the
    # link's event loop
    signal.set_wakeup_fd(-1)
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s servo: %(message)s")
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the link process's to handle
    # a plain flag: a signal handler must take no lock (a second SIGTERM arriving while the
    # first handler held an Event's lock deadlocked the servo process)
    stop_asked = [False]

    def on_term(signum: int, frame: object) -> None:
        stop_asked[0] = True

    signal.signal(signal.SIGTERM, on_term)
    block = SharedBlock(capacity, period_window, name=block_name)
    opener = DeviceOpener(**opener_kwargs)
    try:
        opener.check()
    except Exception as exc:  # noqa: BLE001 - every failure goes back as one line
        _reply(conn, "error", *_failure(exc))
        return
    _reply(conn, "checked", opener.limits)
    device: Device | None = None
    try:
        msg = conn.recv()
        if msg[0] != "build":
            return
        try:
            device = opener.build(msg[1], msg[2])
        except Exception as exc:  # noqa: BLE001
            _reply(conn, "error", *_failure(exc))
            return
        _reply(conn, "built", built_device(device))
        msg = conn.recv()
        if msg[0] != "start":
            return
        config: ServoConfig = msg[1]
        local_model: LocalModelParams = msg[2]
        try:
            core = ServoCore(
                device,
                config,
                local_model=local_model,
                recorder=block.recorder(),
                period_buffer=block.periods,
            )
        except Exception as exc:  # noqa: BLE001
            _reply(conn, "error", *_failure(exc))
            return
        _run_loop(
            conn, block, core, device, clock_origin_s, parent_pid, realtime_priority, stop_asked
        )
    except (EOFError, OSError):  # the link process went away before the loop started
        pass
    finally:
        if device is not None:
            try:
                device.close()
            except OSError:
                pass
        opener.close()
        block.hdr[_STATE] = _ENDED


def _run_loop(
    conn: multiprocessing.connection.Connection,
    block: SharedBlock,
    core: ServoCore,
    device: Device,
    clock_origin_s: float,
    parent_pid: int,
    realtime_priority: int | None,
    stop_asked: list[bool],
) -> None:
    perf = time.perf_counter

    def clock() -> float:
        return perf() - clock_origin_s

    loop = DeadlineLoop(core.config.servo_period_s, clock=clock)
    bridge = _Bridge(block, core, parent_pid)
    counters = {"device_faults": 0, "device_reopens": 0}
    realtime = False

    def extra() -> dict[str, Any]:
        return {"overruns": loop.overruns, "realtime": realtime, **counters}

    bridge.status_extra = extra
    watch_stop = threading.Event()
    reopening: list[threading.Thread] = []

    def reopen() -> None:
        ordinary_priority()  # not the servo's real-time policy, which a new thread inherits
        reopen_device(device, counters, watch_stop)

    if realtime_priority is not None:
        realtime = try_realtime_priority(realtime_priority)
    # a vendor's scheduler callback (OpenHaptics) or the reopen helper takes this process's
    # interpreter lock within about this long of asking, as with the servo thread
    sys.setswitchinterval(SWITCH_INTERVAL_S)

    def tick(now_s: float) -> bool:
        if stop_asked[0] and not bridge.stop_seen:
            bridge.stop_seen = True
            core.request_stop()
        if device.fault is not None and not (reopening and reopening[0].is_alive()):
            # a thread only while the device is away (forces are off meanwhile)
            reopening[:] = [threading.Thread(target=reopen, name="device-reopen", daemon=True)]
            reopening[0].start()
        return bridge.tick(now_s)

    def overrun(missed: int, now_s: float) -> None:
        core.note_overrun(missed, now_s)
        block.hdr[_OVERRUNS] = loop.overruns

    block.hdr[_STATE] = _RUNNING
    _reply(conn, "running", realtime)
    gc.collect()
    gc.freeze()  # what exists now is never scanned again
    gc.disable()  # the tick makes no cycles: reference counting frees its temporaries
    try:
        loop.run(tick, after_tick=core.record_compute, on_overrun=overrun)
    except Exception as exc:  # the device must never keep a force after the loop dies
        core.shutdown_now(f"servo loop failed: {exc!r}")
    finally:
        gc.enable()
        watch_stop.set()
        if not core.stopped:
            core.shutdown_now(None)
        bridge.write_status(block.hdr[_STATUS_REQ])


# -- the link side ----------------------------------------------------------------------------------
class ServoProcess:
    """Handle, in the client's link process, on the servo loop running in its own process.

    The same calls as :class:`client.servo.ServoThread` for the link (:meth:`set_patch`,
    :meth:`notify_link`, :meth:`enable_forces`, :meth:`disable_forces`, :meth:`latest`,
    :meth:`status`, :meth:`stop`), plus the device's set-up, which happens in the servo process:
    :meth:`check` (before any network), :meth:`build` (once ``welcome`` says where the object
    is), :meth:`start`.

    Parameters
    ----------
    opener_kwargs : mapping
        :class:`client.devices.DeviceOpener`'s arguments (``spec`` and keywords), picklable
        (no ``hid_opener``: a fake port cannot cross processes).
    clock_origin_s : float
        ``time.perf_counter()`` at servo time 0 (CLOCK_MONOTONIC: the same in both processes).
    capacity : int
        Telemetry rows of the shared ring.
    period_window : int
        ``ServoConfig.period_window`` of the loop to come.
    realtime_priority : int or None
        SCHED_FIFO priority asked for the loop (None: ordinary).
    on_death : callable(str), optional
        Called from a thread of this process, once, if the servo process ends without being
        told to (the reason as one line).
    start_timeout_s : float
        Longest wait [s] for each set-up answer of the servo process.
    start_method : {"auto", "fork", "spawn"}
        How the servo process is started (:mod:`multiprocessing`); ``auto``: ``fork`` while this
        process has a single thread (``haptic client`` starts it first thing), else ``spawn``.

    Attributes
    ----------
    recorder : TelemetryRecorder
        The shared telemetry ring (read it here; the servo process writes it).
    realtime : bool
        SCHED_FIFO was granted to the loop.
    died_at_s : float or None
        ``time.perf_counter() - clock_origin_s`` when an unexpected end was seen.
    death : str or None
        Why it ended unexpectedly.
    """

    def __init__(
        self,
        opener_kwargs: Mapping[str, Any],
        *,
        clock_origin_s: float,
        capacity: int,
        period_window: int = 1000,
        realtime_priority: int | None = 10,
        on_death: Callable[[str], None] | None = None,
        start_timeout_s: float = 30.0,
        start_method: str = "auto",
    ) -> None:
        if opener_kwargs.get("hid_opener") is not None:
            raise ValueError("a servo process opens the device itself: no hid_opener")
        self.opener_kwargs = dict(opener_kwargs)
        self.clock_origin_s = clock_origin_s
        self.on_death = on_death
        self.start_timeout_s = start_timeout_s
        self.start_method = start_method
        self._priority = realtime_priority
        self.block = SharedBlock(capacity, period_window)
        self.recorder = self.block.recorder()
        self.realtime = False
        self.died_at_s: float | None = None
        self.death: str | None = None
        self.limits: DeviceLimits | None = None
        self.device: BuiltDevice | None = None
        self._config: ServoConfig | None = None
        self._stopping = False
        self._request = 0
        self._forces_seq = 0
        self._lock = threading.Lock()
        self._setup = threading.Lock()
        self._last_pub: tuple[float, ...] | None = None
        self._last_status: tuple[ServoStatus, dict[str, Any]] | None = None
        self._proc: multiprocessing.process.BaseProcess | None = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._monitor: threading.Thread | None = None

    def _clock(self) -> float:
        return time.perf_counter() - self.clock_origin_s

    def _start_method(self) -> str:
        """``fork`` while this process has one thread (the servo process then starts in tens of
        milliseconds with everything already imported; ``spawn`` took 0.9 s on an idle machine
        and 2.5 s beside the demo's other processes), else ``spawn`` (forking a process whose
        other threads may hold locks is unsafe)."""
        method = self.start_method
        if method == "auto":
            single = threading.active_count() == 1
            method = (
                "fork" if single and "fork" in multiprocessing.get_all_start_methods() else "spawn"
            )
        return method

    @property
    def pid(self) -> int | None:
        """The servo process's id (None before :meth:`check`)."""
        return None if self._proc is None else self._proc.pid

    @property
    def running(self) -> bool:
        """The servo process is alive."""
        return self._proc is not None and self._proc.is_alive()

    # -- set-up ------------------------------------------------------------------------------------
    def _ask(self, *msg: Any) -> tuple[Any, ...]:
        conn = self._conn
        assert conn is not None
        if msg:
            conn.send(msg)
        if not conn.poll(self.start_timeout_s):
            raise ServoProcessError(
                f"the servo process did not answer within {self.start_timeout_s:g} s"
            )
        try:
            reply: tuple[Any, ...] = conn.recv()
        except EOFError:
            raise ServoProcessError(self._why_ended()) from None
        if reply[0] == "error":
            kind, text = reply[1], reply[2]
            raise DeviceError(text) if kind == "device" else ServoProcessError(text)
        return reply

    def _why_ended(self) -> str:
        proc = self._proc
        if proc is None:
            return "the servo process was never started"
        proc.join(0.5)
        code = proc.exitcode
        if code is None:
            return "the servo process stopped answering"
        if code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            return f"the servo process was killed ({name})"
        return f"the servo process exited with code {code}"

    def check(self) -> None:
        """Start the servo process and have it check and open the device (before any network):
        :meth:`spawn` then :meth:`wait_checked`.

        Raises
        ------
        DeviceError
            As :meth:`client.devices.DeviceOpener.check`.
        ServoProcessError
            The process could not be started or did not answer.
        """
        self.spawn()
        self.wait_checked()

    def spawn(self) -> None:
        """Start the servo process (it imports, then checks and opens the device); returns at
        once. A second call does nothing.

        Raises
        ------
        ServoProcessError
            The process could not be started.
        """
        if self._proc is not None:
            return
        ctx: Any = multiprocessing.get_context(self._start_method())
        parent, child = ctx.Pipe()
        level = logging.getLogger("haptic").getEffectiveLevel()
        proc = ctx.Process(
            target=_servo_main,
            args=(
                child,
                self.block.name,
                self.block.capacity,
                self.block.period_window,
                self.opener_kwargs,
                self.clock_origin_s,
                os.getpid(),
                self._priority,
                level,
            ),
            name="haptic-servo",
            daemon=True,
        )
        try:
            proc.start()
        except (OSError, RuntimeError) as exc:
            raise ServoProcessError(f"cannot start the servo process: {exc}") from exc
        child.close()
        self._proc, self._conn = proc, parent

    def wait_checked(self) -> None:
        """Wait until the servo process checked and opened the device (:meth:`spawn` first);
        returns at once once it has.

        Raises
        ------
        DeviceError
            As :meth:`client.devices.DeviceOpener.check`.
        ServoProcessError
            The process did not answer or ended.
        """
        with self._setup:
            if self._monitor is not None:
                return
            try:
                reply = self._ask()
            except BaseException:
                self._end()
                raise
            self.limits = reply[1]
            self._monitor = threading.Thread(target=self._watch, name="servo-monitor", daemon=True)
            self._monitor.start()

    def build(self, anchor: tuple[float, ...], normal: tuple[float, ...]) -> BuiltDevice:
        """Have the servo process place the device on the object and open it.

        Raises
        ------
        DeviceError
            As :meth:`client.devices.DeviceOpener.build`.
        """
        reply = self._ask("build", tuple(anchor), tuple(normal))
        self.device = reply[1]
        return self.device

    def start(self, config: ServoConfig, local_model: LocalModelParams) -> None:
        """Start the servo loop (forces off until :meth:`enable_forces` and the first patch).

        Raises
        ------
        ServoProcessError
            The loop could not be built (bad parameters: the message says which).
        """
        self._config = config
        reply = self._ask("start", config, local_model)
        self.realtime = bool(reply[1])

    def _watch(self) -> None:
        proc = self._proc
        assert proc is not None
        multiprocessing.connection.wait([proc.sentinel])
        if self._stopping:
            return
        t = self._clock()
        self.death = self._why_ended()
        self.died_at_s = t
        log.error("%s: forces ramp to zero", self.death)
        if self.on_death is not None:
            self.on_death(self.death)

    # -- the link's calls --------------------------------------------------------------------------
    def set_patch(self, update: LocalModelUpdate) -> LocalModelUpdate:
        """Hand ``update`` to the servo loop (applied whole between two ticks); the link spoke.

        Returns what will be applied (K_h and B_h clamped to the device).
        """
        with self._lock:
            self.block.write_patch(update)
            self.block.flt[_LINK_S] = self._clock()
        lim = self.device.limits if self.device is not None else None
        return update if lim is None else clamp_to_device(update, lim)[0]

    def notify_link(self, now_s: float | None = None) -> None:
        """The server spoke (patch or pong); ``now_s`` defaults to the servo clock now."""
        t = self._clock() if now_s is None else now_s
        with self._lock:
            if t > self.block.flt[_LINK_S]:
                self.block.flt[_LINK_S] = t

    def _forces(self, on: bool) -> None:
        with self._lock:
            hdr = self.block.hdr
            hdr[_FORCES] = 1 if on else 0
            self._forces_seq += 1
            hdr[_FORCES_SEQ] = self._forces_seq

    def enable_forces(self) -> None:
        """See :meth:`client.servo.ServoCore.enable_forces`."""
        self._forces(True)

    def disable_forces(self) -> None:
        """See :meth:`client.servo.ServoCore.disable_forces`."""
        self._forces(False)

    def latest(self) -> ServoSnapshot | None:
        """The newest tick's state and period statistics (None before the first tick).

        After an unexpected end of the servo process: its last state with the force ramping to
        zero over ``ServoConfig.ramp_s`` from :attr:`died_at_s`, so the simulation lets go of
        the object smoothly.
        """
        pub = self.block.published()
        if pub is None:  # none yet, or a servo killed in the middle of a write: the last whole one
            pub = self._last_pub
            if pub is None:
                return None
        self._last_pub = pub
        periods = list(self.block.periods.cast("d"))
        snap = snapshot_of(pub, periods, int(pub[0]))
        if self.died_at_s is None:
            return snap
        ramp = self.ramp_s
        g = max(0.0, 1.0 - (self._clock() - self.died_at_s) / ramp)
        fx, fy, fz = snap.force_n
        return replace(snap, force_n=(g * fx, g * fy, g * fz), force_scale=g * snap.force_scale)

    def _status_payload(self, timeout_s: float = 0.5) -> tuple[ServoStatus, dict[str, Any]] | None:
        hdr = self.block.hdr
        if self.running and hdr[_STATE] == _RUNNING:
            with self._lock:
                self._request += 1
                req = self._request
                hdr[_STATUS_REQ] = req
            t_end = time.monotonic() + timeout_s
            while hdr[_STATUS_ACK] != req and time.monotonic() < t_end and self.running:
                time.sleep(0.002)
        payload = self.block.read_status()
        if payload is not None:
            self._last_status = payload
        return self._last_status

    def status(self) -> ServoStatus:
        """The servo's safety state (:meth:`client.servo.ServoCore.status`), asked of the servo
        process (its last answer once it ended); ``error`` says why if it died."""
        payload = self._status_payload()
        if payload is None:
            status = ServoStatus(
                ticks=0,
                counts={},
                last_event=None,
                forces_enabled=False,
                has_patch=False,
                link_alive=False,
                force_scale=0.0,
                device_fault=None,
                stiffness_clamps=0,
                stopped=True,
            )
        else:
            status = payload[0]
        if self.death is not None:
            status = replace(status, error=self.death, stopped=True, force_scale=0.0)
        return status

    @property
    def ramp_s(self) -> float:
        """The loop's force ramp time [s] (``ServoConfig.ramp_s``; the default before
        :meth:`start`)."""
        return (self._config or ServoConfig()).ramp_s

    @property
    def overruns(self) -> int:
        """Deadlines the loop missed and skipped so far."""
        return int(self.block.hdr[_OVERRUNS])

    @property
    def counters(self) -> dict[str, int]:
        """``device_faults`` and ``device_reopens`` as the servo process last reported them."""
        payload = self._last_status
        extra = {} if payload is None else payload[1]
        return {k: int(extra.get(k, 0)) for k in ("device_faults", "device_reopens")}

    def stop(self, timeout_s: float | None = None) -> bool:
        """Ramp forces down, disable them, end the servo process and free the shared block.

        Returns
        -------
        bool
            True if the process ended by itself (False: it had to be terminated).
        """
        self._stopping = True  # an end from here on is no death (one already seen was reported)
        ramp = self.ramp_s
        wait = ramp + 1.0 if timeout_s is None else timeout_s
        proc = self._proc
        ok = True
        if proc is not None and proc.is_alive():
            self._status_payload(0.2)  # the counters as they stand, in case it must be killed
            self.block.hdr[_STOP] = 1
            proc.join(wait)
            if proc.is_alive():
                ok = False
                proc.terminate()  # SIGTERM: its handler still ramps forces down
                proc.join(1.0)
                if proc.is_alive():
                    proc.kill()
                    proc.join(1.0)
        payload = self.block.read_status()
        if payload is not None:
            self._last_status = payload
        self._end()
        return ok

    def _end(self) -> None:
        self._stopping = True
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(1.0)
        try:
            self.block.shm.unlink()
        except FileNotFoundError:
            pass

    def close(self) -> None:
        """:meth:`stop` if it was not stopped (idempotent)."""
        if self._conn is not None or self.running:
            self.stop()
