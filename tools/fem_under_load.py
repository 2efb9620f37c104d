"""Where a FEM room's tick time goes on a busy machine: wall time, CPU time and run-queue wait.

``python tools/fem_under_load.py --json FILE`` runs, ``--repeats`` times and alternating, a
``haptic server --object fem`` (the liver sphere) with its simulation thread at the ordinary
policy (``HAPTIC_TICK_PRIORITY=off``) and asking for a real-time one (``realtime``,
:mod:`server.priority`), with ``--users`` users of ``haptic bench load``
(:mod:`haptic_collab.bench.load_clients`) and ``--burners`` CPU-bound processes beside it. The
burners are started by this script, so they share the server's session (and so its autogroup,
``/proc/sys/kernel/sched_autogroup_enabled``), as two busy commands in the terminal that runs
``haptic demo`` do; ``haptic bench rooms --compare priority --burners N`` measures the other
case (a server in a session of its own).

The server runs in a child process of this script with :meth:`server.room.Room.handle_timer`
wrapped, so that each tick records: its lateness (from its due time) [s], its wall time [s],
the thread's CPU time in it (:func:`time.thread_time`) [s], and how long the thread waited for a
CPU while runnable across it (``/proc/thread-self/schedstat``; accounted when the thread gets a
CPU, so it includes the wait to wake up for the tick) [s]. Over the window it reads each
thread's CPU and run-queue wait (``/proc/self/task/TID/schedstat``, named from
:func:`threading.enumerate`: ``MainThread`` is the event loop, ``patch-prefetch_0`` the
prefetcher), and each user's patch rate. Linux only. A diagnosis tool: medians of runs side by
side, no thresholds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

MODES = ("off", "realtime")
#: ``--sweep``: each user's spot swings along the sphere's surface, +-SWEEP_RAD [rad] about the
#: centre SWEEP_RADIUS_M [m] behind it, at SWEEP_HZ, so its contact keeps reaching patches that
#: are not solved yet and the prefetch thread works (the default liver sphere: r 0.1 m).
SWEEP_RAD, SWEEP_HZ, SWEEP_RADIUS_M = 0.5, 0.1, 0.1
SWEEP_ENV = "FEM_UNDER_LOAD_SWEEP"


def _swept(user_state: Any) -> Any:
    """``user_state`` with its spot rotated about the axis normal x (any direction across it)."""

    def state(spec: Any, spot: Any, elapsed_s: float, *rest: Any) -> Any:
        import math

        base, normal = spot
        centre = [base[i] - SWEEP_RADIUS_M * normal[i] for i in range(3)]
        a = [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0]
        t = [a[1] * normal[2] - a[2] * normal[1], a[2] * normal[0] - a[0] * normal[2]]
        t.append(a[0] * normal[1] - a[1] * normal[0])
        norm = math.sqrt(sum(c * c for c in t))
        t = [c / norm for c in t]
        th = SWEEP_RAD * math.sin(2 * math.pi * SWEEP_HZ * elapsed_s + 0.7 * spec.slot)
        n = [math.cos(th) * normal[i] + math.sin(th) * t[i] for i in range(3)]
        moved = ([centre[i] + SWEEP_RADIUS_M * n[i] for i in range(3)], n)
        return user_state(spec, moved, elapsed_s, *rest)

    return state


if os.environ.get(SWEEP_ENV):  # in the users' spawned worker too: it imports this file first
    import haptic_collab.bench.rooms as _rooms

    _rooms.user_state = _swept(_rooms.user_state)  # type: ignore[assignment]
BURNER = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    pass"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _threads() -> dict[str, tuple[float, float]]:
    """Per thread of this process: (CPU s, run-queue wait s), named by its Python name."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as f:
                run_ns, wait_ns, _ = f.read().split()
        except OSError:
            continue
        out[names.get(int(tid), f"tid {tid}")] = (int(run_ns) / 1e9, int(wait_ns) / 1e9)
    return out


