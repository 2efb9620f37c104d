"""``python -m haptic_collab.bench.rooms``: many rooms, in one process or a process each, side by side.

Runs the same server twice in each of ``repeats`` runs, the two modes alternating so that the
shared machine's load falls on both: all rooms in one process, then each room in a process of
its own (``haptic server --room-processes``). The default room is a FEM solid (``--object fem``,
the liver preset) and ``balloon_rooms`` balloon rooms (``[rooms.bN]``) are beside it (by default
1 + 7: eight rooms). Each room has ``users`` users run as ``haptic bench load`` runs them
(:mod:`haptic_collab.bench.load_clients`: a 1 kHz device's ``hello``, resting 2 mm in or pressing
gently, a ``state`` twice per simulation tick with the force of a proportional local model
against its last patch, a ``ping`` every 0.5 s), spread over ``workers`` worker processes, each
with a loopback source address of its own (127.0.0.2, .3, ...) and niced +5, as the users' own
machines. A user whose connection closes joins again after :data:`REJOIN_DELAY_S` with the
resume token of its last welcome, as ``haptic client`` does.

After every user joined and a warm-up, a window of ``duration_s`` measures per room: each
user's patch rate [Hz] and its share of the simulation rate (the slowest user's rate per room
and run is in the summary, ``slowest_user_patch_rate_hz``, and printed at the end), the tick cost p50 / p99 [ms]
(``/status``: the room's last 512 ticks at the window's end), the tick lateness p99 [ms]
(``haptic_room_tick_lateness_seconds`` of ``/metrics``, the window's difference, interpolated
within its bucket: buckets 0.5, 1, 2, 5, 10, 20, 50 ms..., so a p99 is exact only to its bucket)
and the overruns in the window; the machine's CPU use over the window (``/proc/stat``) and load
average say how busy the shared machine was. With room processes it then kills one balloon room's
process (``kill -9``) and measures the other rooms' patch rates over the next ``kill_window_s``,
the time from the kill until a new user of that room is welcomed (joinable again) and gets its
first patch, and its own users' way back (their first patch after the kill, and whether their resume tokens gave
them their user ids back). Memory: resident (RSS) and proportional (PSS: pages shared with the
fork server or another process split between them) set of the server and of each room's process.

Then, per object (balloon, FEM) and mode, a server with that one room is started
``repeats`` times: how long until it listens with its room ticking (``haptic server`` prints
its address only then) and its memory, and with a process per room how long the room's process
took to start (``/status``'s ``process.start_s``).

``--compare priority`` runs, instead of the two modes above, the same server in one process
with its simulation thread at the ordinary policy (``tick_priority`` off) and asking for a
real-time one (:mod:`server.priority`), alternating; ``--burners N`` runs N CPU-bound processes
beside it for the whole run (a busy machine: docs/fem.md, "Under load"), and each run records
the server's scheduling policy as the kernel reports it (``tick_policy``).

A benchmark driver (clocks, processes, sockets); nothing here is imported by the server. The
machine is shared: report medians and ratios of runs side by side, never thresholds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import queue
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from haptic_collab.bench.load_clients import (
    JOIN_TIMEOUT_S,
    PING_INTERVAL_S,
    STATES_PER_TICK,
    ClientSpec,
    client_specs,
    user_hello,
    user_spot,
    user_state,
)
from haptic_collab.server_process import ServerProcess

#: How long [s] a user whose connection closed waits before it joins again.
REJOIN_DELAY_S = 0.25
#: How long [s] the coordinator waits for every user to join.
READY_TIMEOUT_S = 120.0
MODES = (("one_process", ()), ("room_processes", ("--room-processes",)))
#: ``--compare priority``: the server's simulation thread at the ordinary policy, then asking
#: for a real-time one (``$HAPTIC_TICK_PRIORITY``, :mod:`server.priority`), all in one process.
PRIORITY_MODES = (("tick_priority_off", ()), ("tick_priority_realtime", ()))
#: The server's ``$HAPTIC_TICK_PRIORITY`` per mode (a mode not listed keeps the environment's).
MODE_TICK_PRIORITY = {"tick_priority_off": "off", "tick_priority_realtime": "realtime"}
#: What each CPU-bound process beside the server runs (``--burners``): one core's worth of load,
#: until its parent (this bench) is gone, also when the bench is killed.
BURNER = "import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n    pass"


@dataclass(frozen=True)
class _Spec:
    room: str
    client: ClientSpec


def _path(room: str) -> str:
    return "/ws" if room == "default" else f"/rooms/{room}/ws"


# ------------------------------------------------------------------------- the users' workers
async def _user(port: int, spec: _Spec, rec: dict[str, Any], source: str | None) -> None:
    """One user, kept connected (joining again with its resume token) until cancelled."""
    url = f"ws://127.0.0.1:{port}{_path(spec.room)}"
    token: str | None = None
    while True:
        try:
            async with connect(
                url,
                local_addr=(source, 0) if source else None,
                open_timeout=JOIN_TIMEOUT_S,
                max_size=64 * 1024 * 1024,
            ) as ws:
                hello = user_hello(spec.client)
                if token is not None:
                    hello["resume"] = token
                await ws.send(json.dumps(hello))
                welcome = json.loads(await asyncio.wait_for(ws.recv(), JOIN_TIMEOUT_S))
                if welcome.get("type") != "welcome":
                    rec["errors"].append((time.monotonic(), str(welcome.get("code"))))
                    raise ConnectionError("refused")
                now = time.monotonic()
                rec["welcomes"].append((now, welcome["user_id"], bool(welcome.get("resumed"))))
                token = welcome.get("resume_token")
                await _user_session(ws, spec, rec, welcome)
        except (OSError, TimeoutError, InvalidHandshake, ConnectionClosed, ValueError):
            pass
        rec["drops"].append(time.monotonic())
        await asyncio.sleep(REJOIN_DELAY_S)


async def _user_session(ws: Any, spec: _Spec, rec: dict[str, Any], welcome: dict[str, Any]) -> None:
    """States twice per tick and pings every 0.5 s; every patch's arrival time recorded."""
    sim_rate = float(welcome["sim_rate_hz"])
    spot = user_spot(spec.client, welcome["object"])
    patch: dict[str, Any] | None = None
    pings: dict[int, float] = {}
    rtt: list[float] = []

    async def receive() -> None:
        nonlocal patch
        async for frame in ws:
            if isinstance(frame, bytes):
                continue
            msg = json.loads(frame)
            kind = msg.get("type")
            now = time.monotonic()
            if kind == "patch":
                patch = msg
                rec["patches"].append(now)
            elif kind == "pong":
                sent = pings.pop(int(msg.get("id", -1)), None)
                if sent is not None:
                    rtt.append((now - sent) * 1e3)
            elif kind == "error":
                rec["errors"].append((now, str(msg.get("code"))))

    receiver = asyncio.create_task(receive())
    loop = asyncio.get_running_loop()
    period = 1.0 / (STATES_PER_TICK * sim_rate)
    t_start = t_next = next_ping = loop.time()
    seq = ping_id = 0
    try:
        while not receiver.done():
            now = loop.time()
            seq += 1
            state = user_state(
                spec.client, spot, now - t_start, patch, seq, rtt[-1] if rtt else None
            )
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
    finally:
        receiver.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await receiver


