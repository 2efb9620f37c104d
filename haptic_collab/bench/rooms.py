"""``python -m haptic_collab.bench.rooms``: one FEM room beside balloon rooms, one process or many.

Runs the same server twice, side by side in one run: all rooms in one process, then each room in
a process of its own (``haptic server --room-processes``). The default room is a FEM solid
(``--object fem``, the liver preset) and ``balloon_rooms`` balloon rooms (``[rooms.bN]``) beside
it; each room has ``users`` scripted users (a ``state`` every 25 ms, the hand resting 3 mm into
the top of the object, so the FEM room solves its contacts every tick). After a warm-up, a window
of ``duration_s`` measures per room: each user's patch rate [Hz] (patches it received / window)
and the tick lateness p99 [ms] (``haptic_room_tick_lateness_seconds`` of ``/metrics``, the
window's difference, interpolated within its bucket). With room processes it then kills one
balloon room's process (``kill -9``) and measures the other rooms' patch rates over the next
``kill_window_s`` and the time from the kill until a new user of the killed room is welcomed.

Both modes run ``repeats`` times, alternating, so that the shared machine's load falls on both;
the summary gives medians over the runs (and rooms, users) and the ratio of the balloon rooms'
lateness p99, one process over a process per room. The lateness histogram's buckets are 0.5, 1,
2, 5, 10, 20, 50 ms...: a p99 is exact only to its bucket.

A benchmark driver (clocks, processes, sockets); nothing here is imported by the server. The
machine is shared: report medians and ratios of runs side by side, never thresholds.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import statistics
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from haptic_collab.server_process import ServerProcess
from haptic_collab.shared.protocol import PROTOCOL_VERSION

#: The hand's depth into the top of the object [m].
DEPTH_M = 0.003
#: A user's state period [s].
STATE_PERIOD_S = 0.025


@dataclass
class _User:
    room: str
    patches: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    closed: bool = False


def _path(room: str) -> str:
    return "/ws" if room == "default" else f"/rooms/{room}/ws"


async def _user(port: int, room: str, name: str, user: _User, stop: asyncio.Event) -> None:
    """A scripted user: join, then a state every 25 ms with the hand 3 mm into the top."""
    async with connect(f"ws://127.0.0.1:{port}{_path(room)}") as ws:
        hello = {"type": "hello", "protocol": PROTOCOL_VERSION, "role": "user", "name": name}
        await ws.send(json.dumps(hello))
        welcome = None
        while welcome is None:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 120.0))
            if msg["type"] == "welcome":
                welcome = msg
            elif msg["type"] == "error":
                raise RuntimeError(f"{name}: {msg}")
        top = float(welcome["object"]["bounds_max_m"][2])

        async def read() -> None:
            with contextlib.suppress(ConnectionClosed):
                async for frame in ws:
                    if isinstance(frame, str):
                        msg = json.loads(frame)
                        if msg["type"] == "patch":
                            user.patches.append(time.monotonic())
                        elif msg["type"] == "error":
                            user.errors.append(str(msg.get("code")))
            user.closed = True

        reader = asyncio.create_task(read())
        seq = 0
        with contextlib.suppress(ConnectionClosed):
            while not stop.is_set() and not user.closed:
                seq += 1
                state = {
                    "type": "state",
                    "seq": seq,
                    "probe_m": [0.0, 0.0, top - DEPTH_M],
                    "force_n": [0.0, 0.0, 1.0],
                    "penetration_m": DEPTH_M,
                    "in_contact": True,
                    "k_h": 300.0,
                }
                await ws.send(json.dumps(state))
                await asyncio.sleep(STATE_PERIOD_S)
        reader.cancel()


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
    diff = [(le, a - b) for (le, a), (_, b) in zip(after, before, strict=True)]
    total = diff[-1][1]
    if total <= 0:
        return None
    want, low, low_n = 0.99 * total, 0.0, 0.0
    for le, n in diff:
        if n >= want:
            if le == float("inf") or n == low_n:
                return 1e3 * low
            return 1e3 * (low + (le - low) * (want - low_n) / (n - low_n))
        low, low_n = le, n
    return None


async def _window(users: list[_User], seconds: float) -> dict[str, list[float]]:
    """Per room, each user's patch rate [Hz] over the next ``seconds``."""
    t0 = time.monotonic()
    await asyncio.sleep(seconds)
    t1 = time.monotonic()
    rates: dict[str, list[float]] = {}
    for u in users:
        n = sum(1 for t in u.patches if t0 <= t < t1)
        rates.setdefault(u.room, []).append(n / (t1 - t0))
    return rates


