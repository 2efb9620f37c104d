"""What every haptic device offers the servo loop: position in, force out, and its limits.

DESIGN section 7 and the CHAI3D idea of a generic haptic device: a device is opened, read for the
position of its handle (the probe x_h of the paper), written with the force it should display on
the user, and it publishes the limits the servo loop must respect (largest force, largest stiffness
that is stable at its servo rate, its own damping, its workspace). The servo loop (client/servo.py)
reads and writes a device once per servo period T in three phases: update from device, compute
forces, apply to device.

Conventions (SI units, world frame of the shared object):

- positions in metres, forces in newtons, the force is the one applied *on the user's hand*;
- :meth:`Device.read` takes the time ``t_s`` [s] of the tick (the servo loop's clock): a simulated
  device integrates its physics up to ``t_s``; a real device ignores it or uses it for rate inputs;
- a device never raises from :meth:`Device.read` or :meth:`Device.write` once it is open: when it
  errors or disappears it sets :attr:`Device.fault` to a message and keeps returning its last
  position, so the servo loop can ramp forces down instead of dying mid-tick.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

from haptic_collab.shared.primitives import vec3
from haptic_collab.shared.types import Vec3 as Vec3


class HapticError(StrEnum):
    """Named events the servo loop counts and reports (``ServoCore.status()``).

    FORCE_LIMIT
        The local model asked for more than ``DeviceLimits.max_force_n``; the force was clamped.
    VELOCITY_LIMIT
        The probe moved faster than ``DeviceLimits.max_velocity_m_s``; forces ramped down.
    DEVICE_FAULT
        The device reported a fault (unplugged, read error); forces ramped down.
    LINK_LOST
        No patch or pong from the server within the link timeout; forces ramped down.
    SERVO_OVERRUN
        A servo deadline was missed (and skipped, never piled up).
    """

    FORCE_LIMIT = "force_limit"
    VELOCITY_LIMIT = "velocity_limit"
    DEVICE_FAULT = "device_fault"
    LINK_LOST = "link_lost"
    SERVO_OVERRUN = "servo_overrun"


@dataclass(frozen=True, slots=True)
class DeviceLimits:
    """Limits a device publishes (CHAI3D's device specification), SI units.

    Parameters
    ----------
    max_force_n : float
        Largest force [N] the servo loop may command, >= 0 (peak force of the device). For a
        position-only input (``has_force_output=False``) this bounds the coupling force sent to the
        object instead.
    max_stiffness_n_per_m : float
        Largest local-model stiffness K_h [N/m] the device renders stably at its servo rate, > 0.
        A position-only input displays nothing, so no stiffness limit comes from it: ``inf``
        (allowed only with ``has_force_output=False``) leaves K_h to the gain design.
    max_velocity_m_s : float
        Probe speed [m/s] above which forces are ramped down, > 0; ``inf`` (only with
        ``has_force_output=False``): no limit, nothing is displayed that could run away.
    damping_n_s_per_m : float
        The device's own viscous damping [N*s/m], >= 0.
    workspace_min_m, workspace_max_m : (3,) float
        Corners [m] of the axis-aligned box the handle can reach, in the world frame.
    has_force_output : bool
        False for a position-only input (a SpaceMouse): :meth:`Device.write` is a no-op.
    max_damping_n_s_per_m : float
        Largest virtual damping B_h [N*s/m] the local model may add on the probe velocity, >= 0
        (CHAI3D's ``m_maxLinearDamping``, OpenHaptics' ``HD_NOMINAL_MAX_DAMPING``); 0: none.
    max_continuous_force_n : float or None
        Force [N] the device may display indefinitely (OpenHaptics'
        ``HD_NOMINAL_MAX_CONTINUOUS_FORCE``), 0 < it <= ``max_force_n``; None: not stated, the
        peak force ``max_force_n`` is all that is known.
    thermal_time_constant_s : float or None
        Thermal time constant [s] of the device's motors, > 0, for the servo's peak-force time
        limit (:mod:`client.thermal`: the force limit comes down from the peak to the continuous
        force once the peak has been used long enough); None: the stated assumption
        :data:`client.thermal.DEFAULT_THERMAL_TIME_CONSTANT_S`. Used only with a continuous force.

    Raises
    ------
    ValueError
        Non-finite or out-of-range values, or a workspace corner not below the other.
    """

    max_force_n: float
    max_stiffness_n_per_m: float
    max_velocity_m_s: float
    damping_n_s_per_m: float
    workspace_min_m: Vec3
    workspace_max_m: Vec3
    has_force_output: bool = True
    max_damping_n_s_per_m: float = 0.0
    max_continuous_force_n: float | None = None
    thermal_time_constant_s: float | None = None

    def __post_init__(self) -> None:
        for name in ("max_force_n", "damping_n_s_per_m", "max_damping_n_s_per_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        for name in ("max_stiffness_n_per_m", "max_velocity_m_s"):
            v = getattr(self, name)
            if not self.has_force_output and v == math.inf:
                continue  # a position-only input: no limit comes from the device
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        lo = vec3("workspace_min_m", self.workspace_min_m)
        hi = vec3("workspace_max_m", self.workspace_max_m)
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(
                f"workspace_min_m {lo} must be below workspace_max_m {hi} on every axis"
            )
        object.__setattr__(self, "workspace_min_m", lo)
        object.__setattr__(self, "workspace_max_m", hi)
        c = self.max_continuous_force_n
        if c is not None and not (math.isfinite(c) and 0.0 < c <= self.max_force_n):
            raise ValueError(
                f"max_continuous_force_n must be in (0, max_force_n = {self.max_force_n:g}] N, "
                f"got {c!r}"
            )
        tau = self.thermal_time_constant_s
        if tau is not None and not (math.isfinite(tau) and tau > 0.0):
            raise ValueError(f"thermal_time_constant_s must be finite and > 0 s, got {tau!r}")

    def scaled(self, scale: float) -> DeviceLimits:
        """The limits seen through a workspace scale: ``scale`` world metres per device metre.

        A world displacement x is x / ``scale`` at the handle, so stiffness and damping (the
        device's own and the largest virtual one) divide by ``scale``; speed and the workspace
        (about its centre) multiply by it; forces are unchanged.

        Raises
        ------
        ValueError
            A scale that is not finite and > 0.
        """
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"the workspace scale must be finite and > 0, got {scale!r}")
        lo, hi = self.workspace_min_m, self.workspace_max_m
        c = [0.5 * (a + b) for a, b in zip(lo, hi, strict=True)]
        half = [0.5 * scale * (b - a) for a, b in zip(lo, hi, strict=True)]
        return replace(
            self,
            max_stiffness_n_per_m=self.max_stiffness_n_per_m / scale,
            max_velocity_m_s=self.max_velocity_m_s * scale,
            damping_n_s_per_m=self.damping_n_s_per_m / scale,
            max_damping_n_s_per_m=self.max_damping_n_s_per_m / scale,
            workspace_min_m=(c[0] - half[0], c[1] - half[1], c[2] - half[2]),
            workspace_max_m=(c[0] + half[0], c[1] + half[1], c[2] + half[2]),
        )

    def centered_at(self, center: Sequence[float]) -> DeviceLimits:
        """The same limits with the workspace box moved to be centred on ``center`` (3,) [m]."""
        c = vec3("center", center)
        lo, hi = self.workspace_min_m, self.workspace_max_m
        half = tuple(0.5 * (b - a) for a, b in zip(lo, hi, strict=True))
        return replace(
            self,
            workspace_min_m=(c[0] - half[0], c[1] - half[1], c[2] - half[2]),
            workspace_max_m=(c[0] + half[0], c[1] + half[1], c[2] + half[2]),
        )


class Device(ABC):
    """A haptic device as the servo loop sees it (CHAI3D's generic device, DESIGN section 7).

    Lifecycle: :meth:`open`, then once per servo tick :meth:`read` then :meth:`write`, and finally
    :meth:`close`. Forces are displayed only between :meth:`enable_forces` and
    :meth:`disable_forces`; a freshly opened device has forces disabled.

    Attributes
    ----------
    name : str
        Human-readable name (profile or product).
    limits : DeviceLimits
        What the servo loop must respect.
    fault : str or None
        None while healthy; a message once the device errored or disappeared.
    has_buttons : bool
        The device reports buttons (:meth:`buttons`); then ``haptic client`` lets the user engage
        forces with the first one unless told otherwise (``--engage``). Default False.
    """

    name: str
    limits: DeviceLimits
    fault: str | None
    has_buttons: bool = False

    @abstractmethod
    def open(self) -> None:
        """Connect to the device.

        Raises
        ------
        OSError
            If the device cannot be opened.
        """

    @abstractmethod
    def close(self) -> None:
        """Zero the force, disable it and release the device; safe to call twice."""

    @abstractmethod
    def read(self, t_s: float) -> Vec3:
        """Handle position (x, y, z) [m] at time ``t_s`` [s] (the servo clock, non-decreasing).

        Never raises once open: on error sets :attr:`fault` and returns the last position.
        """

    @abstractmethod
    def write(self, fx: float, fy: float, fz: float) -> None:
        """Command the force (fx, fy, fz) [N] on the user's hand until the next write.

        Ignored while forces are disabled. Never raises once open (sets :attr:`fault`).
        """

    @abstractmethod
    def enable_forces(self) -> None:
        """Allow :meth:`write` to display forces."""

    @abstractmethod
    def disable_forces(self) -> None:
        """Zero the displayed force and ignore further writes until re-enabled."""

    def buttons(self) -> int:
        """The buttons held now, as a bit mask (bit i: button i; a stylus's first button is bit
        0), as of the last :meth:`read`. 0 for a device without buttons (the default)."""
        return 0

    def reopen(self) -> bool:
        """Try to recover a faulted device by opening it again (it was unplugged and came back).

        The client calls this with backoff, from another thread than the servo loop's, while
        :attr:`fault` is set; the servo loop keeps forces at zero until the fault clears.

        Returns
        -------
        bool
            True when the device is healthy again; False when it cannot be reopened (the
            default: a device that does not support it, e.g. a simulated one).

        Raises
        ------
        OSError
            The device is still absent.
        """
        return False
