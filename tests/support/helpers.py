"""Builders several test modules share: a resting servo, a scripted servo device and its lab
limits, emulator libraries, TOML refusals."""

from __future__ import annotations

import math
import shutil
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.client.devices.base import Device, DeviceLimits
from haptic_collab.client.devices.opener import make_device
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.shared.primitives import Plane, make_plane

Vec3 = tuple[float, float, float]

SERVO_PERIOD_S = 1e-3  # the servo period [s] of ServoConfig's default 1 kHz
SERVO_RAMP_S = 0.05  # the safety ramp [s] of the scripted servo core


def resting_servo(anchor: Vec3, normal: Vec3, k_h: float = 250.0) -> ServoCore:
    """A servo core with forces on and the plane through ``anchor`` [m] (outward ``normal``) as its
    patch, K_h = ``k_h`` [N/m], no integral term; its device is a simulated hand (``sim:rest``)
    that comes from outside in 0.2 s and rests 2 mm inside the plane. Not ticked yet."""
    dev = make_device("sim:rest", anchor, normal, trajectory_options={"approach_s": 0.2})
    dev.open()
    core = ServoCore(dev, ServoConfig(link_timeout_s=float("inf")))
    core.enable_forces()
    core.set_patch(make_plane(anchor, normal), k_h, 0.0)
    return core


def lab_limits(*, max_velocity_m_s: float, **overrides: Any) -> DeviceLimits:
    """The limits of the tests' lab device: 7.9 N, 1000 N/m, 0.5 N*s/m of its own damping, a
    workspace of +-1 m on each axis, no virtual damping unless ``overrides`` gives
    ``max_damping_n_s_per_m``; the probe speed limit ``max_velocity_m_s`` [m/s] differs between
    the tests, so each states it. ``overrides`` replaces any other field."""
    values: dict[str, Any] = {
        "max_force_n": 7.9,
        "max_stiffness_n_per_m": 1000.0,
        "max_velocity_m_s": max_velocity_m_s,
        "damping_n_s_per_m": 0.5,
        "workspace_min_m": (-1.0, -1.0, -1.0),
        "workspace_max_m": (1.0, 1.0, 1.0),
    }
    return DeviceLimits(**(values | overrides))


class ScriptedDevice(Device):
    """A handle at ``path(tick index)``; records the z force written at each tick."""

    def __init__(
        self,
        path: Callable[[int], float] = lambda n: -0.005,
        *,
        max_damping_n_s_per_m: float = 10.0,
    ) -> None:
        self.name = "scripted"
        self.limits = lab_limits(max_velocity_m_s=1.0, max_damping_n_s_per_m=max_damping_n_s_per_m)
        self.fault: str | None = None
        self.path = path
        self.n = 0
        self.z: list[float] = []  # where the handle was at each tick
        self.fz: list[float] = []
        self.writes: list[Vec3] = []

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read(self, t_s: float) -> Vec3:
        z = self.path(self.n)
        self.n += 1
        self.z.append(z)
        return (0.0, 0.0, z)

    def write(self, fx: float, fy: float, fz: float) -> None:
        self.writes.append((fx, fy, fz))
        self.fz.append(fz)

    def enable_forces(self) -> None:
        pass

    def disable_forces(self) -> None:
        pass


def scripted_core(dev: ScriptedDevice, *, passivity: bool = False) -> ServoCore:
    """A servo core on ``dev`` with forces on, a ``SERVO_RAMP_S`` safety ramp and a link that
    never times out; no patch yet."""
    core = ServoCore(
        dev, ServoConfig(ramp_s=SERVO_RAMP_S, link_timeout_s=math.inf, passivity=passivity)
    )
    core.enable_forces()
    return core


def run(core: ServoCore, ticks: int) -> None:
    """Tick ``core`` ``ticks`` times, each at its own tick index times ``SERVO_PERIOD_S``."""
    for _ in range(ticks):
        n = core.status().ticks
        core.tick(n * SERVO_PERIOD_S)


def plane_at(depth_m: float) -> Plane:
    """The surface z = 0 (outward +z) moved ``depth_m`` outward (+z)."""
    return make_plane((0.0, 0.0, depth_m), (0.0, 0.0, 1.0))


def max_step(values: Sequence[float]) -> float:
    """The largest change [same unit] between consecutive ``values``, either way."""
    return max(abs(b - a) for a, b in zip(values, values[1:], strict=False))


def c_compiler(why: str) -> str:
    """The path of ``cc``; without one, skip the test with ``why``."""
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip(why)
    return cc


def compile_shared_library(
    cc: str,
    output: Path,
    sources: Sequence[Path],
    flags: Sequence[str] = (),
    libs: Sequence[str] = (),
) -> None:
    """Build ``output`` with ``cc -shared -fPIC -O1 FLAGS -o OUTPUT SOURCES LIBS``; a failed build
    fails the test with the compiler's messages."""
    build = subprocess.run(
        [cc, "-shared", "-fPIC", "-O1", *flags, "-o", str(output), *map(str, sources), *libs],
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, f"cannot compile {', '.join(map(str, sources))}:\n{build.stderr}"


def assert_broken_and_missing_toml_refused(
    load: Callable[[Path], object], error: type[Exception], broken: Path
) -> None:
    """``load`` refuses the invalid TOML file ``broken`` naming it, and a missing file beside it."""
    with pytest.raises(error, match="not a valid TOML file") as err:
        load(broken)
    assert broken.name in str(err.value)
    with pytest.raises(error, match="does not exist"):
        load(broken.parent / "absent.toml")


class FakeDevice(Device):
    """A device whose handle is wherever the test puts it; records every write."""

    def __init__(self, position: Vec3 = (0.0, 0.0, 0.0), max_force_n: float = 7.9) -> None:
        self.name = "fake"
        self.limits = lab_limits(max_force_n=max_force_n, max_velocity_m_s=0.5)
        self.fault: str | None = None
        self.position = position
        self.enabled = False
        self.writes: list[Vec3] = []
        self.displayed: Vec3 = (0.0, 0.0, 0.0)

    def open(self) -> None:
        pass

    def close(self) -> None:
        self.disable_forces()

    def read(self, t_s: float) -> Vec3:
        return self.position

    def write(self, fx: float, fy: float, fz: float) -> None:
        self.writes.append((fx, fy, fz))
        if self.enabled:
            self.displayed = (fx, fy, fz)

    def enable_forces(self) -> None:
        self.enabled = True

    def disable_forces(self) -> None:
        self.enabled = False
        self.displayed = (0.0, 0.0, 0.0)
