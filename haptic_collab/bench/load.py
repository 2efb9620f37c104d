"""``haptic bench load``: real users and viewers against a real server process, for minutes.

The server runs in its own process (``python -m haptic_collab.cli server --port 0``), exactly as deployed
on loopback; the port is read from its ``viewer: http://...`` line. N users and M viewers are real
websocket clients speaking the whole protocol (docs/protocol.md), spread over a few worker
processes (``multiprocessing``, spawn), each with its own loopback source address (127.0.0.2, .3,
... on Linux, so that the server's per-address budgets see a few hosts rather than one):

- a **user** says ``hello`` (role user, a proportional local model), rests its probe 2 mm inside
  the object near the welcome's top or side point (an offset along the surface per user) or
  presses gently (2-5 mm, 0.25 Hz), and sends a ``state`` twice per simulation tick with the force
  ``K_h * e`` its local model renders against its last patch (``K_h = 0.5 K_o_eff``), as a servo
  loop reports it, plus a ``ping`` every 0.5 s. It sleeps between sends (asyncio): 32 spinning
  1 kHz servo loops do not fit on two cores next to the server, and the server only ever sees the
  latest state of each simulation period anyway.
- a **viewer** says ``hello`` (role viewer) and reads every frame (surface stream and ``room``),
  as a browser tab does.

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

import asyncio
import contextlib
import json
import math
import multiprocessing as mp
import os
import queue
import re
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from haptic_collab.server_process import ServerProcess

#: The keys every ``haptic bench load --json`` result has (the issue's contract).
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
#: States a user sends per simulation tick (docs/protocol.md: "about twice per simulation tick").
STATES_PER_TICK = 2.0
#: Interval between a user's pings [s] (as ``haptic client``).
PING_INTERVAL_S = 0.5
#: Resting depth of a probe inside the rest surface at its anchor [m].
REST_DEPTH_M = 0.002
#: Extra depth of a pressing user's probe at the bottom of its press [m], and the press rate [Hz].
PRESS_DEPTH_M = 0.003
PRESS_RATE_HZ = 0.25
#: Largest force a scripted user reports [N] (a desktop device's range).
MAX_FORCE_N = 5.0
#: Wait for a client's ``welcome`` and for the server's port [s].
JOIN_TIMEOUT_S = 20.0
_ROOM_HEAD = re.compile(r'"tick":(\d+),.*?"tick_ms":([-+0-9.eE]+),.*?"overruns":(\d+)')


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


@dataclass(frozen=True)
class _ClientSpec:
    """One client a worker runs: role, name and, for users, where and how it touches."""

    role: str
    name: str
    anchor: str = "top"  # "top" or "side" point of the welcome's object
    slot: int = 0  # position around the anchor (0: on it)
    press: bool = False  # pressing gently (else resting)


def _client_specs(users: int, viewers: int) -> list[_ClientSpec]:
    specs = []
    for i in range(users):
        specs.append(
            _ClientSpec(
                "user",
                f"load-u{i:02d}",
                anchor="top" if i % 2 == 0 else "side",
                slot=i // 2,
                press=(i // 2) % 2 == 1,
            )
        )
    specs += [_ClientSpec("viewer", f"load-v{i:02d}") for i in range(viewers)]
    return specs


# ----------------------------------------------------------------------------- client side
@dataclass
class _UserStats:
    name: str
    joined: bool = False
    patches: int = 0  # patches received inside the window
    gap_ms_max: float = 0.0  # longest wait between two patches inside the window [ms]
    errors: int = 0  # error frames received
    disconnects: int = 0  # connections lost or never made
    codes: dict[str, int] = field(default_factory=dict)
    rtt_ms: list[float] = field(default_factory=list)


@dataclass
class _ViewerStats:
    name: str
    joined: bool = False
    frames: int = 0
    bytes: int = 0
    errors: int = 0
    disconnects: int = 0
    codes: dict[str, int] = field(default_factory=dict)


class _Window:
    """The measurement window [t0, t1) on ``time.monotonic`` (the same clock in every process)."""

    def __init__(self) -> None:
        self.t0 = math.inf
        self.t1 = math.inf

    def inside(self, t: float) -> bool:
        return self.t0 <= t < self.t1


def _sub(a: list[float], b: list[float]) -> list[float]:
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def _dot(a: list[float], b: list[float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _unit(a: list[float]) -> list[float]:
    n = math.sqrt(_dot(a, a)) or 1.0
    return [a[0] / n, a[1] / n, a[2] / n]


def _tangents(n: list[float]) -> tuple[list[float], list[float]]:
    """Two unit vectors orthogonal to the unit vector ``n`` and to each other."""
    helper = [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]
    t1 = _unit(_sub(helper, [c * _dot(helper, n) for c in n]))
    t2 = [n[1] * t1[2] - n[2] * t1[1], n[2] * t1[0] - n[0] * t1[2], n[0] * t1[1] - n[1] * t1[0]]
    return t1, t2


def _penetration(patch: dict[str, Any], probe: list[float]) -> tuple[float, list[float]]:
    """Penetration [m] of ``probe`` into the patch's primitive and the outward normal there."""
    prim = patch["primitive"]
    if prim["kind"] == "sphere":
        d = _sub(probe, prim["center"])
        dist = math.sqrt(_dot(d, d))
        return float(prim["radius"]) - dist, _unit(d)
    n = [float(c) for c in prim["normal"]]
    return _dot(_sub(prim["point"], probe), n), n


