"""``haptic bench load``: real users and viewers against a real server process, for minutes.

The server runs in its own process (``python -m haptic_collab.cli server --port 0``), exactly as deployed
on loopback; the port is read from its ``viewer: http://...`` line. N users and M viewers are real
websocket clients speaking the whole protocol (docs/protocol.md), spread over a few worker
processes (``multiprocessing``, spawn), each with its own loopback source address (127.0.0.2, .3,
... on Linux, so that the server's per-address budgets see a few hosts rather than one). What a
user (resting or pressing gently, a ``state`` twice per simulation tick) and a viewer (reading
every frame) do is :mod:`haptic_collab.bench.load_clients`; this module is the coordinator: the
options, the server, the workers, the window and the result.

After every client has joined and a warm-up, a measurement window of ``duration_s`` starts:
patches per user counted by the users, tick costs from the ``room`` frames the viewers receive
(``tick_ms`` of every tick; ``/status`` holds only the last 512), overruns and ticks from
``/status`` at both ends, the server's resident memory (``VmRSS`` of ``/proc/PID/status``) at both
ends and in between, CPU time of the server, the clients and the whole machine, and how long the
server's event loop waited for a CPU (``/proc/PID/schedstat``): on a shared machine that tells
contention from a slow server. ``errors`` counts ``error`` frames received plus connections lost
(or never made) by users and viewers.

This module is a benchmark driver: it reads clocks and starts processes, unlike the sans-I/O
server core. Nothing here is imported by the server.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from haptic_collab.bench.load_clients import JOIN_TIMEOUT_S, ClientSpec, client_specs, worker_main
from haptic_collab.server_process import ServerProcess

#: The keys every ``haptic bench load --json`` result has (what scripts may rely on).
REQUIRED_KEYS = (
    "sim_rate_hz",
    "users",
    "viewers",
    "duration_s",
    "patch_rate_hz_min",
    "patch_rate_hz_p1",
    "tick_ms_p50",
    "tick_ms_p99",
    "overruns_fraction",
    "rss_mb_start",
    "rss_mb_end",
    "errors",
)


# ----------------------------------------------------------------------------- options
@dataclass(frozen=True)
class LoadOptions:
    """What ``haptic bench load`` runs.

    Parameters
    ----------
    users, viewers : int
        Websocket users and viewers (the room holds at most 32 users and 64 viewers).
    duration_s : float
        Length of the measurement window [s], after every client joined and ``warmup_s``.
    sim_rate_hz : float
        The server's simulation rate [Hz] (``haptic server --sim-rate``).
    subdivisions : int
        Icosphere subdivisions of the balloon (4: 2562 vertices, 5: 10242).
    workers : int
        Client worker processes (users and viewers are dealt round-robin).
    warmup_s : float
        Wait after the last client joined before the window opens [s].
    """

    users: int = 32
    viewers: int = 8
    duration_s: float = 60.0
    sim_rate_hz: float = 20.0
    subdivisions: int = 4
    workers: int = 4
    warmup_s: float = 3.0

    def __post_init__(self) -> None:
        if not (0 <= self.users <= 32):
            raise ValueError(f"--users must be in [0, 32] (the room's maximum), got {self.users}")
        if not (0 <= self.viewers <= 64):
            raise ValueError(f"--viewers must be in [0, 64], got {self.viewers}")
        if self.users + self.viewers == 0:
            raise ValueError("nothing to run: give --users or --viewers")
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"--duration must be > 0 s, got {self.duration_s:g}")
        if not (1.0 <= self.sim_rate_hz <= 1000.0):
            raise ValueError(f"--sim-rate must be in [1, 1000] Hz, got {self.sim_rate_hz:g}")
        if not (0 <= self.subdivisions <= 7):
            raise ValueError(f"--subdivisions must be in [0, 7], got {self.subdivisions}")
        if self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")


def subdivisions_for_vertices(n_vertices: int) -> int:
    """The icosphere subdivisions ``s`` whose balloon has ``n_vertices = 10 * 4**s + 2``.

    Raises
    ------
    ValueError
        ``n_vertices`` is not such a count (12, 42, 162, 642, 2562, 10242, 40962, ...).
    """
    counts = {10 * 4**s + 2: s for s in range(8)}
    if n_vertices not in counts:
        raise ValueError(
            "--vertices must be an icosphere's vertex count: "
            + ", ".join(str(c) for c in sorted(counts))
        )
    return counts[n_vertices]


def _machine_cpu() -> tuple[float, float]:
    """(busy, total) CPU time of the whole machine so far [s] (``/proc/stat``)."""
    with open("/proc/stat", encoding="ascii") as f:
        vals = [int(v) for v in f.readline().split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    hz = os.sysconf("SC_CLK_TCK")
    return (sum(vals[:8]) - idle) / hz, sum(vals[:8]) / hz


def percentile(values: list[float], q: float) -> float:
    """Percentile ``q`` in [0, 100] of ``values``, linearly interpolated (numpy's default)."""
    if not values:
        return math.nan
    v = sorted(values)
    pos = (len(v) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(v) - 1)
    return v[lo] + (v[hi] - v[lo]) * (pos - lo)


def _source_addresses(n: int) -> list[str | None]:
    """A loopback source address per worker (127.0.0.2, ...) on Linux; the default elsewhere."""
    if not sys.platform.startswith("linux"):
        return [None] * n
    return [f"127.0.0.{2 + i}" for i in range(n)]


# ----------------------------------------------------------------------------- the benchmark
def run(opts: LoadOptions, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the load benchmark; return the result (:data:`REQUIRED_KEYS` and more).

    Parameters
    ----------
    opts : LoadOptions
        Users, viewers, window length [s], simulation rate [Hz], mesh, worker processes.
    log : callable, optional
        Progress lines (to stderr in the CLI).

    Returns
    -------
    dict
        ``sim_rate_hz`` [Hz]; ``users``, ``viewers``; ``duration_s`` [s] of the window;
        ``patch_rate_hz_min`` and ``patch_rate_hz_p1`` [Hz], the lowest and 1st-percentile
        per-user patch rate measured by the clients; ``tick_ms_p50`` and ``tick_ms_p99`` [ms] over
        every tick of the window (from the viewers' ``room`` frames, else ``/status``);
        ``overruns_fraction``, overruns per tick; ``rss_mb_start`` and ``rss_mb_end`` [MB], the
        server's resident memory; ``errors``, error frames received plus connections lost or never
        made. Also the details: per-user rates, the longest gap between patches [ms], CPU use of
        the server, the clients and the machine [cores], RSS samples, error codes.

    Raises
    ------
    RuntimeError
        The server did not start, or a worker process failed.
    """
    say = log or (lambda _msg: None)
    specs = client_specs(opts.users, opts.viewers)
    n_workers = max(1, min(opts.workers, len(specs)))
    per_worker: list[list[ClientSpec]] = [specs[i::n_workers] for i in range(n_workers)]
    sources = _source_addresses(n_workers)
    say(f"starting the server ({opts.sim_rate_hz:g} Hz, subdivisions {opts.subdivisions})")
    server = ServerProcess(
        "--sim-rate", f"{opts.sim_rate_hz:g}", "--subdivisions", str(opts.subdivisions)
    )
    ctx = mp.get_context("spawn")
    to_coord: Any = ctx.Queue()
    inboxes: list[Any] = [ctx.Queue() for _ in range(n_workers)]
    procs = []
    try:
        say(
            f"server on port {server.port}; {opts.users} users, {opts.viewers} viewers in {n_workers} workers"
        )
        for wid in range(n_workers):
            p = ctx.Process(
                target=worker_main,
                args=(wid, server.port, per_worker[wid], sources[wid], to_coord, inboxes[wid]),
                name=f"bench-load-{wid}",
                daemon=True,
            )
            p.start()
            procs.append(p)
        joined = 0
        for _ in range(n_workers):
            kind, wid, info = _get(to_coord, 4 * JOIN_TIMEOUT_S + 30, server)
            if kind == "failed":
                raise RuntimeError(f"client worker {wid} failed: {info}")
            joined += int(info)
        say(f"{joined} of {len(specs)} clients joined; warming up {opts.warmup_s:g} s")
        time.sleep(opts.warmup_s)
        t0 = time.monotonic() + 0.5
        t1 = t0 + opts.duration_s
        for q in inboxes:
            q.put((t0, t1))
        time.sleep(max(0.0, t0 - time.monotonic()))
        st0, rss0, cpu0, mach0 = server.status(), server.rss_mb(), server.cpu_s(), _machine_cpu()
        wait0 = server.run_wait_s()
        load0 = os.getloadavg()[0]
        samples = [(0.0, round(rss0, 2))]
        sample_every = max(1.0, opts.duration_s / 10.0)
        while True:
            remaining = t1 - time.monotonic()
            if remaining <= 0:
                break
            time.sleep(min(remaining, sample_every))
            if time.monotonic() < t1 - 0.5:
                samples.append((round(time.monotonic() - t0, 1), round(server.rss_mb(), 2)))
                say(f"{time.monotonic() - t0:.0f} s of {opts.duration_s:g} s")
        st1, rss1, cpu1, mach1 = server.status(), server.rss_mb(), server.cpu_s(), _machine_cpu()
        wait1 = server.run_wait_s()
        load1 = os.getloadavg()[0]
        samples.append((round(time.monotonic() - t0, 1), round(rss1, 2)))
        results = []
        for _ in range(n_workers):
            kind, wid, info = _get(to_coord, 60.0, server)
            if kind == "failed":
                raise RuntimeError(f"client worker {wid} failed: {info}")
            results.append(info)
        server_warnings = server.warnings()
    finally:
        for p in procs:
            p.join(10)
            if p.is_alive():
                p.terminate()
        server.stop()
    users = [u for r in results for u in r["users"]]
    viewers = [v for r in results for v in r["viewers"]]
    ticks: dict[int, float] = {}
    for r in results:
        ticks.update(r["ticks"])
    window_s = t1 - t0
    rates = sorted(u["patches"] / window_s for u in users)
    d_ticks = int(st1["tick"]) - int(st0["tick"])
    d_over = int(st1["overruns"]) - int(st0["overruns"])
    costs = list(ticks.values())
    codes: dict[str, int] = {}
    for c in users + viewers:
        for code, n in c["codes"].items():
            codes[code] = codes.get(code, 0) + n
    disconnects = sum(c["disconnects"] for c in users + viewers)
    never_joined = sum(not c["joined"] for c in users + viewers)
    errors = sum(c["errors"] for c in users + viewers) + disconnects
    rtts = [x for u in users for x in u["rtt_ms"]]
    busy = (mach1[0] - mach0[0]) / max(mach1[1] - mach0[1], 1e-9)
    return {
        "sim_rate_hz": opts.sim_rate_hz,
        "users": opts.users,
        "viewers": opts.viewers,
        "duration_s": round(window_s, 3),
        "patch_rate_hz_min": round(rates[0], 3) if rates else None,
        "patch_rate_hz_p1": round(percentile(rates, 1), 3) if rates else None,
        "tick_ms_p50": round(percentile(costs, 50) if costs else float(st1["tick_ms_p50"]), 3),
        "tick_ms_p99": round(percentile(costs, 99) if costs else float(st1["tick_ms_p99"]), 3),
        "overruns_fraction": round(d_over / max(d_ticks, 1), 5),
        "rss_mb_start": round(rss0, 2),
        "rss_mb_end": round(rss1, 2),
        "errors": errors,
        # details
        "vertices": 10 * 4**opts.subdivisions + 2,
        "workers": n_workers,
        "warmup_s": opts.warmup_s,
        "patch_rate_hz_max": round(rates[-1], 3) if rates else None,
        "patch_rate_fraction_min": round(rates[0] / opts.sim_rate_hz, 5) if rates else None,
        "patch_gap_ms_max": round(max((u["gap_ms_max"] for u in users), default=0.0), 1),
        "ticks": d_ticks,
        "overruns": d_over,
        "tick_ms_max": round(max(costs), 3) if costs else None,
        "ticks_seen_by_viewers": len(costs),
        "rtt_ms_p50": round(percentile(rtts, 50), 3) if rtts else None,
        "rtt_ms_p99": round(percentile(rtts, 99), 3) if rtts else None,
        "rss_mb_samples": samples,
        "server_cpu_cores": round((cpu1 - cpu0) / window_s, 3),
        # the event loop was ready but another process had the CPU (a busy machine)
        "server_cpu_wait_fraction": _round_or_none((wait1 - wait0) / window_s, 3),
        "clients_cpu_cores": round(sum(r["cpu_s"] for r in results) / window_s, 3),
        "machine_cpu_busy_fraction": round(busy, 3),
        "machine_cores": os.cpu_count(),
        "machine_loadavg_1min": [round(load0, 2), round(load1, 2)],
        "viewer_kb_per_s": round(
            sum(v["bytes"] for v in viewers) / max(len(viewers), 1) / window_s / 1e3, 2
        ),
        "force_clamps": int(st1.get("force_clamps", 0)) - int(st0.get("force_clamps", 0)),
        "error_codes": codes,
        "server_warnings": len(server_warnings),
        "server_warnings_first": server_warnings[:5],
        "disconnects": disconnects,
        "never_joined": never_joined,
        "per_user_patch_rate_hz": {u["name"]: round(u["patches"] / window_s, 3) for u in users},
    }


def _round_or_none(x: float, digits: int) -> float | None:
    return None if math.isnan(x) else round(x, digits)


def _get(q: Any, timeout_s: float, server: ServerProcess) -> tuple[str, int, Any]:
    """The next worker report, or RuntimeError after ``timeout_s`` or when the server died."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            item: tuple[str, int, Any] = q.get(timeout=1.0)
            return item
        except queue.Empty:
            if server.proc.poll() is not None:
                raise RuntimeError(f"the server exited:\n{server.log_tail()}") from None
            if time.monotonic() > deadline:
                raise RuntimeError("a client worker did not report in time") from None
