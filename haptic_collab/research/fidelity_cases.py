"""What one cell of the fidelity benchmark is: the object, the user's trajectory, the cell itself,
the run's options and its record.

The 1-D model of :mod:`haptic_collab.research.fidelity_1d` along the contact normal (depths in
metres, positive into the object): :class:`ObjectModel` the simulated object relative to the K_o
the simulation reports (:data:`OBJECTS`), :class:`Trajectory` the user's intended probe depth and
where the metrics are taken (:data:`TRAJECTORIES`, :func:`felt_trajectory`), :class:`Cell` one
simulation (a scheme's rendering, an object, a rate, a delay, a hand and a trajectory),
:class:`RunOptions` the servo's imperfections and :class:`Run` the servo-rate record of a batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.research.fidelity_schemes import Rendering
from haptic_collab.shared.full_loop import Hand
from haptic_collab.shared.types import FloatArray

#: A probe further than this from the surface [m] (or not finite) has run away.
RUNAWAY_M = 0.5

ObjectKind = Literal["spring", "sls", "stiffening"]


def stiffening_force(k1: FloatArray | float, xs: FloatArray | float, x: FloatArray) -> FloatArray:
    """``k_1 x_s (exp(x / x_s) - 1)`` [N] at depth ``x`` >= 0 [m] (the exponent capped at 50)."""
    return np.asarray(k1 * xs * np.expm1(np.minimum(x / xs, 50.0)))


def stiffening_depth(k1: FloatArray | float, xs: FloatArray | float, f: FloatArray) -> FloatArray:
    """Depth [m] at which the stiffening law holds the force ``f`` >= 0 [N] (its inverse)."""
    return np.asarray(xs * np.log1p(f / (k1 * xs)))


def stiffening_tangent(k1: FloatArray | float, xs: FloatArray | float, x: FloatArray) -> FloatArray:
    """Tangent stiffness ``k_1 exp(x / x_s)`` [N/m] at depth ``x`` >= 0 [m]."""
    return np.asarray(k1 * np.exp(np.minimum(x / xs, 50.0)))


@dataclass(frozen=True, slots=True)
class ObjectModel:
    """The simulated object along the contact normal (SI units), relative to the K_o reported.

    The simulation reports K_o (what the product's gain design and every scheme that uses a
    stiffness is given) and B_o (:meth:`reported_b_o`), as the product's World does, and
    nothing more; the object itself is ``stiffness_error`` times stiffer, and may have dynamics
    the design does not model:

    ``spring``
        ``F = k_1 x`` (eq. 6 with B_o = 0): what the product's design assumes.
    ``sls``
        a standard linear solid with a surface mass: ``m x'' + b x' + k_1 x + k_2 (x - q) = F``
        with the Maxwell arm ``c_2 q' = k_2 (x - q)``, ``c_2 = k_2 tau``: instantaneous stiffness
        ``k_1 + k_2``, relaxing to ``k_1`` with time constant ``tau`` (Fung, "Biomechanics",
        1993, ch. 2). Stepped by implicit Euler at the simulation rate, as a slow simulation does.
    ``stiffening``
        ``F = k_1 x_s (exp(x / x_s) - 1)``: the exponential strain stiffening of soft tissue
        (Fung 1993), tangent stiffness ``k_1 exp(x / x_s)``; quasi-static.

    with ``k_1 = stiffness_error K_o`` and ``k_2 = relax_ratio k_1``. The contact is unilateral.

    Attributes
    ----------
    name : str
    kind : {"spring", "sls", "stiffening"}
    stiffness_error : float
        True static stiffness over the K_o reported, > 0 (1.2: the object is 20 % stiffer).
    mass_kg, damping_n_s_per_m : float
        Surface mass [kg] and damping [N*s/m] (``sls``).
    relax_ratio : float
        ``k_2 / k_1`` (``sls``).
    relax_time_s : float
        ``tau`` [s] (``sls``).
    stiffening_m : float
        ``x_s`` [m] (``stiffening``).
    """

    name: str = "spring"
    kind: ObjectKind = "spring"
    stiffness_error: float = 1.0
    mass_kg: float = 0.0
    damping_n_s_per_m: float = 0.0
    relax_ratio: float = 0.0
    relax_time_s: float = 0.0
    stiffening_m: float = 0.0

    def __post_init__(self) -> None:
        ok = (
            math.isfinite(self.stiffness_error)
            and self.stiffness_error > 0.0
            and all(
                math.isfinite(v) and v >= 0.0
                for v in (self.mass_kg, self.damping_n_s_per_m, self.relax_ratio)
            )
            and (self.kind != "sls" or self.relax_time_s > 0.0)
            and (self.kind != "stiffening" or self.stiffening_m > 0.0)
        )
        if not ok:
            raise ValueError(f"object model {self.name!r} has an absurd parameter: {self!r}")

    def static_depth_m(self, k_o: float, force_n: FloatArray) -> FloatArray:
        """Depth [m] at which the relaxed object holds ``force_n`` [N] (>= 0) still."""
        k1 = k_o * self.stiffness_error
        f = np.maximum(force_n, 0.0)
        if self.kind == "stiffening":
            return stiffening_depth(k1, self.stiffening_m, f)
        return np.asarray(f / k1)

    def static_force_n(self, k_o: float, depth_m: FloatArray | float) -> FloatArray:
        """Force [N] with which the relaxed object holds a depth ``depth_m`` [m] (0 outside)."""
        k1 = k_o * self.stiffness_error
        x = np.maximum(np.asarray(depth_m, dtype=float), 0.0)
        if self.kind == "stiffening":
            return stiffening_force(k1, self.stiffening_m, x)
        return np.asarray(k1 * x)

    def impedance(self, k_o: float, freq_hz: float, depth_m: float) -> complex:
        """The object's own dynamic stiffness dF/dx [N/m] at ``freq_hz`` about ``depth_m``: what
        an ideal rendering would make the hand feel (the reference of :func:`felt_response`)."""
        k1 = k_o * self.stiffness_error
        w = 2.0 * math.pi * freq_hz
        if self.kind == "stiffening":
            return complex(stiffening_tangent(k1, self.stiffening_m, np.asarray(depth_m)))
        if self.kind == "sls":
            k2 = self.relax_ratio * k1
            jwt = 1j * w * self.relax_time_s
            return (
                k1 + k2 * jwt / (1.0 + jwt) - self.mass_kg * w * w + 1j * w * self.damping_n_s_per_m
            )
        return complex(k1)

    def one_tick_stiffness(self, k_o: float, sim_rate_hz: float) -> float:
        """The stiffness [N/m] the object shows over the first simulation tick of a step push
        from rest: ``m / h^2 + b / h + k_1 + k_2 tau / (tau + h)`` with ``h`` the simulation
        period (the implicit-Euler step the simulator takes); ``k_1`` for the quasi-static
        objects (their tangent at rest).

        Raises
        ------
        ValueError
            Non-positive or non-finite ``k_o`` or ``sim_rate_hz``.
        """
        if not (
            math.isfinite(k_o) and k_o > 0.0 and math.isfinite(sim_rate_hz) and sim_rate_hz > 0
        ):
            raise ValueError(f"k_o and sim_rate_hz must be > 0, got {k_o!r}, {sim_rate_hz!r}")
        k1 = k_o * self.stiffness_error
        if self.kind != "sls":
            return k1
        h = 1.0 / sim_rate_hz
        k2 = self.relax_ratio * k1
        tau = self.relax_time_s
        return self.mass_kg / h**2 + self.damping_n_s_per_m / h + k1 + k2 * tau / (tau + h)

    def reported_b_o(self, k_o: float, sim_rate_hz: float) -> float:
        """The paper's ``B_o`` [N/m] (eq. 9) the simulation reports beside ``k_o``, defined as the
        product's World defines it for its damped and massive objects
        (``server.objects.fem.FemSolid.contact_damping``): the one-tick stiffness from rest less
        the static one. The simulation's model of the object is off by ``stiffness_error`` as its
        K_o is, so both are scaled by it: ``(one_tick - k_1) / stiffness_error`` (0 for the
        springs and the quasi-static stiffening object).

        Raises
        ------
        ValueError
            As :meth:`one_tick_stiffness`.
        """
        k1 = k_o * self.stiffness_error
        return max(0.0, (self.one_tick_stiffness(k_o, sim_rate_hz) - k1) / self.stiffness_error)

    def reported_k_o(self, k_o: float, depth_m: float) -> float:
        """The K_o [N/m] the simulation reports with its surface at ``depth_m`` [m] (as
        :func:`haptic_collab.research.fidelity_1d.simulate` publishes it): the stiffening
        object's tangent stiffness as the simulation believes it; ``k_o`` for every other."""
        if self.kind == "stiffening":
            d = max(float(depth_m), 0.0)
            return float(stiffening_tangent(k_o, self.stiffening_m, np.asarray(d)))
        return float(k_o)

    def peak_stiffness(self, k_o: float, depth_m: float) -> float:
        """The largest |dF/dx| [N/m] the object shows down to ``depth_m`` at any speed."""
        k1 = k_o * self.stiffness_error
        if self.kind == "stiffening":
            return float(stiffening_tangent(k1, self.stiffening_m, np.asarray(depth_m)))
        if self.kind == "sls":
            return k1 * (1.0 + self.relax_ratio)
        return k1