def _record_error(stats: _UserStats | _ViewerStats, msg: dict[str, Any]) -> None:
    stats.errors += 1
    code = str(msg.get("code", "?"))
    stats.codes[code] = stats.codes.get(code, 0) + 1


async def _join(
    ws: Any, hello: dict[str, Any], stats: _UserStats | _ViewerStats
) -> dict[str, Any] | None:
    """Send ``hello``; the server's welcome, or None when it answered otherwise (an error counted).

    Raises
    ------
    TimeoutError
        No answer within :data:`JOIN_TIMEOUT_S`.
    """
    await ws.send(json.dumps(hello))
    welcome: dict[str, Any] = json.loads(await asyncio.wait_for(ws.recv(), JOIN_TIMEOUT_S))
    if welcome.get("type") != "welcome":
        if welcome.get("type") == "error":
            _record_error(stats, welcome)
        return None
    stats.joined = True
    return welcome


async def _leave(ws: Any, receiver: asyncio.Task[None], stop: asyncio.Event) -> None:
    """End a session whose ``receiver`` is done or ``stop`` is set.

    Stopped: say bye and give the receiver 3 s to read the server's close. Otherwise the
    connection ended by itself: re-raise how (the receiver's exception).
    """
    if stop.is_set():
        with contextlib.suppress(Exception):
            await ws.send('{"type":"bye"}')
        with contextlib.suppress(Exception):
            await asyncio.wait_for(asyncio.shield(receiver), 3.0)
    else:
        receiver.result()  # re-raise how the connection ended


async def _cancel(task: asyncio.Task[None]) -> None:
    """Cancel ``task`` and wait for it, whatever it raises."""
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await task


