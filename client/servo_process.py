"""The servo in its own process: device, local model, safety and telemetry off the link's GIL.

Why: with the servo as a thread of the client, 98 % of its missed deadlines were waits
to retake the interpreter lock after its sleep, held by the link's thread (patch parsing, the
sample, the recorder) while that thread was preempted on a busy machine. A process has its own
interpreter lock; the servo process runs nothing but the loop.

This module owns the link process's handle on that process (:class:`ServoProcess`): starting it,
its set-up dialogue, the link's calls, and noticing its death. The block they share is
:mod:`client.servo_block`, the servo process's own side :mod:`client.servo_child`, and what both
hosts of the loop do with the device :mod:`client.servo_device`.

What runs where:

- **servo process** (:func:`client.servo_child.servo_main`, spawned): opens the device (so
  vendor callbacks and HID ports live where the loop is), runs :class:`client.servo.ServoCore`
  on :class:`client.scheduler.DeadlineLoop` in its main thread, under SCHED_FIFO when allowed,
  writes the telemetry ring, and reopens a faulted device from a helper thread
  (:func:`client.servo_device.reopen_device`, on a thread started only while the device is
  away, at ordinary priority). Before the loop it collects and freezes its garbage and turns the
  cyclic collector off: the tick makes no reference cycles, so its temporaries are freed by
  reference counting and no collection ever pauses a tick.
- **link process** (the client's main process, :class:`ServoProcess`, this module): hands
  patches and force switches to the servo and reads its latest state, all through one
  shared-memory block (:class:`client.servo_block.SharedBlock`: the published tick and the
  patch under seqlocks, the period window, the status, the telemetry ring; each side writes its
  own words only, so no lock is taken and the servo never waits on the link).

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
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any

from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.devices.base import DeviceLimits
from haptic_collab.client.servo import (
    ServoConfig,
    ServoSnapshot,
    ServoStatus,
    clamp_to_device,
    snapshot_of,
)
from haptic_collab.client.servo_block import (
    FLT_LINK_S,
    HDR_FORCES,
    HDR_FORCES_SEQ,
    HDR_OVERRUNS,
    HDR_STATE,
    HDR_STATUS_ACK,
    HDR_STATUS_REQ,
    HDR_STOP,
    STATE_RUNNING,
    ServoProcessError,
    SharedBlock,
)
from haptic_collab.client.servo_child import servo_main
from haptic_collab.client.servo_device import BuiltDevice
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate

log = logging.getLogger("haptic.client")

__all__ = ["ServoProcess", "ServoProcessError"]


class ServoProcess:
    """Handle, in the client's link process, on the servo loop running in its own process.

    The same calls as :class:`client.servo_thread.ServoThread` for the link (:meth:`set_patch`,
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
            target=servo_main,
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
            self.block.flt[FLT_LINK_S] = self._clock()
        lim = self.device.limits if self.device is not None else None
        return update if lim is None else clamp_to_device(update, lim)[0]

    def notify_link(self, now_s: float | None = None) -> None:
        """The server spoke (patch or pong); ``now_s`` defaults to the servo clock now."""
        t = self._clock() if now_s is None else now_s
        with self._lock:
            if t > self.block.flt[FLT_LINK_S]:
                self.block.flt[FLT_LINK_S] = t

    def _forces(self, on: bool) -> None:
        with self._lock:
            hdr = self.block.hdr
            hdr[HDR_FORCES] = 1 if on else 0
            self._forces_seq += 1
            hdr[HDR_FORCES_SEQ] = self._forces_seq

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
        if self.running and hdr[HDR_STATE] == STATE_RUNNING:
            with self._lock:
                self._request += 1
                req = self._request
                hdr[HDR_STATUS_REQ] = req
            t_end = time.monotonic() + timeout_s
            while hdr[HDR_STATUS_ACK] != req and time.monotonic() < t_end and self.running:
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
        return int(self.block.hdr[HDR_OVERRUNS])

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
            self.block.hdr[HDR_STOP] = 1
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
