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
from dataclasses import replace
from enum import StrEnum
from typing import Annotated, Any

from pydantic import BeforeValidator, ValidationInfo

from haptic_collab.shared.checks import (
    FiniteFloat,
    NonNegFinite,
    PositiveFinite,
    PositiveOrInf,
    params_dataclass,
)
from haptic_collab.shared.primitives import vec3
from haptic_collab.shared.types import Vec3 as Vec3


def _corner(value: Any, info: ValidationInfo) -> Vec3:
    """A workspace corner given as any 3 numbers (a list, a numpy array) as a tuple of floats."""
    return vec3(info.field_name or "workspace corner", value)


#: A workspace corner [m]: 3 finite numbers, stored as a tuple of floats.
_Corner = Annotated[tuple[FiniteFloat, FiniteFloat, FiniteFloat], BeforeValidator(_corner)]


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


@params_dataclass(frozen=True, slots=True)
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
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values (``inf``
        stiffness or velocity with force output), a continuous force above the peak, or a
        workspace corner not below the other.
    """

    max_force_n: NonNegFinite
    max_stiffness_n_per_m: PositiveOrInf
    max_velocity_m_s: PositiveOrInf
    damping_n_s_per_m: NonNegFinite
    workspace_min_m: _Corner
    workspace_max_m: _Corner
    has_force_output: bool = True
    max_damping_n_s_per_m: NonNegFinite = 0.0
    max_continuous_force_n: PositiveFinite | None = None
    thermal_time_constant_s: PositiveFinite | None = None

    def __post_init__(self) -> None:
        if self.has_force_output:  # a position-only input may say inf: no limit from the device
            for name in ("max_stiffness_n_per_m", "max_velocity_m_s"):
                v = getattr(self, name)
                if not math.isfinite(v):
                    raise ValueError(
                        f"{name} must be finite for a device with force output (inf only with "
                        f"has_force_output=False), got {v!r}"
                    )
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise ValueError(
                f"workspace_min_m {lo} must be below workspace_max_m {hi} on every axis"
            )
        c = self.max_continuous_force_n
        if c is not None and not c <= self.max_force_n:
            raise ValueError(
                f"max_continuous_force_n must be in (0, max_force_n = {self.max_force_n:g}] N, "
                f"got {c!r}"
            )

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
