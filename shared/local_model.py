"""The local model L(z): a proportional or proportional-integral virtual coupling at the servo rate.

Paper eq. (12): ``L(z) = K_h + T*I/(z - 1)``, stepped every servo period T with the penetration
e [m] in and the interaction force [N] out (along the outward normal: it pushes the probe out of
the object, and the object inward by the same amount, Step 3 of section 6).

Difference equations implemented (n is the servo tick)::

    f(n)   = K_h * e(n) + s(n)                       proportional + integral force [N]
    s(n+1) = s(n) + T * I * (e(n) - theta(n))        integrator fed with e - theta (sec. 5.1)

which is the state-space realization ``A_L = 1, B_L = 1, C_L = T*I, D_L = K_h`` of eq. (12) with
state ``lambda = s / (T*I)`` (see :func:`shared.stability.local_model_state_space`).

The integration threshold theta (section 5.1):

- ``fixed`` (eq. 17): theta = 0 out of contact, theta_bar in contact;
- ``variable`` (eq. 18): theta_1 while penetrating or holding; while exiting theta grows linearly
  with the integral force s up to theta_2, reached when s >= i_tot_bar. The paper prints the
  exiting branch as theta_2 / I_tot, which its own text ("grows linearly ... up to a certain limit
  and then is fixed to such limit") contradicts; we implement the text:
  theta = theta_2 * min(1, s / i_tot_bar). "Exiting" is decided each tick from the probe's own
  depth rate (the user's motion, never the proxy's jumps), low-pass filtered: exiting while it is
  below ``-direction_deadband_m_s`` (or, without a depth rate, while e falls by more than
  ``direction_deadband_m`` per tick).

Why eq. 18's branch has no memory. Eq. 18 makes theta a function of the penetration speed *now*.
An earlier version latched the branch (exiting until a motion inward was seen), which turns eq.
18 into a relay with hysteresis inside the loop: switching to theta_2 drains the integral, the
hand sinks back in, which reads as "penetrating", back to theta_1, the integral refills and
pushes the hand out, which reads as "exiting" ... A relay with hysteresis closed around a lagging
loop sustains a limit cycle (describing function: the hysteresis is a phase lag, so each cycle
feeds energy in); with the simulated hand it was 0.55-0.6 mm peak to peak at K_o = 300 and
1000 N/m once anything (a 2 mm nudge of the hand) set it off, 1 mm in the loopback demo, and no
speed deadband can stop it because the switch itself moves the probe at tens of mm/s. Without the
latch the branch is a memoryless function of the filtered speed: the extra integral drain acts
only while the probe moves out faster than the deadband, so it behaves like a (nonlinear) spring
on the outward stroke rather than a delayed relay, and nothing is left switched once the motion
stops. Measured with the simulated hand holding a press, nudged: 0.02-0.09 mm peak to peak (eq.
17: 0-0.07 mm), no branch switch during the hold; over eleven hands spanning the design's hand
box at most 0.25 mm (300 N/m) and 0.48 mm (1000 N/m), eq. 17 0.6 mm and one 10 mm bounce.

Contact is unilateral by default: a contact only pushes. Out of contact (e <= 0) the proportional
term is zero and the integral force is *driven to zero linearly* over ``release_time_s`` rather
than dropped at once (section 5.1: "this should not occur instantaneously ... Typical time
intervals can be small multiples of NT"). The integral never pulls (s >= 0) and the force is never
negative. ``unilateral=False`` gives the linear bilateral coupling analysed in sections 3-5 (used to
reproduce Fig. 7 and to check the lifting against a direct simulation).

Changing gains without a bump. A new patch may bring new gains in the middle of a press (the
interim gains of a new K_o cell replaced by the designed ones a few seconds later, on a busy
machine during a hold). The integral force is kept, but the proportional part steps by
(K_h,old - K_h,new)*e: with A's hold in the two-user demo (e = 6.6 mm) tripling K_h from 43 to
127 N/m threw a 0.56 N jolt at the hand and moved the probe 2 mm within 0.1 s. With
``gain_transfer_s`` > 0 the step is carried by a transfer force b that takes its place at the
change and is driven linearly to zero over ``gain_transfer_s`` ("bumpless parameter changes",
Astrom and Hagglund, *Advanced PID Control*, ISA 2006)::

    f(n) = K_h * e(n) + s(n) + b(n),    b -> b + (K_h,old - K_h,new) * e  at a change

The loop itself is the new gains' (the design verified for them) from the first tick; b is an
input from outside it, bounded by the step it replaces and gone after ``gain_transfer_s``. Out of
contact b is zero.

Nothing here reads a clock: time advances one servo period per :meth:`LocalModel.step`.
"""