async def _worker_async(
    port: int, specs: list[_Spec], source: str | None, to_coord: Any, inbox: Any
) -> None:
    recs = [
        {
            "room": s.room,
            "name": s.client.name,
            "patches": [],
            "errors": [],
            "welcomes": [],
            "drops": [],
        }
        for s in specs
    ]
    tasks = []
    loop = asyncio.get_running_loop()
    deadline = loop.time() + READY_TIMEOUT_S
    for spec, rec in zip(specs, recs, strict=True):
        tasks.append(asyncio.create_task(_user(port, spec, rec, source)))
        while not rec["welcomes"] and loop.time() < deadline:  # one join at a time
            await asyncio.sleep(0.02)
    to_coord.put(("ready", sum(1 for r in recs if r["welcomes"])))
    await loop.run_in_executor(None, inbox.get)  # "stop"
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    to_coord.put(("result", recs))


def _worker_main(
    port: int, specs: list[_Spec], source: str | None, to_coord: Any, inbox: Any
) -> None:
    """Entry point of a users' worker process (spawned; niced +5 as ``haptic bench load``'s)."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(5)
    try:
        asyncio.run(_worker_async(port, specs, source, to_coord, inbox))
    except BaseException as exc:
        to_coord.put(("failed", f"{type(exc).__name__}: {exc}"))
        raise


class _Workers:
    """The users' worker processes of one session."""

    def __init__(self, port: int, rooms: list[str], users: int, workers: int) -> None:
        specs = [_Spec(r, c) for r in rooms for c in client_specs(users, 0)]
        specs = [_Spec(s.room, _renamed(s.client, f"{s.room}-{s.client.name}")) for s in specs]
        ctx = mp.get_context("spawn")
        self.to_coord: Any = ctx.Queue()
        self.inboxes = [ctx.Queue() for _ in range(workers)]
        linux = sys.platform.startswith("linux")
        self.procs = [
            ctx.Process(
                target=_worker_main,
                args=(
                    port,
                    specs[w::workers],
                    f"127.0.0.{2 + w}" if linux else None,
                    self.to_coord,
                    self.inboxes[w],
                ),
                daemon=True,
            )
            for w in range(workers)
        ]
        self.expected = len(specs)
        for p in self.procs:
            p.start()

    def wait_ready(self) -> int:
        joined = 0
        for _ in self.procs:
            kind, *rest = self.to_coord.get(timeout=READY_TIMEOUT_S + 30.0)
            if kind == "failed":
                raise RuntimeError(f"a users' worker failed: {rest[0]}")
            joined += int(rest[0])
        return joined

    def stop(self) -> list[dict[str, Any]]:
        for inbox in self.inboxes:
            inbox.put("stop")
        recs: list[dict[str, Any]] = []
        for _ in self.procs:
            try:
                kind, *rest = self.to_coord.get(timeout=60.0)
            except queue.Empty:
                break
            if kind == "result":
                recs += rest[0]
        for p in self.procs:
            p.join(10.0)
            if p.is_alive():
                p.kill()
        return recs


