"""The servo loop's timing and safety parameters (:class:`ServoConfig`), SI units.

Its own module so that the loop (:mod:`client.servo`) and its safety supervisor
(:mod:`client.safety`) both read it without importing each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ServoConfig:
    """Timing and safety parameters of the servo loop, SI units.

    Parameters
    ----------
    servo_rate_hz : float
        Servo rate 1/T [Hz], > 0 (default 1000).
    link_timeout_s : float
        Silence [s] of the link (no patch, no pong) after which forces ramp down, > 0; ``inf``
        disables the check (default 0.25).
    ramp_s : float
        Duration [s] of a full ramp of the safety gain between 0 and 1, > 0 (default 0.075).
    velocity_filter_s : float
        Time constant [s] of the first-order filter on the probe velocity used by the velocity
        limit, >= 0 (default 0.005).
    velocity_resume_ratio : float
        Forces come back when the filtered speed falls below this fraction of the limit
        (hysteresis), in (0, 1] (default 0.8).
    period_window : int
        Ticks over which :meth:`ServoCore.latest` reports period statistics, >= 2 (default 1000).
    passivity : bool
        Run the time-domain passivity observer and controller at the device port
        (:mod:`shared.passivity`; Hannaford and Ryu 2002), default False (the client turns it on
        for either local model: ``client.app.passivity_on``).
    passivity_energy_bias_j : float
        Energy [J] the port may give the user before the controller damps, >= 0 (default 1 mJ).
    engage_with_button : bool
        The user engages forces with the device's first button, as in the vendors' examples: a
        press (button 0 going down) engages them, the next press disengages them (a ramp to
        zero). Until the first press no force is displayed, whatever else allows it. False
        (default): :meth:`ServoCore.enable_forces` alone engages them (simulated devices, the
        demo, devices without buttons).

    Raises
    ------
    ValueError
        Out-of-range values.
    """

    servo_rate_hz: float = 1000.0
    link_timeout_s: float = 0.25
    ramp_s: float = 0.075
    velocity_filter_s: float = 0.005
    velocity_resume_ratio: float = 0.8
    period_window: int = 1000
    passivity: bool = False
    passivity_energy_bias_j: float = 1e-3
    engage_with_button: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.servo_rate_hz) and self.servo_rate_hz > 0.0):
            raise ValueError(f"servo_rate_hz must be > 0, got {self.servo_rate_hz!r}")
        if not (self.link_timeout_s > 0.0):
            raise ValueError(f"link_timeout_s must be > 0 (or inf), got {self.link_timeout_s!r}")
        if not (math.isfinite(self.ramp_s) and self.ramp_s > 0.0):
            raise ValueError(f"ramp_s must be > 0, got {self.ramp_s!r}")
        if not (math.isfinite(self.velocity_filter_s) and self.velocity_filter_s >= 0.0):
            raise ValueError(f"velocity_filter_s must be >= 0, got {self.velocity_filter_s!r}")
        if not (0.0 < self.velocity_resume_ratio <= 1.0):
            raise ValueError("velocity_resume_ratio must be in (0, 1]")
        if self.period_window < 2:
            raise ValueError("period_window must be >= 2 ticks")
        if not (
            math.isfinite(self.passivity_energy_bias_j) and self.passivity_energy_bias_j >= 0.0
        ):
            raise ValueError("passivity_energy_bias_j must be finite and >= 0 J")

    @property
    def servo_period_s(self) -> float:
        """Servo period T [s]."""
        return 1.0 / self.servo_rate_hz

    @property
    def ramp_step(self) -> float:
        """Change of the safety gain per tick, T / ramp_s."""
        return min(1.0, self.servo_period_s / self.ramp_s)
