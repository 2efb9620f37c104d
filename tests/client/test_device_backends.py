"""Device backends (docs/devices.md): a lab's own device found through the entry-point group
``haptic_collab.devices``, unknown prefixes, a backend whose vendor library is missing, and the
built-in sim and hid backends with and without their entry points.

A lab's package is "installed" the way pip leaves it: a module and a ``*.dist-info`` folder with
METADATA and entry_points.txt, in a folder put on sys.path (importlib.metadata finds it there).
"""

from __future__ import annotations

import asyncio
import json
import re
import struct
import sys
import tomllib
from collections.abc import Iterator
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType

import pytest

from haptic_collab.cli import main
from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.client.devices import backends
from haptic_collab.client.devices.backends import DeviceError
from haptic_collab.client.devices.hid import ProfileHidDevice
from haptic_collab.client.devices.hid_backend import HID_BACKEND
from haptic_collab.client.devices.opener import DeviceOpener, list_devices, make_device
from haptic_collab.client.devices.sim import SimDevice
from haptic_collab.client.devices.sim_backend import SIM_BACKEND
from haptic_collab.client.devices.trajectories import Press, Rest

ROOT = Path(__file__).resolve().parents[2]
ANCHOR = (0.01, -0.02, 0.1)
NORMAL = (0.0, 0.0, 1.0)

#: What the lab's backend without its vendor library says (its available()).
NOSDK_MESSAGE = "nosdk needs the Acme haptics SDK (acme_haptics): pip install acme-haptics"

LABPKG = f'''
"""A lab's own device package, as a lab would write it (outside haptic_collab)."""

from haptic_collab.client.devices import Device, DeviceError, DeviceLimits
from haptic_collab.client.devices.backends import DeviceBackend

OFFSET_M = 0.004  # the fixed probe sits this far outside the anchor
CALLS = []  # (backend, args, options.acquire) of every open()


class FixedDevice(Device):
    """A probe that never moves."""

    def __init__(self, serial, position):
        self.serial = serial
        self.name = f"labdev:{{serial}}"
        self.position = position
        self.limits = DeviceLimits(
            4.0, 600.0, 1.0, 0.0, (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)
        ).centered_at(position)
        self.fault = None
        self.is_open = False

    def open(self):
        if self.serial == "unplugged":
            raise OSError("the arm does not answer")
        self.is_open = True

    def close(self):
        self.is_open = False

    def read(self, t_s):
        return self.position

    def write(self, fx, fy, fz):
        pass

    def enable_forces(self):
        pass

    def disable_forces(self):
        pass


class LabBackend(DeviceBackend):
    name = "labdev"
    description = "the lab's fixed probe: labdev:SERIAL"

    def detect(self):
        return [{{"spec": "labdev:bench-1", "serial": "bench-1"}}]

    def open(self, args, options):
        CALLS.append(("labdev", args, options.acquire))
        if not args:
            raise DeviceError("labdev needs the probe's serial: --device labdev:SERIAL")
        return FixedDevice(args, (0.0, 0.0, 0.0))

    def place(self, device, anchor, normal):
        return FixedDevice(
            device.serial, tuple(a + OFFSET_M * n for a, n in zip(anchor, normal))
        )


class NoSdkBackend:  # any object with the members will do; this one is given as a class
    name = "nosdk"
    description = "a device whose vendor library is not installed"

    def available(self):
        return {NOSDK_MESSAGE!r}

    def detect(self):
        raise AssertionError("detect() of a backend that is not available")

    def open(self, args, options):
        CALLS.append(("nosdk", args, options.acquire))
        raise AssertionError("open() of a backend that is not available")

    def place(self, device, anchor, normal):
        return device


BACKEND = LabBackend()
'''

LAB_ENTRY_POINTS = {
    "labdev": "labpkg:BACKEND",
    "nosdk": "labpkg:NoSdkBackend",
    "broken": "labpkg_gone:BACKEND",  # its module was uninstalled
}