def _renamed(spec: ClientSpec, name: str) -> ClientSpec:
    return ClientSpec(spec.role, name, spec.anchor, spec.slot, spec.press)


# ------------------------------------------------------------------------- readings
def _get(port: int, path: str) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30) as res:
        return str(res.read().decode())


def _lateness(port: int) -> dict[str, list[tuple[float, float]]]:
    """Each room's cumulative lateness buckets [(upper bound s, count)] from ``/metrics``."""
    out: dict[str, list[tuple[float, float]]] = {}
    for fam in text_string_to_metric_families(_get(port, "/metrics")):
        if fam.name != "haptic_room_tick_lateness_seconds":
            continue
        for s in fam.samples:
            if s.name.endswith("_bucket"):
                out.setdefault(s.labels["room"], []).append((float(s.labels["le"]), s.value))
    return out


def _p99_ms(before: list[tuple[float, float]], after: list[tuple[float, float]]) -> float | None:
    """The 99th percentile [ms] of the observations between two cumulative bucket readings,
    interpolated linearly within its bucket (the +Inf bucket answers its lower bound)."""
    return _quantile_ms(before, after, 0.99)


def _quantile_ms(
    before: list[tuple[float, float]], after: list[tuple[float, float]], q: float
) -> float | None:
    """The ``q`` quantile [ms] of the observations between two cumulative bucket readings
    [(upper bound s, count)], interpolated linearly within its bucket (as :func:`_p99_ms`)."""
    diff = [(le, a - b) for (le, a), (_, b) in zip(after, before, strict=True)]
    total = diff[-1][1]
    if total <= 0:
        return None
    want, low, low_n = q * total, 0.0, 0.0
    for le, n in diff:
        if n >= want:
            if le == float("inf") or n == low_n:
                return 1e3 * low
            return 1e3 * (low + (le - low) * (want - low_n) / (n - low_n))
        low, low_n = le, n
    return None


def _memory_mb(pid: int) -> dict[str, float | None]:
    """Resident (``VmRSS``) and proportional (``Pss``) set of a process [MB] (None: unreadable)."""
    out: dict[str, float | None] = {"rss": None, "pss": None}
    for path, key, field_ in (
        (f"/proc/{pid}/status", "rss", "VmRSS:"),
        (f"/proc/{pid}/smaps_rollup", "pss", "Pss:"),
    ):
        try:
            with open(path, encoding="ascii") as f:
                for line in f:
                    if line.startswith(field_):
                        out[key] = round(int(line.split()[1]) / 1024.0, 1)
                        break
        except (OSError, ValueError):
            pass
    return out


def _cpu_ticks() -> tuple[int, int] | None:
    """The machine's (busy, total) CPU jiffies since boot (``/proc/stat``; None elsewhere)."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return sum(fields) - idle, sum(fields)


def _proc_s(pid: int) -> tuple[float, float] | None:
    """CPU time [s] a process has used (all its threads; ``/proc/PID/stat``) and how long its
    main thread has waited for a CPU while runnable [s] (``/proc/PID/schedstat``); None when
    it cannot be read."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/schedstat", encoding="ascii") as f:
            wait_ns = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    hz = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / hz, wait_ns / 1e9


