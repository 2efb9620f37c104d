"""Builders several test modules share: a resting servo, emulator libraries, TOML refusals."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable, Sequence
from pathlib import Path

import pytest

from haptic_collab.client.devices import make_device
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.shared.primitives import make_plane

Vec3 = tuple[float, float, float]


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
