"""The openhaptics backend (client/devices/openhaptics.py) driving the real pyOpenHaptics binding
against an emulator of libHD.

The emulator is our own C (tests/support/emulators/hd_sim.c, written from the public HD API
signatures): a simulated device, a 1 kHz scheduler thread, frames, an error FIFO, the driver's
safety errors, and hooks to set the stylus and read the force at the "motors". It is compiled
here with ``cc`` (skipped without one) into a temporary folder as ``libHD.so``.

Every test that loads the library runs in its own Python process (this file run as a script:
``python test_openhaptics_backend.py SCENARIO ARGS``) with ``LD_LIBRARY_PATH`` on that folder,
the way a user's process finds the real libHD. Not in the pytest process, because:

- a shared library cannot be unloaded, and the binding keeps it from its import on: the other
  tests (test_devices.py, test_device_backends.py) must keep seeing what CI has, a machine
  without libHD, where the openhaptics backend is unavailable;
- the emulator's state (an initialized device, a scheduler thread, queued errors) and the
  binding's module state would leak from one test to the next;
- a scenario that hangs in C (a scheduler that never returns) is killed by the timeout instead
  of taking the whole session down.

Each scenario prints one ``RESULT {json}`` line; the tests assert on it what a user would notice.
Exercised: the real pyOpenHaptics Python code (library loading, init_device, get_model, the limit
getters, start/stop_scheduler, close_device) and our ctypes calls into the emulated libHD from a
real scheduler thread. Not exercised: the real libHD, a real device, the HD scheduler's real
timing (docs/device-openhaptics.md).
"""

from __future__ import annotations

import asyncio
import ctypes
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.client.devices.backends import HID_STANDOFF_M, DeviceError, DeviceOptions
from haptic_collab.client.devices.openhaptics import BACKEND, OpenHapticsDevice
from tests.support.helpers import c_compiler, compile_shared_library

ROOT = Path(__file__).resolve().parents[2]
EMULATOR_C = Path(__file__).resolve().parents[1] / "support" / "emulators" / "hd_sim.c"
RESULT = "RESULT "
ANCHOR = (0.01, -0.02, 0.1)
NORMAL = (0.0, 0.0, 1.0)

#: The emulator's defaults (hd_sim.c): a "Touch" with these nominal limits.
SIM_MAX_FORCE_N = 3.3
SIM_CONTINUOUS_N = 0.88
SIM_STIFFNESS_N_PER_MM = 0.4
SIM_DAMPING_N_PER_MM_S = 0.004
SIM_VELOCITY_MM_S = 800.0

HD_EXCEEDED_MAX_FORCE = 0x0201
HD_EXCEEDED_MAX_VELOCITY = 0x0203
HD_WARM_MOTORS = 0x0200


def expected_world(
    p_mm: tuple[float, float, float],
    workspace_mm: tuple[float, ...],
    scale: float,
    anchor: tuple[float, float, float] = ANCHOR,
    normal: tuple[float, float, float] = NORMAL,
) -> tuple[float, float, float]:
    """Where a stylus at ``p_mm`` (device frame: x right, y up, z toward the user) is in the world
    (z up, y away from the user), worked out here from the documented mapping."""
    c = [(workspace_mm[i] + workspace_mm[i + 3]) / 2 for i in range(3)]
    d = [(p_mm[i] - c[i]) / 1000.0 for i in range(3)]
    centre = [anchor[i] + HID_STANDOFF_M * normal[i] for i in range(3)]
    return (centre[0] + scale * d[0], centre[1] - scale * d[2], centre[2] + scale * d[1])


# -- the scenarios (run in a child process that has the emulator on its LD_LIBRARY_PATH) ----------


def _emulator() -> Any:
    """The emulated libHD's test hooks (the same library the binding loads: same SONAME)."""
    lib = ctypes.CDLL("libHD.so")
    d3 = [ctypes.c_double] * 3
    lib.sim_set_position.argtypes = d3
    lib.sim_set_velocity.argtypes = d3
    lib.sim_get_force.argtypes = [ctypes.POINTER(ctypes.c_double)]
    lib.sim_set_model.argtypes = [ctypes.c_char_p]
    lib.sim_set_device_name.argtypes = [ctypes.c_char_p]
    lib.sim_set_limits.argtypes = [ctypes.c_double] * 5
    lib.sim_set_usable_workspace.argtypes = [ctypes.POINTER(ctypes.c_double)]
    lib.sim_inject_error.argtypes = [ctypes.c_uint]
    for name in ("sim_ticks", "sim_frames", "sim_violations"):
        getattr(lib, name).restype = ctypes.c_ulong
    return lib


