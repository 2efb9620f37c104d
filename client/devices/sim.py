"""Simulated haptic device held by a simulated hand (DESIGN section 7).

The device handle is a point mass m = m_device + m_hand [kg] with the device's viscous damping
b_d [N*s/m]. The hand is a spring-damper (k_hand [N/m], b_hand [N*s/m]) pulling the handle toward
a hand trajectory x_d(t) (:mod:`client.devices.trajectories`; t counts from the first read). The force f [N] the servo loop
writes acts on the handle and is held constant until the next write (zero-order hold), saturated
at the device's peak force. Per axis::

    m dv/dt = k_hand (x_d - x) + b_hand (v_d - v) - b_d v + f

integrated with semi-implicit (symplectic) Euler in sub-steps of at most T / substeps between two
reads (T the servo period): ``v += h a(x, v); x += h v``. The hand target x_d is sampled once per
read (it moves slowly) and its velocity v_d is the finite difference of two reads. The handle
stops at the workspace box (a mechanical end stop: position clamped, velocity zeroed) and the
position returned by :meth:`SimDevice.read` is quantized to the encoder resolution.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from haptic_collab.client.devices.base import Device, DeviceLimits, Vec3
from haptic_collab.client.devices.profiles import SimProfile
from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, params_dataclass

Trajectory = Callable[[float], Vec3]


@params_dataclass(frozen=True, slots=True)
class HandParams:
    """The simulated user's hand: a spring-damper with some mass, SI units.

    Parameters
    ----------
    stiffness_n_per_m : float
        Hand (arm) stiffness k_hand [N/m], > 0; DESIGN: 100-500 N/m (default 300).
    damping_n_s_per_m : float
        Hand damping b_hand [N*s/m], >= 0 (default 5).
    mass_kg : float
        Hand mass moving with the handle [kg], >= 0 (default 0.45; about 0.5 kg with the device).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values.
    """

    stiffness_n_per_m: PositiveFinite = 300.0
    damping_n_s_per_m: NonNegFinite = 5.0
    mass_kg: NonNegFinite = 0.45


class SimDevice(Device):
    """A simulated device: point mass + damping, held by a spring-damper hand (module docstring).

    Parameters
    ----------
    profile : SimProfile
        Device specification (mass, encoder, limits).
    trajectory : callable
        ``trajectory(t) -> (x, y, z)`` [m], the hand target, t [s] since the first read.
    hand : HandParams
        The simulated hand.
    limits : DeviceLimits, optional
        Limits with the workspace placed in the world (default: the profile's, centred on the
        trajectory's start point).
    servo_period_s : float
        Servo period T [s] (default 1e-3); the sub-step is at most T / ``substeps``.
    substeps : int
        Sub-steps per servo period, >= 1 (default 10).

    Raises
    ------
    ValueError
        Bad ``servo_period_s`` or ``substeps``.
    """

    #: Longest interval [s] integrated in one read; a longer gap (a paused thread) is cut to this.
    MAX_GAP_S = 0.5

    def __init__(
        self,
        profile: SimProfile,
        trajectory: Trajectory,
        hand: HandParams | None = None,
        *,
        limits: DeviceLimits | None = None,
        servo_period_s: float = 1e-3,
        substeps: int = 10,
    ) -> None:
        if not (math.isfinite(servo_period_s) and servo_period_s > 0.0):
            raise ValueError(f"servo_period_s must be > 0, got {servo_period_s!r}")
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps!r}")
        self.profile = profile
        self.name = f"sim:{profile.name}"
        self.trajectory = trajectory
        self.hand = hand if hand is not None else HandParams()
        self.limits = limits if limits is not None else profile.limits.centered_at(trajectory(0.0))
        self.fault: str | None = None
        self._h_max = servo_period_s / substeps
        self._mass = profile.mass_kg + self.hand.mass_kg
        self._res = profile.encoder_resolution_m
        self._open = False
        self._enabled = False
        self._f = (0.0, 0.0, 0.0)
        self._t: float | None = None
        self._t0 = 0.0
        self._x = (0.0, 0.0, 0.0)
        self._v = (0.0, 0.0, 0.0)
        self._target = (0.0, 0.0, 0.0)
        self._q = (0.0, 0.0, 0.0)

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> None:
        """Start the simulation (the handle appears at the hand target on the first read)."""
        self._open = True
        self._t = None

    def close(self) -> None:
        """Zero and disable the force; the simulation stops advancing."""
        self._enabled = False
        self._f = (0.0, 0.0, 0.0)
        self._open = False

    def enable_forces(self) -> None:
        """Allow :meth:`write` to act on the handle."""
        self._enabled = True

    def disable_forces(self) -> None:
        """Zero the force and ignore writes."""
        self._enabled = False
        self._f = (0.0, 0.0, 0.0)

    def inject_fault(self, message: str = "simulated fault") -> None:
        """Make the device report a fault (for tests and demos of the safety ramp)."""
        self.fault = message

    # -- state (for tests and telemetry) -------------------------------------------------------
    @property
    def position_m(self) -> Vec3:
        """True (unquantized) handle position [m]."""
        return self._x

    @property
    def velocity_m_s(self) -> Vec3:
        """Handle velocity [m/s]."""
        return self._v

    @property
    def hand_target_m(self) -> Vec3:
        """Hand target [m] sampled at the last read."""
        return self._target

    @property
    def applied_force_n(self) -> Vec3:
        """Force [N] acting on the handle now (after saturation; zero while disabled)."""
        return self._f

    # -- servo interface -----------------------------------------------------------------------
    def read(self, t_s: float) -> Vec3:
        """Integrate the handle up to ``t_s`` [s] and return its quantized position (x, y, z) [m].

        The hand trajectory's clock starts at the first read after :meth:`open`: the hand target
        at servo time ``t_s`` is ``trajectory(t_s - t_first_read)``.
        """
        t_prev = self._t
        if t_prev is None:
            self._t0 = t_s
            tgt = self.trajectory(0.0)
            self._t = t_s
            self._target = tgt
            self._x = self._clamp(tgt)
            self._v = (0.0, 0.0, 0.0)
            return self._quantize()
        dt = t_s - t_prev
        if dt <= 0.0:
            return self._q
        self._t = t_s
        if dt > self.MAX_GAP_S:
            dt = self.MAX_GAP_S
        tgt = self.trajectory(t_s - self._t0)
        otx, oty, otz = self._target
        tx, ty, tz = tgt
        self._target = tgt
        vtx, vty, vtz = (tx - otx) / dt, (ty - oty) / dt, (tz - otz) / dt
        n = math.ceil(dt / self._h_max - 1e-9)
        h = dt / n
        hand = self.hand
        k, b = hand.stiffness_n_per_m, hand.damping_n_s_per_m
        bd = self.limits.damping_n_s_per_m
        c = h / self._mass
        fx, fy, fz = self._f
        # Constant parts of the force over the interval: hand target pull and device force.
        ux = k * tx + b * vtx + fx
        uy = k * ty + b * vty + fy
        uz = k * tz + b * vtz + fz
        bb = b + bd
        x, y, z = self._x
        vx, vy, vz = self._v
        for _ in range(n):
            vx += c * (ux - k * x - bb * vx)
            vy += c * (uy - k * y - bb * vy)
            vz += c * (uz - k * z - bb * vz)
            x += h * vx
            y += h * vy
            z += h * vz
        lo, hi = self.limits.workspace_min_m, self.limits.workspace_max_m
        if x < lo[0] or x > hi[0]:
            x, vx = (lo[0] if x < lo[0] else hi[0]), 0.0
        if y < lo[1] or y > hi[1]:
            y, vy = (lo[1] if y < lo[1] else hi[1]), 0.0
        if z < lo[2] or z > hi[2]:
            z, vz = (lo[2] if z < lo[2] else hi[2]), 0.0
        self._x = (x, y, z)
        self._v = (vx, vy, vz)
        return self._quantize()

    def write(self, fx: float, fy: float, fz: float) -> None:
        """Hold the force (fx, fy, fz) [N] on the handle, saturated at ``limits.max_force_n``."""
        if not self._enabled:
            return
        m2 = fx * fx + fy * fy + fz * fz
        fmax = self.limits.max_force_n
        if m2 > fmax * fmax:
            s = fmax / math.sqrt(m2)
            fx, fy, fz = fx * s, fy * s, fz * s
        self._f = (fx, fy, fz)

    # -- helpers -------------------------------------------------------------------------------
    def _clamp(self, p: Vec3) -> Vec3:
        lo, hi = self.limits.workspace_min_m, self.limits.workspace_max_m
        return (
            min(max(p[0], lo[0]), hi[0]),
            min(max(p[1], lo[1]), hi[1]),
            min(max(p[2], lo[2]), hi[2]),
        )

    def _quantize(self) -> Vec3:
        r = self._res
        x, y, z = self._x
        if r > 0.0:
            q = (round(x / r) * r, round(y / r) * r, round(z / r) * r)
        else:
            q = (x, y, z)
        self._q = q
        return q