from __future__ import annotations

import math
from dataclasses import field, replace
from typing import Literal

from haptic_collab.shared.checks import (
    NonNegFinite,
    PositiveFinite,
    PositiveOrInf,
    params_dataclass,
)
from haptic_collab.shared.checks import nonneg as _finite_nonneg

ThresholdMode = Literal["none", "fixed", "variable"]


@params_dataclass(frozen=True, slots=True)
class ThresholdParams:
    """Integration threshold theta of section 5.1 (eq. 17 and 18). All lengths in metres.

    Parameters
    ----------
    mode : {"none", "fixed", "variable"}
        ``none``: theta = 0 (the integral drives e to zero); ``fixed``: eq. 17 with ``theta_m``;
        ``variable``: eq. 18 with ``theta_1_m``, ``theta_2_m`` and ``i_tot_bar_n``.
    theta_m : float
        theta_bar of eq. 17 [m]: the steady-state penetration tolerated.
    theta_1_m, theta_2_m : float
        eq. 18 thresholds [m] while penetrating and (at most) while exiting.
    i_tot_bar_n : float
        Integral force [N] at which the exiting threshold reaches ``theta_2_m`` (eq. 18's I_tot bar).
    direction_deadband_m : float
        Used when :meth:`LocalModel.step` is given no probe velocity: eq. 18 exits on a tick whose
        penetration falls by more than this [m]; otherwise theta_1.
    direction_deadband_m_s : float
        With a probe velocity given to :meth:`LocalModel.step`: eq. 18 exits while the filtered
        probe speed *out* of the object exceeds this [m/s]; slower, still, or inward: theta_1. It
        must exceed what encoder quantization can make of the filtered speed: a probe whose
        reported position stays within R counts of q [m] gives at most ``R q / (T + tau)``
        (:func:`encoder_speed_bound`).
    direction_filter_s : float
        Time constant tau [s] of the first-order filter on that probe velocity (> 0).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Negative, non-finite or non-numeric values, an unknown
        mode, or i_tot_bar_n <= 0 in variable mode.
    """

    mode: ThresholdMode = "fixed"
    theta_m: NonNegFinite = 0.001
    theta_1_m: NonNegFinite = 0.0005
    theta_2_m: NonNegFinite = 0.003
    i_tot_bar_n: NonNegFinite = 1.0
    direction_deadband_m: NonNegFinite = 0.0
    direction_deadband_m_s: NonNegFinite = 0.0
    direction_filter_s: PositiveFinite = 0.02

    def __post_init__(self) -> None:
        if self.mode == "variable" and self.i_tot_bar_n <= 0.0:
            raise ValueError("i_tot_bar_n must be > 0 for the variable threshold (eq. 18)")


def encoder_speed_bound(
    encoder_resolution_m: float, counts: float, filter_s: float, servo_period_s: float
) -> float:
    """Largest filtered speed [m/s] that quantization alone can produce: ``R q / (T + tau)``.

    The filter is ``v_f(n) = v_f(n-1) + a (v(n) - v_f(n-1))``, ``a = T / (T + tau)``, on the
    backward difference ``v(n) = (x(n) - x(n-1)) / T`` of the reported position. Summing by parts,
    ``v_f(n) = (a / T) (x(n) - sum_k a (1 - a)^k x(n - 1 - k))`` (from rest): the reported position
    minus a weighted mean (weights summing to at most 1) of earlier ones. If every reported
    position lies within ``R`` counts (a band of width ``R q``), ``|v_f| <= a R q / T =
    R q / (T + tau)``, whatever the pattern of the noise. A still probe dithering over ``R``
    counts can therefore never drive the filtered speed past this bound.

    Parameters
    ----------
    encoder_resolution_m : float
        Encoder count q [m], >= 0.
    counts : float
        Width R of the band of counts the noise spans, >= 0.
    filter_s, servo_period_s : float
        Filter time constant tau [s] and servo period T [s], > 0.

    Raises
    ------
    ValueError
        Out-of-range values.
    """
    q = _finite_nonneg("encoder_resolution_m", encoder_resolution_m)
    r = _finite_nonneg("counts", counts)
    for name, v in (("filter_s", filter_s), ("servo_period_s", servo_period_s)):
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"{name} must be > 0 s, got {v!r}")
    return r * q / (servo_period_s + filter_s)


