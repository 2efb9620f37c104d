"""The servo loop in its own process (client.servo_process): forces through shared memory, and
what happens when either side dies.

Each test starts a real servo process (spawned, as ``haptic client`` does) with a simulated
device pressing a plane patch the test hands over; times are the servo clock's
(``time.perf_counter() - origin``, CLOCK_MONOTONIC in both processes).
"""

from __future__ import annotations

import asyncio
import gc
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.recorder import COLUMNS
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.client.servo_block import SharedBlock
from haptic_collab.client.servo_child import _Bridge
from haptic_collab.client.servo_device import built_device
from haptic_collab.client.servo_process import ServoProcess
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.primitives import make_plane

ROOT = Path(__file__).resolve().parents[2]
ANCHOR = (0.0, 0.0, 0.05)
NORMAL = (0.0, 0.0, 1.0)
RAMP_S = ServoConfig().ramp_s
FORCE = COLUMNS.index("force_n")
SCALE = COLUMNS.index("force_scale")
T_COL = COLUMNS.index("t_s")

pytestmark = pytest.mark.slow


def _patch() -> LocalModelUpdate:
    return LocalModelUpdate(make_plane(ANCHOR, NORMAL), 300.0, 0.0)


def _pressing(sp: ServoProcess, origin: float, timeout_s: float = 30.0) -> None:
    """Hand the plane over every 20 ms (a live link) until the scripted hand presses it."""
    t_end = time.perf_counter() + timeout_s
    while time.perf_counter() < t_end:
        sp.set_patch(_patch())
        snap = sp.latest()
        if snap is not None and snap.force_n[2] > 1.0 and snap.force_scale == 1.0:
            return
        time.sleep(0.02)
    raise AssertionError("the simulated hand never pressed the plane")


def _started(origin: float, **kwargs: object) -> ServoProcess:
    sp = ServoProcess(
        {"spec": "sim:press", "servo_rate_hz": 1000.0},
        clock_origin_s=origin,
        capacity=30_000,
        **kwargs,  # type: ignore[arg-type]
    )
    sp.check()
    sp.build(ANCHOR, NORMAL)
    sp.start(ServoConfig(), LocalModelParams(k_h=1.0, servo_period_s=1e-3))
    sp.enable_forces()
    return sp


def test_a_servo_process_renders_the_patches_it_is_handed_and_stops_with_a_ramp() -> None:
    origin = time.perf_counter()
    sp = _started(origin)
    try:
        assert sp.device is not None and sp.device.name.startswith("sim:")
        _pressing(sp, origin)
        snap = sp.latest()
        assert snap is not None
        # the force the user feels is the plane's: K_h times the penetration, along the normal
        assert snap.force_n[2] == pytest.approx(300.0 * snap.penetration_m, rel=0.05)
        assert snap.servo_rate_hz > 0.0  # its period statistics come through (not timed here)
        # a K_h above the device's stiffness is clamped, as the thread's servo does
        big = LocalModelUpdate(make_plane(ANCHOR, NORMAL), 1e6, 0.0)
        applied = sp.set_patch(big)
        assert applied.k_h == sp.device.limits.max_stiffness_n_per_m
        status = sp.status()
        assert status.ticks > 100 and status.forces_enabled and not status.stopped
    finally:
        assert sp.stop()
    rows = sp.recorder.rows()  # the shared ring, read in this process
    assert rows.shape[0] > 500
    f, g = rows[:, FORCE], rows[:, SCALE]
    assert f.max() > 1.0 and f[-1] == 0.0 and g[-1] == 0.0
    # the stop ramps the force down over the ramp time: no step bigger than a tick's share
    down = int(np.flatnonzero(g == 1.0)[-1])
    assert rows.shape[0] - down == pytest.approx(RAMP_S / 1e-3, abs=3)
    # about 1.3 % of the force per tick, plus the hand moving; a jump would be all of it
    assert np.abs(np.diff(f[down:])).max() <= 0.1 * f[down]
    status = sp.status()
    assert status.stopped and status.error is None
    assert sp.counters == {"device_faults": 0, "device_reopens": 0}


