"""End to end over real websockets on loopback.

- Two users feel each other (server and two clients as separate processes, as users run them): A
  presses into the top of the balloon while B rests on its side; B's surface moves outward and the
  force B's local model renders rises by at least 20 %.
- A hostile connection (garbage, NaN, huge forces, oversized frames, a flood) gets clear errors and
  is closed where it must be, while a well-behaved user keeps getting patches every tick (scripted
  websocket peers against an in-process server).
- Link loss in the middle of a press (the server process stops) ramps the client's force to zero,
  and the client rejoins when a server comes back on the same port.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from pathlib import Path

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from haptic_collab.client.servo import ServoConfig
from haptic_collab.demo_report import hold_shake_mm
from haptic_collab.server.app import ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.shared.protocol import ObjectInfo
from tests.support.processes import (
    finish_client,
    good_user,
    server_process,
    start_client,
    wait_until,
)

pytestmark = pytest.mark.slow

SIM_RATE = 20.0
SERVER_ARGS = ("--sim-rate", f"{SIM_RATE:g}")


async def start_server(port: int = 0, subdivisions: int = 4) -> ServerApp:
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=subdivisions))
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", port)
    await app.start()
    return app


def object_info(subdivisions: int = 4) -> ObjectInfo:
    """The object a ``haptic server --subdivisions N`` serves (its welcome's ``object``)."""
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=subdivisions))
    return Room(world, SIM_RATE).object_info


def along(cols, prefix, normal):
    v = np.stack([cols[f"{prefix}_x_m"], cols[f"{prefix}_y_m"], cols[f"{prefix}_z_m"]], axis=1)
    return v @ np.asarray(normal)


def recent_force(csv: Path) -> float:
    """The mean force over the last 100 complete rows of a recording still being written [N]."""
    try:
        text = csv.read_text()
    except FileNotFoundError:
        return 0.0
    lines = text.split("\n")
    if len(lines) < 3:
        return 0.0
    header = lines[0].split(",")
    col = header.index("force_n")
    rows = [r.split(",") for r in lines[1:-1][-100:]]  # the last piece may be half a line
    return float(np.mean([float(r[col]) for r in rows if len(r) == len(header)]))