def _pct_ms(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    s = sorted(xs)
    return round(1e3 * s[min(len(s) - 1, int(q * len(s)))], 3)


def child(opts: argparse.Namespace) -> None:
    """The instrumented server; prints one JSON line with the window's readings, then exits."""
    import haptic_collab.cli.blas_threads  # noqa: F401  (one BLAS thread, as `haptic` does)
    from haptic_collab.bench.rooms import _rates, _Workers
    from haptic_collab.cli import main
    from haptic_collab.server.room import Room

    ticks: list[tuple[float, float, float, float]] = []
    original = Room.handle_timer

    def schedstat() -> float:
        with open("/proc/thread-self/schedstat") as f:
            return int(f.read().split()[1]) / 1e9

    def handle_timer(self: Room, now_s: float) -> Any:
        due = self.get_timer()
        if not now_s >= due:
            return original(self, now_s)
        t0, c0, w0 = time.perf_counter(), time.thread_time(), schedstat()
        out = original(self, now_s)
        t1, c1, w1 = time.perf_counter(), time.thread_time(), schedstat()
        ticks.append((now_s - due, t1 - t0, c1 - c0, w1 - w0))
        return out

    Room.handle_timer = handle_timer  # type: ignore[method-assign]

    def driver() -> None:
        time.sleep(opts.start_s)
        workers = _Workers(opts.port, ["default"], opts.users, 1)
        workers.wait_ready()
        time.sleep(opts.warmup_s)
        n0, t0, th0, load = len(ticks), time.monotonic(), _threads(), os.getloadavg()
        time.sleep(opts.duration_s)
        n1, t1, th1 = len(ticks), time.monotonic(), _threads()
        rates = _rates(workers.stop(), t0, t1, ["default"])["default"]
        win = ticks[n0:n1]
        res: dict[str, Any] = {"mode": opts.mode, "load_avg": load, "ticks": len(win)}
        for i, name in enumerate(("lateness", "wall", "cpu", "runqueue_wait")):
            for q in (0.5, 0.99):
                res[f"{name}_ms_p{round(q * 100)}"] = _pct_ms([t[i] for t in win], q)
        res["patch_share"] = [round(r / opts.sim_rate, 4) for r in rates]
        span = t1 - t0
        res["threads_share"] = {
            k: {
                "cpu": round((th1[k][0] - th0[k][0]) / span, 4),
                "runqueue_wait": round((th1[k][1] - th0[k][1]) / span, 4),
            }
            for k in th1
            if k in th0
        }
        print("RESULT " + json.dumps(res), flush=True)
        os._exit(0)

    threading.Thread(target=driver, daemon=True).start()
    main(["server", "--object", "fem", "--port", str(opts.port), "--sim-rate", str(opts.sim_rate)])


def parent(opts: argparse.Namespace) -> dict[str, Any]:
    """The runs, alternating the modes, with the burners running throughout."""
    burners = [subprocess.Popen([sys.executable, "-c", BURNER]) for _ in range(opts.burners)]
    runs: list[dict[str, Any]] = []
    try:
        for rep in range(opts.repeats):
            for mode in MODES:
                print(f"[fem under load] run {rep + 1}: {mode}", file=sys.stderr, flush=True)
                env = dict(os.environ, HAPTIC_TICK_PRIORITY=mode)
                if opts.sweep:
                    env[SWEEP_ENV] = "1"
                cmd = [sys.executable, __file__, "--child", "--mode", mode]
                cmd += ["--port", str(_free_port())]
                for k in ("users", "warmup_s", "duration_s", "sim_rate", "start_s"):
                    cmd += [f"--{k.replace('_', '-')}", str(getattr(opts, k))]
                p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
                line = next((ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")), None)
                if line is None:
                    raise RuntimeError(f"run {rep + 1} {mode} gave no result:\n{p.stderr[-2000:]}")
                runs.append({"repeat": rep + 1} | json.loads(line[len("RESULT ") :]))
    finally:
        for b in burners:
            b.kill()
            b.wait()
    keys = [k for k in runs[0] if k.endswith(("_p50", "_p99"))]
    summary: dict[str, Any] = {}
    for mode in MODES:
        mine = [r for r in runs if r["mode"] == mode]
        summary[mode] = {k: statistics.median(r[k] for r in mine) for k in keys}
        shares = [s for r in mine for s in r["patch_share"]]
        summary[mode]["patch_share_min"] = min(shares) if shares else None
        summary[mode]["main_thread_runqueue_wait_share_median"] = statistics.median(
            r["threads_share"]["MainThread"]["runqueue_wait"] for r in mine
        )
    return {
        "what": "FEM room (liver sphere), tick priority off vs realtime, alternating, burners "
        "in the server's session",
        "command": "python tools/fem_under_load.py " + " ".join(sys.argv[1:]),
        "machine": {"cpus": os.cpu_count(), "kernel": platform.release()},
        "burners": opts.burners,
        "users": opts.users,
        "sweep": {"rad": SWEEP_RAD, "hz": SWEEP_HZ} if opts.sweep else None,
        "runs": runs,
        "summary": summary,
    }


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--burners", type=int, default=2)
    p.add_argument("--users", type=int, default=2)
    p.add_argument("--warmup-s", type=float, default=8.0)
    p.add_argument("--duration-s", type=float, default=20.0)
    p.add_argument("--sim-rate", type=float, default=20.0)
    p.add_argument("--start-s", type=float, default=6.0, help="the server's start-up [s]")
    p.add_argument("--json", default=None)
    p.add_argument("--sweep", action="store_true", help="the users sweep (SWEEP_RAD, SWEEP_HZ)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--mode", choices=MODES, default="off", help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    return p.parse_args(argv)


if __name__ == "__main__":
    options = parse()
    if options.child:
        child(options)
    else:
        result = parent(options)
        text = json.dumps(result, indent=2)
        if options.json:
            Path(options.json).write_text(text + "\n")
        print(text)
