"""The servo loop on a thread of the client's process: :class:`ServoThread` times a ServoCore.

:class:`ServoThread` runs :class:`client.servo.ServoCore` on its own thread at ``servo_rate_hz``
with :class:`client.scheduler.DeadlineLoop`: tick k is due at ``start + k*T`` (integer tick counts,
never accumulated float time); a deadline missed by more than ``late_tolerance`` periods is
counted (``SERVO_OVERRUN``) and skipped, never piled up. Clock and sleep are injected. It asks for
SCHED_FIFO and lowers the interpreter's thread switch interval while it runs, and offers the link
the same calls as :class:`client.servo_process.ServoProcess` (``haptic client --servo thread``;
by default the servo runs in a process of its own).
"""

from __future__ import annotations

import threading
import time

from haptic_collab.client.scheduler import (
    Clock,
    DeadlineLoop,
    Sleep,
    _switch_interval,
    try_realtime_priority,
)
from haptic_collab.client.servo import ServoCore, ServoSnapshot, ServoStatus
from haptic_collab.shared.local_model_update import LocalModelUpdate

__all__ = ["ServoThread"]


class ServoThread:
    """Runs a :class:`ServoCore` at its servo rate on a dedicated thread (DESIGN section 4).

    Parameters
    ----------
    core : ServoCore
        The core to tick; its device must be open.
    clock, sleep : callable
        Injected time source and sleep (defaults :func:`time.perf_counter`, :func:`time.sleep`);
        ``notify_link()`` without an argument uses the same clock.
    spin_s : float
        Busy-wait margin [s] before each deadline (default 3e-4).
    late_tolerance : float
        Lateness, in periods, beyond which a deadline is missed and skipped (default 0.5).
    switch_interval_s : float or None
        While running, the interpreter's thread switch interval is lowered to this [s] (default
        2e-4) so another Python thread holding the GIL delays a tick by at most about this much;
        None leaves it alone. Restored on stop.
    realtime_priority : int or None
        SCHED_FIFO priority (1-99) asked for the servo thread (default 10; see
        :func:`try_realtime_priority`); None keeps the ordinary policy. Whether it was granted is
        :attr:`realtime`.
    name : str
        Thread name.

    Notes
    -----
    The caller opens the device before :meth:`start` and closes it after :meth:`stop`.
    """

    def __init__(
        self,
        core: ServoCore,
        *,
        clock: Clock = time.perf_counter,
        sleep: Sleep = time.sleep,
        spin_s: float = 3e-4,
        late_tolerance: float = 0.5,
        switch_interval_s: float | None = 2e-4,
        realtime_priority: int | None = 10,
        name: str = "haptic-servo",
    ) -> None:
        self.core = core
        self.clock = clock
        self.loop = DeadlineLoop(
            core.config.servo_period_s,
            clock=clock,
            sleep=sleep,
            spin_s=spin_s,
            late_tolerance=late_tolerance,
        )
        self._switch = switch_interval_s
        self._priority = realtime_priority
        self.realtime = False
        self._old_switch: float | None = None
        self._name = name
        self._thread: threading.Thread | None = None

    @property
    def servo_rate_hz(self) -> float:
        """Set servo rate [Hz]."""
        return self.core.config.servo_rate_hz

    @property
    def overruns(self) -> int:
        """Deadlines the loop missed and skipped so far."""
        return self.loop.overruns

    @property
    def running(self) -> bool:
        """The thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def run(self, max_ticks: int | None = None) -> int:
        """Run the servo loop in the calling thread until stopped (or ``max_ticks``).

        An unexpected exception in a tick zeroes and disables the device's forces, is stored in
        ``status().error`` and ends the loop.

        Returns
        -------
        int
            Ticks run.
        """
        core = self.core
        try:
            return self.loop.run(
                core.tick,
                max_ticks=max_ticks,
                after_tick=core.record_compute,
                on_overrun=core.note_overrun,
            )
        except Exception as exc:  # the device must never keep a force after the loop dies
            core.shutdown_now(f"servo loop failed: {exc!r}")
            return 0

    def _main(self) -> None:
        if self._priority is not None:
            self.realtime = try_realtime_priority(self._priority)
        self.run()

    def start(self) -> None:
        """Start the servo thread.

        Raises
        ------
        RuntimeError
            Already running.
        """
        if self.running:
            raise RuntimeError("servo thread already running")
        if self._switch is not None:
            _switch_interval.lower(self._switch)
            self._old_switch = self._switch
        self._thread = threading.Thread(target=self._main, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float | None = None) -> bool:
        """Ramp forces down, disable them and join the thread.

        Parameters
        ----------
        timeout_s : float, optional
            Longest wait [s]; default the ramp time plus one second. If the thread has not ended
            by then it is told to halt after its current tick.

        Returns
        -------
        bool
            True if the thread ended (or was not running).
        """
        core = self.core
        core.request_stop()
        th = self._thread
        ok = True
        if th is not None:
            wait = core.config.ramp_s + 1.0 if timeout_s is None else timeout_s
            th.join(wait)
            if th.is_alive():
                self.loop.halt()
                th.join(0.5)
            ok = not th.is_alive()
            self._thread = None
        if ok and not core.stopped:
            core.shutdown_now(None)  # no thread ran the ramp: zero and disable at once
        if self._old_switch is not None:
            _switch_interval.restore()
            self._old_switch = None
        return ok

    # -- delegation for the network side -------------------------------------------------------------
    def set_patch(self, update: LocalModelUpdate) -> LocalModelUpdate:
        """Hand ``update`` to the servo loop (:meth:`ServoCore.set_patch`); also link activity now.

        Returns what will be applied (K_h and B_h clamped to the device).
        """
        patch = self.core.set_patch(update)
        self.core.notify_link(self.clock())
        return patch

    def notify_link(self, now_s: float | None = None) -> None:
        """The server spoke (patch or pong); ``now_s`` defaults to the servo clock now."""
        self.core.notify_link(self.clock() if now_s is None else now_s)

    def enable_forces(self) -> None:
        """See :meth:`ServoCore.enable_forces`."""
        self.core.enable_forces()

    def disable_forces(self) -> None:
        """See :meth:`ServoCore.disable_forces`."""
        self.core.disable_forces()

    def latest(self) -> ServoSnapshot | None:
        """See :meth:`ServoCore.latest` (never blocks the tick)."""
        return self.core.latest()

    def status(self) -> ServoStatus:
        """See :meth:`ServoCore.status`."""
        return self.core.status()
