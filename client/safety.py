"""The servo's safety supervisor: when forces may be on, how strongly, and how large.

STYLE rule 9 as device vendors do it. Each servo tick :meth:`SafetySupervisor.update` takes the
tick's inputs (the user's switches, the stylus button, the link's age, the device's fault, whether
the position was finite, the probe speed) and returns the safety gain g in [0, 1]; then
:meth:`SafetySupervisor.output` clamps the rendered force and scales it by g, runs the passivity
controller at the device port and steps the motors' heat model. It reads no clock, touches no
device and never raises on bad input: a bad input is a fault.

- Forces are off until :meth:`~SafetySupervisor.enable` *and* the first patch
  (:meth:`~SafetySupervisor.patch_arrived`); with ``ServoConfig.engage_with_button`` also until a
  press of button 0 (the next press disengages).
- g ramps linearly (never jumps) by T / ``ramp_s`` per tick, g(k) = clip(g(k-1) +- T/ramp_s,
  0, 1): down to zero when the link is silent for ``link_timeout_s`` (``LINK_LOST``; back up only
  after a *new* patch), when the device reports a fault or a non-finite position
  (``DEVICE_FAULT``), when the probe's filtered speed exceeds ``limits.max_velocity_m_s``
  (``VELOCITY_LIMIT``; back below ``velocity_resume_ratio`` of it to resume: hysteresis), on
  :meth:`~SafetySupervisor.disable` and on :meth:`~SafetySupervisor.request_stop`; back up to one
  when the cause is gone.
- Every force is clamped to the device's max: ``limits.max_force_n``, or, when the device states
  a continuous force, the peak-force time limit :attr:`SafetySupervisor.thermal`
  (:class:`client.thermal.ThermalLimit`, stepped each tick with the force displayed)
  (``FORCE_LIMIT``, counted once per episode).
- With ``ServoConfig.passivity`` (and a device that can damp), the time-domain passivity
  observer and controller (:class:`shared.passivity.PassivityController`; Hannaford and Ryu
  2002) acts on the scaled force at the device port. It lives here rather than in the renderer
  because it acts on what the device is about to display, after the clamp and the safety gain,
  and bounds it by the device's damping: an output guard, like the clamp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from haptic_collab.client.devices.base import DeviceLimits, HapticError
from haptic_collab.client.servo_config import ServoConfig
from haptic_collab.client.thermal import (
    DEFAULT_THERMAL_TIME_CONSTANT_S,
    ThermalLimit,
    ThermalParams,
)
from haptic_collab.shared.passivity import PassivityController, PassivityParams


@dataclass(frozen=True, slots=True)
class ServoEvent:
    """One safety event: its kind, the servo time [s] it happened, a human-readable detail."""

    kind: HapticError
    t_s: float
    detail: str


class SafetySupervisor:
    """Safety state machine of one servo loop (module docstring); time is an input.

    Parameters
    ----------
    limits : DeviceLimits
        The device's limits (max force, continuous force, max velocity, max damping).
    config : ServoConfig
        Period, ramp, link timeout, velocity hysteresis, button engagement and passivity.

    Attributes
    ----------
    scale : float
        Safety gain g in [0, 1] of the last :meth:`update`.
    want : bool
        Nothing withheld forces at the last :meth:`update` (g is ramping up or at one).
    ramping : bool
        g changed at the last :meth:`update`.
    limited : bool
        The last :meth:`output` clamped the force.
    fault : str or None
        The device fault (or non-finite position) of the last :meth:`update`.
    link_ok : bool
        The link spoke within ``link_timeout_s`` at the last :meth:`update`.
    need_patch : bool
        No current patch (before the first, and after a link loss until a new one).
    overspeed : bool
        The probe speed is above the limit (not yet back under the resume speed).
    enabled : bool
        Forces enabled by the user (:meth:`enable`).
    engaged : bool
        Forces engaged with the stylus button (always True without ``engage_with_button``).
    stopping : bool
        A stop was requested (:meth:`request_stop`).
    counts : dict of HapticError to int
        Events per kind (every kind present).
    last_event : ServoEvent or None
        The newest event.
    thermal : ThermalLimit or None
        The peak-force time limit (None when the device states no continuous force).
    passivity : PassivityController or None
        The passivity controller (None when off).

    Notes
    -----
    Read the attributes, never assign them. :meth:`enable`, :meth:`disable`,
    :meth:`request_stop` and :meth:`notify_link` may be called from any thread (each is one
    store); the rest only from the servo thread.
    """

    __slots__ = (
        "limits",
        "scale",
        "want",
        "ramping",
        "limited",
        "fault",
        "link_ok",
        "need_patch",
        "overspeed",
        "enabled",
        "engaged",
        "stopping",
        "counts",
        "last_event",
        "thermal",
        "passivity",
        "_step",
        "_fmax",
        "_vmax2",
        "_vresume2",
        "_timeout",
        "_inv_T",
        "_by_button",
        "_button_was",
        "_link_t",
    )

    def __init__(self, limits: DeviceLimits, config: ServoConfig) -> None:
        T = config.servo_period_s
        self.limits = limits
        self._step = config.ramp_step
        self._fmax = limits.max_force_n
        self._vmax2 = limits.max_velocity_m_s**2
        self._vresume2 = (config.velocity_resume_ratio * limits.max_velocity_m_s) ** 2
        self._timeout = config.link_timeout_s
        self._inv_T = 1.0 / T
        # peak force for a limited time, then the continuous force (client.thermal)
        self.thermal: ThermalLimit | None = None
        if (
            limits.has_force_output
            and limits.max_continuous_force_n is not None
            and limits.max_force_n > 0
        ):
            self.thermal = ThermalLimit(
                ThermalParams(
                    peak_force_n=limits.max_force_n,
                    continuous_force_n=limits.max_continuous_force_n,
                    time_constant_s=limits.thermal_time_constant_s
                    or DEFAULT_THERMAL_TIME_CONSTANT_S,
                    servo_period_s=T,
                )
            )
        self.passivity: PassivityController | None = None
        if config.passivity and limits.has_force_output and limits.max_damping_n_s_per_m > 0.0:
            # the controller's damper is bounded by what the device can render stably
            self.passivity = PassivityController(
                PassivityParams(
                    max_damping_n_s_per_m=limits.max_damping_n_s_per_m,
                    energy_bias_j=config.passivity_energy_bias_j,
                    servo_period_s=T,
                    max_force_n=limits.max_force_n,
                )
            )
        # switches set from other threads
        self.enabled = False
        self.stopping = False
        self._link_t = -math.inf
        # the stylus button (ServoConfig.engage_with_button)
        self._by_button = config.engage_with_button
        self.engaged = not config.engage_with_button
        self._button_was = False
        # tick state
        self.need_patch = True
        self.scale = 0.0
        self.want = False
        self.ramping = False
        self.overspeed = False
        self.limited = False
        self.link_ok = False
        self.fault: str | None = None
        # events
        self.counts: dict[HapticError, int] = dict.fromkeys(HapticError, 0)
        self.last_event: ServoEvent | None = None

    # -- switches (any thread) ---------------------------------------------------------------------
    def enable(self) -> None:
        """Allow forces (they ramp up once a patch is current and nothing else withholds them)."""
        self.enabled = True

    def disable(self) -> None:
        """Ramp forces down to zero and keep them there until :meth:`enable`."""
        self.enabled = False

    def request_stop(self) -> None:
        """Ramp forces down for good (the caller disables the device once g is zero)."""
        self.stopping = True

    def notify_link(self, now_s: float) -> None:
        """The server spoke (a patch or a pong arrived) at servo time ``now_s`` [s]."""
        if now_s > self._link_t:
            self._link_t = now_s

    # -- servo thread ------------------------------------------------------------------------------
    def patch_arrived(self, now_s: float) -> None:
        """A new patch was handed over at servo time ``now_s`` [s]: it is current, the link spoke."""
        self.need_patch = False
        if now_s > self._link_t:
            self._link_t = now_s

    def event(self, kind: HapticError, t_s: float, detail: str) -> None:
        """Count one event of ``kind`` at servo time ``t_s`` [s] and make it the last event."""
        self.counts[kind] += 1
        self.last_event = ServoEvent(kind, t_s, detail)

    def zero(self) -> None:
        """Drop g to zero at once (the servo loop died or stopped without running the ramp)."""
        self.scale = 0.0

    def update(
        self,
        now_s: float,
        pressed: bool,
        fault: str | None,
        position_ok: bool,
        speed2_m2_s2: float,
    ) -> float:
        """Advance the state machine one servo period; return the safety gain g in [0, 1].

        Parameters
        ----------
        now_s : float
            Servo time [s] of the tick.
        pressed : bool
            Button 0 is down (only read with ``engage_with_button``: a press toggles
            :attr:`engaged`).
        fault : str or None
            The device's fault message, None when healthy.
        position_ok : bool
            The device gave a finite position (False is a ``DEVICE_FAULT``).
        speed2_m2_s2 : float
            Squared filtered probe speed [m^2/s^2], compared with the device's max velocity.

        Returns
        -------
        float
            g after this period's ramp step; also :attr:`scale`. :attr:`want`, :attr:`ramping`,
            :attr:`fault` and :attr:`link_ok` are updated, and events counted
            (``VELOCITY_LIMIT``, ``DEVICE_FAULT``, ``LINK_LOST``, in that order).
        """
        if self._by_button:  # a press of button 0 toggles the engagement
            if pressed and not self._button_was:
                self.engaged = not self.engaged
            self._button_was = pressed
        if self.overspeed:
            if speed2_m2_s2 < self._vresume2:
                self.overspeed = False
        elif speed2_m2_s2 > self._vmax2:
            self.overspeed = True
            self.event(HapticError.VELOCITY_LIMIT, now_s, "probe speed above the device limit")
        if fault is None and not position_ok:
            fault = "device reported a non-finite position"
        if fault is not None and self.fault is None:
            self.event(HapticError.DEVICE_FAULT, now_s, fault)
        self.fault = fault
        link_ok = now_s - self._link_t <= self._timeout
        if self.link_ok and not link_ok and not self.need_patch:
            self.need_patch = True
            self.event(HapticError.LINK_LOST, now_s, "no patch or pong within the link timeout")
        self.link_ok = link_ok
        want = (
            self.enabled
            and self.engaged
            and not self.need_patch
            and link_ok
            and fault is None
            and not self.overspeed
            and not self.stopping
        )
        self.want = want
        s0 = self.scale
        if want:
            s = s0 + self._step
            if s > 1.0:
                s = 1.0
        else:
            s = s0 - self._step
            if s < 0.0:
                s = 0.0
        self.scale = s
        self.ramping = s != s0
        return s

    def output(
        self,
        f: float,
        nx: float,
        ny: float,
        nz: float,
        dx: float,
        dy: float,
        dz: float,
        now_s: float,
        displayed: bool,
    ) -> tuple[float, float, float, float]:
        """The force to write: clamp f, scale by g, passivity controller, heat model.

        F = g * clamp(f, +-F_max) * n, then the passivity controller's damping on the port
        velocity d / T; the heat model is stepped with \\|F\\| (0 when the device's forces are
        off).

        Parameters
        ----------
        f : float
            Rendered force magnitude [N] along n (:meth:`client.render.LocalRenderer.render`).
        nx, ny, nz : float
            Outward unit normal n.
        dx, dy, dz : float
            The probe's move since the last tick [m] (the port velocity is d / T).
        now_s : float
            Servo time [s] (for the ``FORCE_LIMIT`` event).
        displayed : bool
            The device's forces are on (it displays what is written).

        Returns
        -------
        fx, fy, fz : float
            Force [N] to write to the device.
        f_n : float
            g * clamp(f) [N], the force along n before the passivity controller.
        """
        th = self.thermal
        fmax = self._fmax if th is None else th.limit_n
        limited = f > fmax or f < -fmax
        if limited:
            f = fmax if f > 0.0 else -fmax
            if not self.limited:
                self.event(
                    HapticError.FORCE_LIMIT,
                    now_s,
                    "local model force above the device max"
                    if fmax >= self._fmax
                    else f"motors warm: force limited to {fmax:.2f} N, falling to the continuous "
                    "force",
                )
        self.limited = limited
        fo = f * self.scale
        fx, fy, fz = fo * nx, fo * ny, fo * nz
        pc = self.passivity
        if pc is not None:  # passivity observer/controller at the device port
            it = self._inv_T
            fx, fy, fz = pc.step(fx, fy, fz, dx * it, dy * it, dz * it)
        if th is not None:  # the motors heat with the force displayed (the safety scale included)
            th.step(math.sqrt(fx * fx + fy * fy + fz * fz) if displayed else 0.0)
        return fx, fy, fz, fo

    def passivity_energies(self) -> dict[str, float] | None:
        """The passivity controller's energies [J] (``ServoStatus.passivity``); None when off."""
        pc = self.passivity
        if pc is None:
            return None
        return {
            "observed_j": pc.observed_energy_j,
            "dissipated_j": pc.dissipated_energy_j,
            "active_j": pc.active_energy_j,
        }