def _force(lib: Any) -> list[float]:
    f = (ctypes.c_double * 3)()
    lib.sim_get_force(f)
    return [f[0], f[1], f[2]]


def _state(lib: Any) -> dict[str, Any]:
    return {
        "scheduler_running": lib.sim_scheduler_running(),
        "initialized": lib.sim_initialized(),
        "force_output": lib.sim_force_output(),
        "callbacks_active": lib.sim_callbacks_active(),
        "violations": lib.sim_violations(),
        "force": _force(lib),
    }


def _until(pred: Callable[[], bool], timeout_s: float = 2.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.001)
    return pred()


def _limits(dev: Any) -> dict[str, Any]:
    lim = dev.limits
    return {
        "max_force_n": lim.max_force_n,
        "max_continuous_force_n": lim.max_continuous_force_n,
        "max_stiffness_n_per_m": lim.max_stiffness_n_per_m,
        "max_damping_n_s_per_m": lim.max_damping_n_s_per_m,
        "max_velocity_m_s": lim.max_velocity_m_s,
        "workspace_min_m": list(lim.workspace_min_m),
        "workspace_max_m": list(lim.workspace_max_m),
        "sources": dict(dev.hd_limits.sources),
        "model": dev.model,
        "name": dev.name,
    }


def _opened(spec: str, anchor: Any = ANCHOR, normal: Any = NORMAL) -> Any:
    from haptic_collab.client.devices.opener import DeviceOpener

    opener = DeviceOpener(spec)
    opener.check()
    return opener.build(anchor, normal)


def scenario_lazy(args: dict[str, Any]) -> dict[str, Any]:
    import haptic_collab.client.devices.openhaptics as oh

    out: dict[str, Any] = {
        "binding_imported_by_module": "pyOpenHaptics" in sys.modules,
        "libhd_loaded_by_module": "libHD.so" in Path("/proc/self/maps").read_text(),
    }
    out["available"] = oh.BACKEND.available()
    out["libhd_loaded_by_available"] = "libHD.so" in Path("/proc/self/maps").read_text()
    import pyOpenHaptics.hd_define as hd_define

    names = [n for n in dir(oh) if n.startswith("HD_") and hasattr(hd_define, n)]
    out["codes_compared"] = len(names)
    out["codes_differing"] = [n for n in names if getattr(oh, n) != getattr(hd_define, n)]
    return out


def scenario_unavailable(args: dict[str, Any]) -> dict[str, Any]:
    if args.get("block_binding"):
        sys.modules["pyOpenHaptics"] = None  # type: ignore[assignment]  # as if not installed
    from haptic_collab.client.devices.backends import DeviceError
    from haptic_collab.client.devices.opener import DeviceOpener, list_devices
    from haptic_collab.client.devices.openhaptics import BACKEND

    out: dict[str, Any] = {"available": BACKEND.available()}
    try:
        DeviceOpener("openhaptics").check()
        out["opener"] = None
    except DeviceError as exc:
        out["opener"] = str(exc)
    entry = [d for d in list_devices() if d["kind"] == "backend" and d["name"] == "openhaptics"]
    out["listed"] = {k: entry[0][k] for k in ("available", "message", "devices")}
    return out