@params_dataclass(frozen=True, slots=True)
class LocalModelParams:
    """Parameters of the local model (eq. 12), SI units.

    Parameters
    ----------
    k_h : float
        Proportional stiffness K_h [N/m], > 0.
    i_gain : float
        Integral weight I [N/(m*s)], >= 0; 0 gives the proportional local model L(z) = K_h.
    servo_period_s : float
        Servo period T [s], > 0 (1e-3 for a 1 kHz servo rate).
    threshold : ThresholdParams
        Integration threshold (eq. 17-18).
    release_time_s : float
        Interval [s] over which the integral force is driven linearly to zero on release (> 0);
        pick a small multiple of the simulation period N*T (section 5.1).
    unilateral : bool
        True: a contact only pushes (e <= 0 is no contact). False: the linear bilateral coupling of
        the paper's analysis.
    integral_limit_n : float
        Largest integral force [N] (anti-windup). Set it to the device's maximum force: an integral
        beyond what the device can render only makes the surface push on after the user leaves.
    recovery_m_per_n : float
        The object's compliance 1/K_o [m/N], >= 0 (0: off). With an integral, a contact is kept
        while the probe stays within ``s * recovery_m_per_n`` outside the proxy: the object's
        surface follows a retreating probe back by the deformation the integral force holds, and
        the proxy is a copy of it one loop delay old. Without it, a PI contact on a soft object
        releases whenever the probe leaves the stale proxy by a fraction of a millimetre, and
        falls into a relaxation limit cycle (``haptic bench fidelity`` measured up to 4 mm peak to
        peak). The local model stays linear (eq. 12) inside that band, as the analysis assumes.
    gain_transfer_s : float
        Time [s] over which the force step of a change of gains in contact is carried off
        (module docstring, "Changing gains without a bump"), >= 0; 0 (default): the force steps
        as eq. (12) with the new gains says.

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values
        (``integral_limit_n`` may be ``inf``).
    """

    k_h: PositiveFinite
    i_gain: NonNegFinite = 0.0
    servo_period_s: PositiveFinite = 1e-3
    threshold: ThresholdParams = field(default_factory=ThresholdParams)
    release_time_s: PositiveFinite = 0.1
    unilateral: bool = True
    integral_limit_n: PositiveOrInf = math.inf
    recovery_m_per_n: NonNegFinite = 0.0
    gain_transfer_s: NonNegFinite = 0.0


