"""The ``forcedimension`` device backend, driving the real forcedimension-core binding against an
emulator of the Force Dimension SDK's library.

What runs: the installed forcedimension-core Python code (its library search, its version check,
its ctypes declarations of every symbol, its dhd functions) and our backend, against
tests/support/emulators/fd_sim.c, our own C emulator of libdrd written from the public function
signatures. The fixture compiles it with ``cc``, adds ``int NAME(void){return -1;}`` for every
other dhd*/drd* symbol the installed binding binds (found by scanning its source, so a new binding
version still loads), and installs the result where the binding looks for the SDK:
``$FDSDK/lib/release/lin-<machine>-gcc/libdrd.so.3.17.6``. What does not run: the real SDK, a
real device, USB.

Why a subprocess per test: forcedimension-core loads libdrd when it is first imported and keeps it
for the life of the process (it cannot be re-imported against another library, or without one
once it has one). Each test therefore runs the binding-dependent part in a fresh Python process
(the small scripts :data:`HOOKS` and :data:`HARNESS` plus the test's own lines) with FDSDK set,
and checks what that process reports; the pytest process never imports the binding with the emulator, so other tests
(and the "no library" case) are unaffected.
"""

from __future__ import annotations

import dataclasses
import glob
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.client.devices import forcedimension as fd
from haptic_collab.client.devices.backends import DeviceError, DeviceOptions
from tests.support.helpers import c_compiler, compile_shared_library

ROOT = Path(__file__).resolve().parents[2]
EMULATOR_C = Path(__file__).resolve().parents[1] / "support" / "emulators" / "fd_sim.c"
#: The file name the binding accepts (libdrd.so.*, SDK 3.16 or newer; the emulator says 3.17.6).
LIBRARY_NAME = "libdrd.so.3.17.6"
INSTALL = "pip install 'forcedimension-core>=1.0' (the forcedimension extra; in a checkout: pip install -e '.[forcedimension]')"

ANCHOR = (0.01, -0.02, 0.1)
NORMAL = (0.0, 0.0, 1.0)
#: Workspace centre: 2 cm (HID_STANDOFF_M) outside the anchor.
CENTER = (0.01, -0.02, 0.12)


def _binding_dir() -> Path | None:
    spec = importlib.util.find_spec("forcedimension_core")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def bound_symbols(package: Path) -> set[str]:
    """Every ``dhd*``/``drd*`` symbol the binding's source binds (``_libdhd.NAME``/``_libdrd.NAME``)."""
    names: set[str] = set()
    for path in package.rglob("*.py"):
        text = path.read_text(encoding="utf-8", errors="replace")
        names.update(re.findall(r"_lib(?:dhd|drd)\.((?:dhd|drd)\w+)", text))
    return names


def defined_symbols(c_source: str) -> set[str]:
    """The ``dhd*``/``drd*`` functions a C file defines (a definition starts a line)."""
    return set(re.findall(r"^[A-Za-z_][\w \t*]*?\b((?:dhd|drd)\w+)\s*\(", c_source, re.M))


@pytest.fixture(scope="module")
def fdsdk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An FDSDK folder holding the emulator built as libdrd (skips without cc or the binding)."""
    cc = c_compiler(
        "no C compiler (cc) on PATH to build the libdrd emulator tests/support/emulators/fd_sim.c"
    )
    if sys.version_info[:2] >= fd.MAX_PYTHON:
        pytest.skip("forcedimension-core supports Python < 3.13 only")
    package = _binding_dir()
    if package is None:
        pytest.skip(f"forcedimension-core is not installed ({INSTALL})")
    bound = bound_symbols(package)
    assert len(bound) > 50, f"found only {len(bound)} bound symbols in {package}: layout changed?"
    source = EMULATOR_C.read_text(encoding="utf-8")
    defined = defined_symbols(source)
    assert {"dhdOpen", "dhdGetPosition", "dhdSetForce", "dhdGetSDKVersion"} <= defined
    root = tmp_path_factory.mktemp("fdsdk")
    stubs = root / "not_emulated.c"
    stubs.write_text(
        "/* generated: every other symbol the binding binds fails (-1) */\n"
        + "".join(f"int {name}(void){{return -1;}}\n" for name in sorted(bound - defined)),
        encoding="utf-8",
    )
    lib_dir = root / "lib" / "release" / f"lin-{platform.machine()}-gcc"
    lib_dir.mkdir(parents=True)
    compile_shared_library(cc, lib_dir / LIBRARY_NAME, [EMULATOR_C, stubs])
    return root


#: Start of a subprocess with the emulator: its test hooks (the same library the binding loads:
#: one dlopen by the same path).
HOOKS = '''
import ctypes, glob, os

lib = glob.glob(os.path.join(os.environ["FDSDK"], "lib", "release", "*", "libdrd.so.*"))[0]
sim = ctypes.CDLL(lib)
sim.sim_set_position.argtypes = [ctypes.c_double] * 3
sim.sim_set_velocity.argtypes = [ctypes.c_double] * 3
sim.sim_set_buttons.argtypes = [ctypes.c_uint]
sim.sim_set_type.argtypes = [ctypes.c_int, ctypes.c_char_p]
sim.sim_set_max_force.argtypes = [ctypes.c_double]
for _hook in ("sim_set_attached", "sim_fail_position", "sim_fail_velocity", "sim_fail_force"):
    getattr(sim, _hook).argtypes = [ctypes.c_int]


def force():
    """The force [N] the emulated device displays now, device frame."""
    buf = (ctypes.c_double * 3)()
    sim.sim_get_force(buf)
    return list(buf)
'''

#: Start of every subprocess: the backend, and ``out`` (printed as JSON at the end).
HARNESS = """
import dataclasses, json

