"""The thread that ticks the rooms asks for a real-time priority, falls back, and says so.

The OS calls are replaced by recording fakes (the pytest thread's own policy is never changed),
except in the last test, which asks the real kernel from a thread of its own and is skipped
where the kernel refuses.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import os
import threading
from typing import Any

import pytest

from haptic_collab.client.servo_thread import ServoThread
from haptic_collab.server.app import ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.priority import TICK_NICE, TICK_RT_PRIORITY, TickPriority
from haptic_collab.server.room import Room

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setscheduler"), reason="no POSIX scheduling calls on this OS"
)

FIFO = os.SCHED_FIFO if hasattr(os, "SCHED_FIFO") else 1
OTHER = os.SCHED_OTHER if hasattr(os, "SCHED_OTHER") else 0
RESET = getattr(os, "SCHED_RESET_ON_FORK", 0)


class FakeOS:
    """Records the scheduling calls; refuses real-time and/or nice when told to."""

    def __init__(self, mp: pytest.MonkeyPatch, refuse_fifo: bool, refuse_nice: bool) -> None:
        self.sched: list[tuple[int, int, int]] = []
        self.nice: list[int] = []
        self.refuse_fifo, self.refuse_nice = refuse_fifo, refuse_nice
        mp.setattr(os, "sched_setscheduler", self.setscheduler)
        mp.setattr(os, "sched_getscheduler", lambda pid: OTHER)
        mp.setattr(os, "sched_getparam", lambda pid: os.sched_param(0))
        mp.setattr(os, "setpriority", self.setpriority)
        mp.setattr(os, "getpriority", lambda which, who: 0)

    def setscheduler(self, pid: int, policy: int, param: Any) -> None:
        if self.refuse_fifo and policy & ~RESET == FIFO:
            raise PermissionError(1, "Operation not permitted")
        self.sched.append((pid, policy, param.sched_priority))

    def setpriority(self, which: int, who: int, value: int) -> None:
        if self.refuse_nice and value < 0:
            raise PermissionError(13, "Permission denied")
        self.nice.append(value)


def test_it_asks_sched_fifo_below_the_client_servo_and_not_for_later_threads(monkeypatch):
    fake = FakeOS(monkeypatch, refuse_fifo=False, refuse_nice=False)
    prio = TickPriority("realtime")
    assert prio.ask() == f"SCHED_FIFO {TICK_RT_PRIORITY}"
    # this thread only (pid 0), threads and processes started later reset to the ordinary policy
    assert fake.sched == [(0, FIFO | RESET, TICK_RT_PRIORITY)]
    servo_default = inspect.signature(ServoThread).parameters["realtime_priority"].default
    assert 1 <= TICK_RT_PRIORITY < servo_default  # a client servo on this machine preempts it
    assert fake.nice == []
    prio.restore()
    assert fake.sched[-1] == (0, OTHER, 0)


def test_refused_real_time_falls_back_to_a_negative_nice_and_says_so(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="haptic.server")
    fake = FakeOS(monkeypatch, refuse_fifo=True, refuse_nice=False)
    prio = TickPriority("realtime", "room 'b1'")
    assert prio.ask() == f"nice {TICK_NICE}"
    assert fake.nice == [TICK_NICE]
    assert all(policy & ~RESET == OTHER for _, policy, _ in fake.sched)
    lines = [r.getMessage() for r in caplog.records]
    assert any("room 'b1'" in ln and "refused" in ln and f"nice {TICK_NICE}" in ln for ln in lines)
    prio.restore()
    assert fake.nice == [TICK_NICE, 0]


def test_both_refused_logs_one_warning_and_the_thread_keeps_its_priority(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="haptic.server")
    fake = FakeOS(monkeypatch, refuse_fifo=True, refuse_nice=True)
    prio = TickPriority("realtime")
    assert prio.ask() == "ordinary"
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "PermissionError" in warnings[0] and 'tick_priority = "off"' in warnings[0]
    assert fake.nice == []
    prio.restore()  # nothing was granted: nothing to give back
    assert fake.nice == []
    assert all(policy & ~RESET == OTHER for _, policy, _ in fake.sched)


def test_off_asks_nothing(monkeypatch):
    fake = FakeOS(monkeypatch, refuse_fifo=False, refuse_nice=False)
    prio = TickPriority("off")
    assert prio.ask() == "off"
    prio.restore()
    assert fake.sched == [] and fake.nice == []
    with pytest.raises(ValueError, match="tick priority"):
        TickPriority("high")


def test_haptic_servers_default_is_realtime_and_the_environment_turns_it_off(monkeypatch):
    monkeypatch.delenv("HAPTIC_TICK_PRIORITY", raising=False)
    assert ServerOptions().tick_priority == "realtime"
    monkeypatch.setenv("HAPTIC_TICK_PRIORITY", "off")
    assert ServerOptions().tick_priority == "off"


@pytest.mark.parametrize("refuse", [False, True])
async def test_the_server_asks_when_it_starts_and_gives_it_back_when_it_stops(monkeypatch, refuse):
    fake = FakeOS(monkeypatch, refuse_fifo=refuse, refuse_nice=refuse)
    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=2))
    app = ServerApp(Room(world, 20.0), "127.0.0.1", 0, tick_priority="realtime")
    assert fake.sched == []  # nothing before start
    await app.start()
    try:
        assert app.tick_priority.granted == ("ordinary" if refuse else "SCHED_FIFO 5")
        for _ in range(400):  # it ticks either way (bounded wait, no time asserted)
            if app.room.tick_count > 2:
                break
            await asyncio.sleep(0.025)
        assert app.room.tick_count > 2
    finally:
        await app.stop()
    if not refuse:
        assert fake.sched == [(0, FIFO | RESET, TICK_RT_PRIORITY), (0, OTHER, 0)]


def test_on_a_real_kernel_threads_started_later_get_the_ordinary_policy():
    """Asked from a thread of its own: granted, that thread is SCHED_FIFO and a thread it starts
    (the patch prefetcher, to_thread's workers) is not; restored, it is ordinary again."""
    seen: dict[str, Any] = {}

    def child() -> None:
        seen["child"] = os.sched_getscheduler(0)

    def ticker() -> None:
        prio = TickPriority("realtime")
        seen["granted"] = prio.ask()
        seen["own"] = os.sched_getscheduler(0)
        t = threading.Thread(target=child)
        t.start()
        t.join()
        prio.restore()
        seen["after"] = os.sched_getscheduler(0)

    t = threading.Thread(target=ticker)
    t.start()
    t.join()
    if not seen["granted"].startswith("SCHED_FIFO"):
        pytest.skip(f"the kernel refused real-time here ({seen['granted']})")
    assert seen["own"] == FIFO | RESET  # real-time, not passed on
    assert seen["child"] == OTHER
    assert seen["after"] == OTHER
