"""Time-domain passivity observer and controller (PO/PC) at the haptic device port.

After Hannaford and Ryu, "Time-domain passivity control of haptic interfaces", IEEE Trans.
Robotics and Automation 18(1), 2002, and Ryu, Kwon and Hannaford, "Stable teleoperation with
time-domain passivity control", IEEE TRA 20(2), 2004: the impedance-causality version for a haptic
display. The device is the position (flow) input, the virtual environment (here the local model,
:mod:`shared.local_model`) returns a force, and the PC is a variable damper *in series* with the
environment (same velocity, forces add), so it can only add dissipation.

Sign conventions (force ``f`` [N] is the force ON the handle, ``v`` [m/s] the handle velocity):

- the power the environment receives from the user is ``-f . v``; ``+f . v`` is delivered to him;
- the observed energy E > 0 means the environment has absorbed energy so far (passive so far),
  E < 0 means it has produced energy (active).

Difference equations implemented (n is the servo tick, T the servo period, v(n) the backward
difference (x(n) - x(n-1)) / T supplied by the caller, f_a the force actually applied, f_d the
force the environment asked for)::

    E(n)      = E(n-1) - f_a(n-1) . (x(n) - x(n-1))          observer, exact for a zero-order hold
    E_p(n)    = E(n) - T f_d(n) . v(n)                       prediction over the coming tick
    alpha(n)  = min(alpha_max, (-E_bias - E_p(n)) / (T |v(n)|^2))   if E_p(n) < -E_bias, else 0
    f_a(n)    = clamp(f_d(n) - alpha(n) v(n), f_max)         series damper, then the force limit

The one-tick alignment matters: the force applied during tick n-1 acted while the handle moved
from x(n-1) to x(n), so the observer pairs f_a(n-1) with v(n) (Hannaford and Ryu's rectangular
sum pairs f(n) with v(n), which credits the zero-order hold with dissipation it does not have).
With the exact alignment a sampled spring ``f = -K x`` is seen as slightly active: it leaks
``K/2 sum |x(n) - x(n-1)|^2`` to the user, the energy of Colgate and Schenkel's passivity
condition ``b > K T / 2``. A local model with at least that much damping is seen as passive;
without it the PC supplies the missing damping (or ``energy_bias_j`` tolerates the leak).

The prediction uses the current velocity, so E can end a tick below ``-energy_bias_j`` by the
prediction error ``T f . (v(n+1) - v(n))``, by the damping limit ``alpha_max`` (a device can only
render so much damping at its servo rate) or by the force limit; the PC repays such a deficit on
the following ticks. With zero velocity no damper can dissipate anything and the force passes
through unchanged.

Reset policy: energy exchanged while out of contact is zero, so by default (``reset_on_release``)
the observer forgets E whenever the desired force is exactly zero, which is what the unilateral
local model returns out of contact. Each contact is therefore kept passive on its own: a surplus
stored by one contact (a user pressing long into a damped surface) cannot mask an active next
contact, a deficit left at release is not repaid as drag in free space, and energy stored in a
released virtual spring is returned during the release, before the force reaches zero, and is
legitimately accounted. :meth:`PassivityController.reset` does the same on demand (for instance
when a new session or a new patch must start from a clean slate).

Nothing here reads a clock or allocates arrays: :meth:`PassivityController.step` uses plain floats
so that it can run at 1 kHz in CPython.
"""

from __future__ import annotations

import math

from haptic_collab.shared.checks import (
    NonNegFinite,
    PositiveFinite,
    PositiveOrInf,
    params_dataclass,
)


@params_dataclass(frozen=True, slots=True, kw_only=True)
class PassivityParams:
    """Parameters of the passivity observer and controller, SI units.

    Parameters
    ----------
    max_damping_n_s_per_m : float
        Largest damping alpha the PC may render [N*s/m], finite and > 0: the device's limit at its
        servo rate (a larger damper at 1 kHz would itself vibrate).
    enabled : bool
        True: the PC acts. False: the force passes through unchanged (up to ``max_force_n``) and
        the observer still measures energy (telemetry).
    energy_bias_j : float
        Energy [J] the environment may give the user before the PC acts, finite and >= 0: a small
        tolerance for sampling and encoder noise. The PC keeps E >= -energy_bias_j.
    servo_period_s : float
        Servo period T [s], finite and > 0 (1e-3 for a 1 kHz servo rate).
    max_force_n : float
        Largest force magnitude [N] sent to the device, > 0 (may be ``inf``). The desired force is
        clamped before the prediction and the force out after the damper.
    reset_on_release : bool
        True: forget E on every tick whose desired force is exactly zero (out of contact).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-boolean flags, or non-finite, non-numeric or
        out-of-range numbers (``max_force_n`` may be ``inf``).
    """

    max_damping_n_s_per_m: PositiveFinite
    enabled: bool = True
    energy_bias_j: NonNegFinite = 0.0
    servo_period_s: PositiveFinite = 1e-3
    max_force_n: PositiveOrInf = math.inf
    reset_on_release: bool = True


