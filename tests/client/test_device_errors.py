"""Devices that are not there: checked before the network, one line with what to do; a device lost
while running is a device fault (forces to zero, reopened with backoff), never a network retry."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.devices.hid import ProfileHidDevice, open_error_message
from haptic_collab.client.devices.opener import DeviceOpener
from haptic_collab.client.recorder import load_recording

# -- the one line -----------------------------------------------------------------------------------


def test_an_absent_device_points_to_haptic_devices() -> None:
    msg = open_error_message(0x256F, 0xC635, OSError("open failed"), attached=[])
    assert msg.startswith("cannot open hid:256f:c635: no device with these ids is attached")
    assert "`haptic devices`" in msg and "\n" not in msg


def test_a_node_the_user_may_not_open_gets_the_udev_hint() -> None:
    attached = [{"vendor_id": 0x256F, "product_id": 0xC635, "path": b"/dev/hidraw-not-yours"}]
    msg = open_error_message(0x256F, 0xC635, OSError("open failed"), attached=attached)
    assert "permission denied on /dev/hidraw-not-yours" in msg
    assert 'ATTRS{idVendor}=="256f"' in msg and "udevadm control --reload" in msg
    assert "\n" not in msg
    # an explicit PermissionError says the same even when the path is not a hidraw node
    attached = [{"vendor_id": 0x256F, "product_id": 0xC635, "path": b"1-2:1.0"}]
    msg = open_error_message(0x256F, 0xC635, PermissionError(13, "denied"), attached=attached)
    assert "permission denied" in msg and "udev rule" in msg


def test_an_attached_device_that_refuses_is_told_apart() -> None:
    attached = [{"vendor_id": 0x1209, "product_id": 0x0001, "path": b"1-2:1.0"}]
    msg = open_error_message(0x1209, 0x0001, OSError("open failed"), attached=attached)
    assert "attached but refused to open (open failed)" in msg and "other program" in msg


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("sim:juggle", "unknown simulated device 'sim:juggle'"),
        ("hid:1234:5678", "--hid-profile"),
        ("hid:zz:1", "VID:PID"),
        ("usb:1:2", "unknown device spec"),
        ("sim:replay:/no/such/file.csv", "cannot open replay file"),
    ],
)
def test_bad_specs_are_one_line_device_errors(spec: str, says: str) -> None:
    with pytest.raises(DeviceError, match="^[^\n]*$") as info:
        DeviceOpener(spec).check()
    assert says in str(info.value)


class FakePort:
    """A generic 3-DoF device (the bundled ``example-3dof-force`` profile's reports).

    Every read returns one input report at ``position_m`` (device frame) unless unplugged.
    """

    def __init__(self, position_m: tuple[float, float, float]) -> None:
        self.position_m = position_m
        self.unplugged = False
        self.closed = False
        self.forces: list[bytes] = []

    def read(self, max_length: int) -> list[int]:
        if self.unplugged:
            raise OSError("read error")
        um = [round(v * 1e6) for v in self.position_m]
        return list(bytes([1]) + struct.pack("<iii", *um))

    def write(self, data: bytes) -> int:
        if self.unplugged:
            raise OSError("write error")
        self.forces.append(bytes(data))
        return len(data)

    def close(self) -> None:
        self.closed = True


class FakeBus:
    """Opens :class:`FakePort`s; while ``plugged`` is False every open fails as hidapi's does."""

    def __init__(self, position_m: tuple[float, float, float]) -> None:
        self.position_m = position_m
        self.plugged = True
        self.opens = 0
        self.failed_opens = 0
        self.ports: list[FakePort] = []

    def __call__(self, vendor_id: int, product_id: int) -> FakePort:
        if not self.plugged:
            self.failed_opens += 1
            raise OSError("open failed")
        self.opens += 1
        port = FakePort(self.position_m)
        self.ports.append(port)
        return port

    def unplug(self) -> None:
        self.plugged = False
        for p in self.ports:
            p.unplugged = True


def test_the_port_opened_by_the_check_is_the_one_the_device_uses() -> None:
    bus = FakeBus((0.0, 0.0, 0.0))
    opener = DeviceOpener("hid:1209:0001", hid_opener=bus)
    opener.check()
    assert bus.opens == 1  # opened before any network
    dev = opener.build((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))
    assert isinstance(dev, ProfileHidDevice) and bus.opens == 1
    assert dev.read(0.0) == pytest.approx((0.0, 0.0, 0.12))  # 20 mm outside the anchor
    dev.close()
    # a device that went away between the check and the welcome: a DeviceError, not a retry
    opener = DeviceOpener("hid:1209:0001", hid_opener=bus)
    opener.check()
    bus.unplug()
    opener.close()
    assert bus.ports[-1].closed  # the unused early port is released
    with pytest.raises(DeviceError, match="cannot open hid:1209:0001"):
        opener.build((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))


def test_a_device_that_cannot_be_opened_is_refused_before_the_network() -> None:
    bus = FakeBus((0.0, 0.0, 0.0))
    bus.plugged = False
    # a reachable server: a client that got as far as the network would connect to it
    with socket.create_server(("127.0.0.1", 0)) as srv:
        srv.setblocking(False)
        opts = ClientOptions(
            url=f"ws://127.0.0.1:{srv.getsockname()[1]}/ws",
            device="hid:1209:0001",
            hid_opener=bus,
            join_timeout_s=30.0,
        )
        with pytest.raises(DeviceError, match="cannot open hid:1209:0001"):
            asyncio.run(run_client(opts))
        with pytest.raises(BlockingIOError):
            srv.accept()  # no connection was ever made
    assert bus.failed_opens == 1


# -- lost while running ---------------------------------------------------------------------------


async def _wait_for(predicate, timeout_s: float, what: str) -> None:  # type: ignore[no-untyped-def]
    t_end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.1)


