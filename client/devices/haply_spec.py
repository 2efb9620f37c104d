"""What a ``haply:`` spec says: the port, the workspace scale, the reply timeout and the limits.

``haptic client --device haply:PORT[,KEY=VALUE...]`` (docs/device-haply.md):
:func:`parse_haply_args` reads the ``ARGS`` into a :class:`HaplyConfig`, whose
:class:`Inverse3Specs` are the Inverse3's own limits (assumed defaults, each overridable by a
spec key) and fold into the world-frame :class:`client.devices.base.DeviceLimits` the servo loop
sees. Pure values: nothing here imports the vendor binding or touches a port (that is
:mod:`client.devices.haply`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

from haptic_collab.client.devices._vendor import workspace_scale
from haptic_collab.client.devices.backends import DeviceError, one_line
from haptic_collab.client.devices.base import DeviceLimits, Vec3

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "SPEC_LIMIT_OPTIONS",
    "SPEC_OPTIONS",
    "HaplyConfig",
    "Inverse3Specs",
    "parse_haply_args",
]

#: Longest wait [s] for one state reply in the servo loop (spec option ``timeout_ms``). The binding
#: waits up to this for the reply's first byte and again for the rest, so a silent device costs
#: one call of about twice this, once; then the device is faulted and stops waiting.
DEFAULT_TIMEOUT_S = 0.020


@dataclass(frozen=True, slots=True)
class Inverse3Specs:
    """The Inverse3's own limits, in its own frame and units, before any workspace scale.

    HaplyHardwareAPI reports no limits, and Haply's published specifications were not available
    to us, so every default is an **assumption**, chosen conservatively (Touch-class values)
    and overridable per spec (``haply:PORT,max_force_n=5``; docs/device-haply.md).

    Parameters
    ----------
    max_force_n : float
        Peak force [N] the servo loop may command (assumed 3.0).
    max_continuous_force_n : float or None
        Force [N] the device may hold indefinitely (assumed 1.0).
    max_stiffness_n_per_m : float
        Largest stiffness [N/m] rendered stably at 1 kHz with this backend's one-tick force delay
        (assumed 500; Haply's own HaplyHardwareAPI haptic-ball example renders 800 at 1 kHz).
    max_velocity_m_s : float
        Handle speed [m/s] above which the servo loop ramps forces down (assumed 0.5).
    damping_n_s_per_m : float
        The device's own damping [N*s/m] (unknown: 0).
    max_damping_n_s_per_m : float
        Largest virtual damping [N*s/m] the local model may add (assumed 2.0).
    workspace_center_m : (3,) float
        Centre [m] of the reachable box, device frame (assumed (0, -0.14, 0.20): where Haply's
        haptic-ball example puts the object to touch).
    workspace_half_m : (3,) float
        Half sizes [m] of the box (assumed 0.08 each: that example's ball radius).
    """

    max_force_n: float = 3.0
    max_continuous_force_n: float | None = 1.0
    max_stiffness_n_per_m: float = 500.0
    max_velocity_m_s: float = 0.5
    damping_n_s_per_m: float = 0.0
    max_damping_n_s_per_m: float = 2.0
    workspace_center_m: Vec3 = (0.0, -0.14, 0.20)
    workspace_half_m: Vec3 = (0.08, 0.08, 0.08)

    def world_limits(self, scale: float, center: Sequence[float]) -> DeviceLimits:
        """The limits in the world frame: device metres times ``scale`` around ``center`` [m].

        Stiffness and damping divide by ``scale`` (a world displacement is ``scale`` times the
        handle's), speed and workspace multiply by it, forces are unchanged.

        Raises
        ------
        ValueError
            A non-positive scale, or limits :class:`DeviceLimits` refuses.
        """
        h = self.workspace_half_m
        return (
            DeviceLimits(
                max_force_n=self.max_force_n,
                max_stiffness_n_per_m=self.max_stiffness_n_per_m,
                max_velocity_m_s=self.max_velocity_m_s,
                damping_n_s_per_m=self.damping_n_s_per_m,
                workspace_min_m=(-h[0], -h[1], -h[2]),
                workspace_max_m=(h[0], h[1], h[2]),
                max_damping_n_s_per_m=self.max_damping_n_s_per_m,
                max_continuous_force_n=self.max_continuous_force_n,
            )
            .scaled(scale)
            .centered_at(center)
        )


#: Spec options that override an :class:`Inverse3Specs` value (device frame, unscaled).
SPEC_LIMIT_OPTIONS = (
    "max_force_n",
    "max_continuous_force_n",
    "max_stiffness_n_per_m",
    "max_velocity_m_s",
    "damping_n_s_per_m",
    "max_damping_n_s_per_m",
)
#: Every spec option (``haply:PORT,KEY=VALUE,...``).
SPEC_OPTIONS = ("scale", "timeout_ms", *SPEC_LIMIT_OPTIONS)


@dataclass(frozen=True, slots=True)
class HaplyConfig:
    """What a ``haply:`` spec says (:func:`parse_haply_args`).

    Attributes
    ----------
    port : str or None
        The serial port; None: find it with HaplyHardwareAPI's detection when opening.
    scale : float
        World metres per device metre.
    timeout_s : float
        Longest wait [s] for a state reply in the servo loop.
    specs : Inverse3Specs
        The device's own limits (defaults, with the spec's overrides).
    """

    port: str | None
    scale: float = 1.0
    timeout_s: float = DEFAULT_TIMEOUT_S
    specs: Inverse3Specs = Inverse3Specs()


def parse_haply_args(args: str) -> HaplyConfig:
    """Parse the ``ARGS`` of ``haply:ARGS``: ``[PORT][,KEY=VALUE]...``.

    ``PORT`` is a path (``/dev/ttyACM0``, ``/dev/serial/by-id/...``; a bare name such as
    ``ttyACM0`` means ``/dev/ttyACM0``); none means detection. Keys: ``scale`` (world metres per
    device metre, default 1), ``timeout_ms`` (state reply timeout, default 20) and the
    :data:`SPEC_LIMIT_OPTIONS`. Items are separated by commas, so a port whose path holds a comma
    cannot be named (use its /dev/serial/by-id or by-path alias).

    Raises
    ------
    DeviceError
        Two ports, an unknown key, a value that is not a finite number or out of range, or limits
        that do not hold together (one line each).
    """
    spec = f"haply:{args}" if args else "haply"
    port: str | None = None
    values: dict[str, float] = {}
    for raw in args.split(","):
        item = raw.strip()
        if not item:
            continue
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq:
            if port is not None:
                raise DeviceError(
                    f"{spec!r} names two ports ({port!r}, {item!r}); use haply:PORT[,KEY=VALUE...]"
                )
            port = item if "/" in item else f"/dev/{item}"
            continue
        if key not in SPEC_OPTIONS:
            raise DeviceError(
                f"unknown option {key!r} in {spec!r}; known: {', '.join(SPEC_OPTIONS)} "
                "(docs/device-haply.md)"
            )
        if key == "scale":
            values[key] = workspace_scale(spec, text, "use haply:PORT[,KEY=VALUE...]")
            continue
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise DeviceError(f"option {key!r} in {spec!r} must be a finite number, got {text!r}")
        values[key] = value
    scale = values.pop("scale", 1.0)
    timeout_ms = values.pop("timeout_ms", DEFAULT_TIMEOUT_S * 1e3)
    if not 1.0 <= timeout_ms <= 1000.0:
        raise DeviceError(f"timeout_ms in {spec!r} must be in [1, 1000], got {timeout_ms:g}")
    overrides: dict[str, Any] = dict(values)  # only SPEC_LIMIT_OPTIONS are left
    specs = replace(Inverse3Specs(), **overrides)
    try:
        specs.world_limits(scale, (0.0, 0.0, 0.0))
    except ValueError as exc:
        raise DeviceError(f"bad limits in {spec!r}: {one_line(exc)}") from None
    return HaplyConfig(port=port, scale=scale, timeout_s=timeout_ms * 1e-3, specs=specs)