def test_a_killed_servo_process_is_noticed_at_once_and_its_force_ramps_to_zero() -> None:
    origin = time.perf_counter()
    deaths: list[str] = []
    sp = _started(origin, on_death=deaths.append)
    try:
        _pressing(sp, origin)
        f0 = sp.latest().force_n[2]  # type: ignore[union-attr]
        pid = sp.pid
        assert pid is not None
        t_kill = time.perf_counter() - origin
        os.kill(pid, signal.SIGKILL)
        t_end = time.perf_counter() + 2.0
        while sp.died_at_s is None and time.perf_counter() < t_end:
            time.sleep(0.001)
        while not deaths and time.perf_counter() < t_end:
            time.sleep(0.001)
        assert sp.died_at_s is not None
        assert sp.died_at_s - t_kill < 0.1  # noticed within 0.1 s
        assert deaths and "SIGKILL" in deaths[0]
        # what the link reports to the server: the last force, ramping to zero, never a jump
        # (read times bracket each value: on a busy machine the reads are irregular, so the ramp
        # is judged by its slope over the time between them, not by the step between two reads)
        reads: list[tuple[float, float, float]] = []
        while (time.perf_counter() - origin) - sp.died_at_s < RAMP_S + 0.03:
            t0 = time.perf_counter() - origin
            f = sp.latest().force_n[2]  # type: ignore[union-attr]
            reads.append((t0, time.perf_counter() - origin, f))
            time.sleep(0.002)
        seen = [f for _, _, f in reads]
        assert seen[-1] == 0.0 and np.all(np.diff(seen) <= 1e-12)
        slope = 1.2 * f0 / RAMP_S  # [N/s]: the ramp's, with the press's own wobble
        assert seen[0] >= 0.8 * f0 - slope * (reads[0][1] - sp.died_at_s)
        for (a0, _, fa), (_, b1, fb) in zip(reads[:-1], reads[1:], strict=True):
            assert fa - fb <= slope * (b1 - a0) + 1e-9  # a ramp, never a jump
        assert "SIGKILL" in (sp.status().error or "")
    finally:
        sp.stop()


HELPER = """
import json, sys, time
from haptic_collab.client.servo import ServoConfig
from haptic_collab.client.servo_process import ServoProcess
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.primitives import make_plane

if __name__ == "__main__":
    origin = time.perf_counter()
    sp = ServoProcess({"spec": "sim:press"}, clock_origin_s=origin, capacity=30000)
    sp.check()
    sp.build((0.0, 0.0, 0.05), (0.0, 0.0, 1.0))
    sp.start(ServoConfig(), LocalModelParams(k_h=1.0, servo_period_s=1e-3))
    sp.enable_forces()
    print(json.dumps({"block": sp.block.name, "pid": sp.pid, "origin": origin}), flush=True)
    while True:  # a live link until this process is killed
        sp.set_patch(LocalModelUpdate(make_plane((0.0, 0.0, 0.05), (0.0, 0.0, 1.0)), 300.0, 0.0))
        time.sleep(0.02)
"""


def _gone(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_servo_ramps_forces_down_and_ends_when_its_link_process_is_killed(
    tmp_path: Path,
) -> None:
    script = tmp_path / "link.py"
    script.write_text(HELPER)
    link = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,  # the tracker's note on the block it frees
        text=True,
    )
    try:
        assert link.stdout is not None
        info = json.loads(link.stdout.readline())
        block = SharedBlock(30000, ServoConfig().period_window, name=info["block"])
        rec = block.recorder()
        t_end = time.perf_counter() + 30.0
        while time.perf_counter() < t_end:
            rows = rec.rows_from(max(rec.total - 50, 0))[1]
            if rows.shape[0] and rows[:, FORCE].min() > 1.0 and rows[-1, SCALE] == 1.0:
                break
            time.sleep(0.02)
        else:
            raise AssertionError("the servo never pressed the plane")
        t_kill = time.perf_counter() - info["origin"]
        link.kill()
        link.wait(5.0)
        t_end = time.perf_counter() + 5.0
        while not _gone(info["pid"]) and time.perf_counter() < t_end:
            time.sleep(0.01)
        assert _gone(info["pid"])  # the servo process ended by itself
        rows = rec.rows_from(0, settled=True)[1]
        t, f, g = rows[:, T_COL], rows[:, FORCE], rows[:, SCALE]
        after = t > t_kill
        t_ramp = t[after & (g < 1.0)][0]
        assert t_ramp - t_kill < 0.1  # the servo noticed within 0.1 s
        assert f[-1] == 0.0 and g[-1] == 0.0
        window = t > t_kill - 0.05
        assert np.abs(np.diff(f[window])).max() <= 0.1 * f.max()  # a ramp, never a jump
    finally:
        if link.poll() is None:
            link.kill()
    # the killed process's resource tracker frees the block once the servo process let go of it
    from multiprocessing import resource_tracker

    resource_tracker.unregister(block.shm._name, "shared_memory")  # type: ignore[attr-defined]


