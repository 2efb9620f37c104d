"""The ``haply`` backend: the real, unmodified HaplyHardwareAPI binding against our Inverse3 emulator.

The emulator (tests/support/emulators/inverse3.py) serves the master side of a pseudo-terminal
from a separate process; the backend opens the slave side by path through the compiled binding,
exactly as it opens ``/dev/ttyACM0``. What is asserted is what a user would notice: the backend
says what to install when the binding is missing, opens the port before the network, reports the
handle where the emulator puts it (world frame, scaled, placed outside the anchor), sends the
written force in newtons, turns a device that stops answering into a fault and a zero force
within one tick without hanging, closes cleanly, and opens the port again.

Not exercised here: a real Inverse3, USB CDC, firmware timing, the VerseGrip.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from haptic_collab.client.devices import backends
from haptic_collab.client.devices import haply as haply_mod
from haptic_collab.client.devices.backends import HID_STANDOFF_M, DeviceError
from haptic_collab.client.devices.base import DeviceLimits, HapticError
from haptic_collab.client.devices.haply import BACKEND, INSTALL_HINT, Inverse3Device
from haptic_collab.client.devices.haply_spec import Inverse3Specs, parse_haply_args
from haptic_collab.client.devices.opener import DeviceOpener, list_devices, make_device
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.shared.primitives import make_plane
from tests.support.emulators.inverse3 import Inverse3Emulator

pytestmark = pytest.mark.timeout(60)

needs_binding = pytest.mark.skipif(
    importlib.util.find_spec("HaplyHardwareAPI") is None or sys.platform != "linux",
    reason="needs HaplyHardwareAPI (pip install -e '.[dev]') and Linux pseudo-terminals",
)

#: Where the emulated handle sits (device frame): 1 cm right of and 5 cm above the assumed
#: workspace centre (0, -0.14, 0.20).
HANDLE = (0.01, -0.14, 0.25)
SIDE_ANCHOR = (0.05, 0.0, 0.1)
SIDE_NORMAL = (1.0, 0.0, 0.0)


Vec = Sequence[float]


def placed_centre(anchor: Vec, normal: Vec) -> list[float]:
    """Where the workspace centre goes: ``HID_STANDOFF_M`` outside the anchor, like HID devices."""
    return [a + HID_STANDOFF_M * n for a, n in zip(anchor, normal, strict=True)]


def world(p_dev: Vec, centre: Vec = (0.0, 0.0, 0.0), scale: float = 1.0) -> list[float]:
    """Where the backend must report device position ``p_dev`` (the documented mapping)."""
    d = Inverse3Specs().workspace_center_m
    return [centre[i] + scale * (p_dev[i] - d[i]) for i in range(3)]


def box_centre(lim: DeviceLimits) -> list[float]:
    return [0.5 * (a + b) for a, b in zip(lim.workspace_min_m, lim.workspace_max_m, strict=True)]


def close_to(a: Vec, b: Vec, tol: float = 1e-6) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@pytest.fixture
def emulator() -> Iterator[Inverse3Emulator]:
    with Inverse3Emulator(position=HANDLE) as emu:
        yield emu


@pytest.fixture
def devices(emulator: Inverse3Emulator) -> Iterator[list[Inverse3Device]]:
    """Devices to close before the emulator stops (whatever the test did)."""
    made: list[Inverse3Device] = []
    yield made
    for dev in made:
        dev.close()


#: Reply timeout [s] of the tests that are not about timeouts: the emulator is a Python process
#: that a loaded machine may stall far longer than the 20 ms default.
PATIENT_S = 1.0


def opened(
    devices: list[Inverse3Device], emu: Inverse3Emulator, timeout_s: float = PATIENT_S
) -> Inverse3Device:
    """An opened device on the emulator's port, centred on the world origin (not placed)."""
    dev = Inverse3Device(emu.path, timeout_s=timeout_s, open_timeout_s=2.0)
    devices.append(dev)
    dev.open()
    return dev


# -- without the binding ------------------------------------------------------------------------