async def _user_session(
    ws: Any, spec: _ClientSpec, stats: _UserStats, window: _Window, stop: asyncio.Event
) -> None:
    """One connection of a user: hello, welcome, then states, pings and patches until ``stop``."""
    hello = {
        "type": "hello",
        "protocol": 1,
        "role": "user",
        "name": spec.name,
        "device": {"profile": "bench-load", "max_force_n": 7.9, "max_stiffness_n_per_m": 1000.0},
        "servo_rate_hz": 1000.0,
        "local_model": "p",
    }
    welcome = await _join(ws, hello, stats)
    if welcome is None:
        return
    obj = welcome["object"]
    sim_rate = float(welcome["sim_rate_hz"])
    anchor = [float(c) for c in obj[f"{spec.anchor}_m"]]
    normal = _unit([float(c) for c in obj[f"{spec.anchor}_normal"]])
    t1, t2 = _tangents(normal)
    # slot 0 on the anchor, then rings of 8 at 5 % of the radius apart, along the surface
    ring, k = (0, 0) if spec.slot == 0 else (1 + (spec.slot - 1) // 8, (spec.slot - 1) % 8)
    r_off = 0.05 * float(obj["radius_m"]) * ring
    phi = 2.0 * math.pi * k / 8.0 + 0.3 * ring
    base = [anchor[i] + r_off * (math.cos(phi) * t1[i] + math.sin(phi) * t2[i]) for i in range(3)]
    loop = asyncio.get_running_loop()
    patch: dict[str, Any] | None = None
    last_patch_t: float | None = None
    pings: dict[int, float] = {}

    async def receive() -> None:
        nonlocal patch, last_patch_t
        async for frame in ws:
            now = time.monotonic()
            if isinstance(frame, bytes):
                continue
            msg = json.loads(frame)
            kind = msg.get("type")
            if kind == "patch":
                patch = msg
                if window.inside(now):
                    stats.patches += 1
                    if last_patch_t is not None and last_patch_t >= window.t0:
                        stats.gap_ms_max = max(stats.gap_ms_max, (now - last_patch_t) * 1e3)
                last_patch_t = now
            elif kind == "pong":
                sent = pings.pop(int(msg.get("id", -1)), None)
                if sent is not None:
                    stats.rtt_ms.append((now - sent) * 1e3)
            elif kind == "error":
                _record_error(stats, msg)

    receiver = asyncio.create_task(receive())
    period = 1.0 / (STATES_PER_TICK * sim_rate)
    t_start = loop.time()
    t_next = t_start
    next_ping = t_start
    seq = ping_id = 0
    phase = 0.37 * spec.slot  # pressing users are out of step with each other
    try:
        while not stop.is_set() and not receiver.done():
            now = loop.time()
            depth = REST_DEPTH_M
            if spec.press:
                depth += (
                    PRESS_DEPTH_M
                    * 0.5
                    * (1.0 - math.cos(2 * math.pi * PRESS_RATE_HZ * (now - t_start) + phase))
                )
            probe = [base[i] - normal[i] * depth for i in range(3)]
            e, n, k_h = 0.0, normal, 0.0
            if patch is not None:
                e, n = _penetration(patch, probe)
                k_h = 0.5 * float(patch["k_o_eff"])
            f = min(k_h * max(e, 0.0), MAX_FORCE_N)
            seq += 1
            rtt = stats.rtt_ms[-1] if stats.rtt_ms else None
            state: dict[str, Any] = {
                "type": "state",
                "seq": seq,
                "probe_m": probe,
                "force_n": [f * c for c in n],
                "penetration_m": e,
                "in_contact": e > 0.0,
                "k_h": k_h,
                "i_gain": 0.0,
                "servo_rate_hz": 1000.0,
                "period_us_p99": 1000.0,
                "patch_tick": int(patch["tick"]) if patch is not None else -1,
            }
            if rtt is not None:
                state["rtt_ms"] = rtt
            await ws.send(json.dumps(state))
            if now >= next_ping:
                ping_id += 1
                pings[ping_id] = time.monotonic()
                await ws.send(json.dumps({"type": "ping", "id": ping_id, "t_client_s": now}))
                next_ping = now + PING_INTERVAL_S
            t_next += period
            delay = t_next - loop.time()
            if delay < -period:  # far behind (a stalled process): skip, never send in a burst
                t_next = loop.time() + period
                delay = period
            await asyncio.sleep(max(delay, 0.0))
        await _leave(ws, receiver, stop)
    finally:
        await _cancel(receiver)


async def _viewer_session(
    ws: Any,
    spec: _ClientSpec,
    stats: _ViewerStats,
    window: _Window,
    stop: asyncio.Event,
    ticks: dict[int, float],
) -> None:
    """One connection of a viewer: hello, then read every frame until ``stop``."""
    hello = {"type": "hello", "protocol": 1, "role": "viewer", "name": spec.name}
    if await _join(ws, hello, stats) is None:
        return

    async def receive() -> None:
        async for frame in ws:
            now = time.monotonic()
            inside = window.inside(now)
            if inside:
                stats.frames += 1
                stats.bytes += len(frame)
            if isinstance(frame, bytes):
                continue
            if frame.startswith('{"type":"room"'):
                m = _ROOM_HEAD.search(frame, 0, 400)
                if m is None:
                    msg = json.loads(frame)
                    tick, cost = int(msg["tick"]), float(msg["tick_ms"])
                else:
                    tick, cost = int(m.group(1)), float(m.group(2))
                if inside:
                    ticks[tick] = cost
                continue
            msg = json.loads(frame)
            if msg.get("type") == "error":
                _record_error(stats, msg)

    receiver = asyncio.create_task(receive())
    stopper = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait({receiver, stopper}, return_when=asyncio.FIRST_COMPLETED)
        await _leave(ws, receiver, stop)
    finally:
        stopper.cancel()
        await _cancel(receiver)


async def _run_client(
    spec: _ClientSpec,
    url: str,
    local_addr: tuple[str, int] | None,
    stats: _UserStats | _ViewerStats,
    window: _Window,
    stop: asyncio.Event,
    ticks: dict[int, float],
) -> None:
    """Keep one client connected until ``stop``; every lost or refused connection is counted."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidHandshake

    while not stop.is_set():
        try:
            async with connect(
                url, local_addr=local_addr, open_timeout=JOIN_TIMEOUT_S, max_size=64 * 1024 * 1024
            ) as ws:
                if isinstance(stats, _UserStats):
                    await _user_session(ws, spec, stats, window, stop)
                else:
                    await _viewer_session(ws, spec, stats, window, stop, ticks)
        except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed, ValueError):
            pass
        if stop.is_set():
            return
        stats.disconnects += 1
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), 1.0)


async def _worker_async(
    wid: int, port: int, specs: list[_ClientSpec], source: str | None, to_coord: Any, inbox: Any
) -> None:
    url = f"ws://127.0.0.1:{port}/ws"
    local_addr = (source, 0) if source else None
    window = _Window()
    stop = asyncio.Event()
    ticks: dict[int, float] = {}
    stats: list[_UserStats | _ViewerStats] = [
        _UserStats(s.name) if s.role == "user" else _ViewerStats(s.name) for s in specs
    ]
    tasks = []
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 2 * JOIN_TIMEOUT_S
    for spec, st in zip(specs, stats, strict=True):
        # one at a time: a join never waits behind this worker's other joins (pending caps)
        tasks.append(
            asyncio.create_task(_run_client(spec, url, local_addr, st, window, stop, ticks))
        )
        while not st.joined and loop.time() < deadline and not tasks[-1].done():
            await asyncio.sleep(0.02)
    to_coord.put(("ready", wid, sum(st.joined for st in stats)))
    t0, t1 = await loop.run_in_executor(None, inbox.get)
    window.t0, window.t1 = t0, t1
    while time.monotonic() < t0:
        await asyncio.sleep(min(0.1, max(0.0, t0 - time.monotonic())))
    cpu0 = sum(os.times()[:2])
    await asyncio.sleep(max(0.0, t1 - time.monotonic()))
    cpu1 = sum(os.times()[:2])
    await asyncio.sleep(0.2)  # the last patches of the window are in flight
    stop.set()
    await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 15.0)
    to_coord.put(
        (
            "result",
            wid,
            {
                "users": [asdict(s) for s in stats if isinstance(s, _UserStats)],
                "viewers": [asdict(s) for s in stats if isinstance(s, _ViewerStats)],
                "ticks": ticks,
                "cpu_s": cpu1 - cpu0,
            },
        )
    )


def _worker_main(
    wid: int, port: int, specs: list[_ClientSpec], source: str | None, to_coord: Any, inbox: Any
) -> None:
    """Entry point of a client worker process (spawned).

    The workers stand in for the users' own machines: they run at a lower priority (nice +5) so
    that on a shared machine the load generators do not take the server's core.
    """
    with contextlib.suppress(OSError, AttributeError):
        os.nice(5)
    try:
        asyncio.run(_worker_async(wid, port, specs, source, to_coord, inbox))
    except BaseException as exc:  # report, so that the coordinator does not wait in vain
        to_coord.put(("failed", wid, f"{type(exc).__name__}: {exc}"))
        raise


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
    specs = _client_specs(opts.users, opts.viewers)
    n_workers = max(1, min(opts.workers, len(specs)))
    per_worker: list[list[_ClientSpec]] = [specs[i::n_workers] for i in range(n_workers)]
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
                target=_worker_main,
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