async def _rejoin_s(port: int, room: str, since: float) -> float:
    """Seconds from ``since`` until a new user of ``room`` gets its first patch."""
    while True:
        user, stop = _User(room), asyncio.Event()
        task = asyncio.create_task(_user(port, room, "probe", user, stop))
        deadline = time.monotonic() + 5.0
        while not user.patches and not task.done() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        stop.set()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 5.0)
        if user.patches:
            return user.patches[0] - since
        await asyncio.sleep(0.05)


def _rss_mb(pid: int) -> float | None:
    """Resident memory of a process [MB] (``VmRSS``; None when it cannot be read)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except (OSError, ValueError):
        pass
    return None


async def _session(
    port: int, rooms: list[str], opts: argparse.Namespace, kill: bool, server_pid: int
) -> dict:
    users = [_User(r) for r in rooms for _ in range(opts.users)]
    stop = asyncio.Event()
    tasks = [
        asyncio.create_task(_user(port, u.room, f"{u.room}-{i}", u, stop))
        for i, u in enumerate(users)
    ]
    out: dict[str, Any] = {}
    try:
        await asyncio.sleep(opts.warmup_s)
        before = await asyncio.to_thread(_lateness, port)
        rates = await _window(users, opts.duration_s)
        after = await asyncio.to_thread(_lateness, port)
        out["rooms"] = {
            r: {
                "patch_rate_hz": [round(x, 2) for x in rates[r]],
                "lateness_ms_p99": _p99_ms(before[r], after[r]),
            }
            for r in rooms
        }
        status = json.loads(await asyncio.to_thread(_get, port, "/status"))
        out["rss_mb"] = {"server": _rss_mb(server_pid)}
        for r in rooms:
            process = status["rooms"][r].get("process")
            if process is not None and process.get("pid") is not None:
                out["rss_mb"][r] = _rss_mb(int(process["pid"]))
        if kill:
            victim = rooms[1]
            pid = int(status["rooms"][victim]["process"]["pid"])
            t_kill = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            rejoin = asyncio.create_task(_rejoin_s(port, victim, t_kill))
            during = await _window(users, opts.kill_window_s)
            out["kill"] = {
                "room": victim,
                "others_patch_rate_hz": {
                    r: [round(x, 2) for x in during[r]] for r in rooms if r != victim
                },
                "rejoin_s": round(await asyncio.wait_for(rejoin, 60.0), 3),
                "killed_users_errors": sorted(
                    {e for u in users if u.room == victim for e in u.errors}
                ),
            }
    finally:
        stop.set()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
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
    """Both modes side by side; the result (module docstring)."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-rooms-"))
    cfg = tmp / "rooms.toml"
    rooms = _config(cfg, opts, tmp / "volumes")
    result: dict[str, Any] = {
        "what": "1 FEM room + balloon rooms, one process vs a process per room",
        "sim_rate_hz": opts.sim_rate,
        "users_per_room": opts.users,
        "duration_s": opts.duration_s,
        "kill_window_s": opts.kill_window_s,
        "fem_subdivisions": opts.fem_subdivisions,
        "balloon_subdivisions": opts.subdivisions,
        "cpus": os.cpu_count(),
        "load_avg_start": os.getloadavg(),
    }
    runs: list[dict[str, Any]] = []
    for rep in range(opts.repeats):  # the two modes alternate: the machine's load hits both
        run_: dict[str, Any] = {}
        for mode, extra in (("one_process", []), ("room_processes", ["--room-processes"])):
            print(f"[bench rooms] run {rep + 1}: {mode}", file=sys.stderr, flush=True)
            with ServerProcess("--config", str(cfg), *extra) as server:
                run_[mode] = asyncio.run(
                    _session(server.port, rooms, opts, bool(extra), server.proc.pid)
                )
                run_[mode]["server_warnings"] = len(server.warnings())
        runs.append(run_)
    result["load_avg_end"] = os.getloadavg()
    result["runs"] = runs
    result["summary"] = _summary(runs, rooms)
    return result