class PassivityController:
    """Passivity observer and series-damper controller at the device port (Hannaford and Ryu 2002).

    Call :meth:`step` once per servo tick, between computing the environment's force and writing
    the device, with that force and the device velocity; write the force it returns. See the
    module docstring for the difference equations and sign conventions.

    Parameters
    ----------
    params : PassivityParams
        Limits, tolerance and servo period.

    Examples
    --------
    >>> pc = PassivityController(PassivityParams(max_damping_n_s_per_m=20.0))
    >>> pc.step(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    (1.0, 0.0, 0.0)
    """

    __slots__ = (
        "params",
        "_t",
        "_b_max",
        "_bias",
        "_f_max",
        "_f_max2",
        "_energy",
        "_dissipated",
        "_active",
        "_alpha",
        "_was_active",
        "_fdx",
        "_fdy",
        "_fdz",
        "_fax",
        "_fay",
        "_faz",
    )

    def __init__(self, params: PassivityParams) -> None:
        self.params = params
        self._t = params.servo_period_s
        self._b_max = params.max_damping_n_s_per_m
        self._bias = params.energy_bias_j
        self._f_max = params.max_force_n
        self._f_max2 = params.max_force_n * params.max_force_n
        self._dissipated = 0.0
        self._active = 0.0
        self._fdx = self._fdy = self._fdz = 0.0
        self._fax = self._fay = self._faz = 0.0
        self.reset()

    def reset(self) -> None:
        """Forget the observed energy E (set it to 0 J) and the last alpha.

        The force held from the last tick is still accounted on the next tick (it acts until
        then), and the running totals :attr:`dissipated_energy_j` and :attr:`active_energy_j` are
        kept. Build a new controller to start from nothing.
        """
        self._energy = 0.0
        self._alpha = 0.0
        self._was_active = False

    @property
    def observed_energy_j(self) -> float:
        """Observed energy E(n) [J] the environment (with the PC) has absorbed since the last reset.

        Computed from the forces actually applied and the true displacements: ``-E`` is exactly the
        net energy delivered to the user.
        """
        return self._energy

    @property
    def dissipated_energy_j(self) -> float:
        """Total energy [J] the PC's damper removed since construction, >= 0.

        Summed as ``alpha(n) |v(n)|^2 T`` (Hannaford and Ryu's accounting, with the damper's share
        of any force-limit scaling), that is with the velocity of the tick the damper acts on.
        """
        return self._dissipated

    @property
    def active_energy_j(self) -> float:
        """Total energy [J] the environment, before the PC, gave the user while the port was active.

        Sums ``max(0, f_d(n-1) . (x(n) - x(n-1)))`` over the ticks whose prediction found a deficit
        (``E_p < -energy_bias_j``), whether or not the PC is enabled: what the PC had to fight, or
        what the user received with the PC disabled. Zero for a passive environment. Telemetry.
        """
        return self._active

    @property
    def alpha_n_s_per_m(self) -> float:
        """Damping alpha [N*s/m] the PC commanded on the last tick, in [0, max_damping_n_s_per_m]."""
        return self._alpha

    def step(
        self, fx: float, fy: float, fz: float, vx: float, vy: float, vz: float
    ) -> tuple[float, float, float]:
        """Observe the last interval and return the force to apply during this tick.

        Parameters
        ----------
        fx, fy, fz : float
            Force [N] the environment wants to apply ON the handle this tick, f_d(n).
        vx, vy, vz : float
            Handle velocity [m/s], the backward difference (x(n) - x(n-1)) / T over the interval
            that just ended.

        Returns
        -------
        (3,) tuple of float
            Force [N] to write to the device, f_a(n): f_d(n) minus the PC's damping alpha(n) v(n),
            clamped to ``max_force_n`` in magnitude.

        Raises
        ------
        ValueError
            If any input is not finite (the state is left unchanged).
        """
        if not math.isfinite(fx + fy + fz + vx + vy + vz):
            raise ValueError(
                f"passivity step needs finite force and velocity, got f=({fx!r}, {fy!r}, {fz!r}) "
                f"v=({vx!r}, {vy!r}, {vz!r})"
            )
        t = self._t
        dx = vx * t
        dy = vy * t
        dz = vz * t
        # Observer: the force held over the interval that just ended against its displacement.
        energy = self._energy - (self._fax * dx + self._fay * dy + self._faz * dz)
        if self._was_active:
            out = self._fdx * dx + self._fdy * dy + self._fdz * dz
            if out > 0.0:
                self._active += out
        if fx == 0.0 and fy == 0.0 and fz == 0.0 and self.params.reset_on_release:
            energy = 0.0
        # Desired force, limited to what the device can render.
        f2 = fx * fx + fy * fy + fz * fz
        if f2 > self._f_max2:
            s = self._f_max / math.sqrt(f2)
            fx *= s
            fy *= s
            fz *= s
        self._fdx = fx
        self._fdy = fy
        self._fdz = fz
        # Controller: predict the energy after this tick with the current velocity.
        predicted = energy - t * (fx * vx + fy * vy + fz * vz)
        active = predicted < -self._bias
        alpha = 0.0
        vv = vx * vx + vy * vy + vz * vz
        if active and vv > 0.0 and self.params.enabled:
            deficit = -self._bias - predicted
            tvv = t * vv
            # Written without a division that a tiny |v| could overflow or make 0/0.
            alpha = self._b_max if deficit >= self._b_max * tvv else deficit / tvv
            fx -= alpha * vx
            fy -= alpha * vy
            fz -= alpha * vz
            f2 = fx * fx + fy * fy + fz * fz
            scale = 1.0
            if f2 > self._f_max2:
                scale = self._f_max / math.sqrt(f2)
                fx *= scale
                fy *= scale
                fz *= scale
            self._dissipated += scale * alpha * vv * t
        self._energy = energy
        self._was_active = active
        self._alpha = alpha
        self._fax = fx
        self._fay = fy
        self._faz = fz
        return (fx, fy, fz)
