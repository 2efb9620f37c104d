"""The scheduling priority of the thread that ticks a room: real-time when the OS allows it.

On a busy machine the simulation tick is late because the kernel does not run it, not because it
costs more: with CPU-bound processes beside a FEM room, the event loop's thread waits runnable for
a CPU (``/proc/thread-self/schedstat``) for most of a tick's wall time, while its CPU time
(:func:`time.thread_time`) stays as on a quiet machine and the GIL and the patch prefetch thread
take next to nothing (docs/fem.md, "Under load"). So the cure is at the scheduler: the thread
running the event loop (which ticks the room, and reads and writes its users' frames) asks for
SCHED_FIFO at a low priority, as haptic vendors' servo threads and
:func:`client.scheduler.try_realtime_priority` do. Where that is refused (no CAP_SYS_NICE, or a
container without a real-time budget) it asks for a negative nice instead, and where that is
refused too it logs one warning and runs as before.

Why it cannot starve the machine: the loop sleeps between ticks (its duty cycle is in
docs/fem.md), Linux caps real-time threads at ``sched_rt_runtime_us`` /
``sched_rt_period_us`` of each CPU (95 % by default), and the priority (:data:`TICK_RT_PRIORITY`)
is below the client servo thread's 10, so a client on the same machine still preempts the
server. ``SCHED_RESET_ON_FORK`` is set with it: threads and processes started from this thread
later (the patch prefetch thread, ``asyncio.to_thread``'s workers, the gain-design processes,
room processes) run under the ordinary policy at nice 0, not at this thread's priority.

Linux applies :func:`os.sched_setscheduler` and :func:`os.setpriority` with pid 0 to the calling
thread only: call :meth:`TickPriority.ask` and :meth:`TickPriority.restore` from the thread that
runs the event loop.
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass, field

log = logging.getLogger("haptic.server")

#: SCHED_FIFO priority (1-99) asked for the ticking thread: below the client servo's 10.
TICK_RT_PRIORITY = 5
#: The nice value asked for when real-time is refused (negative: ahead of ordinary processes).
TICK_NICE = -10
#: Values of the ``tick_priority`` option: ``realtime`` asks (falling back as above), ``off``
#: leaves the thread as it is.
TICK_PRIORITIES = ("realtime", "off")


@dataclass
class TickPriority:
    """Ask for, and later give back, a real-time priority for the calling thread.

    Parameters
    ----------
    mode : str
        ``"realtime"``: SCHED_FIFO at :data:`TICK_RT_PRIORITY`, else nice :data:`TICK_NICE`,
        else unchanged (one warning); ``"off"``: unchanged.
    who : str
        Named in the log lines (e.g. ``"server"``, ``"room 'b1'"``).

    Attributes
    ----------
    granted : str
        What the thread got: ``"SCHED_FIFO 5"``, ``"nice -10"``, ``"ordinary"`` (refused) or
        ``"off"`` (not asked); ``""`` before :meth:`ask`.

    Raises
    ------
    ValueError
        ``mode`` not one of :data:`TICK_PRIORITIES`.
    """

    mode: str = "realtime"
    who: str = "server"
    granted: str = ""
    _saved_policy: tuple[int, int] | None = field(default=None, repr=False)
    _saved_nice: int | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.mode not in TICK_PRIORITIES:
            raise ValueError(f"tick priority must be one of {TICK_PRIORITIES}, got {self.mode!r}")

    def ask(self) -> str:
        """Ask for the priority (see the class); log what was granted. Returns :attr:`granted`."""
        if self.mode == "off":
            self.granted = "off"
            return self.granted
        why_fifo = self._fifo()
        if why_fifo is None:
            self.granted = f"SCHED_FIFO {TICK_RT_PRIORITY}"
            log.info(
                "%s: the simulation thread runs at SCHED_FIFO priority %d (tick_priority = "
                '"off" or HAPTIC_TICK_PRIORITY=off keeps the ordinary policy)',
                self.who,
                TICK_RT_PRIORITY,
            )
            return self.granted
        why_nice = self._nice()
        if why_nice is None:
            self.granted = f"nice {TICK_NICE}"
            log.info(
                "%s: real-time priority refused (%s); the simulation thread runs at nice %d",
                self.who,
                why_fifo,
                TICK_NICE,
            )
            return self.granted
        self.granted = "ordinary"
        log.warning(
            "%s: real-time priority refused (%s) and nice %d refused (%s): the simulation "
            "ticks at the ordinary priority and may be late on a busy machine (docs/deploy.md: "
            'CAP_SYS_NICE; tick_priority = "off" or HAPTIC_TICK_PRIORITY=off silences it)',
            self.who,
            why_fifo,
            TICK_NICE,
            why_nice,
        )
        return self.granted

    def restore(self) -> None:
        """Give the calling thread back the policy and nice value it had before :meth:`ask`."""
        if self._saved_policy is not None:
            policy, prio = self._saved_policy
            self._saved_policy = None
            try:
                os.sched_setscheduler(0, policy, os.sched_param(prio))
            except (OSError, ValueError) as exc:
                log.warning("%s: could not restore the scheduling policy: %s", self.who, exc)
        if self._saved_nice is not None:
            nice, self._saved_nice = self._saved_nice, None
            try:
                os.setpriority(os.PRIO_PROCESS, 0, nice)
            except OSError as exc:  # lowering it back is always allowed; kept for odd kernels
                log.warning("%s: could not restore the nice value: %s", self.who, exc)

    def _fifo(self) -> str | None:
        """SCHED_FIFO | SCHED_RESET_ON_FORK for the calling thread; None if granted, else why."""
        setsched = getattr(os, "sched_setscheduler", None)
        fifo = getattr(os, "SCHED_FIFO", None)
        if setsched is None or fifo is None:
            return "not supported on this OS"
        try:
            saved = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            setsched(
                0, fifo | getattr(os, "SCHED_RESET_ON_FORK", 0), os.sched_param(TICK_RT_PRIORITY)
            )
        except (OSError, ValueError) as exc:
            return f"{type(exc).__name__}: {exc}"
        self._saved_policy = saved
        return None

    def _nice(self) -> str | None:
        """Nice :data:`TICK_NICE` for the calling thread; None if granted, else why not."""
        setprio = getattr(os, "setpriority", None)
        if setprio is None:
            return "not supported on this OS"
        try:
            saved = os.getpriority(os.PRIO_PROCESS, 0)
            reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
            if reset and hasattr(os, "sched_setscheduler"):  # threads started later: nice 0
                with contextlib.suppress(OSError):  # setting the flag needs no privilege
                    os.sched_setscheduler(0, os.SCHED_OTHER | reset, os.sched_param(0))
            setprio(os.PRIO_PROCESS, 0, TICK_NICE)
        except OSError as exc:
            return f"{type(exc).__name__}: {exc}"
        self._saved_nice = saved
        return None