#: The design model: a spring of exactly the K_o reported.
SPRING = ObjectModel()
#: The spring, 20 % softer / stiffer than the K_o reported (an estimate off by 20 %).
SPRING_SOFTER = ObjectModel("spring-0.8", stiffness_error=0.8)
SPRING_STIFFER = ObjectModel("spring-1.2", stiffness_error=1.2)
#: A viscoelastic object with mass: twice as stiff to a quick press as at rest, relaxing with
#: a 0.1 s time constant (corner 1.6 Hz, inside the band a hand judges stiffness in), 20 g
#: of surface mass.
SLS = ObjectModel("sls", "sls", mass_kg=0.02, relax_ratio=1.0, relax_time_s=0.1)
#: Strain stiffening: 1.65 times stiffer at 5 mm, 2.7 times at 10 mm.
STIFFENING = ObjectModel("stiffening", "stiffening", stiffening_m=10e-3)
#: Every object model of the benchmark, the design model first.
OBJECTS: tuple[ObjectModel, ...] = (SPRING, SPRING_SOFTER, SPRING_STIFFER, SLS, STIFFENING)


@dataclass(frozen=True, slots=True)
class Trajectory:
    """The user's intended probe depth y(t) [m] (module docstring), and where metrics are taken.

    ``y(t) = y0 + (y1 - y0) r(t) + a sin(2 pi f (t - t_s))`` for ``t_s <= t < t_e`` (whole
    cycles), with the ramp ``r`` going 0 -> 1 from ``ramp_start_s`` over ``ramp_s``, minimum-jerk
    (``ramp="smooth"``) or at constant speed (``"linear"``, the hand already moving at that speed
    at t = 0: an impact).

    Attributes
    ----------
    name : str
        ``press``, ``tap``, ``impact``, or ``sine`` (position source, felt stiffness).
    duration_s : float
    y0_m, y1_m : float
        Start and end depth [m] (negative: outside the object).
    ramp_start_s, ramp_s : float
    ramp : {"smooth", "linear"}
    sine_amplitude_m, sine_hz, sine_start_s, sine_end_s : float
    hold_window_s : (float, float)
        Where hold p2p, force ripple and the steady-state error are measured.
    energy_window_s : (float, float)
        Where the energy given to the user is summed.
    """

    name: str
    duration_s: float
    y0_m: float
    y1_m: float
    ramp_start_s: float = 0.0
    ramp_s: float = 0.0
    ramp: Literal["smooth", "linear"] = "smooth"
    sine_amplitude_m: float = 0.0
    sine_hz: float = 0.0
    sine_start_s: float = 0.0
    sine_end_s: float = 0.0
    hold_window_s: tuple[float, float] = (0.0, 0.0)
    energy_window_s: tuple[float, float] = (0.0, 0.0)

    def target(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(y, y')`` [m], [m/s] at times ``t`` [s] (any shape)."""
        y = np.full_like(t, self.y0_m)
        yd = np.zeros_like(t)
        dy = self.y1_m - self.y0_m
        if self.ramp_s > 0.0:
            u = np.clip((t - self.ramp_start_s) / self.ramp_s, 0.0, 1.0)
            inside = (u > 0.0) & (u < 1.0)
            if self.ramp == "smooth":
                y = y + dy * (10 * u**3 - 15 * u**4 + 6 * u**5)
                yd = yd + np.where(inside, dy * 30 * u**2 * (1 - u) ** 2 / self.ramp_s, 0.0)
            else:
                y = y + dy * u
                moving = (t >= self.ramp_start_s) & (t < self.ramp_start_s + self.ramp_s)
                yd = yd + np.where(moving, dy / self.ramp_s, 0.0)
        else:
            y = np.full_like(t, self.y1_m)
        if self.sine_amplitude_m > 0.0:
            on = (t >= self.sine_start_s) & (t < self.sine_end_s)
            w = 2.0 * math.pi * self.sine_hz
            ph = w * (t - self.sine_start_s)
            y = y + np.where(on, self.sine_amplitude_m * np.sin(ph), 0.0)
            yd = yd + np.where(on, self.sine_amplitude_m * w * np.cos(ph), 0.0)
        return y, yd


#: Press 10 mm into the object (from 2 mm outside, over 0.4 s) and hold.
PRESS = Trajectory(
    "press",
    duration_s=4.0,
    y0_m=-2e-3,
    y1_m=10e-3,
    ramp_start_s=0.1,
    ramp_s=0.4,
    hold_window_s=(3.0, 4.0),
    energy_window_s=(0.0, 4.0),
)
#: Press as above, settle, tap at 4 Hz with 1 mm amplitude for 2 s (8 cycles), hold (the hold
#: is judged a second after the last tap: the box's lightest-damped hand rings that long alone).
TAP = replace(
    PRESS,
    name="tap",
    duration_s=6.0,
    sine_amplitude_m=1e-3,
    sine_hz=4.0,
    sine_start_s=2.0,
    sine_end_s=4.0,
    hold_window_s=(5.0, 6.0),
    energy_window_s=(2.0, 4.0),
)
#: Approach from 20 mm outside at 0.3 m/s (the hand already moving) to an intended 10 mm; hold
#: (judged from 4 s: a soft, light-damped hand bounces off and needs that long even on an ideal
#: object).
IMPACT = Trajectory(
    "impact",
    duration_s=5.0,
    y0_m=-20e-3,
    y1_m=10e-3,
    ramp_start_s=0.0,
    ramp_s=0.1,
    ramp="linear",
    hold_window_s=(4.0, 5.0),
    energy_window_s=(0.0, 5.0),
)
#: The trajectories of the benchmark grid.
TRAJECTORIES: tuple[Trajectory, ...] = (PRESS, TAP, IMPACT)

#: Deepest point [m] about which the position-source probe oscillates to measure felt stiffness.
FELT_DEPTH_M = 5e-3
#: Amplitude [m] of that oscillation.
FELT_AMPLITUDE_M = 0.25e-3
#: Time [s] from the start of the felt probe's press to its oscillation: the probe holds still
#: from the end of its half-second ramp until then.
FELT_SINE_START_S = 4.0
#: Settling [s] from the start of the oscillation to the start of the felt fit.
FELT_SETTLE_S = 2.0
#: What the second felt measurement adds to both the hold and the settling [s]. It is made only
#: of a response the first found not steady or not still while held
#: (:func:`haptic_collab.research.fidelity_metrics.felt_response`), for every scheme alike: a
#: rendering that changes once, as the product's does 2 s after its own-response check
#: identifies the object, is then measured after the change, and a limit cycle still is not.
#: With 2 s every such condition of the full grid traced on 2026-11-25 was measured (the change
#: came at 3.2-8.8 s); with 4 s the same.
FELT_RETRY_EXTRA_S = 2.0


def felt_depth_m(k_o: float, max_force_n: float, obj: ObjectModel | None = None) -> float:
    """Depth [m] of the felt-stiffness oscillation on an object reported at ``k_o`` [N/m]: at
    most :data:`FELT_DEPTH_M`, shallow enough that the object's force at the bottom of the
    oscillation (its static force there plus its stiffest response to the oscillation) stays
    within 80 % of the device's force ``max_force_n`` [N] (a saturated force would read as no
    stiffness at all); ``obj`` defaults to the design model (``K_o x``)."""
    o = obj if obj is not None else SPRING
    amp = FELT_AMPLITUDE_M

    def peak(d: float) -> float:
        return float(o.static_force_n(k_o, d)) + o.peak_stiffness(k_o, d + amp) * amp

    lo, hi = 2.0 * amp, FELT_DEPTH_M
    if peak(hi) <= 0.8 * max_force_n:
        return hi
    if peak(lo) >= 0.8 * max_force_n:
        return lo
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if peak(mid) <= 0.8 * max_force_n else (lo, mid)
    return lo


def felt_window_s(freq_hz: float) -> float:
    """Length [s] of the window the felt stiffness at ``freq_hz`` is fitted over: the shortest
    multiple of 0.2 s holding an even number of whole cycles, at least 2 below 1 Hz, 4 below
    4 Hz and 8 above (each half is then whole cycles of the probe and of every simulation rate
    of the grid, so the multirate ripple drops out of the fit).

    Raises
    ------
    ValueError
        A frequency that is not positive, or that no window up to 20 s fits.
    """
    if not (math.isfinite(freq_hz) and freq_hz > 0.0):
        raise ValueError(f"felt frequency must be > 0 Hz, got {freq_hz!r}")
    least = 2 if freq_hz < 1.0 else (4 if freq_hz < 4.0 else 8)
    for k in range(1, 101):
        n = freq_hz * 0.2 * k
        if abs(n - round(n)) < 1e-6 and round(n) % 2 == 0 and round(n) >= least:
            return 0.2 * k
    raise ValueError(f"no fitting window of whole cycles up to 20 s for {freq_hz!r} Hz")


def felt_trajectory(
    freq_hz: float, depth_m: float = FELT_DEPTH_M, *, longer: bool = False
) -> Trajectory:
    """Position-source probe: ramp to ``depth_m`` (:func:`felt_depth_m`), hold still until
    :data:`FELT_SINE_START_S`, then oscillate at ``freq_hz`` by :data:`FELT_AMPLITUDE_M`; the
    felt stiffness is fitted over :func:`felt_window_s` after :data:`FELT_SETTLE_S` of settling
    (a 400 ms round trip needs them). ``longer``: the hold and the settling each
    :data:`FELT_RETRY_EXTRA_S` longer (the second measurement of a response the first did not
    find steady: :func:`haptic_collab.bench.fidelity.run`).

    Raises
    ------
    ValueError
        As :func:`felt_window_s`.
    """
    extra = FELT_RETRY_EXTRA_S if longer else 0.0
    t_s = FELT_SINE_START_S + extra
    t_fit = t_s + FELT_SETTLE_S + extra
    t_e = t_fit + felt_window_s(freq_hz)
    return Trajectory(
        f"sine-{freq_hz:g}hz" + ("-longer" if longer else ""),
        duration_s=t_e,
        y0_m=0.0,
        y1_m=depth_m,
        ramp_start_s=0.0,
        ramp_s=0.5,
        sine_amplitude_m=FELT_AMPLITUDE_M,
        sine_hz=freq_hz,
        sine_start_s=t_s,
        sine_end_s=t_e + 1.0,
        hold_window_s=(t_fit, t_e),
        energy_window_s=(t_s, t_e),
    )


@dataclass(frozen=True, slots=True)
class OtherUser:
    """A second user pressing and releasing on the same object, as the 1-D model sees it from the
    first user's contact (SI units).

    The 1-D model has one contact. Another user's press reaches it through the object's
    compliance: pressing elsewhere on a closed object (the demo's balloon, A on the top while B
    rests on the side) bulges the surface under this user outward. That is modelled here, and only
    that: the rest surface under this user's contact moves outward by ``bulge_m`` times a
    minimum-jerk ramp while the other presses (from ``start_s`` over ``ramp_s``, held until
    ``release_s``, back over ``ramp_s``), and the object's law about its rest surface is unchanged
    (its force is a function of the depth past the moved rest surface; the viscoelastic object's
    mass and arms act on that relative depth). One way only: this user's force does not move the
    other (the other is a prescribed motion, not a second hand). The server sends no rest plane
    while two users are in the room, so no scheme is told where the rest surface has moved.

    Attributes
    ----------
    bulge_m : float
        Outward displacement [m] of the rest surface under this user while the other holds, > 0.
    start_s, ramp_s, release_s : float
        Start of the press [s], its ramp [s] and the start of the release [s].
    """

    bulge_m: float = 1e-3
    start_s: float = 1.0
    ramp_s: float = 0.3
    release_s: float = 2.0

    def __post_init__(self) -> None:
        ok = all(
            math.isfinite(v) and v >= 0.0
            for v in (self.bulge_m, self.start_s, self.ramp_s, self.release_s)
        )
        if not (ok and self.bulge_m > 0.0 and self.release_s >= self.start_s + self.ramp_s):
            raise ValueError(f"an absurd other user: {self!r}")

    def rest_depth_m(self, t: FloatArray) -> FloatArray:
        """Depth [m] of the rest surface under this user at times ``t`` [s] (0 alone, negative:
        moved outward, toward the probe)."""

        def ramp(t0: float) -> FloatArray:
            if self.ramp_s <= 0.0:
                return np.asarray(t >= t0, dtype=float)
            u = np.clip((t - t0) / self.ramp_s, 0.0, 1.0)
            return np.asarray(10 * u**3 - 15 * u**4 + 6 * u**5)

        return np.asarray(-self.bulge_m * (ramp(self.start_s) - ramp(self.release_s)))


#: The other user of the two-user hand cells: presses from 1 s, holds, and has let go by 2.3 s,
#: before every trajectory's hold window (the press and tap are judged after it).
OTHER_USER = OtherUser()

#: The other user of the two-user follow probe (:func:`follow_trajectory`): the probe held still
#: from 0.5 s, the other pressing from 1.5 s, holding until 3 s, let go by 3.3 s.
OTHER_USER_FOLLOW = OtherUser(start_s=1.5, release_s=3.0)

#: The windows [s] of the follow probe: before the other presses, while it holds, after it let go.
FOLLOW_WINDOWS_S = ((1.0, 1.5), (2.5, 3.0), (4.0, 4.5))


def follow_depth_m(k_o: float, max_force_n: float, obj: ObjectModel, bulge_m: float) -> float:
    """Depth [m] the follow probe holds at on an object reported at ``k_o`` [N/m]: at most
    :data:`FELT_DEPTH_M`, at least 0.5 mm, shallow enough that the relaxed object's force with
    the other user's bulge (``bulge_m`` [m]) stays within 80 % of ``max_force_n`` [N]."""
    lo, hi = 0.5e-3, FELT_DEPTH_M

    def force(d: float) -> float:
        return float(obj.static_force_n(k_o, d + bulge_m))

    if force(hi) <= 0.8 * max_force_n:
        return hi
    if force(lo) >= 0.8 * max_force_n:
        return lo
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if force(mid) <= 0.8 * max_force_n else (lo, mid)
    return lo


def follow_trajectory(depth_m: float) -> Trajectory:
    """Position-source probe of the two-user grid: ramp to ``depth_m`` over 0.5 s and hold still
    to 4.5 s while :data:`OTHER_USER_FOLLOW` presses and lets go (:data:`FOLLOW_WINDOWS_S`)."""
    return Trajectory(
        "follow",
        duration_s=4.5,
        y0_m=0.0,
        y1_m=depth_m,
        ramp_start_s=0.0,
        ramp_s=0.5,
        hold_window_s=(2.5, 3.0),
        energy_window_s=(0.0, 4.5),
    )


@dataclass(frozen=True, slots=True)
class Cell:
    """One simulation: a scheme's rendering of one object, rate, delay, hand and trajectory.

    Attributes
    ----------
    rendering : Rendering
    k_o : float
        Object stiffness K_o the simulation reports [N/m], > 0 (the object itself is ``obj``).
    sim_rate_hz : float
        Simulation rate [Hz]; the servo rate over it must be a whole number.
    delay_ms : float
        One-way network delay [ms], a whole number of servo ticks, >= 0.
    hand : Hand or None
        None: the probe is a position source (it follows the trajectory exactly).
    trajectory : Trajectory
    obj : ObjectModel
        The object (default: the design model, a spring of exactly K_o).
    stale_sample : bool
        The simulation takes what the servo sent :func:`stale_ticks` servo ticks before its
        freshest (False, the default: the last servo tick's, the paper's Step 3): the other end
        of the sampling phase. The client sends its state every half simulation period
        (``client.session.ClientSession.state_interval_s``), so the state the simulation reads
        is at most N/2 servo ticks old (N the servo ticks per simulation period); the servo's
        and the simulation's clocks are not synchronised, so a rendering runs at every age in
        between.
    other : OtherUser or None
        A second user on the object (None: this user is alone, and the server sends the rest
        plane).
    """

    rendering: Rendering
    k_o: float
    sim_rate_hz: float
    delay_ms: float
    hand: Hand | None
    trajectory: Trajectory
    obj: ObjectModel = SPRING
    stale_sample: bool = False
    other: OtherUser | None = None


def stale_ticks(rate_ratio: int) -> int:
    """Servo ticks [-] by which the state the simulation reads is older at the stale end of the
    sampling phase: N // 2 for N servo ticks per simulation period (the client's state every half
    simulation period, ``client.session.ClientSession.state_interval_s``)."""
    return int(rate_ratio) // 2


@dataclass(frozen=True, slots=True)
class RunOptions:
    """Imperfections of the servo a run may add (SI units; all off by default).

    Attributes
    ----------
    jitter_s : float
        Servo wake-up jitter [s]: each tick starts up to this early or late (uniform, drawn
        from ``seed``), so a period lasts ``T`` plus the difference of two draws; the servo
        still computes with the nominal ``T`` (as the client does).
    quantum_m : float
        Encoder resolution [m]: the servo reads the probe rounded to it (Phantom Desktop:
        0.023 mm, ~0.055 mm for a Novint Falcon).
    seed : int
    """

    jitter_s: float = 0.0
    quantum_m: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.jitter_s) and 0.0 <= self.jitter_s < 0.5e-3):
            raise ValueError(f"jitter_s must be in [0, 0.5 ms), got {self.jitter_s!r}")
        if not (math.isfinite(self.quantum_m) and 0.0 <= self.quantum_m <= 1e-3):
            raise ValueError(f"quantum_m must be in [0, 1 mm], got {self.quantum_m!r}")


@dataclass(slots=True)
class Run:
    """Servo-rate record of a batch of cells, shapes (B, n_ticks).

    Attributes
    ----------
    t : (n_ticks,) float
        Time [s] of each servo tick.
    x : (B, n_ticks) float
        Probe depth [m] at the start of each tick (what the servo read).
    f : (B, n_ticks) float
        Force [N] the device wrote that tick (outward, held over the tick).
    runaway : (B,) bool
        The probe left :data:`RUNAWAY_M` or went non-finite (frozen from then on).
    """

    t: FloatArray
    x: FloatArray
    f: FloatArray
    runaway: NDArray[np.bool_]
