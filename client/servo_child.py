"""The servo process's own side: its entry point, the device's set-up, and the loop it runs.

:func:`servo_main` is what :class:`client.servo_process.ServoProcess` starts (a module-level
function: under ``spawn`` the child finds it by its qualified name). It opens the device (so vendor
callbacks and HID ports live where the loop is), answers the link process's set-up requests over a
pipe (checked, built, running, or one line of error), then runs :class:`client.servo.ServoCore` on
:class:`client.scheduler.DeadlineLoop` in its main thread, under SCHED_FIFO when allowed. Each tick
exchanges patches, force switches, the stop flag, status requests and the published tick with the
shared block (:class:`_Bridge`, :mod:`client.servo_block`) and writes the telemetry ring. A faulted
device is reopened from a helper thread (:func:`client.servo_device.reopen_device`, on a thread
started only while the device is away, at ordinary priority). Before the loop it collects and
freezes its garbage and turns the cyclic collector off: the tick makes no reference cycles, so its
temporaries are freed by reference counting and no collection ever pauses a tick.

When the link process goes (killed, crashed) the kernel sends this process SIGTERM
(``PR_SET_PDEATHSIG``) and the loop also compares ``os.getppid()`` every tick; either way forces
ramp to zero (``ServoConfig.ramp_s``), the device's forces are disabled and the process exits.
"""

from __future__ import annotations

import gc
import logging
import math
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.devices.base import Device
from haptic_collab.client.devices.opener import DeviceOpener
from haptic_collab.client.scheduler import DeadlineLoop, ordinary_priority, try_realtime_priority
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.client.servo_block import (
    FLT_LINK_S,
    HDR_FORCES,
    HDR_FORCES_SEQ,
    HDR_OVERRUNS,
    HDR_PATCH_SEQ,
    HDR_STATE,
    HDR_STATUS_ACK,
    HDR_STATUS_REQ,
    HDR_STOP,
    STATE_ENDED,
    STATE_RUNNING,
    SharedBlock,
)
from haptic_collab.client.servo_device import built_device, reopen_device
from haptic_collab.shared.local_model import LocalModelParams

__all__ = ["SWITCH_INTERVAL_S", "servo_main"]

#: The servo process's thread switch interval [s] (:func:`sys.setswitchinterval`), as
#: :class:`client.servo_thread.ServoThread` sets while it runs.
SWITCH_INTERVAL_S = 2e-4


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
        if hdr[HDR_PATCH_SEQ] != self.patch_seen:
            self.patch_seen, update = block.read_patch(self.patch_seen)
            if update is not None:
                core.set_patch(update)
        t = block.flt[FLT_LINK_S]
        if t > self.link_s:
            self.link_s = t
            core.notify_link(t)
        f = hdr[HDR_FORCES_SEQ]
        if f != self.forces_seen:
            self.forces_seen = f
            if hdr[HDR_FORCES] == 1:
                core.enable_forces()
            else:
                core.disable_forces()
        if not self.stop_seen and (hdr[HDR_STOP] or os.getppid() != self.parent_pid):
            self.stop_seen = True
            core.request_stop()
        r = hdr[HDR_STATUS_REQ]
        if r != hdr[HDR_STATUS_ACK]:
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


def servo_main(
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
    """Entry point of the servo process (started by :class:`client.servo_process.ServoProcess`).

    Checks and opens the device, answers the set-up requests on ``conn``, runs the loop until it
    is told to stop or the link process goes, then closes the device. Every failure goes back on
    ``conn`` as ``("error", kind, one line)`` (``kind`` ``"device"`` for a
    :class:`client.devices.DeviceError`); nothing is raised.

    Parameters
    ----------
    conn : multiprocessing.connection.Connection
        This end of the set-up pipe: ``("build", anchor (3,) [m], normal (3,))`` then
        ``("start", ServoConfig, LocalModelParams)`` in; ``("checked", limits)``,
        ``("built", BuiltDevice)``, ``("running", realtime)`` out.
    block_name : str
        The :class:`client.servo_block.SharedBlock` to attach to.
    capacity, period_window : int
        The block's telemetry rows and period window (as the link process created it).
    opener_kwargs : mapping
        :class:`client.devices.DeviceOpener`'s arguments.
    clock_origin_s : float
        ``time.perf_counter()`` at servo time 0 [s].
    parent_pid : int
        The link process's id (its end is noticed every tick).
    realtime_priority : int or None
        SCHED_FIFO priority asked for the loop (None: ordinary).
    log_level : int
        The ``logging`` level of this process.
    """
    from haptic_collab.client.workers import die_with_parent

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
        block.hdr[HDR_STATE] = STATE_ENDED


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
        block.hdr[HDR_OVERRUNS] = loop.overruns

    block.hdr[HDR_STATE] = STATE_RUNNING
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
        bridge.write_status(block.hdr[HDR_STATUS_REQ])