def install(
    folder: Path,
    monkeypatch: pytest.MonkeyPatch,
    module: str,
    text: str,
    eps: dict[str, str],
) -> None:
    """Put ``module`` and its distribution's metadata (the entry points ``eps``) on sys.path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{module}.py").write_text(text, encoding="utf-8")
    info = folder / f"{module}-0.1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module}\nVersion: 0.1.0\n")
    lines = "".join(f"{name} = {value}\n" for name, value in eps.items())
    (info / "entry_points.txt").write_text(f"[{backends.ENTRY_POINT_GROUP}]\n{lines}")
    monkeypatch.syspath_prepend(str(folder))


@pytest.fixture
def labpkg(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    """The lab's package installed; yields its module (imported through the entry point)."""
    install(tmp_path / "site", monkeypatch, "labpkg", LABPKG, LAB_ENTRY_POINTS)
    try:
        backend = backends.get_backend("labdev")
        yield sys.modules[type(backend).__module__]
    finally:
        sys.modules.pop("labpkg", None)


def expected_probe(offset_m: float) -> tuple[float, float, float]:
    return tuple(a + offset_m * n for a, n in zip(ANCHOR, NORMAL, strict=True))  # type: ignore[return-value]


def backend_entry(devices: list[dict[str, object]], name: str) -> dict[str, object]:
    [entry] = [d for d in devices if d["kind"] == "backend" and d["name"] == name]
    return entry


# -- (a) a lab's own backend, found through its entry point ---------------------------------------


def test_a_labs_backend_opens_through_make_device_and_the_opener(labpkg: ModuleType) -> None:
    dev = make_device("labdev:bench-7", ANCHOR, NORMAL)
    assert type(dev).__name__ == "FixedDevice" and dev.name == "labdev:bench-7"
    assert labpkg.CALLS == [("labdev", "bench-7", False)]  # make_device does not acquire
    dev.open()
    assert dev.read(0.0) == pytest.approx(expected_probe(0.004))
    lo, hi = dev.limits.workspace_min_m, dev.limits.workspace_max_m
    assert all(a < p < b for a, p, b in zip(lo, expected_probe(0.004), hi, strict=True))

    opener = DeviceOpener("labdev:bench-7")
    opener.check()  # before any network: the backend is asked to acquire the hardware
    assert labpkg.CALLS[-1] == ("labdev", "bench-7", True)
    dev = opener.build(ANCHOR, NORMAL)
    assert dev.is_open  # type: ignore[attr-defined]  # build opened the placed device
    assert dev.read(0.0) == pytest.approx(expected_probe(0.004))
    opener.close()
    assert dev.is_open  # type: ignore[attr-defined]  # close() leaves a built device alone


def test_a_labs_device_that_cannot_be_used_is_a_one_line_device_error(labpkg: ModuleType) -> None:
    with pytest.raises(DeviceError) as info:
        DeviceOpener("labdev").check()
    assert str(info.value) == "labdev needs the probe's serial: --device labdev:SERIAL"
    opener = DeviceOpener("labdev:unplugged")
    opener.check()
    with pytest.raises(DeviceError) as info:
        opener.build(ANCHOR, NORMAL)
    assert str(info.value) == "cannot open labdev:unplugged: the arm does not answer"