def _recorded(path: Path) -> dict[str, np.ndarray]:
    try:
        return load_recording(path)
    except (ValueError, OSError):
        return {"t_s": np.empty(0), "force_n": np.empty(0), "fault": np.empty(0)}


@pytest.mark.slow
async def test_an_unplugged_device_is_reopened_and_the_link_is_left_alone(tmp_path: Path) -> None:
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.main import ServerOptions, build_world
    from haptic_collab.server.room import Room

    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=3))
    app = ServerApp(Room(world, 20.0), "127.0.0.1", 0)
    await app.start()
    info = app.room.object_info
    # the device frame's origin is 20 mm outside the top: hold the probe 3 mm inside the top
    n = np.asarray(info.top_normal)
    bus = FakeBus(tuple((-0.023 * n).tolist()))  # type: ignore[arg-type]
    record, summary = tmp_path / "A.csv", tmp_path / "A.json"
    opts = ClientOptions(
        url=f"ws://127.0.0.1:{app.port}/ws", name="A", device="hid:1209:0001", hid_opener=bus,
        record=record, summary=summary, duration_s=120.0, anchor="top",
    )  # fmt: skip
    client = asyncio.create_task(run_client(opts))
    try:

        def pressing() -> bool:
            f = _recorded(record)["force_n"]
            return f.size > 200 and bool(np.all(f[-200:] > 0.05))

        await _wait_for(pressing, 60.0, "forces on")  # gains designed, force felt
        bus.unplug()
        t_unplug = _recorded(record)["t_s"][-1]
        await asyncio.sleep(1.5)  # several reopen attempts fail meanwhile
        assert bus.failed_opens >= 1
        bus.plugged = True

        def pressing_again() -> bool:
            cols = _recorded(record)
            late = cols["t_s"] > t_unplug + 1.5
            return late.sum() > 200 and bool(np.all(cols["force_n"][late][-200:] > 0.05))

        await _wait_for(pressing_again, 20.0, "forces back after the device came back")
    finally:
        client.cancel()
        with pytest.raises(asyncio.CancelledError):
            await client
        await app.stop()
    # the summary and the recording are written even though the run was cancelled
    s = json.loads(summary.read_text())
    assert s["joins"] == 1  # one connection for the whole run: the link was never restarted
    assert s["device_faults"] == 1 and s["device_reopens"] == 1
    assert s["record"]["rows_dropped"] == 0
    cols = load_recording(record)
    t, f, fault = cols["t_s"], cols["force_n"], cols["fault"]
    t_fault = t[np.argmax(fault > 0)]  # the first tick that saw the device gone
    assert t_unplug - 0.05 <= t_fault
    away = (t > t_fault) & (t < t_fault + 1.2)  # the first reopen tries fail meanwhile
    assert fault[away].min() == 1
    # forces ramp to zero (75 servo ticks, 75 ms at 1 kHz when no tick is late) and stay there
    # while the device is away
    assert np.all(f[away & (t > t_fault + 0.25)] == 0.0)
    assert np.abs(np.diff(f[(t > t_fault - 0.05) & (t < t_fault + 0.1)])).max() < 0.2  # a ramp
    assert f[(t > t_fault - 0.05) & (t < t_fault)].min() > 0.05  # it was pressing until then
    assert bus.opens == 2  # the early open, then one successful reopen