class LocalModel:
    """Stateful local model L(z) of eq. (12) with the threshold of eq. (17)/(18).

    Call :meth:`step` once per servo tick with the penetration [m]; it returns the force magnitude
    [N] along the outward normal. Gains may be changed between ticks with :meth:`set_gains` (the
    integral state is kept and, with ``gain_transfer_s``, the proportional part's step is carried
    off smoothly).

    Examples
    --------
    >>> lm = LocalModel(LocalModelParams(k_h=200.0))
    >>> lm.step(0.005)
    1.0
    """

    __slots__ = (
        "params",
        "_s_max",
        "_k_h",
        "_ti",
        "_s",
        "_theta",
        "_e_prev",
        "_exiting",
        "_release_step",
        "_force",
        "_in_contact",
        "_v_f",
        "_a_v",
        "_rec",
        "_b",
        "_b_step",
    )

    def __init__(self, params: LocalModelParams) -> None:
        self.params = params
        self._k_h = params.k_h
        self._ti = params.servo_period_s * params.i_gain
        self._s_max = params.integral_limit_n
        self._rec = params.recovery_m_per_n
        th = params.threshold
        self._a_v = params.servo_period_s / (params.servo_period_s + th.direction_filter_s)
        self.reset()

    def reset(self) -> None:
        """Forget the integral and contact state (force 0 on the next tick out of contact)."""
        self._s = 0.0
        self._theta = 0.0
        self._e_prev = 0.0
        self._exiting = False
        self._release_step = 0.0
        self._force = 0.0
        self._in_contact = False
        self._v_f = 0.0
        self._b = 0.0
        self._b_step = 0.0

    def set_gains(
        self,
        k_h: float,
        i_gain: float,
        recovery_m_per_n: float | None = None,
        *,
        carry_n: float = 0.0,
        drop_integral: bool = False,
    ) -> None:
        """Replace K_h [N/m] and I [N/(m*s)] between ticks; the integral force is kept.

        With ``drop_integral`` and in contact, the integral force is handed to the transfer force
        instead (it then fades over ``gain_transfer_s``, or at once without it): a local model
        with own-force compensation carries the force the object holds in its compensation, an
        integral kept beside it would push the surface in for ever (:mod:`shared.full_loop`).

        ``recovery_m_per_n`` (1/K_o of the new patch [m/N], see :class:`LocalModelParams`)
        replaces the contact's recovery band when given. In contact, with ``gain_transfer_s`` >
        0, the step (K_h,old - K_h,new)*e of the last tick's penetration e, plus ``carry_n`` [N]
        (the step of a force the caller adds on top, e.g. a probe damper's (B_old - B_new)*v),
        becomes a transfer force driven to zero over ``gain_transfer_s`` (module docstring).

        Raises
        ------
        ValueError
            If the gains are out of range (see :class:`LocalModelParams`).
        """
        k_old = self._k_h
        if recovery_m_per_n is None:
            self.params = replace(self.params, k_h=k_h, i_gain=i_gain)
        else:  # one validated copy (all or nothing), not two: this runs inside a servo tick
            self.params = replace(
                self.params, k_h=k_h, i_gain=i_gain, recovery_m_per_n=recovery_m_per_n
            )
        self._k_h = self.params.k_h
        self._ti = self.params.servo_period_s * self.params.i_gain
        self._rec = self.params.recovery_m_per_n
        step = (k_old - self._k_h) * self._e_prev + carry_n
        if drop_integral and self._in_contact and self._s != 0.0:
            step += self._s
            self._s = 0.0
        transfer = self.params.gain_transfer_s
        if self._in_contact and transfer > 0.0 and step != 0.0 and math.isfinite(step):
            self._b += step
            self._b_step = self._b * self.params.servo_period_s / transfer

    @property
    def transfer_n(self) -> float:
        """Transfer force b [N] still carried from the last change of gains (0 when none)."""
        return self._b

    @property
    def integral_n(self) -> float:
        """Current integral force s [N]."""
        return self._s

    @property
    def theta_m(self) -> float:
        """Threshold theta [m] used on the last tick."""
        return self._theta

    @property
    def force_n(self) -> float:
        """Force [N] returned by the last tick (Step 3: the force the simulation samples)."""
        return self._force

    @property
    def in_contact(self) -> bool:
        """Whether the last tick was in contact (e > 0, or always for a bilateral coupling)."""
        return self._in_contact

    def _threshold(self, e: float, v: float | None) -> float:
        th = self.params.threshold
        if th.mode == "none":
            return 0.0
        if th.mode == "fixed":
            return th.theta_m
        # eq. 18 is a function of the penetration speed *now*: no state is latched (module
        # docstring, "Why eq. 18's branch has no memory").
        if v is not None:
            # the user's motion decides (never the proxy's jumps): filtered probe depth rate
            self._v_f += self._a_v * (v - self._v_f)
            exiting = self._v_f < -th.direction_deadband_m_s
        else:
            exiting = e - self._e_prev < -th.direction_deadband_m
        self._exiting = exiting
        if not exiting:
            return th.theta_1_m
        ratio = self._s / th.i_tot_bar_n
        return th.theta_2_m * (ratio if ratio < 1.0 else 1.0)

    def step(self, penetration_m: float, depth_rate_m_s: float | None = None) -> float:
        """Advance one servo period with penetration e [m]; return the force [N] (eq. 12).

        ``depth_rate_m_s`` is the probe's velocity along the inward normal [m/s] (its backward
        difference); eq. 18's penetrating/exiting branch follows it, filtered, when given, and
        the change of e otherwise. A non-finite penetration is treated as loss of contact (the
        force ramps down, never jumps).
        """
        e = penetration_m
        if not math.isfinite(e):
            e = -1.0
        p = self.params
        b = self._b
        if b != 0.0:  # the transfer force of a change of gains, driven to zero
            nb = b - self._b_step
            self._b = nb if (nb > 0.0) == (b > 0.0) and nb != 0.0 else 0.0
        if not p.unilateral:
            self._in_contact = True
            theta = self._threshold(e, depth_rate_m_s) if self._ti > 0.0 else 0.0
            f = self._k_h * e + self._s + b
            s = self._s + self._ti * (e - theta)
            self._s = s if abs(s) <= self._s_max else math.copysign(self._s_max, s)
        elif e > 0.0 or (self._in_contact and e > -self._s * self._rec):
            self._in_contact = True
            theta = self._threshold(e, depth_rate_m_s) if self._ti > 0.0 else 0.0
            f = self._k_h * e + self._s + b
            s = self._s + self._ti * (e - theta)
            self._s = 0.0 if s < 0.0 else (s if s < self._s_max else self._s_max)
            self._release_step = 0.0
            if f < 0.0:
                f = 0.0
        else:
            # Release: drive the integral force to zero linearly over release_time_s (sec. 5.1).
            theta = 0.0
            if self._in_contact or self._release_step == 0.0:
                self._release_step = self._s * p.servo_period_s / p.release_time_s
            self._in_contact = False
            self._v_f = 0.0  # a new contact starts from rest
            self._exiting = False
            self._b = 0.0  # no transfer out of contact
            f = self._s
            s = self._s - self._release_step
            self._s = s if s > 0.0 else 0.0
        self._theta = theta
        self._e_prev = e
        self._force = f
        return f
