"""Timing of the servo thread: the deadline scheduler and the process-wide real-time tweaks.

:class:`DeadlineLoop` runs a tick callable at ``start + k*T`` (integer tick counts, never
accumulated float time); it sleeps until ``spin_s`` before the deadline and spins the rest; a
deadline missed by more than ``late_tolerance`` periods is counted and skipped, never piled up.
Clock and sleep are injected.

:func:`try_realtime_priority` and the switch-interval counter change the process or the calling
thread (SCHED_FIFO, :func:`sys.setswitchinterval`); :class:`client.servo_thread.ServoThread` uses them
while it runs.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

Clock = Callable[[], float]
Sleep = Callable[[float], None]


@dataclass
class DeadlineLoop:
    """Deadline scheduler: tick k is due at ``start + k * period_s`` (integer k, no float drift).

    Parameters
    ----------
    period_s : float
        Period T [s], > 0.
    clock : callable
        Monotonic clock [s] (default :func:`time.perf_counter`).
    sleep : callable
        ``sleep(seconds)`` (default :func:`time.sleep`).
    spin_s : float
        The last ``spin_s`` [s] before a deadline are busy-waited on ``clock`` instead of slept
        (sleep overshoots by ~0.1 ms on a stock Linux kernel; default 3e-4).
    late_tolerance : float
        A deadline is missed when the loop gets to it more than ``late_tolerance * period_s``
        late; missed deadlines are skipped (default 0.5).

    Attributes
    ----------
    overruns : int
        Deadlines missed and skipped so far.
    ticks : int
        Ticks run so far.
    """

    period_s: float
    clock: Clock = time.perf_counter
    sleep: Sleep = time.sleep
    spin_s: float = 3e-4
    late_tolerance: float = 0.5
    overruns: int = field(default=0, init=False)
    ticks: int = field(default=0, init=False)
    _halt: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0.0):
            raise ValueError(f"period_s must be > 0, got {self.period_s!r}")
        if not (0.0 < self.late_tolerance < 1.0):
            raise ValueError("late_tolerance must be in (0, 1) periods")

    def halt(self) -> None:
        """Make :meth:`run` return after the current tick (from any thread)."""
        self._halt = True

    def run(
        self,
        tick: Callable[[float], bool],
        *,
        max_ticks: int | None = None,
        after_tick: Callable[[float], None] | None = None,
        on_overrun: Callable[[int, float], None] | None = None,
    ) -> int:
        """Call ``tick(now_s)`` at every deadline until it returns True, ``max_ticks`` or halt.

        Parameters
        ----------
        tick : callable
            ``tick(now_s) -> stop``; ``now_s`` [s] is the clock when the deadline was reached.
        max_ticks : int, optional
            Stop after this many ticks.
        after_tick : callable, optional
            ``after_tick(compute_s)`` with the tick's duration [s].
        on_overrun : callable, optional
            ``on_overrun(missed, now_s)`` when deadlines were missed and skipped.

        Returns
        -------
        int
            Ticks run by this call.
        """
        clock, sleep = self.clock, self.sleep
        T, spin = self.period_s, self.spin_s
        tol = self.late_tolerance * T
        self._halt = False
        start = clock()
        k = 0
        done = 0
        while True:
            deadline = start + k * T
            now = clock()
            wait = deadline - now
            if wait > spin:
                sleep(wait - spin)
                now = clock()
            while now < deadline:
                now = clock()
            stop = tick(now)
            end = clock()
            done += 1
            if after_tick is not None:
                after_tick(end - now)
            if stop or self._halt or (max_ticks is not None and done >= max_ticks):
                break
            k += 1
            if end - (start + k * T) > tol:
                k_next = math.ceil((end - tol - start) / T)
                missed = k_next - k
                self.overruns += missed
                if on_overrun is not None:
                    on_overrun(missed, end)
                k = k_next
        self.ticks += done
        return done


class _SwitchInterval:
    """Reference-counted lowering of the interpreter's thread switch interval (process-wide)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved = 0.0

    def lower(self, interval_s: float) -> None:
        with self._lock:
            if self._users == 0:
                self._saved = sys.getswitchinterval()
            self._users += 1
            sys.setswitchinterval(min(sys.getswitchinterval(), interval_s))

    def restore(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                sys.setswitchinterval(self._saved)


_switch_interval = _SwitchInterval()


def try_realtime_priority(priority: int) -> bool:
    """Put the calling thread under SCHED_FIFO at ``priority`` (1-99) if the OS allows it.

    What haptic vendors do for their servo thread: a real-time thread is not preempted by the
    ordinary processes of the machine, so it wakes on time even when the CPUs are busy. The loop
    still sleeps most of each period, and Linux caps real-time threads at 95 % of a CPU by
    default, so it cannot lock the machine up.

    Returns
    -------
    bool
        True if granted; False where unsupported or not permitted (the thread keeps its policy).
    """
    setsched = getattr(os, "sched_setscheduler", None)
    fifo = getattr(os, "SCHED_FIFO", None)
    if setsched is None or fifo is None:
        return False
    try:
        setsched(0, fifo, os.sched_param(priority))
    except (OSError, ValueError):
        return False
    return True


def ordinary_priority() -> bool:
    """Put the calling thread back under the ordinary policy (SCHED_OTHER), e.g. a helper thread
    started by a real-time thread (a new thread inherits its creator's policy).

    Returns
    -------
    bool
        True if done; False where unsupported or not permitted.
    """
    setsched = getattr(os, "sched_setscheduler", None)
    other = getattr(os, "SCHED_OTHER", None)
    if setsched is None or other is None:
        return False
    try:
        setsched(0, other, os.sched_param(0))
    except (OSError, ValueError):
        return False
    return True