def test_without_the_binding_available_is_one_line_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(sys.modules, "HaplyHardwareAPI", None)  # `import HaplyHardwareAPI` fails
    msg = BACKEND.available()
    assert msg is not None and "\n" not in msg
    assert (
        msg.endswith(f": {INSTALL_HINT}")
        and "pip install 'HaplyHardwareAPI>=0.1.13'" in INSTALL_HINT
    )
    # haptic client stops on exactly that line, before opening anything
    for attempt in (
        lambda: DeviceOpener("haply:/dev/ttyACM0").check(),
        lambda: make_device("haply:/dev/ttyACM0", SIDE_ANCHOR, SIDE_NORMAL),
    ):
        with pytest.raises(DeviceError) as info:
            attempt()
        assert str(info.value) == msg
    entry = next(b for b in backends.list_backends() if b["name"] == "haply")
    assert entry["available"] is False and entry["message"] == msg


def test_the_binding_is_imported_only_when_needed() -> None:
    code = (
        "import sys; import haptic_collab.client.devices.haply as h; "
        "h.parse_haply_args('/dev/ttyACM0,scale=2'); print('HaplyHardwareAPI' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_spec_names_a_port_and_options() -> None:
    assert parse_haply_args("/dev/ttyACM0").port == "/dev/ttyACM0"
    assert parse_haply_args("ttyACM1").port == "/dev/ttyACM1"
    by_path = "/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0"  # colons are part of the path
    assert parse_haply_args(by_path).port == by_path
    assert parse_haply_args("").port is None  # `haply` alone: detection when opened
    cfg = parse_haply_args("/dev/ttyACM0,scale=2.5,timeout_ms=5,max_force_n=6")
    assert (cfg.port, cfg.scale, cfg.timeout_s, cfg.specs.max_force_n) == (
        "/dev/ttyACM0",
        2.5,
        0.005,
        6.0,
    )
    assert parse_haply_args("scale=0.5").port is None
    for bad, says in [
        ("/dev/a,/dev/b", "two ports"),
        ("/dev/a,speed=3", "unknown option 'speed'"),
        ("/dev/a,scale=0", "bad workspace scale"),
        ("/dev/a,scale=1e6", "<= 100"),  # as the other vendors: no millionfold workspace
        ("/dev/a,scale=nan", "bad workspace scale"),
        ("/dev/a,max_force_n=nan", "finite number"),
        ("/dev/a,timeout_ms=0", "timeout_ms"),
        ("/dev/a,max_continuous_force_n=9", "max_continuous_force_n"),
    ]:
        with pytest.raises(DeviceError, match=says) as info:
            parse_haply_args(bad)
        assert "\n" not in str(info.value)


def test_the_workspace_scale_is_folded_into_the_limits() -> None:
    specs = Inverse3Specs()
    one = specs.world_limits(1.0, (0.0, 0.0, 0.0))
    two = specs.world_limits(2.0, (0.1, 0.2, 0.3))
    assert two.max_force_n == one.max_force_n == specs.max_force_n  # forces unchanged
    assert two.max_continuous_force_n == specs.max_continuous_force_n
    assert two.max_stiffness_n_per_m == specs.max_stiffness_n_per_m / 2.0
    assert two.max_damping_n_s_per_m == specs.max_damping_n_s_per_m / 2.0
    assert two.max_velocity_m_s == specs.max_velocity_m_s * 2.0
    for i, c in enumerate((0.1, 0.2, 0.3)):
        assert math.isclose(two.workspace_max_m[i] - two.workspace_min_m[i], 4 * 0.08)
        assert math.isclose(0.5 * (two.workspace_max_m[i] + two.workspace_min_m[i]), c)


def test_detect_reads_udev_names_and_writes_to_no_port(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    haply_port, other_port = tmp_path / "ttyACM0", tmp_path / "ttyACM1"
    haply_port.write_bytes(b"")
    other_port.write_bytes(b"")
    (by_id / "usb-Haply_Robotics_Inverse3_0123-if00").symlink_to(haply_port)
    (by_id / "usb-Arduino_Uno_42-if00").symlink_to(other_port)
    monkeypatch.setattr(haply_mod, "SERIAL_BY_ID", str(by_id))
    found = BACKEND.detect()
    assert found == [
        {
            "spec": f"haply:{by_id / 'usb-Haply_Robotics_Inverse3_0123-if00'}",
            "kind": "inverse3",
            "port": os.path.realpath(haply_port),
            "by_id": "usb-Haply_Robotics_Inverse3_0123-if00",
        }
    ]
    assert haply_port.read_bytes() == b"" and other_port.read_bytes() == b""  # nothing written
    monkeypatch.setattr(haply_mod, "SERIAL_BY_ID", str(tmp_path / "absent"))
    assert BACKEND.detect() == []


# -- with the binding and the emulator --------------------------------------------------------------


@needs_binding
def test_available_with_the_binding_and_the_builtin_listing() -> None:
    assert BACKEND.available() is None
    assert {d["name"] for d in list_devices() if d["kind"] == "backend"} >= {"haply"}
    assert backends.get_backend("haply") is BACKEND


@needs_binding
def test_make_device_builds_without_touching_the_port(emulator: Inverse3Emulator) -> None:
    dev = make_device(f"haply:{emulator.path},scale=2", SIDE_ANCHOR, SIDE_NORMAL)
    try:
        assert isinstance(dev, Inverse3Device) and not dev.is_open
        assert close_to(box_centre(dev.limits), placed_centre(SIDE_ANCHOR, SIDE_NORMAL))
        time.sleep(0.05)
        assert emulator.wakeups == 0 and emulator.force_count == 0
    finally:
        dev.close()


@needs_binding
def test_the_client_opens_the_port_before_the_network_and_reads_the_placed_scaled_position(
    emulator: Inverse3Emulator,
) -> None:
    opener = DeviceOpener(f"haply:{emulator.path},scale=2,timeout_ms={PATIENT_S * 1e3:g}")
    opener.check()  # before any network: the port is opened and the wake-up reply checked
    assert emulator.wakeups == 1
    dev = opener.build(SIDE_ANCHOR, SIDE_NORMAL)  # the server's welcome gave the anchor
    try:
        assert isinstance(dev, Inverse3Device) and dev.is_open
        assert dev.info is not None and dev.info["device_id"] == 0x049D
        assert emulator.wakeups == 1  # the port opened by check() is the one used
        centre = placed_centre(SIDE_ANCHOR, SIDE_NORMAL)
        assert close_to(dev.read(0.0), world(HANDLE, centre, 2.0))
        # the user moves the handle 3 cm toward -x (into the object along the side normal)
        moved = (HANDLE[0] - 0.03, HANDLE[1] + 0.01, HANDLE[2])
        emulator.set_state(moved, (-0.1, 0.0, 0.0))
        pos = dev.read(0.001)
        assert close_to(pos, world(moved, centre, 2.0))
        assert math.isclose(pos[0], SIDE_ANCHOR[0] + HID_STANDOFF_M + 2 * -0.02, abs_tol=1e-6)
        assert close_to(dev.velocity, (-0.2, 0.0, 0.0))  # world velocity scales too
        # the Inverse3 has no buttons (the VerseGrip is another port): forces engage with a patch
        assert dev.buttons() == 0 and dev.has_buttons is False
        assert dev.limits.max_stiffness_n_per_m == Inverse3Specs().max_stiffness_n_per_m / 2
        assert close_to(box_centre(dev.limits), centre)
    finally:
        dev.close()
        opener.close()


@needs_binding
def test_a_written_force_reaches_the_emulator_in_newtons_one_round_trip_per_tick(
    emulator: Inverse3Emulator, devices: list[Inverse3Device]
) -> None:
    dev = opened(devices, emulator)
    dev.read(0.0)
    assert emulator.last_force() == (0.0, 0.0, 0.0)  # forces start disabled: zero is sent
    dev.write(1.0, 1.0, 1.0)  # ignored while disabled
    dev.read(0.001)
    assert emulator.last_force() == (0.0, 0.0, 0.0)
    dev.enable_forces()
    dev.write(1.0, -2.0, 0.5)  # world frame [N]; world and device axes agree
    dev.read(0.002)  # the stored force goes out with this tick's exchange
    assert emulator.last_force() == (1.0, -2.0, 0.5)
    dev.write(6.0, 0.0, 8.0)  # 10 N: clamped to the device's max_force_n (3 N), same direction
    dev.read(0.003)
    f = emulator.last_force()
    assert f is not None and close_to(f, (1.8, 0.0, 2.4))
    # one serial round trip per servo tick
    n0, ticks = emulator.force_count, 500
    for k in range(ticks):
        dev.read(0.004 + k * 1e-3)
        dev.write(0.25, 0.0, -0.25)
    assert emulator.force_count - n0 == ticks
    dev.disable_forces()  # the zero goes out now, not at a next read that may never come
    assert emulator.force_count - n0 == ticks + 1 and emulator.last_force() == (0.0, 0.0, 0.0)


@needs_binding
def test_an_emulator_that_stops_answering_is_a_fault_and_zero_force_within_one_tick(
    emulator: Inverse3Emulator, devices: list[Inverse3Device]
) -> None:
    dev = opened(devices, emulator, timeout_s=0.3)
    dev.enable_forces()
    for k in range(5):
        dev.read(k * 1e-3)
        dev.write(0.0, 0.0, 1.5)
    last_pos = dev.read(0.005)
    assert emulator.last_force() == (0.0, 0.0, 1.5) and dev.fault is None
    emulator.set_silent(True)  # it still reads what it gets, and answers nothing
    ticks = 0
    while dev.fault is None and ticks < 10:
        dev.write(0.0, 0.0, 1.5)
        dev.read(0.006 + ticks * 1e-3)
        ticks += 1
    assert dev.fault is not None and ticks == 1, (ticks, dev.fault)
    assert "no state reply within 300 ms" in dev.fault and "\n" not in dev.fault
    # one call of about twice the timeout, then no more waiting (ticks == 1 above); how long
    # it took is left to the test's own timeout, not asserted
    # a zero force was sent the moment the fault was seen
    end = time.monotonic() + 2.0
    while emulator.last_force() != (0.0, 0.0, 0.0) and time.monotonic() < end:
        time.sleep(0.005)
    assert emulator.last_force() == (0.0, 0.0, 0.0)
    # a faulted device returns its last position at once and leaves the port alone
    n = emulator.force_count
    for k in range(100):
        assert dev.read(0.1 + k * 1e-3) == last_pos
        dev.write(0.0, 0.0, 2.0)
    assert emulator.force_count == n  # not one more exchange with the port
    # it answers again: the client's reopen() brings the device back, forces from zero
    emulator.set_silent(False)
    emulator.set_state((0.0, -0.15, 0.21))
    assert dev.reopen() is True and dev.fault is None
    assert close_to(dev.read(0.3), world((0.0, -0.15, 0.21)))
    assert emulator.last_force() == (0.0, 0.0, 0.0)
    dev.write(0.0, 0.0, 0.5)
    dev.read(0.301)
    assert emulator.last_force() == (0.0, 0.0, 0.5)


@needs_binding
def test_the_servo_loop_presses_through_the_binding_and_ramps_down_on_silence(
    emulator: Inverse3Emulator, devices: list[Inverse3Device]
) -> None:
    """What the user feels: the servo loop's spring force in newtons, then nothing."""
    anchor, normal = (0.0, 0.0, 0.1), (0.0, 0.0, 1.0)
    dev = opened(devices, emulator, timeout_s=0.3)
    assert BACKEND.place(dev, anchor, normal) is dev  # the centre goes 2 cm above the anchor
    # the handle 24 mm below the workspace centre: 4 mm inside the top face
    emulator.set_state((0.0, -0.14, 0.176))
    core = ServoCore(dev, ServoConfig(ramp_s=0.05))
    core.enable_forces()
    core.set_patch(make_plane(anchor, normal), 300.0, 0.0)  # K_h = 300 N/m, no integral term
    t = 0.0
    for k in range(120):  # the 50 ms ramp, and then some
        t = k * 1e-3
        if k % 10 == 0:
            core.notify_link(t)
        core.tick(t)
    snap = core.latest()
    assert snap is not None and snap.in_contact
    assert snap.penetration_m == pytest.approx(0.004, abs=1e-6)
    f = emulator.last_force()
    assert f is not None and close_to(f, (0.0, 0.0, 300.0 * 0.004), tol=1e-5)  # 1.2 N, up
    emulator.set_silent(True)
    core.tick(t + 1e-3)
    status = core.status()
    assert status.counts[HapticError.DEVICE_FAULT.value] == 1
    assert status.device_fault is not None and "no state reply" in status.device_fault
    end = time.monotonic() + 2.0
    while emulator.last_force() != (0.0, 0.0, 0.0) and time.monotonic() < end:
        time.sleep(0.005)
    assert emulator.last_force() == (0.0, 0.0, 0.0)
    n = emulator.force_count
    for k in range(100):  # the servo loop ramps down; the faulted device leaves the port alone
        core.tick(t + (k + 2) * 1e-3)
    assert core.status().force_scale == 0.0 and emulator.force_count == n


@needs_binding
def test_an_unplugged_emulator_is_a_fault_and_reopen_raises_until_it_is_back(
    emulator: Inverse3Emulator, devices: list[Inverse3Device]
) -> None:
    dev = opened(devices, emulator, timeout_s=0.1)
    dev.read(0.0)
    emulator.unplug()  # the pty's master side closes, as when the cable is pulled
    dev.read(0.001)
    assert dev.fault is not None
    with pytest.raises(OSError):
        dev.reopen()
    assert dev.fault is not None  # still faulted: the client keeps trying with backoff


@needs_binding
def test_close_is_clean_and_the_port_can_be_opened_again(
    emulator: Inverse3Emulator, devices: list[Inverse3Device]
) -> None:
    dev = Inverse3Device(emulator.path, timeout_s=PATIENT_S, open_timeout_s=2.0)
    devices.append(dev)
    dev.close()  # never opened: fine
    before = open_fds()
    dev.open()
    assert open_fds() == before + 1  # the serial port
    dev.enable_forces()
    dev.write(0.5, 0.5, 0.0)
    dev.read(0.0)
    assert emulator.last_force() == (0.5, 0.5, 0.0)
    dev.close()
    assert emulator.last_force() == (0.0, 0.0, 0.0)  # closing leaves the device at zero force
    assert open_fds() == before and not dev.is_open
    dev.close()  # twice: fine
    n = emulator.force_count
    assert dev.read(1.0) == dev.read(1.0) and emulator.force_count == n  # closed: no exchange
    dev.open()  # the same port again
    assert emulator.wakeups == 2 and dev.fault is None
    emulator.set_state((0.02, -0.14, 0.20))
    assert close_to(dev.read(2.0), world((0.02, -0.14, 0.20)))
    dev.close()
    assert open_fds() == before


@needs_binding
def test_open_refuses_what_is_not_an_inverse3(tmp_path: Path) -> None:
    # a regular file: the binding would write its wake-up byte into it; we never hand it over
    f = tmp_path / "not-a-port"
    f.write_bytes(b"precious")
    with pytest.raises(OSError, match="not a serial port"):
        Inverse3Device(str(f)).open()
    assert f.read_bytes() == b"precious"
    # an absent port, through the client: one line, what and what to do
    with pytest.raises(DeviceError) as info:
        DeviceOpener(f"haply:{tmp_path / 'ttyACM9'}").check()
    assert str(info.value).startswith(f"cannot open haply:{tmp_path / 'ttyACM9'}: ")
    assert "does not exist: plug the Inverse3 in" in str(info.value)
    # something that answers the wake-up without a device UUID (what the binding returns for no
    # reply at all), and something that does not answer
    with Inverse3Emulator(uuid=bytes(16)) as no_uuid, Inverse3Emulator() as mute:
        with pytest.raises(OSError, match="answers like an Inverse3.*without a device UUID"):
            Inverse3Device(no_uuid.path, open_timeout_s=2.0).open()
        mute.set_silent(True)
        with pytest.raises(OSError, match="no wake-up reply within 50 ms"):
            Inverse3Device(mute.path, open_timeout_s=0.05).open()


@pytest.mark.parametrize("name", ["haply", "forcedimension", "openhaptics"])
def test_a_vendor_backend_places_only_a_device_it_opened(name: str) -> None:
    sim = make_device("sim:rest", SIDE_ANCHOR, SIDE_NORMAL)
    message = f"{sim.name} was not opened by the {name} backend"
    with pytest.raises(DeviceError, match=f"^{re.escape(message)}$"):
        backends.get_backend(name).place(sim, SIDE_ANCHOR, SIDE_NORMAL)
