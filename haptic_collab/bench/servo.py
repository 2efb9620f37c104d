"""Servo-loop benchmark: does the 1 kHz loop keep time, and what does a tick cost?

Two loops run one after the other on the same scheduler (:class:`client.scheduler.DeadlineLoop`, real
clock, the calling thread):

1. *minimal*: the scheduler alone, each tick only stores its time: what this machine and Python
   can do at best;
2. *servo*: a full :class:`client.servo.ServoCore` tick: simulated ``phantom-desktop`` device with
   its hand running a press into a plane (10 sub-steps per tick), PI local model (eq. 12, fixed
   threshold eq. 17), safety checks, force write and telemetry row.

Targets (DESIGN section 4, the servo rate): mean rate within 0.1 % of the set rate, period p99 of
the servo loop within 1.2x the minimal loop's, compute p50 <= 20 us per tick. Speed is measured
here, never asserted in tests. ``python -m haptic_collab.bench.servo --duration 5 --rate 1000`` prints
the JSON.
"""

from __future__ import annotations

import argparse
import array
import json
import math
import os
import platform
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from haptic_collab.client.devices.opener import make_device
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.scheduler import DeadlineLoop, try_realtime_priority
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams
from haptic_collab.shared.primitives import make_plane


def _in_thread(fn: Callable[[], dict[str, Any]], priority: int | None) -> dict[str, Any]:
    """Run ``fn`` on a fresh thread (as the servo thread runs), optionally real-time."""
    out: dict[str, Any] = {}

    def main() -> None:
        granted = try_realtime_priority(priority) if priority is not None else False
        cpu0, wall0 = time.thread_time(), time.perf_counter()
        out.update(fn())
        cpu, wall = time.thread_time() - cpu0, time.perf_counter() - wall0
        out["realtime"] = granted
        out["cpu_pct_of_one_core"] = 100.0 * cpu / wall if wall > 0 else math.nan

    th = threading.Thread(target=main, name="bench-servo")
    th.start()
    th.join()
    if not out:
        raise RuntimeError("benchmark thread failed")
    return out


def _period_stats(times_s: np.ndarray, rate_hz: float) -> dict[str, float]:
    """Rate and period statistics [us] from tick times (n,) [s]."""
    periods = np.diff(times_s)
    if periods.size == 0:
        return {"ticks": int(times_s.size)}
    span = float(times_s[-1] - times_s[0])
    rate = periods.size / span if span > 0 else math.nan
    return {
        "ticks": int(times_s.size),
        "rate_hz": rate,
        "rate_error_pct": 100.0 * (rate - rate_hz) / rate_hz,
        "period_mean_us": float(periods.mean() * 1e6),
        "period_p50_us": float(np.percentile(periods, 50) * 1e6),
        "period_p99_us": float(np.percentile(periods, 99) * 1e6),
        "period_max_us": float(periods.max() * 1e6),
        "period_std_us": float(periods.std() * 1e6),
    }


def _minimal(duration_s: float, rate_hz: float, spin_s: float) -> dict[str, Any]:
    n = max(2, int(round(duration_s * rate_hz)))
    times = array.array("d", bytes(8 * n))
    count = [0]

    def tick(now: float) -> bool:
        i = count[0]
        times[i] = now
        count[0] = i + 1
        return False

    loop = DeadlineLoop(1.0 / rate_hz, spin_s=spin_s)
    loop.run(tick, max_ticks=n)
    t = np.frombuffer(times, dtype=np.float64)[: count[0]]
    span = float(t[-1] - t[0]) if t.size > 1 else math.nan
    return {
        **_period_stats(t, rate_hz),
        "missed_deadlines": loop.overruns,
        "missed_per_s": loop.overruns / span if span > 0 else math.nan,
    }


def _servo(duration_s: float, rate_hz: float, spin_s: float, profile: str) -> dict[str, Any]:
    n = max(2, int(round(duration_s * rate_hz)))
    T = 1.0 / rate_hz
    anchor, normal = (0.0, 0.0, 0.05), (0.0, 0.0, 1.0)
    d = duration_s
    dev = make_device(
        "sim:press",
        anchor,
        normal,
        profile,
        trajectory_options={
            "approach_s": 0.2 * d,
            "press_s": 0.2 * d,
            "hold_s": 0.4 * d,
            "release_s": 0.2 * d,
        },
        servo_rate_hz=rate_hz,
    )
    dev.open()
    lm = LocalModelParams(
        k_h=300.0,
        i_gain=2000.0,
        servo_period_s=T,
        threshold=ThresholdParams(mode="fixed", theta_m=0.001),
    )
    core = ServoCore(
        dev,
        ServoConfig(servo_rate_hz=rate_hz, link_timeout_s=math.inf),
        local_model=lm,
        recorder=TelemetryRecorder(capacity=n),
    )
    core.enable_forces()
    core.set_patch(make_plane(anchor, normal), 300.0, 2000.0)
    loop = DeadlineLoop(T, spin_s=spin_s)
    loop.run(
        core.tick,
        max_ticks=n,
        after_tick=core.record_compute,
        on_overrun=core.note_overrun,
    )
    dev.close()
    rows = core.recorder.rows()
    cols = core.recorder.columns
    t = rows[:, cols.index("t_s")]
    compute = rows[:, cols.index("compute_s")]
    contact = rows[:, cols.index("in_contact")]
    return {
        **_period_stats(t, rate_hz),
        "missed_deadlines": loop.overruns,
        "compute_p50_us": float(np.percentile(compute, 50) * 1e6),
        "compute_p99_us": float(np.percentile(compute, 99) * 1e6),
        "compute_max_us": float(compute.max() * 1e6),
        "ticks_in_contact": int(contact.sum()),
        "max_force_n": float(np.abs(rows[:, cols.index("force_n")]).max()),
    }