def _median(xs: list[float]) -> float | None:
    return round(statistics.median(xs), 3) if xs else None


def _summary(runs: list[dict[str, Any]], rooms: list[str]) -> dict[str, Any]:
    """Medians over every run (and every balloon room, every user), and their ratios."""
    balloon = rooms[1:]
    summary: dict[str, Any] = {}
    for mode in ("one_process", "room_processes"):
        per = [run_[mode]["rooms"] for run_ in runs]
        lat = [r[b]["lateness_ms_p99"] for r in per for b in balloon]
        summary[mode] = {
            "balloon_lateness_ms_p99_median": _median([x for x in lat if x is not None]),
            "balloon_patch_rate_hz_median": _median(
                [x for r in per for b in balloon for x in r[b]["patch_rate_hz"]]
            ),
            "balloon_patch_rate_hz_min": min(
                x for r in per for b in balloon for x in r[b]["patch_rate_hz"]
            ),
            "fem_patch_rate_hz_median": _median(
                [x for r in per for x in r["default"]["patch_rate_hz"]]
            ),
            "fem_lateness_ms_p99_median": _median(
                [r["default"]["lateness_ms_p99"] for r in per if r["default"]["lateness_ms_p99"]]
            ),
        }
    one, many = summary["one_process"], summary["room_processes"]
    if one["balloon_lateness_ms_p99_median"] and many["balloon_lateness_ms_p99_median"]:
        summary["balloon_lateness_p99_ratio_one_over_processes"] = round(
            one["balloon_lateness_ms_p99_median"] / many["balloon_lateness_ms_p99_median"], 2
        )
    kills = [run_["room_processes"]["kill"] for run_ in runs if "kill" in run_["room_processes"]]
    if kills:
        others = [x for k in kills for v in k["others_patch_rate_hz"].values() for x in v]
        summary["kill_others_patch_rate_hz_median"] = _median(others)
        summary["kill_others_patch_rate_hz_min"] = min(others)
        summary["kill_rejoin_s"] = [k["rejoin_s"] for k in kills]
        summary["kill_rejoin_s_median"] = _median([k["rejoin_s"] for k in kills])
    return summary


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The options of this bench (``python -m haptic_collab.bench.rooms --help``)."""
    p = argparse.ArgumentParser(prog="python -m haptic_collab.bench.rooms", description=__doc__)
    p.add_argument("--balloon-rooms", type=int, default=3)
    p.add_argument("--users", type=int, default=2, help="scripted users per room")
    p.add_argument("--sim-rate", type=float, default=20.0)
    p.add_argument("--subdivisions", type=int, default=4, help="of the balloon rooms")
    p.add_argument("--fem-subdivisions", type=int, default=3)
    p.add_argument("--warmup-s", type=float, default=5.0)
    p.add_argument("--duration-s", type=float, default=20.0)
    p.add_argument("--kill-window-s", type=float, default=5.0)
    p.add_argument("--repeats", type=int, default=3, help="runs of both modes, alternating")
    p.add_argument("--json", default=None, help="write the result here (default: stdout)")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    """Run it and print (and with ``--json FILE`` write) the result."""
    opts = parse(argv)
    result = run(opts)
    text = json.dumps(result, indent=2)
    if opts.json:
        Path(opts.json).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
