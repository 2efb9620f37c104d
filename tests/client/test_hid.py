"""HID devices from recorded report bytes: SpaceMouse layout, generic profiles, unplugging.

The reports below follow the public SpaceMouse layout (report id, then int16 little-endian axes)
and the bundled example profiles; no hardware is needed except for the ``hardware`` test.
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.client.devices.hid import ProfileHidDevice, SpaceMouseDevice, list_devices
from haptic_collab.client.devices.hid_backend import parse_hid_ids
from haptic_collab.client.devices.hid_reports import (
    SpaceMouseMapping,
    decode_input,
    encode_output,
    parse_spacemouse_report,
    spacemouse_position,
)
from haptic_collab.client.devices.opener import make_device
from haptic_collab.client.devices.profiles import ProfileError, load_hid_profile, parse_hid_profile

CENTER = (0.0, 0.0, 0.1)


def sm_report(rid: int, a: int, b: int, c: int, *more: int) -> bytes:
    return bytes([rid]) + struct.pack("<" + "h" * (3 + len(more)), a, b, c, *more)


class FakePort:
    """Stands in for ``hid.device``: replays queued reports, then nothing (or an error)."""

    def __init__(self, reports: Sequence[bytes] = ()) -> None:
        self.queue: list[bytes] = list(reports)
        self.unplugged = False
        self.written: list[bytes] = []
        self.closed = False

    def read(self, max_length: int) -> list[int]:
        if self.unplugged:
            raise OSError("read error")
        return list(self.queue.pop(0)) if self.queue else []

    def write(self, data: bytes) -> int:
        if self.unplugged:
            raise OSError("write error")
        self.written.append(bytes(data))
        return len(data)

    def close(self) -> None:
        self.closed = True


def opener_for(port: FakePort):  # type: ignore[no-untyped-def]
    return lambda vid, pid: port


# -- SpaceMouse parsing ----------------------------------------------------------------------------


def test_spacemouse_reports_decode_translation_and_rotation() -> None:
    assert parse_spacemouse_report(sm_report(1, 10, -20, 350)) == ((10, -20, 350), None)
    assert parse_spacemouse_report(sm_report(2, -1, 2, -3)) == (None, (-1, 2, -3))
    # newer models: translation and rotation in one 13-byte report id 1
    assert parse_spacemouse_report(sm_report(1, 5, 6, 7, 8, 9, -10)) == ((5, 6, 7), (8, 9, -10))
    assert parse_spacemouse_report(bytes([3, 1, 0])) == (None, None)  # buttons
    assert parse_spacemouse_report(b"") == (None, None)
    with pytest.raises(ValueError, match="too short"):
        parse_spacemouse_report(bytes([1, 0, 0, 0]))


def test_spacemouse_deflection_maps_into_the_workspace() -> None:
    m = SpaceMouseMapping(travel_m=0.04, full_scale_counts=350.0)
    assert spacemouse_position((0, 0, 0), CENTER, m) == CENTER
    # pressing the cap fully down (+z raw) moves the probe 4 cm down; beyond full scale it clips
    assert spacemouse_position((0, 0, 350), CENTER, m) == pytest.approx((0.0, 0.0, 0.06))
    assert spacemouse_position((0, 0, 700), CENTER, m) == pytest.approx((0.0, 0.0, 0.06))
    # right is +x, pushing away from the user (-y raw) is +y
    assert spacemouse_position((175, -175, 0), CENTER, m) == pytest.approx((0.02, 0.02, 0.1))


def test_spacemouse_device_reads_the_newest_report() -> None:
    port = FakePort([sm_report(1, 0, 0, 100), sm_report(2, 9, 9, 9), sm_report(1, 0, 0, 175)])
    dev = SpaceMouseDevice(0x256F, 0xC635, CENTER, opener=opener_for(port))
    dev.open()
    assert dev.read(0.0) == pytest.approx((0.0, 0.0, 0.08))  # the 175-count report won
    assert dev.read(0.001) == pytest.approx((0.0, 0.0, 0.08))  # silence: cap held still
    assert dev.fault is None
    port.queue.append(sm_report(1, 5, 6, 7, 8, 9, 10))  # a 13-byte report
    assert dev.read(0.002)[0] == pytest.approx(0.04 * 5 / 350)


def test_spacemouse_rate_mode_integrates_and_stays_in_the_workspace() -> None:
    port = FakePort([sm_report(1, 350, 0, 0)])
    m = SpaceMouseMapping(mode="rate", speed_m_s=0.1)
    dev = SpaceMouseDevice(0x256F, 0xC635, CENTER, m, opener=opener_for(port))
    dev.open()
    dev.read(0.0)
    x = dev.read(0.5)
    assert x == pytest.approx((0.05, 0.0, 0.1))  # 0.1 m/s for 0.5 s
    x = dev.read(5.0)
    assert x[0] == pytest.approx(dev.limits.workspace_max_m[0])


def test_unplugged_spacemouse_sets_fault_and_keeps_its_last_position() -> None:
    port = FakePort([sm_report(1, 0, 0, 100)])
    dev = SpaceMouseDevice(0x256F, 0xC635, CENTER, opener=opener_for(port))
    dev.open()
    before = dev.read(0.0)
    port.unplugged = True
    assert dev.read(0.001) == before
    assert dev.fault is not None and "unplugged" in dev.fault
    dev.close()
    assert port.closed


def test_spacemouse_through_make_device_has_no_force_output() -> None:
    dev = make_device("hid:046d:c626", (0.0, 0.0, 0.05), (0.0, 0.0, 1.0))
    assert isinstance(dev, SpaceMouseDevice)
    assert not dev.limits.has_force_output
    assert dev.center == pytest.approx((0.0, 0.0, 0.07))  # centred 2 cm outside the anchor


def test_a_spacemouse_push_comes_from_the_designed_coupling_bounded_as_every_users() -> None:
    """No invented limits: K_h is the gain design's, the force the protocol's bound, no speed cap."""
    from haptic_collab.client.app import ClientOptions, _device_info
    from haptic_collab.client.servo import ServoConfig, ServoCore
    from haptic_collab.shared.primitives import make_plane
    from haptic_collab.shared.protocol import MAX_REPORTED_FORCE_N

    port = FakePort([sm_report(1, 0, 0, 350)] * 5)  # the cap pressed fully down
    dev = SpaceMouseDevice(0x256F, 0xC635, CENTER, opener=opener_for(port))
    dev.open()
    lim = dev.limits
    assert lim.max_force_n == MAX_REPORTED_FORCE_N
    assert lim.max_stiffness_n_per_m == math.inf and lim.max_velocity_m_s == math.inf
    # hello declares the protocol's ranges: the server designs for K_o, bounds by its geometry
    info = _device_info(ClientOptions(url="ws://x", device="hid:256f:c635"), lim)
    assert info.max_force_n == MAX_REPORTED_FORCE_N and info.max_stiffness_n_per_m == 1e5
    # a coupling stiffer than the old invented 5000 N/m cap is rendered as designed
    core = ServoCore(dev, ServoConfig(ramp_s=0.001))
    core.enable_forces()
    below = dev.read(0.0)[2] + 0.004  # a surface 4 mm above the probe: 4 mm of penetration
    core.set_patch(make_plane((0.0, 0.0, below), (0.0, 0.0, 1.0)), 8000.0, 0.0)
    t = 0.0
    for k in range(50):
        if k % 10 == 0:
            core.notify_link(t)
        core.tick(t)
        t += 1e-3
    snap = core.latest()
    assert snap is not None and core.status().stiffness_clamps == 0
    assert snap.force_n[2] == pytest.approx(8000.0 * 0.004)  # 32 N: under the protocol's 50 N


# -- generic profiles -------------------------------------------------------------------------------


def test_bundled_force_profile_decodes_positions_and_encodes_forces() -> None:
    prof = load_hid_profile("example-3dof-force")
    report = bytes([1]) + struct.pack("<iii", 12_000, -5_000, 250)
    assert decode_input(prof.input, report) == pytest.approx((0.012, -0.005, 0.00025))
    assert decode_input(prof.input, bytes([7]) + bytes(12)) is None  # another report id
    with pytest.raises(ValueError, match="too short"):
        decode_input(prof.input, bytes([1, 0, 0]))
    assert prof.output is not None
    out = encode_output(prof.output, 1.5, -0.25, 100.0)  # 100 N clips at int16 max
    assert out[0] == 2 and len(out) == 7
    assert struct.unpack("<hhh", out[1:]) == (1500, -250, 32767)


def test_bundled_rate_profile_is_big_endian_and_position_only() -> None:
    prof = load_hid_profile("example-joystick-rate")
    assert prof.output is None and not prof.limits.has_force_output
    v = decode_input(prof.input, bytes([1]) + struct.pack(">hhh", 32767, 0, -32767))
    assert v == pytest.approx((0.1, 0.0, 0.1), rel=1e-3)


def test_profile_device_reads_writes_and_faults_when_silent() -> None:
    prof = load_hid_profile("example-3dof-force")  # silence_timeout_s = 0.05
    port = FakePort([bytes([1]) + struct.pack("<iii", 1000, 2000, -3000)])
    dev = ProfileHidDevice(prof, CENTER, opener=opener_for(port))
    dev.open()
    assert dev.read(0.0) == pytest.approx((0.001, 0.002, 0.097))
    dev.write(1.0, 0.0, 0.0)
    assert port.written == []  # forces not enabled
    dev.enable_forces()
    dev.write(1.0, 0.0, -0.5)
    assert struct.unpack("<hhh", port.written[-1][1:]) == (1000, 0, -500)
    for k in range(1, 50):  # 49 ms of silence: still fine
        dev.read(k * 1e-3)
    assert dev.fault is None
    for k in range(50, 60):
        dev.read(k * 1e-3)
    assert dev.fault is not None and "no report" in dev.fault
    n = len(port.written)
    dev.write(1.0, 0.0, 0.0)
    dev.write(1.0, 0.0, 0.0)
    # the device must not keep its last force: one zero report, then nothing more
    assert len(port.written) == n + 1
    assert struct.unpack("<hhh", port.written[-1][1:]) == (0, 0, 0)
    dev.close()
    assert port.closed


def test_profile_device_write_error_sets_fault() -> None:
    prof = load_hid_profile("example-3dof-force")
    port = FakePort()
    dev = ProfileHidDevice(prof, CENTER, opener=opener_for(port))
    dev.open()
    dev.enable_forces()
    port.unplugged = True
    dev.write(0.5, 0.0, 0.0)
    assert dev.fault is not None and "write failed" in dev.fault


_RAW = (Path(__file__).parents[2] / "client/devices/profiles/example-3dof-force.json").read_text()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.pop("input"), "test.json: input: Field required"),
        (lambda d: d["input"]["axes"].pop(), r"input\.axes\[2\]: Field required"),
        (lambda d: d["input"]["axes"].append({}), "input.axes: Tuple should have at most 3 items"),
        (
            lambda d: d["input"]["axes"][0].update(type="int24"),
            r"input\.axes\[0\]\.type: Input should be 'int8', .* got 'int24'",
        ),
        (lambda d: d["input"]["axes"][1].update(endian="middle"), "endian"),
        (lambda d: d["input"]["axes"][2].update(scale=0), "non-zero"),
        (lambda d: d.update(vendor_id="0xzz"), "vendor_id"),
        (lambda d: d["output"].update(length=4), "past output.length"),
        (lambda d: d["limits"].update(max_force_n=-1), "max_force_n"),
        (lambda d: d["input"].update(mode="relative"), "input.mode"),
        (lambda d: d["input"]["axes"][0].update(scale="1e-6"), r"axes\[0\]\.scale: .*valid number"),
        (lambda d: d.update(output=[]), "output: Input should be a JSON object"),
    ],
)
def test_malformed_profiles_name_the_problem(edit, message: str) -> None:  # type: ignore[no-untyped-def]
    data = json.loads(_RAW)
    edit(data)
    with pytest.raises(ProfileError, match=message):
        parse_hid_profile(data, "test.json")


def test_every_problem_in_a_profile_is_named_at_once() -> None:
    data = json.loads(_RAW)
    data["input"]["axes"][1]["endian"] = "middle"
    data["limits"]["workspace_size_m"] = [0.1, 0.0, 0.1]
    with pytest.raises(ProfileError) as info:
        parse_hid_profile(data, "test.json")
    msg = str(info.value)
    assert msg.startswith("test.json: input.axes[1].endian: ")
    assert "; limits.workspace_size_m[1]: Input should be greater than 0, got 0.0" in msg


def test_a_profile_may_omit_the_optional_keys_and_carry_unknown_ones() -> None:
    data = json.loads(_RAW)
    for key in ("description", "output", "silence_timeout_s"):
        data.pop(key)
    for ax in data["input"]["axes"]:
        ax.pop("endian")
        ax.pop("offset_m")
    data["input"].pop("mode")
    data["limits"].pop("damping_n_s_per_m")
    data["comment"] = "ignored"
    prof = parse_hid_profile(data, "test.json")
    assert prof.input.mode == "absolute" and prof.silence_timeout_s == 0.1
    assert prof.output is None and not prof.limits.has_force_output
    assert prof.limits.damping_n_s_per_m == 0.0 and prof.description == ""
    report = bytes([1]) + struct.pack("<iii", 1, 2, 3)  # little-endian by default
    assert decode_input(prof.input, report) == pytest.approx((1e-6, 2e-6, 3e-6))


def test_missing_or_invalid_profile_files(tmp_path: Path) -> None:
    with pytest.raises(ProfileError, match="example-3dof-force"):
        load_hid_profile("no-such-profile")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ProfileError, match="not valid JSON"):
        load_hid_profile(bad)


def test_haptic_devices_lists_each_attached_hid_device_once_with_what_it_is(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """hidapi's enumeration (one entry per interface) becomes one line per device and kind."""
    import hid

    def info(vid: int, pid: int, product: str | None, interface: int = 0) -> dict[str, Any]:
        return {
            "vendor_id": vid,
            "product_id": pid,
            "manufacturer_string": "maker" if product else None,
            "product_string": product,
            "interface_number": interface,
        }

    attached = [
        info(0x256F, 0xC635, "SpaceMouse Compact"),
        info(0x256F, 0xC635, "SpaceMouse Compact", interface=1),  # same device, second interface
        info(0x1209, 0x0001, "3-DoF force device"),  # the example-3dof-force profile's ids
        info(0x046D, 0xC077, None),  # a mouse: neither
    ]
    monkeypatch.setattr(hid, "enumerate", lambda *a: attached)
    devs = list_devices()
    assert [d["spec"] for d in devs] == ["hid:256f:c635", "hid:1209:0001", "hid:046d:c077"]
    assert [d["kind"] for d in devs] == ["spacemouse", "profile:example-3dof-force", "unsupported"]
    assert devs[0]["product"] == "SpaceMouse Compact" and devs[2]["product"] == ""
    assert json.loads(json.dumps(devs)) == devs  # `haptic devices --json` prints them as they are


def test_no_hid_backend_lists_nothing_rather_than_failing(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import hid

    def broken(*a: object) -> list[dict[str, Any]]:
        raise OSError("hidapi: no backend")

    monkeypatch.setattr(hid, "enumerate", broken)
    assert list_devices() == []


@pytest.mark.hardware
@pytest.mark.skipif(
    not os.environ.get("HAPTIC_HID_DEVICE"), reason="set HAPTIC_HID_DEVICE=VID:PID to run"
)
def test_real_hid_device_reports_a_position() -> None:
    vid, pid = parse_hid_ids(os.environ["HAPTIC_HID_DEVICE"])
    dev = make_device(f"hid:{vid:04x}:{pid:04x}", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    dev.open()
    try:
        for k in range(200):
            x = dev.read(k * 1e-3)
        assert dev.fault is None
        assert all(math.isfinite(xi) for xi in x)
    finally:
        dev.close()