def run(
    duration_s: float = 5.0,
    rate_hz: float = 1000.0,
    *,
    spin_s: float = 3e-4,
    profile: str = "phantom-desktop",
    realtime_priority: int | None = 10,
) -> dict[str, Any]:
    """Measure the minimal loop, then the full servo loop, each for ``duration_s`` [s].

    Parameters
    ----------
    duration_s : float
        Length [s] of each of the two runs, > 0.
    rate_hz : float
        Servo rate [Hz], > 0.
    spin_s : float
        Busy-wait margin [s] before each deadline (see :class:`client.scheduler.DeadlineLoop`).
    profile : str
        Simulated device profile of the servo run.
    realtime_priority : int or None
        SCHED_FIFO priority asked for the benchmark threads, as :class:`client.servo_thread.ServoThread`
        does by default; None runs them as ordinary threads. ``realtime`` in each result says
        whether it was granted.

    Returns
    -------
    dict
        JSON-able: ``servo`` and ``minimal`` each with ``rate_hz``, ``rate_error_pct``,
        ``period_{mean,p50,p99,max,std}_us``, ``missed_deadlines``, ``cpu_pct_of_one_core``
        (``servo`` also ``compute_{p50,p99,max}_us``); ``p99_ratio`` (servo period p99 / minimal period p99);
        ``targets`` (each target and whether it was met); the settings and the machine.

    Raises
    ------
    ValueError
        Non-positive duration or rate.
    """
    if not (duration_s > 0 and rate_hz > 0):
        raise ValueError("duration_s and rate_hz must be > 0")
    minimal = _in_thread(lambda: _minimal(duration_s, rate_hz, spin_s), realtime_priority)
    servo = _in_thread(lambda: _servo(duration_s, rate_hz, spin_s, profile), realtime_priority)
    ratio = servo.get("period_p99_us", math.nan) / minimal.get("period_p99_us", math.nan)
    targets = {
        "rate_within_0.1_pct": abs(servo.get("rate_error_pct", math.inf)) <= 0.1,
        "p99_within_1.2x_minimal": ratio <= 1.2,
        "compute_p50_le_20_us": servo.get("compute_p50_us", math.inf) <= 20.0,
    }
    return {
        "rate_hz_set": rate_hz,
        "duration_s": duration_s,
        "spin_us": spin_s * 1e6,
        "realtime_priority": realtime_priority,
        "profile": profile,
        "servo": servo,
        "minimal": minimal,
        "p99_ratio": ratio,
        "targets": targets,
        "python": sys.version.split()[0],
        "machine": f"{platform.machine()} {platform.system()} {platform.release()}",
        "cpus": os.cpu_count(),
    }


def main(argv: list[str] | None = None) -> int:
    """Command line: print :func:`run`'s JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--duration", type=float, default=5.0, help="seconds per run (default 5)")
    ap.add_argument("--rate", type=float, default=1000.0, help="servo rate in Hz (default 1000)")
    ap.add_argument("--spin-us", type=float, default=300.0, help="busy-wait margin (default 300)")
    ap.add_argument(
        "--no-realtime", action="store_true", help="do not ask for SCHED_FIFO (ordinary threads)"
    )
    ap.add_argument(
        "--minimal-only",
        action="store_true",
        help="run only the do-nothing loop, in this process's main thread (the reference "
        "``haptic demo --reference-loop`` runs beside the users)",
    )
    args = ap.parse_args(argv)
    if args.minimal_only:
        prio = None if args.no_realtime else 10
        granted = try_realtime_priority(prio) if prio is not None else False
        res = {**_minimal(args.duration, args.rate, args.spin_us * 1e-6), "realtime": granted}
        print(json.dumps(res, indent=2))
        return 0
    res = run(
        args.duration,
        args.rate,
        spin_s=args.spin_us * 1e-6,
        realtime_priority=None if args.no_realtime else 10,
    )
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