def _procs_s(pids: dict[str, int]) -> dict[str, tuple[float, float] | None]:
    return {name: _proc_s(pid) for name, pid in pids.items()}


def _cpu_use(
    before: dict[str, tuple[float, float] | None],
    after: dict[str, tuple[float, float] | None],
    seconds: float,
) -> dict[str, dict[str, float]]:
    """Per process: the share of one CPU it used, and of the window its main thread spent
    runnable but waiting for a CPU, between two :func:`_procs_s` readings."""
    out = {}
    for name, b in before.items():
        a = after.get(name)
        if a is not None and b is not None:
            out[name] = {
                "cpu": round((a[0] - b[0]) / seconds, 3),
                "waiting": round((a[1] - b[1]) / seconds, 3),
            }
    return out


def _busy(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    if before is None or after is None or after[1] == before[1]:
        return None
    return round((after[0] - before[0]) / (after[1] - before[1]), 3)


def _rates(
    recs: list[dict[str, Any]], t0: float, t1: float, rooms: list[str]
) -> dict[str, list[float]]:
    """Per room, each user's patch rate [Hz] in [t0, t1)."""
    out: dict[str, list[float]] = {r: [] for r in rooms}
    for rec in recs:
        n = sum(1 for t in rec["patches"] if t0 <= t < t1)
        out[rec["room"]].append(round(n / (t1 - t0), 2))
    return out


async def _rejoin_s(port: int, room: str, since: float) -> tuple[float, float]:
    """Seconds from ``since`` until a new user of ``room`` is welcomed, and until it gets its
    first patch (it tries again, as a client does, while the room is being restarted)."""
    spec = _Spec(room, ClientSpec("user", "probe"))
    rec: dict[str, Any] = {"patches": [], "errors": [], "welcomes": [], "drops": []}
    task = asyncio.create_task(_user(port, spec, rec, None))
    try:
        while not rec["patches"]:
            await asyncio.sleep(0.01)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
    welcomed = [w[0] for w in rec["welcomes"]]
    return float(welcomed[-1] - since), float(rec["patches"][0] - since)


# ------------------------------------------------------------------------- one session
async def _measure(
    port: int,
    rooms: list[str],
    opts: argparse.Namespace,
    kill: bool,
    server_pid: int,
    worker_pids: list[int],
) -> tuple[dict[str, Any], tuple[float, float], tuple[float, float] | None, str | None]:
    """The window's readings (and the kill's), in the coordinator while the workers run."""
    await asyncio.sleep(opts.warmup_s)
    out: dict[str, Any] = {}
    status0 = json.loads(await asyncio.to_thread(_get, port, "/status"))
    pids = {"server": server_pid} | {f"users{i}": p for i, p in enumerate(worker_pids)}
    for r in rooms:
        process = status0["rooms"][r].get("process")
        if process is not None and process.get("pid") is not None:
            pids[r] = int(process["pid"])
    before = await asyncio.to_thread(_lateness, port)
    procs0, cpu0, t0 = _procs_s(pids), _cpu_ticks(), time.monotonic()
    await asyncio.sleep(opts.duration_s)
    t1, cpu1, procs1 = time.monotonic(), _cpu_ticks(), _procs_s(pids)
    after = await asyncio.to_thread(_lateness, port)
    status = json.loads(await asyncio.to_thread(_get, port, "/status"))
    out["machine"] = {"cpu_busy": _busy(cpu0, cpu1), "load_avg": os.getloadavg()}
    out["processes"] = _cpu_use(procs0, procs1, t1 - t0)
    out["rooms"] = {}
    for r in rooms:
        st, st0 = status["rooms"][r], status0["rooms"][r]
        out["rooms"][r] = {
            "tick_ms_p50": round(st["tick_ms_p50"], 2),
            "tick_ms_p99": round(st["tick_ms_p99"], 2),
            "lateness_ms_p50": _quantile_ms(before[r], after[r], 0.5),
            "lateness_ms_p99": _p99_ms(before[r], after[r]),
            "overruns": st["overruns"] - st0["overruns"],
            "ticks": st["tick"] - st0["tick"],
        }
    out["memory_mb"] = {"server": _memory_mb(server_pid)}
    for r in rooms:
        process = status["rooms"][r].get("process")
        if process is not None and process.get("pid") is not None:
            out["memory_mb"][r] = _memory_mb(int(process["pid"]))
            out["rooms"][r]["start_s"] = process.get("start_s")
            # a process found hung (or dead) in the window would show here
            out["rooms"][r]["restarts"] = process.get("restarts")
            out["rooms"][r]["hangs"] = process.get("hangs")
    kill_window = None
    victim = None
    if kill:
        victim = rooms[1]
        pid = int(status["rooms"][victim]["process"]["pid"])
        t_kill = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        rejoin = asyncio.create_task(_rejoin_s(port, victim, t_kill))
        await asyncio.sleep(opts.kill_window_s)
        kill_window = (t_kill, t_kill + opts.kill_window_s)
        welcome_s, patch_s = await asyncio.wait_for(rejoin, 120.0)
        out["kill"] = {"room": victim, "rejoin_s": round(welcome_s, 3)}
        out["kill"]["rejoin_first_patch_s"] = round(patch_s, 3)
        st = json.loads(await asyncio.to_thread(_get, port, "/status"))["rooms"][victim]
        out["kill"]["restart_start_s"] = st["process"]["start_s"]
    return out, (t0, t1), kill_window, victim


def _session(
    port: int, rooms: list[str], opts: argparse.Namespace, kill: bool, server_pid: int
) -> dict[str, Any]:
    workers = _Workers(port, rooms, opts.users, opts.workers)
    recs: list[dict[str, Any]] = []
    try:
        joined = workers.wait_ready()
        out, (t0, t1), kill_window, victim = asyncio.run(
            _measure(port, rooms, opts, kill, server_pid, [int(p.pid or 0) for p in workers.procs])
        )
        out["joined"], out["expected"] = joined, workers.expected
    finally:
        recs = workers.stop()
    rates = _rates(recs, t0, t1, rooms)
    for r in rooms:
        share = [x / opts.sim_rate for x in rates[r]]
        out["rooms"][r]["patch_rate_hz"] = rates[r]
        out["rooms"][r]["slowest_user_patch_rate_hz"] = min(rates[r]) if rates[r] else None
        out["rooms"][r]["patch_share_min"] = round(min(share), 4) if share else None
    out["errors"] = sorted({code for rec in recs for t, code in rec["errors"] if t0 <= t < t1})
    out["drops_in_window"] = sum(1 for rec in recs for t in rec["drops"] if t0 <= t < t1)
    if kill_window is not None and victim is not None:
        k0, k1 = kill_window
        during = _rates(recs, k0, k1, rooms)
        out["kill"]["others_patch_rate_hz"] = {r: during[r] for r in rooms if r != victim}
        back = []
        for rec in recs:
            if rec["room"] != victim:
                continue
            before_ids = [w[1] for w in rec["welcomes"] if w[0] < k0]
            after = [w for w in rec["welcomes"] if w[0] > k0]
            # its first patch from the room's new process: after its welcome there
            first = next((t for t in rec["patches"] if after and t > after[0][0]), None)
            back.append(
                {
                    "welcome_after_kill_s": round(after[0][0] - k0, 3) if after else None,
                    "first_patch_after_kill_s": None if first is None else round(first - k0, 3),
                    "resumed": bool(after) and after[0][2],
                    "same_user_id": bool(after and before_ids) and after[0][1] == before_ids[-1],
                    "errors": sorted({c for t, c in rec["errors"] if t >= k0}),
                }
            )
        out["kill"]["victims"] = back
    return out


# ------------------------------------------------------------------------- starting rooms
def _starts(opts: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """Start time and memory of a server with one room, per object and mode (module docstring)."""
    out: dict[str, Any] = {}
    for obj in ("balloon", "fem"):
        cfg = tmp / f"one-{obj}.toml"
        subdivisions = opts.fem_subdivisions if obj == "fem" else opts.subdivisions
        cfg.write_text(
            f'object = "{obj}"\nsubdivisions = {subdivisions}\n'
            f'volume_cache = "{tmp / "volumes"}"\nsim_rate = {opts.sim_rate:g}\n'
        )
        for mode, extra in MODES:
            runs = []
            for _ in range(opts.repeats):
                t = time.monotonic()
                with ServerProcess("--config", str(cfg), *extra) as server:
                    listen_s = time.monotonic() - t
                    time.sleep(1.0)  # a few ticks: its memory as it runs
                    status = json.loads(_get(server.port, "/status"))
                    run_: dict[str, Any] = {
                        "listen_s": round(listen_s, 3),
                        "server": _memory_mb(server.proc.pid),
                    }
                    process = status["rooms"]["default"].get("process")
                    if process is not None:
                        run_["room_start_s"] = round(process["start_s"], 3)
                        run_["room"] = _memory_mb(int(process["pid"]))
                runs.append(run_)
            out[f"{obj}/{mode}"] = runs
    return out


def _config(path: Path, opts: argparse.Namespace, cache: Path) -> list[str]:
    rooms = [f"b{i + 1}" for i in range(opts.balloon_rooms)]
    lines = [
        'object = "fem"',
        f"subdivisions = {opts.fem_subdivisions}",
        f'volume_cache = "{cache}"',
        f"sim_rate = {opts.sim_rate:g}",
        f"max_rooms = {1 + len(rooms)}",
    ]
    for r in rooms:
        lines += [f"[rooms.{r}]", 'object = "balloon"', f"subdivisions = {opts.subdivisions}"]
    path.write_text("\n".join(lines) + "\n")
    return ["default", *rooms]


def run(opts: argparse.Namespace) -> dict[str, Any]:
    """Both modes side by side, then the single-room starts; the result (module docstring)."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-rooms-"))
    cfg = tmp / "rooms.toml"
    rooms = _config(cfg, opts, tmp / "volumes")
    result: dict[str, Any] = {
        "what": f"1 FEM room + {opts.balloon_rooms} balloon rooms x {opts.users} users, "
        "one process vs a process per room",
        "sim_rate_hz": opts.sim_rate,
        "users_per_room": opts.users,
        "workers": opts.workers,
        "duration_s": opts.duration_s,
        "kill_window_s": opts.kill_window_s,
        "fem_subdivisions": opts.fem_subdivisions,
        "balloon_subdivisions": opts.subdivisions,
        "cpus": os.cpu_count(),
        "load_avg_start": os.getloadavg(),
    }
    modes = PRIORITY_MODES if opts.compare == "priority" else MODES
    result["compare"] = opts.compare
    result["burners"] = opts.burners
    runs: list[dict[str, Any]] = []
    burners = [
        subprocess.Popen([sys.executable, "-c", BURNER]) for _ in range(max(0, opts.burners))
    ]
    try:
        for rep in range(opts.repeats):  # the two modes alternate: the machine's load hits both
            run_: dict[str, Any] = {}
            for mode, extra in modes:
                print(f"[bench rooms] run {rep + 1}: {mode}", file=sys.stderr, flush=True)
                kill = opts.compare == "processes" and bool(extra)
                t = time.monotonic()
                with (
                    _tick_priority(MODE_TICK_PRIORITY.get(mode)),
                    ServerProcess("--config", str(cfg), *extra) as server,
                ):
                    listen_s = time.monotonic() - t
                    run_[mode] = _session(server.port, rooms, opts, kill, server.proc.pid)
                    run_[mode]["listen_s"] = round(listen_s, 3)
                    run_[mode]["server_warnings"] = len(server.warnings())
                    run_[mode]["tick_policy"] = _policy(server.proc.pid)
            runs.append(run_)
    finally:
        for b in burners:
            b.kill()
            b.wait()
    result["runs"] = runs
    if opts.starts:
        print("[bench rooms] one-room starts", file=sys.stderr, flush=True)
        result["starts"] = _starts(opts, tmp)
    result["load_avg_end"] = os.getloadavg()
    result["summary"] = _summary(runs, rooms, opts.sim_rate, result.get("starts"))
    return result


@contextlib.contextmanager
def _tick_priority(value: str | None) -> Any:
    """``$HAPTIC_TICK_PRIORITY`` set to ``value`` (None: untouched) while a server starts."""
    old = os.environ.get("HAPTIC_TICK_PRIORITY")
    if value is not None:
        os.environ["HAPTIC_TICK_PRIORITY"] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("HAPTIC_TICK_PRIORITY", None)
        else:
            os.environ["HAPTIC_TICK_PRIORITY"] = old


def _policy(pid: int) -> dict[str, int] | None:
    """The scheduling policy and nice value of a process's main thread (``/proc/PID/stat``:
    ``policy`` 0 ordinary, 1 SCHED_FIFO, 2 SCHED_RR; ``rt_priority``); None off Linux."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    # fields[0] is field 3 (state): nice is field 19, rt_priority 40, policy 41
    return {"nice": int(fields[16]), "rt_priority": int(fields[37]), "policy": int(fields[38])}


def _slowest(room: dict[str, Any]) -> float | None:
    """The slowest user's patch rate [Hz] of one room in one run (None: no user's rate)."""
    rates = room.get("patch_rate_hz") or []
    return min(rates) if rates else None


def print_slowest(result: dict[str, Any], file: Any = None) -> None:
    """Per mode and room, the slowest user's patch rate [Hz] of each run, as one table (on
    ``file``, default standard error; "-" for a run in which no user of the room had a rate)."""
    file = sys.stderr if file is None else file
    for mode, summary in result.get("summary", {}).items():
        if not isinstance(summary, dict) or "slowest_user_patch_rate_hz" not in summary:
            continue
        print(f"[bench rooms] {mode}: slowest user's patch rate [Hz] per run", file=file)
        for room, rates in summary["slowest_user_patch_rate_hz"].items():
            shown = ", ".join("-" if r is None else f"{r:.2f}" for r in rates)
            print(f"  {room:>10s}  {shown}", file=file)


def _median(xs: list[float]) -> float | None:
    return round(statistics.median(xs), 3) if xs else None


def _cpu_summary(per: list[dict[str, dict[str, float]]], rooms: list[str]) -> dict[str, Any]:
    """Median over runs of the CPU shares (and waiting shares) of the server (the front with
    room processes), the room processes together and the users' workers together."""
    out: dict[str, Any] = {}
    for group, pick in (
        ("server", lambda n: n == "server"),
        ("room_processes", lambda n: n in rooms),
        ("users", lambda n: n.startswith("users")),
    ):
        for key in ("cpu", "waiting"):
            sums = [sum(v[key] for n, v in p.items() if pick(n)) for p in per if p]
            out[f"{group}_{key}"] = _median(sums)
    return out


def _summary(
    runs: list[dict[str, Any]], rooms: list[str], sim_rate: float, starts: dict[str, Any] | None
) -> dict[str, Any]:
    """Medians over every run (and every balloon room, every user), and their ratios."""
    balloon = rooms[1:]
    summary: dict[str, Any] = {}
    names = list(runs[0]) if runs else []
    for mode in names:
        per = [run_[mode]["rooms"] for run_ in runs]

        def med(key: str, names: list[str], per: list[dict[str, Any]] = per) -> float | None:
            return _median([r[n][key] for r in per for n in names if r[n].get(key) is not None])

        shares = [r[n]["patch_share_min"] for r in per for n in rooms]
        summary[mode] = {
            "rooms_at_99pct": [
                sum(1 for n in rooms if (r[n]["patch_share_min"] or 0) >= 0.99) for r in per
            ],
            "patch_share_min": min((s for s in shares if s is not None), default=None),
            "patch_share_min_per_room_median": {
                n: _median([r[n]["patch_share_min"] for r in per if r[n]["patch_share_min"]])
                for n in rooms
            },
            # per room, each run's slowest user's patch rate [Hz] (None: no user had one)
            "slowest_user_patch_rate_hz": {n: [_slowest(r[n]) for r in per] for n in rooms},
            "balloon_tick_ms_p50_median": med("tick_ms_p50", balloon),
            "balloon_tick_ms_p99_median": med("tick_ms_p99", balloon),
            "balloon_lateness_ms_p99_median": med("lateness_ms_p99", balloon),
            "fem_tick_ms_p50_median": med("tick_ms_p50", ["default"]),
            "fem_tick_ms_p99_median": med("tick_ms_p99", ["default"]),
            "fem_lateness_ms_p50_median": med("lateness_ms_p50", ["default"]),
            "fem_lateness_ms_p99_median": med("lateness_ms_p99", ["default"]),
            "fem_overruns_median": med("overruns", ["default"]),
            "fem_patch_share_median": _median(
                [x / sim_rate for r in per for x in r["default"].get("patch_rate_hz", [])]
            ),
            "machine_cpu_busy": [run_[mode]["machine"]["cpu_busy"] for run_ in runs],
            "cpu_median": _cpu_summary([run_[mode].get("processes", {}) for run_ in runs], rooms),
            "errors": sorted({e for run_ in runs for e in run_[mode]["errors"]}),
        }
    if "one_process" in summary and "room_processes" in summary:
        one, many = summary["one_process"], summary["room_processes"]
        if one["balloon_lateness_ms_p99_median"] and many["balloon_lateness_ms_p99_median"]:
            summary["balloon_lateness_p99_ratio_one_over_processes"] = round(
                one["balloon_lateness_ms_p99_median"] / many["balloon_lateness_ms_p99_median"], 2
            )
    if "tick_priority_off" in summary and "tick_priority_realtime" in summary:
        off, rt = summary["tick_priority_off"], summary["tick_priority_realtime"]
        for key in ("fem_lateness_ms_p50_median", "fem_lateness_ms_p99_median"):
            if off[key] and rt[key]:
                summary[f"{key}_ratio_off_over_realtime"] = round(off[key] / rt[key], 2)
    kills = [
        run_["room_processes"]["kill"] for run_ in runs if "kill" in run_.get("room_processes", {})
    ]
    if kills:
        others = [x for k in kills for v in k["others_patch_rate_hz"].values() for x in v]
        summary["kill_others_patch_rate_hz_median"] = _median(others)
        summary["kill_others_patch_share_min"] = round(min(others) / sim_rate, 4)
        summary["kill_rejoin_s"] = [k["rejoin_s"] for k in kills]
        summary["kill_rejoin_first_patch_s"] = [k["rejoin_first_patch_s"] for k in kills]
        victims = [v for k in kills for v in k["victims"]]
        summary["kill_victims_back_s"] = [v["first_patch_after_kill_s"] for v in victims]
        summary["kill_victims_same_user_id"] = sum(v["same_user_id"] for v in victims)
        summary["kill_victims"] = len(victims)
    if starts:
        summary["starts_median"] = {
            key: {
                field_: _median([r[field_] for r in rs if r.get(field_) is not None])
                for field_ in ("listen_s", "room_start_s")
            }
            | {
                f"{who}_{kind}_mb": _median(
                    [r[who][kind] for r in rs if who in r and r[who][kind] is not None]
                )
                for who in ("server", "room")
                for kind in ("rss", "pss")
            }
            for key, rs in starts.items()
        }
    return summary


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The options of this bench (``python -m haptic_collab.bench.rooms --help``)."""
    p = argparse.ArgumentParser(prog="python -m haptic_collab.bench.rooms", description=__doc__)
    p.add_argument("--balloon-rooms", type=int, default=7)
    p.add_argument(
        "--rooms",
        type=int,
        default=None,
        help="rooms in all: the FEM one and ROOMS-1 balloon rooms (>= 2; overrides "
        "--balloon-rooms)",
    )
    p.add_argument("--users", type=int, default=4, help="users per room")
    p.add_argument("--workers", type=int, default=4, help="the users' worker processes")
    p.add_argument("--sim-rate", type=float, default=20.0)
    p.add_argument("--subdivisions", type=int, default=4, help="of the balloon rooms")
    p.add_argument("--fem-subdivisions", type=int, default=3)
    p.add_argument("--warmup-s", type=float, default=5.0)
    p.add_argument("--duration-s", type=float, default=20.0)
    p.add_argument("--kill-window-s", type=float, default=5.0)
    p.add_argument("--repeats", type=int, default=3, help="runs of both modes, alternating")
    p.add_argument(
        "--no-starts", dest="starts", action="store_false", help="skip the one-room starts"
    )
    p.add_argument(
        "--compare",
        choices=["processes", "priority"],
        default="processes",
        help="processes: one process against a process per room (default); priority: the "
        "simulation thread at the ordinary policy against real-time (tick_priority), one process",
    )
    p.add_argument(
        "--burners",
        type=int,
        default=0,
        help="CPU-bound processes ('while True: pass') beside the server for the whole run",
    )
    p.add_argument("--json", default=None, help="write the result here (default: stdout)")
    opts = p.parse_args(argv)
    if opts.rooms is not None:
        if opts.rooms < 2:
            p.error(
                f"--rooms must be at least 2 (the FEM room and a balloon room), got {opts.rooms}"
            )
        opts.balloon_rooms = opts.rooms - 1
    if not opts.duration_s > 0:
        p.error(f"--duration-s must be > 0, got {opts.duration_s}")
    return opts


def main(argv: list[str] | None = None) -> None:
    """Run it and print (and with ``--json FILE`` write) the result."""
    opts = parse(argv)
    result = run(opts)
    print_slowest(result)
    text = json.dumps(result, indent=2)
    if opts.json:
        Path(opts.json).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