from haptic_collab.client.devices.backends import DeviceError, list_backends
from haptic_collab.client.devices.opener import DeviceOpener, make_device
from haptic_collab.client.devices.forcedimension import BACKEND

ANCHOR = (0.01, -0.02, 0.1)
NORMAL = (0.0, 0.0, 1.0)
out = {}
"""


def run_fd(fdsdk: Path | None, body: str, home: Path) -> tuple[dict[str, Any], str]:
    """Run ``body`` after :data:`HOOKS` and :data:`HARNESS` in a new Python process; its ``out``
    and its stderr.

    ``fdsdk`` None: no FDSDK and no hooks (the binding finds no library); HOME is ``home`` so
    that ``~/.local/lib`` holds no libdrd either.
    """
    env = {k: v for k, v in os.environ.items() if k not in ("FDSDK", "FORCEDIM_SDK")}
    env["HOME"] = str(home)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    prelude = HARNESS
    if fdsdk is not None:
        env["FDSDK"] = str(fdsdk)
        prelude = HOOKS + HARNESS
    script = prelude + textwrap.dedent(body) + "\nprint(json.dumps(out))\n"
    proc = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, f"subprocess failed:\n{proc.stderr}"
    return json.loads(proc.stdout.strip().splitlines()[-1]), proc.stderr


def _approx3(v: Any, expected: Any, tol: float = 1e-12) -> bool:
    return all(abs(a - b) <= tol for a, b in zip(v, expected, strict=True))


# -- without the library ----------------------------------------------------------------------------


def test_without_libdrd_available_says_one_line_and_prints_nothing(tmp_path: Path) -> None:
    if glob.glob("/usr/local/lib/libdrd.so*"):
        pytest.skip("a libdrd is installed in /usr/local/lib: the binding would find it")
    if _binding_dir() is None or sys.version_info[:2] >= fd.MAX_PYTHON:
        pytest.skip("forcedimension-core is not importable here")
    out, stderr = run_fd(
        None,
        """
        out["available"] = BACKEND.available()
        try:
            DeviceOpener("forcedimension:0").check()
        except DeviceError as exc:
            out["check"] = str(exc)
        entry = [b for b in list_backends() if b["name"] == "forcedimension"][0]
        out["listed"] = [entry["available"], entry["message"]]
        """,
        tmp_path,
    )
    msg = out["available"]
    assert isinstance(msg, str) and msg and "\n" not in msg
    assert INSTALL in msg and "Force Dimension SDK" in msg and "FDSDK" in msg
    assert "libdrd" in msg
    # haptic client stops with exactly that line; haptic devices lists it
    assert out["check"] == msg
    assert out["listed"] == [False, msg]
    # the binding's "Could not find libdrd" went nowhere near the terminal
    assert stderr == ""


def test_python_313_or_newer_is_refused_without_importing_the_binding(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(fd, "MAX_PYTHON", (3, 0))
    monkeypatch.setattr(fd, "_dhd", None)
    msg = fd.BACKEND.available()
    assert msg is not None and "\n" not in msg
    assert "Python < 3.0" in msg and INSTALL in msg and "FDSDK" in msg
    assert fd._dhd is None


# -- the spec -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        ("", (None, 1.0)),
        ("0", (0, 1.0)),
        ("2", (2, 1.0)),
        ("scale=2", (None, 2.0)),
        ("1,scale=0.5", (1, 0.5)),
        ("1:scale=0.5", (1, 0.5)),
        ("scale=3,0", (0, 3.0)),
    ],
)
def test_spec_syntax(args: str, expected: tuple[int | None, float]) -> None:
    assert fd.parse_args(args) == expected


@pytest.mark.parametrize(
    ("args", "what"),
    [
        ("abc", "'abc' is not understood"),
        ("0:1", "'1' is not understood"),
        ("-1", "'-1' is not understood"),
        ("200", "bad device index"),
        ("scale=0", "bad workspace scale"),
        ("scale=-2", "bad workspace scale"),
        ("scale=nan", "bad workspace scale"),
        ("scale=big", "bad workspace scale"),
        ("scale=1,scale=2", "'scale=2' is not understood"),
        ("0,,scale=2", "'' is not understood"),
    ],
)
def test_bad_specs_say_the_syntax_in_one_line(args: str, what: str) -> None:
    with pytest.raises(DeviceError) as info:
        fd.BACKEND.open(args, DeviceOptions())
    msg = str(info.value)
    assert "\n" not in msg and what in msg
    assert "forcedimension:ID" in msg and ",scale=S" in msg


def test_placement_and_scale_fold_into_the_world_limits_before_any_hardware() -> None:
    dev = fd.BACKEND.open("scale=2", DeviceOptions())  # acquire=False: the SDK is not touched
    assert isinstance(dev, fd.ForceDimensionDevice) and dev.device_id is None
    placed = fd.BACKEND.place(dev, ANCHOR, NORMAL)
    assert placed is dev and dev.center == pytest.approx(CENTER)
    lim = dev.limits  # CHAI3D's default model until open() reads the real one
    assert lim.max_stiffness_n_per_m == pytest.approx(5000.0 / 2)
    assert lim.max_velocity_m_s == pytest.approx(fd.MAX_VELOCITY_M_S * 2)
    assert lim.workspace_max_m[2] - lim.workspace_min_m[2] == pytest.approx(4 * 0.075)
    dev.close()
    dev.close()  # safe twice, never opened


# -- with the emulator ------------------------------------------------------------------------------


def test_a_falcon_reads_writes_and_closes_in_the_world_frame(fdsdk: Path, tmp_path: Path) -> None:
    out, stderr = run_fd(
        fdsdk,
        """
        # FD frame: 1 cm toward the user, 2 cm right, 3 cm down; moving; buttons 0 and 2 held
        sim.sim_set_position(0.01, 0.02, -0.03)
        sim.sim_set_velocity(0.1, 0.2, 0.3)
        sim.sim_set_buttons(0b101)
        out["available"] = BACKEND.available()
        out["detect"] = BACKEND.detect()
        dev = make_device("forcedimension:0,scale=2", ANCHOR, NORMAL)
        out["opens_by_make_device"] = sim.sim_opens()
        dev.open()
        out["name"] = dev.name
        out["limits"] = dataclasses.asdict(dev.limits)
        out["position"] = dev.read(0.0)
        out["velocity"] = dev.velocity_m_s
        out["buttons"] = dev.buttons()
        dev.write(1.0, -2.0, 0.5)
        out["force_while_disabled"] = force()
        dev.enable_forces()
        out["force_mode"] = sim.sim_force_enabled()
        dev.write(1.0, -2.0, 0.5)  # world: 1 N right, 2 N toward the user, 0.5 N up
        out["force"] = force()
        dev.disable_forces()
        out["after_disable"] = [force(), sim.sim_force_enabled()]
        dev.enable_forces()
        dev.write(0.0, 0.0, 3.0)
        dev.close()
        dev.close()
        out["closed"] = [sim.sim_opens(), sim.sim_closes(), sim.sim_force_enabled(), sim.sim_open_id()]
        out["force_after_close"] = force()
        out["read_after_close"] = dev.read(0.1)
        out["fault"] = dev.fault
        """,
        tmp_path,
    )
    assert stderr == ""
    assert out["available"] is None
    assert out["detect"] == [{"spec": "forcedimension:0", "index": 0}]
    assert out["opens_by_make_device"] == 0  # make_device does not touch the hardware
    assert "Novint Falcon" in out["name"]
    # world = centre + 2 * (y_d, -x_d, z_d)
    assert _approx3(out["position"], (0.01 + 0.04, -0.02 - 0.02, 0.12 - 0.06))
    assert _approx3(out["velocity"], (0.4, -0.2, 0.6))
    assert out["buttons"] == 0b101
    assert out["force_while_disabled"] == [0.0, 0.0, 0.0]
    assert out["force_mode"] == 1
    assert out["force"] == [2.0, 1.0, 0.5]  # (-fy, fx, fz) in newtons, not scaled
    assert out["after_disable"] == [[0.0, 0.0, 0.0], 0]
    lim = out["limits"]
    assert lim["max_force_n"] == 8.0  # the Falcon's (no SDK software limit set)
    assert lim["max_stiffness_n_per_m"] == pytest.approx(3000.0 / 2)
    assert lim["max_damping_n_s_per_m"] == pytest.approx(20.0 / 2)
    assert lim["max_velocity_m_s"] == pytest.approx(fd.MAX_VELOCITY_M_S * 2)
    assert lim["damping_n_s_per_m"] == 0.0
    assert lim["max_continuous_force_n"] is None
    assert lim["has_force_output"] is True
    assert lim["workspace_min_m"] == pytest.approx([c - 0.08 for c in CENTER])
    assert lim["workspace_max_m"] == pytest.approx([c + 0.08 for c in CENTER])
    assert out["closed"] == [1, 1, 0, -1]
    assert out["force_after_close"] == [0.0, 0.0, 0.0]
    assert _approx3(out["read_after_close"], tuple(out["position"]))
    assert out["fault"] is None


def test_limits_follow_the_model_and_the_sdk_force_limit(fdsdk: Path, tmp_path: Path) -> None:
    out, _ = run_fd(
        fdsdk,
        """
        from haptic_collab.client.devices.forcedimension import ForceDimensionDevice
        CENTER = (0.01, -0.02, 0.12)
        for system_type, name in ((33, b"omega.3"), (63, b"delta.3"), (104, b"sigma.7"),
                                  (206, b"sigma.3"), (60, b"falcon")):
            sim.sim_set_type(system_type, name)
            sim.sim_set_max_force(5.0 if system_type == 60 else -1.0)
            dev = ForceDimensionDevice(None, 1.0, CENTER)
            dev.open()
            lim = dev.limits
            out[str(system_type)] = [dev.name, lim.max_force_n, lim.max_stiffness_n_per_m,
                                     lim.max_damping_n_s_per_m,
                                     lim.workspace_max_m[0] - CENTER[0], dev.read(0.0)]
            dev.close()
        sim.sim_set_type(-1, None)  # dhdGetSystemType fails: the binding raises ValueError
        dev = ForceDimensionDevice(None, 1.0, CENTER)
        try:
            dev.open()
        except OSError as exc:
            out["no_type"] = [type(exc).__name__, str(exc)]
        out["released"] = [sim.sim_opens(), sim.sim_closes(), sim.sim_open_id()]
        """,
        tmp_path,
    )
    origin = tuple(CENTER)
    assert out["33"][:5] == ["forcedimension (omega.3)", 12.0, 5000.0, 30.0, pytest.approx(0.075)]
    assert out["63"][:5] == ["forcedimension (delta.3)", 20.0, 5000.0, 30.0, pytest.approx(0.15)]
    assert out["104"][:5] == [
        "forcedimension (sigma.7 right)",
        12.0,
        4000.0,
        30.0,
        pytest.approx(0.075),
    ]
    # sigma.3 is not in CHAI3D's table: its default model, named after the SDK's name
    assert out["206"][:5] == [
        "forcedimension (Force Dimension device (sigma.3))",
        12.0,
        5000.0,
        30.0,
        pytest.approx(0.075),
    ]
    assert out["60"][1:4] == [5.0, 3000.0, 20.0]  # dhdGetMaxForce's 5 N caps the Falcon's 8 N
    for key in ("33", "63", "206", "60"):
        assert _approx3(out[key][5], origin)
    # sigma.7 right: CHAI3D's workspace offset (-0.01, 0.02, 0) [FD frame], rotated into the world
    assert _approx3(out["104"][5], (CENTER[0] + 0.02, CENTER[1] + 0.01, CENTER[2]))
    assert out["no_type"] == [
        "DeviceOpenError",
        "cannot open forcedimension: cannot read the device type: simulated communication error",
    ]
    assert out["released"] == [6, 6, -1]  # the device whose type failed was closed again


def test_a_failing_read_faults_zeroes_the_force_and_recovers_after_a_replug(
    fdsdk: Path, tmp_path: Path
) -> None:
    out, stderr = run_fd(
        fdsdk,
        """
        opener = DeviceOpener("forcedimension")
        opener.check()  # before the network: the device is opened and held
        out["opens_after_check"] = sim.sim_opens()
        dev = opener.build(ANCHOR, NORMAL)
        out["opens_after_build"] = sim.sim_opens()  # the same session, not opened twice
        sim.sim_set_position(0.0, 0.0, 0.01)
        out["before"] = dev.read(0.0)
        dev.enable_forces()
        dev.write(0.0, 0.0, 3.0)
        out["force"] = force()
        sim.sim_set_position(0.0, 0.0, 0.02)
        sim.sim_fail_position(1)
        out["faulted_read"] = dev.read(0.001)
        out["fault"] = dev.fault
        out["force_after_fault"] = force()
        dev.write(0.0, 0.0, 3.0)
        out["force_after_write"] = force()
        # unplugged: reopen keeps failing; plugged back: the device answers again
        sim.sim_fail_position(0)
        sim.sim_set_attached(0)
        try:
            dev.reopen()
        except OSError as exc:
            out["reopen_absent"] = str(exc)
        out["fault_while_absent"] = dev.fault is not None
        sim.sim_set_attached(1)
        out["reopen"] = dev.reopen()
        out["after_reopen"] = [dev.fault, dev.device_id, sim.sim_open_id(), sim.sim_force_enabled()]
        out["read_after_reopen"] = dev.read(0.002)
        dev.write(0.0, 0.0, 1.5)
        out["force_after_reopen"] = force()
        # a failing dhdSetForce is a fault too; a velocity estimator timeout is not
        sim.sim_fail_velocity(1)
        dev.read(0.003)
        out["velocity_timeout"] = [dev.fault, dev.velocity_errors]
        sim.sim_fail_force(1)
        dev.write(0.0, 0.0, 1.0)
        out["write_fault"] = dev.fault
        sim.sim_fail_force(0)
        dev.close()
        dev.close()
        out["closed"] = [sim.sim_closes(), sim.sim_open_id(), sim.sim_force_enabled(), force()]
        # a device that is not there: one line before any network
        try:
            DeviceOpener("forcedimension:3").check()
        except DeviceError as exc:
            out["absent"] = str(exc)
        # the client stops before the welcome: the held device is released
        early = DeviceOpener("forcedimension:0")
        early.check()
        early.close()
        out["released_early"] = [sim.sim_open_id(), sim.sim_closes()]
        """,
        tmp_path,
    )
    assert stderr == ""
    assert out["opens_after_check"] == 1 and out["opens_after_build"] == 1
    assert _approx3(out["before"], (0.01, -0.02, 0.13))
    assert out["force"] == [0.0, 0.0, 3.0]
    assert _approx3(out["faulted_read"], tuple(out["before"]))  # the last position, kept
    assert out["fault"] == (
        "forcedimension (Novint Falcon): dhdGetPosition failed (simulated communication error); "
        "device unplugged or switched off?"
    )
    assert out["force_after_fault"] == [0.0, 0.0, 0.0]
    assert out["force_after_write"] == [0.0, 0.0, 0.0]
    assert "simulated: no device found" in out["reopen_absent"]
    assert out["fault_while_absent"] is True
    assert out["reopen"] is True
    assert out["after_reopen"] == [None, 1, 1, 1]  # a new SDK ID, used; force mode back on
    assert _approx3(out["read_after_reopen"], (0.01, -0.02, 0.14))
    assert out["force_after_reopen"] == [0.0, 0.0, 1.5]
    assert out["velocity_timeout"] == [None, 1]
    assert out["write_fault"].startswith("forcedimension (Novint Falcon): dhdSetForce failed (")
    assert out["closed"] == [2, -1, 0, [0.0, 0.0, 0.0]]
    absent = out["absent"]
    assert "\n" not in absent
    assert absent.startswith("cannot open forcedimension:3: simulated: invalid device index; ")
    assert "haptic devices" in absent
    assert out["released_early"] == [-1, 3]


def test_the_emulator_implements_only_functions_the_binding_declares() -> None:
    """Every function fd_sim.c defines has its signature from the binding's declarations."""
    package = _binding_dir()
    if package is None:
        pytest.skip(f"forcedimension-core is not installed ({INSTALL})")
    defined = defined_symbols(EMULATOR_C.read_text(encoding="utf-8"))
    assert defined <= bound_symbols(package)


def test_the_falcon_limits_are_chai3d_s() -> None:
    """CHAI3D 3.3.0's Falcon: 8 N, 3000 N/m, 20 N*s/m, 0.04 m workspace radius."""
    falcon = fd.MODELS[60]
    assert dataclasses.astuple(falcon)[:5] == ("Novint Falcon", 8.0, 3000.0, 20.0, 0.04)
    assert falcon.source == "chai3d 3.3.0 src/devices/CDeltaDevices.cpp:1132-1146"