def test_two_users_feel_each_other_over_websockets(tmp_path):
    """Server and two clients as separate processes, as users run them."""
    info = object_info()
    # A: hand waits 6 s, approaches 1 s, presses 1.5 s to a target ~20 mm in, holds 4 s. B's forces
    # come on once its first gains are checked (interim gains, a few hundred ms after joining on an
    # idle machine, seconds when every design worker starts at once on a busy 2-core one; the
    # first-contact latency has its own test in tests/client/test_first_contact.py).
    with server_process(tmp_path / "server.log", 0, *SERVER_ARGS, "--subdivisions", "4") as server:
        b_proc = start_client(tmp_path, "B", server.url, "--device", "sim:rest", "--duration", "14")
        a_proc = start_client(
            tmp_path, "A", server.url, "--device", "sim:press", "--duration", "14",
            "--trajectory", "delay_s=6,approach_s=1,press_s=1.5,hold_s=4,release_s=1",
        )  # fmt: skip
        a_sum, a = finish_client(a_proc, tmp_path, "A")
        b_sum, b = finish_client(b_proc, tmp_path, "B")
    b["t_s"] = b["t_s"] + (b_sum["clock_origin_s"] - a_sum["clock_origin_s"])  # A's clock
    # both had checked gains (forces on) before A touched
    assert a_sum["first_gains_s"] is not None and b_sum["first_gains_s"] is not None
    hold_end = 6.0 + 1.0 + 1.5 + 4.0
    during_a = (a["t_s"] > hold_end - 1.0) & (a["t_s"] < hold_end)
    during_b = (b["t_s"] > hold_end - 1.0) & (b["t_s"] < hold_end)
    before_b = (b["t_s"] > 4.8) & (b["t_s"] < 5.8)
    # A pushed into the top and the object pushed back: the probe stopped short of the hand's
    # 20 mm target (about 10 mm in with the designed gains, deeper while interim gains render)
    a_depth = info.top_m[2] - np.mean(a["probe_z_m"][during_a])
    assert 0.004 < a_depth < 0.018, a_depth
    assert np.mean(a["force_n"][during_a]) > 1.0
    # the PI integral stays within the Phantom Desktop's continuous force (1.75 N); when A pushes
    # harder the proportional part gives the rest, up to the 7.9 N peak
    assert a["integral_n"].max() <= 1.75 + 1e-9 and a["force_n"].max() > 1.75
    # B's surface moved outward and B's rendered force rose by at least 20 %
    side_n = np.array(b_sum["anchor"]["normal"])  # the side B rests on (by join order)
    # (the object's surface: the rendered proxy less B's own-force compensation offset)
    surface_b = along(b, "proxy", side_n) - b["own_offset_m"]
    proxy_before = np.mean(surface_b[before_b])
    proxy_during = np.mean(surface_b[during_b])
    # (B's hand resists: with own-force compensation B feels the object's own stiffness and its
    # surface moves out 0.2 mm where the paper's softer coupling let it move 0.5 mm)
    assert proxy_during - proxy_before > 0.0001, (proxy_before, proxy_during)
    f_before = np.mean(b["force_n"][before_b])
    f_during = np.mean(b["force_n"][during_b])
    assert f_before > 0.05  # B really rests on the balloon
    assert f_during >= 1.2 * f_before, (f_before, f_during)
    # both held a stable contact: the hands do not shake over the last second of the hold. A
    # slow creep is not a shake (A's integral stops at the device's continuous force, 1.75 N,
    # and the probe then sinks until the proportional part carries the rest; B's surface moves
    # out under it): judge the motion left after a straight-line trend
    # (the 0.5 s after a change of gains, interim -> designed arriving late on a busy machine,
    # are left out: the equilibrium moves, smoothly, there; haptic_collab.demo_report.hold_shake_mm)
    for cols, normal in ((a, info.top_normal), (b, side_n)):
        probe = along(cols, "probe", np.asarray(normal))
        window = (hold_end - 1.0, hold_end)
        shake = hold_shake_mm(cols["t_s"], probe, cols["k_h_n_per_m"], window)
        assert shake < 1.0, shake
        held = (cols["t_s"] > window[0]) & (cols["t_s"] < window[1])
        drift = abs(probe[held][-1] - probe[held][0])
        assert drift < 0.003, f"the hold drifted by {drift * 1e3:.1f} mm in 1 s"
    assert a_sum["patches"] > 100 and b_sum["patches"] > 100


async def _hostile(url: str) -> dict[str, list]:
    """Sends every kind of bad input over several connections; returns what came back."""
    seen: dict[str, list] = {}

    async def session(label: str, frames: list, hello: bool = True) -> None:
        got: list = []
        seen[label] = got
        try:
            async with connect(url, max_size=2**20) as ws:
                if hello:
                    await ws.send(
                        json.dumps({"type": "hello", "protocol": 1, "role": "user", "name": label})
                    )
                    await ws.recv()
                for f in frames:
                    await ws.send(f)
                with contextlib.suppress(TimeoutError):
                    while True:
                        msg = await asyncio.wait_for(ws.recv(), 0.5)
                        if isinstance(msg, str) and '"error"' in msg:
                            got.append(json.loads(msg))
        except ConnectionClosed:
            got.append("closed")

    nan_state = '{"type":"state","seq":1,"probe_m":[0,0,NaN],"force_n":[0,0,1]}'
    big_force = '{"type":"state","seq":2,"probe_m":[0,0,0.09],"force_n":[0,0,1e5]}'
    await session("garbage", ["{oops", '{"type":"warp"}', nan_state, big_force, b"\x00\xff"])
    await session(
        "nohello", ['{"type":"state","seq":1,"probe_m":[0,0,0],"force_n":[0,0,0]}'], hello=False
    )
    await session("oversized", ["x" * 40000])
    flood = [json.dumps({"type": "ping", "id": i, "t_client_s": 0}) for i in range(1500)]
    await session("flood", flood)
    return seen


