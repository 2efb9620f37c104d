"""Peak force for a limited time: a motor-heating model that lowers the force limit to the
device's continuous force once the peak has been used for long enough.

A force-feedback device states two forces: its peak (the Phantom Desktop's 7.9 N), which its
motors give only for moments, and its continuous force (1.75 N), which they can give for ever
without overheating (OpenHaptics' ``HD_NOMINAL_MAX_FORCE`` and
``HD_NOMINAL_MAX_CONTINUOUS_FORCE``). The servo clamps every force at the peak; without a time
limit a PI hold that asks for 2-3 N asks for it for as long as the user holds, and a real device
warms up until its driver faults (OpenHaptics' ``HD_WARM_MOTORS``,
``HD_EXCEEDED_MAX_FORCE_IMPULSE``) and drops the force at once.

The model is the I²t protection of motor drives: the heat of a winding grows with the square of
its current, i.e. of the force, and leaks away with the winding's thermal time constant tau.
Normalised so that the continuous force held for ever settles at 1::

    h(n+1) = h(n) + (T / tau) * ((F(n) / F_c)^2 - h(n))

From cold (h = 0) a constant force F > F_c reaches h = 1 after ``-tau * ln(1 - (F_c / F)^2)``:
with the Desktop's numbers and tau = 15 s, 0.75 s at the 7.9 N peak, 22 s at 2 N; forces at or
below F_c never get there.

The limit. While h <= 1 the limit is the peak force. Once h passes 1, the limit starts from the
force displayed at that moment and moves down toward F_c at ``clamp_rate_n_s`` (never a step:
the hand feels the object soften over a second or two); it moves back up to the peak at the same
rate once h has fallen below ``release_heat`` (0.8), i.e. after the user has eased off for a
while. This is how OpenHaptics' own example (PreventWarmMotors) treats the device's measured
motor temperature: a clamp started at the force of the moment, lowered gradually toward the
continuous force while a motor is warm, raised gradually once it has cooled, with hysteresis
between the two. A device that reports its motor temperature (normalised between room and
overheat temperature, as ``HD_MOTOR_TEMPERATURE``) can pass it in: the limit then also comes down
when the device says its motors are warm (above ``device_hot`` = 0.7, back below
``device_cool`` = 0.5, the example's thresholds), whichever says so first.

Nothing here reads a clock: time advances one servo period per :meth:`ThermalLimit.step`.
"""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import Field

from haptic_collab.shared.checks import (
    FiniteFloat,
    NonNegFinite,
    PositiveFinite,
    PositiveOrInf,
    params_dataclass,
)

#: Thermal time constant [s] assumed for a device that states none. The winding time constants of
#: the small ironless DC motors these devices use are of the order of ten seconds in the motor
#: makers' catalogues; none of the vendors supported here publishes its devices' own value.
DEFAULT_THERMAL_TIME_CONSTANT_S = 15.0


@params_dataclass(frozen=True, slots=True)
class ThermalParams:
    """Parameters of the peak-force time limit, SI units.

    Parameters
    ----------
    peak_force_n : float
        Peak force F_p [N] (the device's ``max_force_n``), > 0.
    continuous_force_n : float
        Continuous force F_c [N], 0 < F_c <= F_p.
    time_constant_s : float
        Thermal time constant tau [s] of the model, > 0.
    servo_period_s : float
        Servo period T [s], > 0.
    clamp_rate_n_s : float
        How fast the limit moves between F_p and F_c [N/s], > 0 (default 1 N/s).
    release_heat : float
        Modelled heat h below which the limit goes back up, in [0, 1) (default 0.8).
    device_hot, device_cool : float
        The device's own normalised motor temperature above which the limit comes down, and below
        which it may go back up, 0 <= cool < hot (defaults 0.7 and 0.5).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values
        (``device_hot`` may be ``inf``: never hot), F_c above F_p, or cool not below hot.
    """

    peak_force_n: PositiveFinite
    continuous_force_n: PositiveFinite
    time_constant_s: PositiveFinite = DEFAULT_THERMAL_TIME_CONSTANT_S
    servo_period_s: PositiveFinite = 1e-3
    clamp_rate_n_s: PositiveFinite = 1.0
    release_heat: Annotated[FiniteFloat, Field(ge=0, lt=1)] = 0.8
    device_hot: PositiveOrInf = 0.7
    device_cool: NonNegFinite = 0.5

    def __post_init__(self) -> None:
        c = self.continuous_force_n
        if not c <= self.peak_force_n:
            raise ValueError(
                f"continuous_force_n must be in (0, peak_force_n = {self.peak_force_n:g}] N, "
                f"got {c!r}"
            )
        if not self.device_cool < self.device_hot:
            raise ValueError(
                f"device_cool ({self.device_cool!r}) must be >= 0 and below device_hot "
                f"({self.device_hot!r})"
            )


class ThermalLimit:
    """The force limit [N] of one servo tick after another (module docstring).

    Call :meth:`step` once per servo tick with the force magnitude the device displayed; read
    :attr:`limit_n` for the clamp of the next tick.

    Examples
    --------
    >>> lim = ThermalLimit(ThermalParams(peak_force_n=7.9, continuous_force_n=1.75))
    >>> lim.limit_n
    7.9
    """

    __slots__ = ("params", "_a", "_inv_fc2", "_dl", "_heat", "_limit", "_hot")

    def __init__(self, params: ThermalParams) -> None:
        self.params = params
        self._a = min(1.0, params.servo_period_s / params.time_constant_s)
        self._inv_fc2 = 1.0 / (params.continuous_force_n * params.continuous_force_n)
        self._dl = params.clamp_rate_n_s * params.servo_period_s
        self._heat = 0.0
        self._limit = params.peak_force_n
        self._hot = False

    @property
    def heat(self) -> float:
        """Modelled heat h (1: the continuous force held for ever)."""
        return self._heat

    @property
    def limit_n(self) -> float:
        """Force limit [N] for the next tick, between F_c and F_p."""
        return self._limit

    @property
    def hot(self) -> bool:
        """Whether the limit is being held below the peak (the motors are warm)."""
        return self._hot

    def step(self, force_n: float, device_temperature: float | None = None) -> float:
        """Advance one servo period in which the device displayed ``force_n`` [N].

        ``device_temperature``: the device's own normalised motor temperature (the warmest
        motor), when it reports one. A non-finite force counts as the peak (the worst case).
        Returns the limit [N] for the next tick.
        """
        p = self.params
        f = abs(force_n) if math.isfinite(force_n) else p.peak_force_n
        h = self._heat + self._a * (f * f * self._inv_fc2 - self._heat)
        self._heat = h
        dev = device_temperature if device_temperature is not None else 0.0
        if not math.isfinite(dev):
            dev = 1.0
        if not self._hot:
            if h > 1.0 or dev > p.device_hot:
                self._hot = True
                # start from the force of the moment: the clamp never steps the force down
                self._limit = min(self._limit, max(f, p.continuous_force_n))
        elif h < p.release_heat and dev < p.device_cool:
            self._hot = False
        lim = self._limit
        if self._hot:
            lim = lim - self._dl
            if lim < p.continuous_force_n:
                lim = p.continuous_force_n
        elif lim < p.peak_force_n:
            lim = lim + self._dl
            if lim > p.peak_force_n:
                lim = p.peak_force_n
        self._limit = lim
        return lim