def test_list_devices_lists_a_labs_backend_and_what_it_detects(
    labpkg: ModuleType, capsys: pytest.CaptureFixture[str]
) -> None:
    devices = list_devices()
    lab_device = {
        "spec": "labdev:bench-1",
        "serial": "bench-1",
        "kind": "labdev",
        "backend": "labdev",
    }
    assert lab_device in devices
    lab = backend_entry(devices, "labdev")
    assert lab == {
        "kind": "backend",
        "name": "labdev",
        "spec": "labdev:",
        "description": "the lab's fixed probe: labdev:SERIAL",
        "available": True,
        "message": None,
        "entry_point": "labpkg:BACKEND",
        "devices": [lab_device],
    }
    # the built-in entries keep their keys
    assert {d["profile"] for d in devices if d["kind"] == "sim"} == {"phantom-desktop", "touch"}
    assert backend_entry(devices, "sim")["available"] is True
    # a backend whose vendor library is missing says so, and is not asked to detect anything
    nosdk = backend_entry(devices, "nosdk")
    assert nosdk["available"] is False and nosdk["message"] == NOSDK_MESSAGE
    assert nosdk["devices"] == []
    # a backend whose module is gone is listed, not fatal
    broken = backend_entry(devices, "broken")
    assert broken["available"] is False
    assert str(broken["message"]).startswith(
        "cannot load device backend 'broken' (labpkg_gone:BACKEND): No module named 'labpkg_gone'"
    )
    # what `haptic devices --json` prints
    assert main(["devices", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert backend_entry(printed, "labdev") == lab and lab_device in printed


# -- (b) an unknown prefix --------------------------------------------------------------------------


def test_an_unknown_prefix_names_the_known_backends() -> None:
    for attempt in (
        lambda: DeviceOpener("usb:1:2").check(),
        lambda: make_device("usb:1:2", ANCHOR, NORMAL),
    ):
        with pytest.raises(DeviceError, match="^[^\n]*$") as info:
            attempt()
        msg = str(info.value)
        assert msg.startswith("unknown device spec 'usb:1:2': no device backend 'usb'; ")
        known = msg.split("known backends: ", 1)[1].split(" (", 1)[0].split(", ")
        assert known[:2] == ["hid", "sim"] and set(known) >= {"hid", "sim", "openhaptics", "haply"}


def test_an_unknown_prefix_names_the_installed_backends_too(labpkg: ModuleType) -> None:
    with pytest.raises(DeviceError) as info:
        DeviceOpener("labdevv:bench-1").check()
    known = str(info.value).split("known backends: ", 1)[1].split(" (", 1)[0].split(", ")
    assert known[:2] == ["hid", "sim"] and {"broken", "labdev", "nosdk"} <= set(known)


# -- (c) a backend whose vendor library is missing --------------------------------------------------


def test_a_backend_without_its_vendor_library_says_exactly_what_to_install(
    labpkg: ModuleType,
) -> None:
    with pytest.raises(DeviceError) as info:
        DeviceOpener("nosdk:arm-1").check()
    assert str(info.value) == NOSDK_MESSAGE
    with pytest.raises(DeviceError) as info:
        make_device("nosdk:arm-1", ANCHOR, NORMAL)
    assert str(info.value) == NOSDK_MESSAGE
    # haptic client stops there, before any network (nothing listens on port 9)
    opts = ClientOptions(url="ws://127.0.0.1:9/ws", device="nosdk:arm-1", join_timeout_s=30.0)
    with pytest.raises(DeviceError) as info:  # a join attempt would end in ConnectionError
        asyncio.run(run_client(opts))
    assert str(info.value) == NOSDK_MESSAGE
    assert not [c for c in labpkg.CALLS if c[0] == "nosdk"]  # open() was never called


def test_a_backend_that_cannot_be_loaded_is_a_one_line_device_error(labpkg: ModuleType) -> None:
    with pytest.raises(DeviceError, match="^[^\n]*$") as info:
        DeviceOpener("broken:x").check()
    assert str(info.value).startswith("cannot load device backend 'broken' (labpkg_gone:BACKEND)")
    assert "reinstall the package that provides it" in str(info.value)


# -- (d) the built-in backends, with and without their entry points ---------------------------------


def test_the_builtins_are_registered_as_entry_points() -> None:
    table = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    assert table[backends.ENTRY_POINT_GROUP] == backends.BUILTIN_BACKENDS  # the fallback agrees
    installed = {ep.name: ep for ep in entry_points(group=backends.ENTRY_POINT_GROUP)}
    assert "sim" in installed and "hid" in installed, "reinstall: pip install -e '.[dev]'"
    assert installed["sim"].load() is SIM_BACKEND
    assert installed["hid"].load() is HID_BACKEND


class FakePort:
    """A generic 3-DoF device (the bundled ``example-3dof-force`` profile) held at its origin."""

    def __init__(self) -> None:
        self.closed = False

    def read(self, max_length: int) -> list[int]:
        return list(bytes([1]) + struct.pack("<iii", 0, 0, 0))

    def write(self, data: bytes) -> int:
        return len(data)

    def close(self) -> None:
        self.closed = True


@pytest.fixture(params=["entry points only", "built-in fallback only"])
def builtins_found_by(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    if request.param == "entry points only":
        monkeypatch.setattr(backends, "BUILTIN_BACKENDS", {})
    else:  # a source checkout that was never (re)installed
        monkeypatch.setattr(backends, "entry_points", lambda **_: [])
    return str(request.param)


def test_the_builtins_work(builtins_found_by: str) -> None:
    assert {"hid", "sim"} <= set(backends.backend_names())
    dev = make_device("sim:press", ANCHOR, NORMAL)
    assert isinstance(dev, SimDevice) and isinstance(dev.trajectory, Press)
    assert dev.trajectory.anchor == ANCHOR

    opener = DeviceOpener("sim:rest", profile="touch")
    opener.check()
    sim = opener.build(ANCHOR, NORMAL)
    assert isinstance(sim, SimDevice) and isinstance(sim.trajectory, Rest)
    assert sim.trajectory.anchor == ANCHOR and sim.limits.max_force_n == 3.3

    ports: list[FakePort] = []

    def bus(vendor_id: int, product_id: int) -> FakePort:
        ports.append(FakePort())
        return ports[-1]

    opener = DeviceOpener("hid:1209:0001", hid_opener=bus)
    opener.check()
    assert len(ports) == 1  # opened before any network
    hid = opener.build(ANCHOR, NORMAL)
    assert isinstance(hid, ProfileHidDevice) and len(ports) == 1
    assert hid.read(0.0) == pytest.approx(expected_probe(0.02))  # 20 mm outside the anchor
    hid.close()
    assert ports[0].closed

    devices = list_devices()
    for name in ("hid", "sim"):
        entry = backend_entry(devices, name)
        assert entry["available"] is True
        if builtins_found_by == "entry points only":
            module = f"haptic_collab.client.devices.{name}_backend"
            assert entry["entry_point"] == f"{module}:{name.upper()}_BACKEND"
        else:
            assert entry["entry_point"] is None
    assert {d["profile"] for d in devices if d["kind"] == "sim"} == {"phantom-desktop", "touch"}


def test_a_stale_entry_point_for_a_builtin_falls_back_to_the_builtin(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    install(tmp_path, monkeypatch, "oldlab", "", {"sim": "oldlab_removed:SIM"})
    assert isinstance(make_device("sim:press", ANCHOR, NORMAL), SimDevice)
    DeviceOpener("sim:press").check()


# -- the example of docs/devices.md, as written there -----------------------------------------------


def docs_block(after: str, lang: str) -> str:
    text = (ROOT / "docs" / "devices.md").read_text(encoding="utf-8")
    found = re.search(re.escape(after) + r".*?```" + lang + r"\n(.*?)```", text, re.S)
    assert found is not None, f"docs/devices.md has no {lang} block after {after}"
    return found.group(1)


def test_the_example_of_the_docs_works_as_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    project = tomllib.loads(docs_block("`labpkg/pyproject.toml`:", "toml"))["project"]
    eps = project["entry-points"][backends.ENTRY_POINT_GROUP]
    install(tmp_path, monkeypatch, "labpkg", docs_block("`labpkg/labpkg.py`:", "python"), eps)
    try:
        opener = DeviceOpener("labdev:bench-1")
        opener.check()
        dev = opener.build(ANCHOR, NORMAL)
        assert dev.read(0.0) == pytest.approx(expected_probe(-0.005))  # 5 mm inside the object
        dev.enable_forces()
        dev.write(0.0, 0.0, 1.5)
        assert dev.arm.force == (0.0, 0.0, 1.5)  # type: ignore[attr-defined]
        dev.close()
        assert dev.arm is None and dev.fault is None  # type: ignore[attr-defined]

        with pytest.raises(DeviceError) as info:
            DeviceOpener("labdev:bench-9").check()
        line = str(info.value)
        assert line.startswith("cannot open labdev:bench-9: no arm with this serial is attached")
        assert f"haptic client: error: {line}" in (ROOT / "docs" / "devices.md").read_text()

        assert main(["devices", "--json"]) == 0
        entry = backend_entry(json.loads(capsys.readouterr().out), "labdev")
        assert entry == json.loads(docs_block("names its `backend`. Then it lists", "json"))
    finally:
        sys.modules.pop("labpkg", None)