@pytest.mark.alone  # a patch rate to the tick: beside two FEM convergence tests on 2 cores
# (CI of 3eacebd, 2026-11-28) the in-process server once missed 3 ticks in a row for everyone
async def test_hostile_input_gets_errors_and_the_other_user_keeps_working():
    app = await start_server(subdivisions=3)
    url = f"ws://127.0.0.1:{app.port}/ws"
    try:
        good, bad = await asyncio.gather(good_user(url, 4.0), _hostile(url))
    finally:
        await app.stop()
    codes = {k: [m["code"] for m in v if isinstance(m, dict)] for k, v in bad.items()}
    assert codes["garbage"][:5] == [
        "malformed_json",
        "unknown_type",
        "non_finite",
        "force_limit",
        "binary_not_expected",
    ]
    assert "closed" not in bad["garbage"]  # soft errors keep the connection
    assert codes["nohello"] == ["expected_hello"] and bad["nohello"][-1] == "closed"
    assert codes["oversized"] == ["frame_too_large"] and bad["oversized"][-1] == "closed"
    assert "rate_limited" in codes["flood"] and bad["flood"][-1] == "closed"
    # the good user got a patch on (nearly) every tick throughout
    assert len(good) >= 0.8 * 4.0 * SIM_RATE
    assert max(np.diff(good)) <= 3
    assert np.all(np.isfinite(app.room.world.vertices))


def test_link_loss_ramps_force_to_zero_and_the_client_rejoins(tmp_path):
    """The server process goes away in the middle of a press and comes back on the same port."""
    server = server_process(tmp_path / "server1.log", 0, *SERVER_ARGS, "--subdivisions", "3")
    try:
        proc = start_client(
            # long enough for the link's backoff (up to 5 s) after a slow restart on a busy machine
            tmp_path, "A", server.url, "--device", "sim:press", "--duration", "20",
            "--trajectory", "delay_s=0.5,approach_s=1,press_s=1,hold_s=30",
        )  # fmt: skip
        csv = tmp_path / "A.csv"
        # A is pressing: the recording shows a firm force (read only complete lines)
        assert wait_until(lambda: recent_force(csv) > 0.5, 60.0), "A never pressed"
        time.sleep(1.0)
    finally:
        t_loss = time.perf_counter()
        server.stop()  # the server goes away in the middle of the press
    t_gone = time.perf_counter()  # the first server has exited
    time.sleep(1.5)
    t_back = time.perf_counter()
    with server_process(tmp_path / "server2.log", server.port, *SERVER_ARGS, "--subdivisions", "3"):
        summary, cols = finish_client(proc, tmp_path, "A")
    t = cols["t_s"] + (summary["clock_origin_s"] - t_loss)  # seconds since Ctrl-C to the server
    f, ramping = cols["force_n"], cols["ramping"]
    before = (t > -0.5) & (t < 0.0)
    assert np.mean(f[before]) > 0.5  # A was really pressing
    # The outage: the longest stretch of zero force after Ctrl-C. A loaded server may take a
    # moment to act on Ctrl-C (even stall and resume first); it has surely gone by t_gone.
    zero = (f == 0.0) & (t > 0.0)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], zero.astype(int), [0]])))
    runs = list(zip(edges[::2], edges[1::2], strict=True))
    assert runs, "the force never reached zero after the loss"
    start, end = max(runs, key=lambda r: r[1] - r[0])
    # nothing rendered while it was gone: once the link timeout and the ramp have passed after
    # the server exited, the force stays at zero until the second server is back (the client's
    # own safety rule, whatever the machine's speed)
    cfg = ServoConfig()
    gone = (t >= t_gone - t_loss + cfg.link_timeout_s + cfg.ramp_s + 0.01) & (t <= t_back - t_loss)
    assert gone.any() and np.all(f[gone] == 0.0), f[gone].max(initial=0.0)
    assert t[start] <= t_gone - t_loss + cfg.link_timeout_s + cfg.ramp_s + 0.01
    assert t[end - 1] >= t_back - t_loss  # the longest zero stretch is the outage
    # a ramp, not a jump: the force falls in small steps over ramp_s of servo ticks (counted
    # in ticks, not wall time) into the outage
    ramp = np.flatnonzero(ramping[:start] == 0)
    ramp_start = ramp[-1] + 1 if ramp.size else 0
    assert 0 < start - ramp_start <= cfg.ramp_s * 1000.0 + 5, start - ramp_start
    assert np.abs(np.diff(f[ramp_start - 1 : start + 1])).max() < 0.2
    assert f[ramp_start - 1] > 0.5  # it ramped down from the press
    assert summary["joins"] >= 2  # rejoined the restarted server
    late = t > t_back - t_loss + 3.0
    assert np.mean(f[late]) > 0.5  # and presses again