def scenario_open_read_write(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    lib.sim_set_usable_workspace((ctypes.c_double * 6)(*args["workspace_mm"]))
    lib.sim_set_position(*args["position_mm"])
    lib.sim_set_velocity(*args["velocity_mm_s"])
    lib.sim_set_buttons(args["buttons"])
    from haptic_collab.client.devices.opener import DeviceOpener

    out: dict[str, Any] = {}
    opener = DeviceOpener(args["spec"])
    opener.check()
    out["after_check"] = _state(lib)  # initialized before the network, scheduler not yet
    dev: Any = opener.build(args["anchor"], args["normal"])
    out["after_build"] = _state(lib)
    out["position"] = list(dev.read(0.0))
    out["buttons"] = dev.buttons()
    out["velocity_m_s"] = list(dev.velocity_m_s)
    out["limits"] = _limits(dev)
    f_world = args["force_world_n"]
    dev.write(*f_world)  # forces not enabled yet: nothing reaches the motors
    time.sleep(0.02)
    out["force_before_enable"] = _force(lib)
    dev.enable_forces()
    dev.write(*f_world)
    _until(lambda: any(_force(lib)))
    out["force_enabled"] = _force(lib)
    dev.disable_forces()
    _until(lambda: not any(_force(lib)))
    out["force_after_disable"] = _force(lib)
    lib.sim_set_position(*args["moved_mm"])
    lib.sim_set_buttons(0)
    time.sleep(0.02)
    out["moved"] = list(dev.read(0.1))
    out["buttons_released"] = dev.buttons()
    ticks0, t0 = lib.sim_frames(), time.monotonic()
    time.sleep(0.2)
    out["frames_per_s"] = (lib.sim_frames() - ticks0) / (time.monotonic() - t0)
    out["fault"] = dev.fault
    dev.close()
    out["after_close"] = _state(lib)
    dev.close()  # twice is fine
    out["read_after_close"] = list(dev.read(0.2))
    dev.write(1.0, 0.0, 0.0)  # ignored, no error
    out["after_second_close"] = _state(lib)
    return out


def scenario_limits(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    lib.sim_set_model(args["model"].encode())
    lib.sim_set_limits(*args["limits"])
    lib.sim_set_usable_workspace((ctypes.c_double * 6)(*args["workspace_mm"]))
    from haptic_collab.client.devices.opener import DeviceOpener

    opener = DeviceOpener(args["spec"])
    opener.check()
    dev = opener.build(ANCHOR, NORMAL)
    out = _limits(dev)
    dev.close()
    out["after_close"] = _state(lib)
    return out


def scenario_hd_error(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    lib.sim_set_position(5.0, 10.0, -5.0)
    dev = _opened("openhaptics")
    dev.enable_forces()
    kind = args["kind"]
    fz = 10.0 if kind == "force" else 1.0  # 10 N up: more than the device's 3.3 N
    dev.write(0.0, 0.0, fz)
    if kind != "force":
        _until(lambda: any(_force(lib)))
        if kind == "velocity":
            lib.sim_set_velocity(0.0, 0.0, 1500.0)  # 1.5 m/s: above the 0.8 m/s the driver allows
        else:
            lib.sim_inject_error(args["code"])
    before = list(dev.read(0.0))
    t = 0.0
    while dev.fault is None and t < 2.0:
        t += 0.001
        dev.read(t)
        dev.write(0.0, 0.0, fz)  # the servo loop keeps writing
        time.sleep(0.001)
    out: dict[str, Any] = {"fault": dev.fault, "position_before": before}
    lib.sim_set_velocity(0.0, 0.0, 0.0)
    lib.sim_set_position(50.0, 50.0, 20.0)  # a faulted device keeps its last position
    for _ in range(20):
        dev.write(0.0, 0.0, 1.0)
        out["position_after"] = list(dev.read(t))
        time.sleep(0.001)
    out["while_faulted"] = _state(lib)
    dev.close()
    out["after_close"] = _state(lib)
    return out


def scenario_unplug(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    lib.sim_set_position(0.0, 0.0, 0.0)
    dev = _opened("openhaptics")
    dev.enable_forces()
    dev.write(0.0, 0.0, 1.0)
    _until(lambda: any(_force(lib)))
    lib.sim_unplug(1)
    _until(lambda: dev.read(0.0) is not None and dev.fault is not None)
    out: dict[str, Any] = {"fault": dev.fault, "unplugged": _state(lib)}
    try:
        out["reopen_unplugged"] = dev.reopen()
    except OSError as exc:
        out["reopen_unplugged"] = f"OSError: {exc}"
    out["fault_after_failed_reopen"] = dev.fault
    lib.sim_unplug(0)
    lib.sim_set_position(0.0, 10.0, 0.0)
    out["reopen_replugged"] = dev.reopen()
    out["fault_after_reopen"] = dev.fault
    out["position_after_reopen"] = list(dev.read(1.0))
    dev.write(0.0, 0.0, 1.0)  # forces stay enabled across the reopen
    _until(lambda: any(_force(lib)))
    out["force_after_reopen"] = _force(lib)
    dev.close()
    out["after_close"] = _state(lib)
    return out


def scenario_frozen(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    dev = _opened("openhaptics")
    lib.sim_freeze(1)  # the scheduler stops calling back, with no error
    t0 = time.monotonic()
    _until(lambda: dev.read(0.0) is not None and dev.fault is not None, 3.0)
    out: dict[str, Any] = {"fault": dev.fault, "after_s": time.monotonic() - t0}
    dev.close()
    out["after_close"] = _state(lib)
    return out


def scenario_init_failure(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    from haptic_collab.client.devices.backends import DeviceError
    from haptic_collab.client.devices.opener import DeviceOpener

    out: dict[str, Any] = {}
    for case, spec, unplug in (
        ("unknown_name", "openhaptics:Left Arm", 0),
        ("unplugged", "openhaptics", 1),
    ):
        lib.sim_unplug(unplug)
        try:
            DeviceOpener(spec).check()
            out[case] = None
        except DeviceError as exc:
            out[case] = str(exc)
        out[f"{case}_state"] = _state(lib)
    lib.sim_unplug(0)
    import pyOpenHaptics.hd as hd

    out["binding_init_returns"] = hd.init_device("Left Arm")  # the binding does not notice
    hd._lib_hd.hdGetError.restype = hd.HDErrorInfo
    hd._lib_hd.hdGetError()
    lib.sim_set_device_name(b"Left Arm")  # now configured under that name
    dev = _opened("openhaptics:Left Arm")
    out["named_device"] = {"name": dev.name, "fault": dev.fault}
    dev.close()
    out["after_close"] = _state(lib)
    return out


def scenario_unplaced(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    from haptic_collab.client.devices.opener import DeviceOpener

    opener = DeviceOpener("openhaptics")
    opener.check()
    out = {"checked": _state(lib)}
    opener.close()  # the client stopped before the welcome
    out["released"] = _state(lib)
    return out


def scenario_detect(args: dict[str, Any]) -> dict[str, Any]:
    lib = _emulator()
    from haptic_collab.client.devices.opener import list_devices

    found = list_devices()
    return {
        "devices": [
            d for d in found if d.get("backend") == "openhaptics" and d["kind"] != "backend"
        ],
        "backend": [d for d in found if d["kind"] == "backend" and d["name"] == "openhaptics"][0],
        "after": _state(lib),
    }


SCENARIOS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    name.removeprefix("scenario_"): fn
    for name, fn in dict(globals()).items()
    if name.startswith("scenario_") and callable(fn)
}


# -- the tests (pytest process: never loads libHD) -------------------------------------------------


@pytest.fixture(scope="module")
def libhd(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding the emulator compiled as ``libHD.so``."""
    cc = c_compiler(
        "no C compiler (cc) on PATH: the libHD emulator tests/support/emulators/hd_sim.c is "
        "compiled at test time (install gcc or clang)"
    )
    out = tmp_path_factory.mktemp("libhd")
    compile_shared_library(
        cc,
        out / "libHD.so",
        [EMULATOR_C],
        flags=["-Wall", "-Wl,-soname,libHD.so"],
        libs=["-lpthread"],
    )
    return out


def run_scenario(
    name: str, libdir: Path, args: dict[str, Any] | None = None, timeout_s: float = 60.0
) -> dict[str, Any]:
    """Run ``scenario_NAME(args)`` in a new Python with ``libdir`` first on LD_LIBRARY_PATH."""
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = os.pathsep.join(
        p for p in (str(libdir), env.get("LD_LIBRARY_PATH", "")) if p
    )
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), name, json.dumps(args or {})],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout_s,
    )  # fmt: skip
    lines = [line for line in proc.stdout.splitlines() if line.startswith(RESULT)]
    if proc.returncode != 0 or not lines:
        pytest.fail(
            f"scenario {name} exited {proc.returncode}\n--- stdout\n{proc.stdout[-3000:]}\n"
            f"--- stderr\n{proc.stderr[-5000:]}"
        )
    result: dict[str, Any] = json.loads(lines[-1][len(RESULT) :])
    return result


def assert_released(state: dict[str, Any]) -> None:
    """The scheduler stopped, our callback gone, the device disabled, no force, no HD rule broken."""
    assert state == {
        "scheduler_running": 0,
        "initialized": 0,
        "force_output": 0,
        "callbacks_active": 0,
        "violations": 0,
        "force": [0.0, 0.0, 0.0],
    }


def test_the_module_imports_without_the_binding_and_available_loads_it(libhd: Path) -> None:
    r = run_scenario("lazy", libhd)
    assert r["binding_imported_by_module"] is False
    assert r["libhd_loaded_by_module"] is False
    assert r["available"] is None  # pyOpenHaptics imports and our libHD loads
    assert r["libhd_loaded_by_available"] is True
    assert r["codes_compared"] >= 12 and r["codes_differing"] == []


@pytest.mark.parametrize("block_binding", [False, True], ids=["no libHD", "no pyOpenHaptics"])
def test_without_the_library_available_says_one_line_what_to_install(
    tmp_path: Path, block_binding: bool
) -> None:
    r = run_scenario("unavailable", tmp_path, {"block_binding": block_binding})  # an empty folder
    if r["available"] is None:
        pytest.skip("a real libHD.so is installed on this machine")
    msg = r["available"]
    assert "\n" not in msg
    assert "pip install 'pyOpenHaptics>=1.0.1'" in msg
    assert "OpenHaptics driver from 3D Systems" in msg
    if block_binding:
        assert msg.startswith("the openhaptics backend needs the pyOpenHaptics package")
    else:
        assert msg.startswith("the openhaptics backend cannot load libHD.so")
    assert r["opener"] == msg  # haptic client stops with exactly that line, before any network
    assert r["listed"] == {"available": False, "message": msg, "devices": []}


def test_in_this_process_the_backend_is_unavailable_with_one_line() -> None:
    # the pytest process never loads libHD (see the module docstring), as on CI
    msg = BACKEND.available()
    if msg is None:
        pytest.skip("a real libHD.so is installed on this machine")
    assert "\n" not in msg and "pip install 'pyOpenHaptics>=1.0.1'" in msg


def test_open_read_write_in_metres_newtons_and_the_world_frame(libhd: Path) -> None:
    ws = (-80.0, -40.0, -35.0, 80.0, 80.0, 35.0)  # mm; its centre is (0, 20, 0)
    args: dict[str, Any] = {
        "spec": "openhaptics:Default Device,scale=2",
        "anchor": ANCHOR,
        "normal": NORMAL,
        "workspace_mm": ws,
        "position_mm": (10.0, 35.0, -30.0),
        "velocity_mm_s": (100.0, 50.0, -20.0),
        "buttons": 3,
        "force_world_n": (1.0, 0.5, -0.25),
        "moved_mm": (-20.0, 20.0, 10.0),
    }
    r = run_scenario("open_read_write", libhd, args)
    # DeviceOpener.check() (before the network) initialized the device, no scheduler yet
    assert r["after_check"]["initialized"] == 1 and r["after_check"]["scheduler_running"] == 0
    assert r["after_build"]["scheduler_running"] == 1 and r["after_build"]["callbacks_active"] == 1
    # the stylus 10 mm right, 15 mm above the centre, 30 mm away from the user (z = -30), scale 2:
    # 2 cm x, 6 cm y (away), 3 cm z (up) from a centre 2 cm above the anchor
    assert r["position"] == pytest.approx(expected_world(args["position_mm"], ws, 2.0), abs=1e-12)
    assert r["position"] == pytest.approx((0.03, 0.04, 0.15), abs=1e-12)
    assert r["moved"] == pytest.approx(expected_world(args["moved_mm"], ws, 2.0), abs=1e-12)
    # velocity: mm/s -> m/s, rotated, scaled
    assert r["velocity_m_s"] == pytest.approx((0.2, 0.04, 0.1), abs=1e-12)
    assert r["buttons"] == 3 and r["buttons_released"] == 0
    # a world force reaches the motors in newtons, device frame (x, z, -y of the world's)
    assert r["force_before_enable"] == [0.0, 0.0, 0.0]
    assert r["force_enabled"] == pytest.approx((1.0, -0.25, -0.5), abs=1e-12)
    assert r["force_after_disable"] == [0.0, 0.0, 0.0]
    # the workspace in the world: device box * 2 around the centre, axes rotated
    lim = r["limits"]
    assert lim["workspace_min_m"] == pytest.approx((0.01 - 0.16, -0.02 - 0.07, 0.12 - 0.12))
    assert lim["workspace_max_m"] == pytest.approx((0.01 + 0.16, -0.02 + 0.07, 0.12 + 0.12))
    # our callback ran, tick after tick, on the emulator's scheduler (a count, not a rate claim:
    # on a loaded machine the callback waits for the GIL)
    assert r["frames_per_s"] > 20
    assert r["fault"] is None
    assert_released(r["after_close"])
    assert_released(r["after_second_close"])
    assert r["read_after_close"] == r["moved"]


@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_limits_come_from_the_sdk_with_the_scale_folded_in(libhd: Path, scale: float) -> None:
    sdk = (3.7, 1.1, 0.55, 0.0035, 600.0)  # N, N, N/mm, N/(mm/s), mm/s: not CHAI3D's values
    ws = (-100.0, -50.0, -40.0, 100.0, 70.0, 40.0)
    spec = "openhaptics" if scale == 1.0 else f"openhaptics:scale={scale:g}"
    r = run_scenario(
        "limits", libhd, {"spec": spec, "model": "Touch", "limits": sdk, "workspace_mm": ws}
    )
    assert r["model"] == "Touch" and r["name"] == f"{spec} (Touch)"
    assert r["max_force_n"] == pytest.approx(3.7)
    assert r["max_continuous_force_n"] == pytest.approx(1.1)
    assert r["max_stiffness_n_per_m"] == pytest.approx(550.0 / scale)  # N/mm -> N/m, / S
    assert r["max_damping_n_s_per_m"] == pytest.approx(3.5 / scale)  # N/(mm/s) -> N*s/m, / S
    assert r["max_velocity_m_s"] == pytest.approx(0.8 * 0.6 * scale)  # 80 % of the driver's
    size = [b - a for a, b in zip(r["workspace_min_m"], r["workspace_max_m"], strict=True)]
    assert size == pytest.approx((0.2 * scale, 0.08 * scale, 0.12 * scale))
    assert set(r["sources"].values()) == {"sdk"}
    assert_released(r["after_close"])


def test_limits_fall_back_to_chai3d_when_the_sdk_returns_zero(libhd: Path) -> None:
    r = run_scenario(
        "limits",
        libhd,
        {
            "spec": "openhaptics",
            "model": "PHANTOM Omni",
            "limits": (0.0, 0.0, 0.0, float("nan"), 0.0),
            "workspace_mm": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        },
    )
    # CHAI3D 3.3.0 CPhantomDevices.cpp, "PHANTOM Omni": 3.3 N, 700 N/m, 5 N*s/m, radius 0.10 m
    assert r["max_force_n"] == 3.3 and r["max_stiffness_n_per_m"] == 700.0
    assert r["max_damping_n_s_per_m"] == 5.0 and r["max_continuous_force_n"] is None
    assert r["max_velocity_m_s"] == 0.5
    size = [b - a for a, b in zip(r["workspace_min_m"], r["workspace_max_m"], strict=True)]
    assert size == pytest.approx((0.2, 0.2, 0.2))
    assert r["sources"]["max_force_n"] == "chai3d" and r["sources"]["workspace"] == "chai3d"
    assert_released(r["after_close"])


@pytest.mark.parametrize(
    ("kind", "code", "name"),
    [
        ("force", HD_EXCEEDED_MAX_FORCE, "HD_EXCEEDED_MAX_FORCE"),
        ("velocity", HD_EXCEEDED_MAX_VELOCITY, "HD_EXCEEDED_MAX_VELOCITY"),
        ("injected", HD_WARM_MOTORS, "HD_WARM_MOTORS"),
    ],
)
def test_an_hd_error_in_the_servo_callback_is_a_fault_with_zero_force(
    libhd: Path, kind: str, code: int, name: str
) -> None:
    r = run_scenario("hd_error", libhd, {"kind": kind, "code": code})
    assert r["fault"] is not None and "\n" not in r["fault"]
    assert f"HD error 0x{code:04x} {name}" in r["fault"] and r["fault"].endswith("forces off")
    # the motors show zero force and stay there though the servo loop keeps writing; our
    # callback unscheduled itself (the binding's @hd_callback would have raised KeyError)
    assert r["while_faulted"]["force"] == [0.0, 0.0, 0.0]
    assert r["while_faulted"]["callbacks_active"] == 0
    assert r["position_after"] == r["position_before"]  # the last position, no exception
    assert_released(r["after_close"])


def test_an_unplugged_device_faults_and_reopens_when_it_is_back(libhd: Path) -> None:
    r = run_scenario("unplug", libhd)
    assert "HD_COMM_ERROR" in r["fault"] and "unplugged" in r["fault"]
    assert r["unplugged"]["force"] == [0.0, 0.0, 0.0]
    assert r["reopen_unplugged"].startswith("OSError: cannot open openhaptics: hdInitDevice(")
    assert "HD_COMM_ERROR" in r["reopen_unplugged"]
    assert r["fault_after_failed_reopen"] == r["fault"]
    assert r["reopen_replugged"] is True and r["fault_after_reopen"] is None
    assert r["position_after_reopen"] == pytest.approx(
        expected_world((0.0, 10.0, 0.0), (-80, -60, -35, 80, 60, 35), 1.0)
    )
    assert r["force_after_reopen"] == pytest.approx((0.0, 1.0, 0.0))  # world z up = device y
    assert_released(r["after_close"])


def test_a_scheduler_that_stops_calling_back_is_a_fault(libhd: Path) -> None:
    r = run_scenario("frozen", libhd)
    assert r["fault"] is not None and "scheduler has not run" in r["fault"]
    # not before the 0.5 s the backend allows a silent scheduler (how late is the machine's)
    assert r["after_s"] > 0.4
    assert_released(r["after_close"])


def test_a_device_that_cannot_be_initialized_is_one_line_before_the_network(libhd: Path) -> None:
    r = run_scenario("init_failure", libhd)
    # the binding returns HD_INVALID_HANDLE without a word: the backend checks it
    assert r["binding_init_returns"] == 0xFFFFFFFF
    msg = r["unknown_name"]
    assert msg.startswith("cannot open openhaptics:Left Arm: hdInitDevice('Left Arm') failed (")
    assert "HD_COMM_CONFIG_ERROR" in msg and "Touch Setup" in msg and "\n" not in msg
    assert r["unplugged"].startswith("cannot open openhaptics: hdInitDevice('Default Device')")
    assert "HD_COMM_ERROR" in r["unplugged"]
    for case in ("unknown_name_state", "unplugged_state"):
        assert r[case]["initialized"] == 0 and r[case]["scheduler_running"] == 0
    assert r["named_device"] == {"name": "openhaptics:Left Arm (Touch)", "fault": None}
    assert_released(r["after_close"])


def test_a_device_checked_but_never_placed_is_released(libhd: Path) -> None:
    r = run_scenario("unplaced", libhd)
    assert r["checked"]["initialized"] == 1 and r["checked"]["scheduler_running"] == 0
    assert_released(r["released"])


def test_haptic_devices_lists_the_attached_device(libhd: Path) -> None:
    r = run_scenario("detect", libhd)
    assert r["backend"]["available"] is True and r["backend"]["message"] is None
    assert r["devices"] == [
        {
            "spec": "openhaptics",
            "kind": "openhaptics",
            "backend": "openhaptics",
            "device_name": "Default Device",
            "model": "Touch",
            "vendor": "3D Systems (simulated)",
            "max_force_n": SIM_MAX_FORCE_N,
            "max_continuous_force_n": SIM_CONTINUOUS_N,
            "max_stiffness_n_per_m": pytest.approx(SIM_STIFFNESS_N_PER_MM * 1000),
        }
    ]
    assert_released(r["after"])  # detection lets go of the device


# -- in this process: what needs no library ----------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "name", "scale"),
    [
        ("", "Default Device", 1.0),
        ("Default Device", "Default Device", 1.0),
        ("PHANToM 2", "PHANToM 2", 1.0),
        ("Left Arm,scale=0.5", "Left Arm", 0.5),
        ("scale=3", "Default Device", 3.0),
        (",scale=1.5", "Default Device", 1.5),
    ],
)
def test_the_spec_names_the_device_and_the_scale(args: str, name: str, scale: float) -> None:
    dev = BACKEND.open(args, DeviceOptions())  # acquire=False: no library touched
    assert isinstance(dev, OpenHapticsDevice)
    assert (dev.device_name, dev.scale) == (name, scale)
    placed = BACKEND.place(dev, ANCHOR, NORMAL)
    assert placed is dev
    centre = (ANCHOR[0], ANCHOR[1], ANCHOR[2] + HID_STANDOFF_M)
    lo, hi = dev.limits.workspace_min_m, dev.limits.workspace_max_m
    assert [(a + b) / 2 for a, b in zip(lo, hi, strict=True)] == pytest.approx(centre)
    assert dev.read(0.0) == pytest.approx(centre)  # not opened: the centre, no error
    dev.write(1.0, 0.0, 0.0)
    dev.close()
    dev.close()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ("Default Device,gain=2", "unknown option 'gain' in 'openhaptics:Default Device,gain=2'"),
        (
            "scale=0",
            "bad workspace scale in 'openhaptics:scale=0': '0' (need a number > 0 and <= 100",
        ),
        ("scale=101", "bad workspace scale in 'openhaptics:scale=101'"),
        ("scale=big", "bad workspace scale in 'openhaptics:scale=big'"),
        ("scale=inf", "bad workspace scale"),
        ("A,B", "names two devices"),
    ],
)
def test_a_bad_spec_is_a_one_line_device_error(args: str, message: str) -> None:
    with pytest.raises(DeviceError, match="^[^\n]*$") as info:
        BACKEND.open(args, DeviceOptions())
    assert message in str(info.value)


def test_limits_scale_like_the_world_the_user_feels() -> None:
    from haptic_collab.client.devices.openhaptics_limits import HdLimits, world_limits

    base = HdLimits.from_sdk(
        "Touch",
        max_force=3.3,
        max_continuous_force=0.88,
        max_stiffness_n_per_mm=0.4,
        max_damping_n_per_mm_s=0.004,
        velocity_limit_mm_s=500.0,
        usable_workspace_mm=(-80, -60, -35, 80, 60, 35),
    )
    for s in (0.5, 1.0, 4.0):
        lim = world_limits(base, s, (0.0, 0.0, 0.0))
        # a stylus displacement x is s * x in the world: a world spring K feels K * s at the stylus
        assert lim.max_stiffness_n_per_m * s == pytest.approx(400.0)
        assert lim.max_damping_n_s_per_m * s == pytest.approx(4.0)
        assert lim.max_velocity_m_s / s == pytest.approx(0.4)
        assert (lim.max_force_n, lim.max_continuous_force_n) == (3.3, 0.88)
        assert lim.workspace_max_m == pytest.approx((0.08 * s, 0.035 * s, 0.06 * s))


# -- end to end: haptic client --device openhaptics against an in-process server ------------------------


@pytest.mark.slow
async def test_haptic_client_with_an_openhaptics_device_feels_the_object(
    libhd: Path, tmp_path: Path
) -> None:
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.main import ServerOptions, build_world
    from haptic_collab.server.room import Room
    from tests.support.processes import haptic, load_csv

    world = build_world(ServerOptions(sim_rate_hz=20.0, subdivisions=3))
    app = ServerApp(Room(world, 20.0), "127.0.0.1", 0)
    await app.start()
    try:
        env = dict(os.environ)
        env["LD_LIBRARY_PATH"] = os.pathsep.join(
            p for p in (str(libhd), env.get("LD_LIBRARY_PATH", "")) if p
        )
        # the stylus held 23 mm below the workspace centre: 3 mm into the object's top
        env["HD_SIM_POSITION"] = "0,-23,0"
        env["HD_SIM_REPORT"] = str(tmp_path / "motors.json")  # what the motors displayed
        cmd = haptic(
            "client", "--url", f"ws://127.0.0.1:{app.port}/ws", "--name", "A",
            "--device", "openhaptics", "--anchor", "top", "--engage", "auto",
            "--duration", "2.5", "--record", str(tmp_path / "a.csv"),
            "--summary", str(tmp_path / "a.json"),
        )  # fmt: skip
        proc = await asyncio.create_subprocess_exec(
            *cmd, cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=subprocess.STDOUT
        )
        out, _ = await asyncio.wait_for(proc.communicate(), 120.0)
    finally:
        await app.stop()
    assert proc.returncode == 0, out.decode()[-3000:]
    summary = json.loads((tmp_path / "a.json").read_text())
    rec = load_csv(tmp_path / "a.csv")
    top = summary["anchor"]["point_m"]
    assert summary["anchor"]["normal"] == [0.0, 0.0, 1.0]
    assert summary["device_faults"] == 0, out.decode()[-3000:]
    assert summary["servo"]["ticks"] > 500
    # the probe is where the stylus is, in the world: 3 mm under the top
    assert rec["probe_z_m"][-1] == pytest.approx(top[2] - 0.003, abs=1e-9)
    assert rec["probe_x_m"][-1] == pytest.approx(top[0], abs=1e-9)
    # and the user is pushed up, out of the object: world z up is the device's y
    late = rec["t_s"] > rec["t_s"][-1] - 0.5
    assert float(rec["force_z_n"][late].mean()) > 0.1
    motors = json.loads((tmp_path / "motors.json").read_text().splitlines()[-1])
    fx, fy, fz = motors["peak_force"]
    # (the motors show the servo loop's latest force at each HD tick: a sample may be skipped)
    assert 0.8 * float(rec["force_z_n"].max()) <= fy <= float(rec["force_z_n"].max()) + 1e-9
    assert fy > 0.1 and abs(fx) < 0.05 * fy and abs(fz) < 0.05 * fy
    assert motors["last_frame_force"] == [0.0, 0.0, 0.0]  # close() sent a zero-force frame
    assert motors["violations"] == 0 and motors["frames"] > 500


if __name__ == "__main__":
    _name, _args = sys.argv[1], json.loads(sys.argv[2]) if len(sys.argv) > 2 else {}
    _result = SCENARIOS[_name](_args)
    print(RESULT + json.dumps(_result), flush=True)
