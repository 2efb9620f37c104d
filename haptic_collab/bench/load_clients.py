"""The clients of ``haptic bench load``: scripted websocket users and viewers in worker processes.

The coordinator (:mod:`haptic_collab.bench.load`) starts the server and spawns the workers; each
worker (:func:`worker_main`, run in a spawned process) keeps its share of the clients connected
over real websockets, speaking the whole protocol (docs/protocol.md), and reports what they
measured inside the window the coordinator sends it:

- a **user** says ``hello`` (role user, a proportional local model), rests its probe 2 mm inside
  the object near the welcome's top or side point (an offset along the surface per user) or
  presses gently (2-5 mm, 0.25 Hz), and sends a ``state`` twice per simulation tick with the force
  ``K_h * e`` its local model renders against its last patch (``K_h = 0.5 K_o_eff``), as a servo
  loop reports it, plus a ``ping`` every 0.5 s. It sleeps between sends (asyncio): 32 spinning
  1 kHz servo loops do not fit on two cores next to the server, and the server only ever sees the
  latest state of each simulation period anyway.
- a **viewer** says ``hello`` (role viewer) and reads every frame (surface stream and ``room``),
  as a browser tab does; it records the ``tick_ms`` of every ``room`` frame in the window.

Like the coordinator, this is benchmark code: it reads clocks and opens sockets. Nothing here is
imported by the server.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import re
import time
from dataclasses import asdict, dataclass, field
from typing import Any

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


@dataclass(frozen=True)
class ClientSpec:
    """One client a worker runs: role, name and, for users, where and how it touches."""

    role: str
    name: str
    anchor: str = "top"  # "top" or "side" point of the welcome's object
    slot: int = 0  # position around the anchor (0: on it)
    press: bool = False  # pressing gently (else resting)


def client_specs(users: int, viewers: int) -> list[ClientSpec]:
    """The clients of a run: ``users`` users, then ``viewers`` viewers, named in order.

    User ``i`` touches the top point of the object (even ``i``) or its side point (odd ``i``),
    at ring position ``i // 2`` around it, resting or, every other pair, pressing gently.

    Parameters
    ----------
    users, viewers : int
        How many of each, >= 0.

    Returns
    -------
    list of ClientSpec
        ``users + viewers`` specs (names ``load-u00``, ... and ``load-v00``, ...).
    """
    specs = []
    for i in range(users):
        specs.append(
            ClientSpec(
                "user",
                f"load-u{i:02d}",
                anchor="top" if i % 2 == 0 else "side",
                slot=i // 2,
                press=(i // 2) % 2 == 1,
            )
        )
    specs += [ClientSpec("viewer", f"load-v{i:02d}") for i in range(viewers)]
    return specs


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


def user_hello(spec: ClientSpec) -> dict[str, Any]:
    """The ``hello`` of a scripted user: a 1 kHz desktop device with a proportional local model."""
    return {
        "type": "hello",
        "protocol": 1,
        "role": "user",
        "name": spec.name,
        "device": {"profile": "bench-load", "max_force_n": 7.9, "max_stiffness_n_per_m": 1000.0},
        "servo_rate_hz": 1000.0,
        "local_model": "p",
    }


def user_spot(spec: ClientSpec, obj: dict[str, Any]) -> tuple[list[float], list[float]]:
    """Where a scripted user rests [m] and the outward normal there, from the welcome's
    ``object``: slot 0 on its anchor, then rings of 8 at 5 % of the radius apart, along the
    surface."""
    anchor = [float(c) for c in obj[f"{spec.anchor}_m"]]
    normal = _unit([float(c) for c in obj[f"{spec.anchor}_normal"]])
    t1, t2 = _tangents(normal)
    ring, k = (0, 0) if spec.slot == 0 else (1 + (spec.slot - 1) // 8, (spec.slot - 1) % 8)
    r_off = 0.05 * float(obj["radius_m"]) * ring
    phi = 2.0 * math.pi * k / 8.0 + 0.3 * ring
    base = [anchor[i] + r_off * (math.cos(phi) * t1[i] + math.sin(phi) * t2[i]) for i in range(3)]
    return base, normal


def user_state(
    spec: ClientSpec,
    spot: tuple[list[float], list[float]],
    elapsed_s: float,
    patch: dict[str, Any] | None,
    seq: int,
    rtt_ms: float | None,
) -> dict[str, Any]:
    """A scripted user's ``state`` ``elapsed_s`` [s] after it started: its probe 2 mm in at its
    ``spot`` (pressing 3 mm deeper at 0.25 Hz for a pressing user), the force ``K_h e`` of a
    proportional local model with ``K_h = 0.5 K_o_eff`` against its last ``patch``."""
    base, normal = spot
    depth = REST_DEPTH_M
    if spec.press:  # pressing users are out of step with each other
        phase = 0.37 * spec.slot
        depth += (
            PRESS_DEPTH_M * 0.5 * (1.0 - math.cos(2 * math.pi * PRESS_RATE_HZ * elapsed_s + phase))
        )
    probe = [base[i] - normal[i] * depth for i in range(3)]
    e, n, k_h = 0.0, normal, 0.0
    if patch is not None:
        e, n = _penetration(patch, probe)
        k_h = 0.5 * float(patch["k_o_eff"])
    f = min(k_h * max(e, 0.0), MAX_FORCE_N)
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
    if rtt_ms is not None:
        state["rtt_ms"] = rtt_ms
    return state


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
    ws: Any, spec: ClientSpec, stats: _UserStats, window: _Window, stop: asyncio.Event
) -> None:
    """One connection of a user: hello, welcome, then states, pings and patches until ``stop``."""
    welcome = await _join(ws, user_hello(spec), stats)
    if welcome is None:
        return
    sim_rate = float(welcome["sim_rate_hz"])
    spot = user_spot(spec, welcome["object"])
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
    try:
        while not stop.is_set() and not receiver.done():
            now = loop.time()
            seq += 1
            rtt = stats.rtt_ms[-1] if stats.rtt_ms else None
            state = user_state(spec, spot, now - t_start, patch, seq, rtt)
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
    spec: ClientSpec,
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
    spec: ClientSpec,
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
    wid: int, port: int, specs: list[ClientSpec], source: str | None, to_coord: Any, inbox: Any
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


def worker_main(
    wid: int, port: int, specs: list[ClientSpec], source: str | None, to_coord: Any, inbox: Any
) -> None:
    """Entry point of a client worker process (spawned).

    The workers stand in for the users' own machines: they run at a lower priority (nice +5) so
    that on a shared machine the load generators do not take the server's core.

    Parameters
    ----------
    wid : int
        The worker's number (in its reports).
    port : int
        The server's port on 127.0.0.1.
    specs : list of ClientSpec
        The clients this worker runs.
    source : str or None
        Loopback source address of its connections (None: the default).
    to_coord, inbox : multiprocessing queues
        Reports to the coordinator (``("ready", wid, joined)``, ``("result", wid, dict)``,
        ``("failed", wid, message)``); the window ``(t0, t1)`` [s, ``time.monotonic``] from it.

    Raises
    ------
    BaseException
        Whatever ended the worker, after reporting it as ``failed``.
    """
    with contextlib.suppress(OSError, AttributeError):
        os.nice(5)
    try:
        asyncio.run(_worker_async(wid, port, specs, source, to_coord, inbox))
    except BaseException as exc:  # report, so that the coordinator does not wait in vain
        to_coord.put(("failed", wid, f"{type(exc).__name__}: {exc}"))
        raise