def test_the_servo_tick_holds_no_new_memory_and_never_needs_the_collector() -> None:
    """The servo process's tick with its shared-memory exchange: after a warm-up, thousands of
    ticks leave the interpreter's allocated blocks where they were, with the collector off."""
    from haptic_collab.client.devices.opener import DeviceOpener

    opener = DeviceOpener("sim:rest")  # approaches in 1 s, then rests on the plane for ever
    opener.check()
    device = opener.build(ANCHOR, NORMAL)
    block = SharedBlock(2000, 1000)
    try:
        core = ServoCore(
            device,
            ServoConfig(),
            local_model=LocalModelParams(k_h=1.0, servo_period_s=1e-3),
            recorder=block.recorder(),
            period_buffer=block.periods,
        )
        assert built_device(device).limits == device.limits
        bridge = _Bridge(block, core, os.getppid())
        core.enable_forces()
        block.write_patch(_patch())
        t = 0.0
        for _ in range(2000):  # the hand reaches the plane; every branch has run
            block.flt[0] = t
            bridge.tick(t)
            t += 1e-3
        gc.collect()
        gc.disable()
        try:
            for _ in range(1000):  # first-use caches of the interpreter settle
                block.flt[0] = t
                bridge.tick(t)
                t += 1e-3
            before, count = sys.getallocatedblocks(), gc.get_count()[0]
            for _ in range(20_000):
                block.flt[0] = t
                bridge.tick(t)
                t += 1e-3
            grown = sys.getallocatedblocks() - before
            tracked = gc.get_count()[0] - count  # container objects still alive
        finally:
            gc.enable()
        assert core.published is not None and core.published[7] > 0.1  # pressing the plane
        assert grown < 5  # 20 s of servo ticks keep no new memory
        assert tracked < 10  # and leave nothing for the cyclic collector
    finally:
        device.close()
        block.release()
        block.shm.unlink()


async def test_a_client_whose_servo_process_is_killed_stops_with_the_reason(tmp_path: Path) -> None:
    """``haptic client`` end to end: the servo process killed mid-press ends the client with an
    error naming the signal; the force it reported to the server ramped to zero first, and the
    summary and recording are written."""
    from haptic_collab.client.recorder import load_recording
    from haptic_collab.client.servo_process import ServoProcessError
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.main import ServerOptions, build_world
    from haptic_collab.server.room import Room

    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=3))
    app = ServerApp(Room(world, 20.0), "127.0.0.1", 0)
    await app.start()
    record, summary = tmp_path / "A.csv", tmp_path / "A.json"
    opts = ClientOptions(
        url=f"ws://127.0.0.1:{app.port}/ws", name="A", device="sim:rest", anchor="top",
        record=record, summary=summary, duration_s=60.0, servo="process",
    )  # fmt: skip
    client = asyncio.create_task(run_client(opts))
    try:
        t_end = time.monotonic() + 60.0
        while time.monotonic() < t_end:
            await asyncio.sleep(0.1)
            if record.exists():
                rows = load_recording(record)
                if rows["force_n"].size > 300 and np.all(rows["force_n"][-300:] > 0.05):
                    break
        else:
            raise AssertionError("the client never rested on the object with forces on")
        import multiprocessing

        servo = [p for p in multiprocessing.active_children() if p.name == "haptic-servo"]
        assert len(servo) == 1 and servo[0].pid is not None
        os.kill(servo[0].pid, signal.SIGKILL)
        with pytest.raises(ServoProcessError, match="SIGKILL"):
            await asyncio.wait_for(client, 10.0)
    finally:
        if not client.done():
            client.cancel()
        await app.stop()
    s = json.loads(summary.read_text())
    assert s["stopped_by"] == "error" and s["servo_host"] == "process"
    assert "SIGKILL" in (s["servo"]["error"] or "")
    assert s["record"]["rows"] > 300


def test_a_bad_device_is_refused_by_the_servo_process_before_the_network() -> None:
    """The servo process opens the device; a spec it cannot use still stops ``haptic client``
    with the one-line error before any connection is made."""
    with socket.create_server(("127.0.0.1", 0)) as srv:
        srv.setblocking(False)
        opts = ClientOptions(
            url=f"ws://127.0.0.1:{srv.getsockname()[1]}/ws",
            device="sim:juggle",
            servo="process",
            join_timeout_s=30.0,
        )
        with pytest.raises(DeviceError, match="unknown simulated device 'sim:juggle'"):
            asyncio.run(run_client(opts))
        with pytest.raises(BlockingIOError):
            srv.accept()  # no connection was ever made
