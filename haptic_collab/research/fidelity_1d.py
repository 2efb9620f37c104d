"""Side-by-side fidelity of rendering schemes for a slow, delayed deformable object (1-D model).

The product's claim (the paper's section 1 and footnote 4) is that an adaptive local model renders
a slow (tens of Hz), delayed simulation stably and stiffly where the usual approaches do not. This
module measures it: one vectorised multirate simulator runs every scheme against the same hands,
objects, network delays and trajectories (``haptic bench fidelity``, :mod:`haptic_collab.bench.fidelity`).

The 1-D world, along the contact normal, depths in metres (positive into the object):

hand + device (servo rate, exact zero-order hold of the force)
    ``m x'' = -b (x' - y') - k (x - y) - f``: the combined hand and device of
    :class:`shared.full_loop.Hand` holding the probe ``x`` around the user's intended motion ``y``
    (the trajectory); ``f`` [N] is the force the device writes, pushing the probe out. A hand of
    ``None`` is a position source: ``x = y`` (for the felt stiffness).
object (simulation rate)
    an elastic surface of stiffness K_o, unilateral: a force F >= 0 pushes it to ``x_o = F / K_o``
    (eq. 6 with B_o = 0).
network
    the same one-way delay ``d`` both ways, on the servo clock: the simulation ticking at servo
    tick ``n`` reads what the servo sent at ``n - d``; what it publishes reaches the servo from tick
    ``n + 1 + d`` (one tick of computation).

Schemes (:func:`rendering_for` says how each is tuned):

``local-p``, ``local-pi`` (this project)
    the local model of eq. 12 with the product's threshold (eq. 17), release ramp, probe damper,
    proxy hold and, for PI, passivity layer (:mod:`shared.passivity`), gains from the product's own
    full-loop design (:mod:`shared.gain_design`) for the delay the client would measure; the
    simulation receives the force rendered and returns the surface.
``virtual-coupling`` (Colgate, Stanley and Brown 1995; CHAI3D's way)
    the same coupling structure with a fixed spring-damper at the device's maximum stiffness and
    damping, not adapted to K_o; proxy jumps each simulation tick.
``static-local`` (Mark et al. 1996; VRPN ForceDevice's plane)
    a plane at the surface the simulation last reported, rendered with a fixed stiffness (half the
    device's maximum) and no damping.
``direct``
    the simulation computes the contact force ``K_o max(0, x)`` from the probe position it
    received; the servo holds it (zero-order hold) until the next one.
``direct-tdpa`` (Ryu, Kwon and Hannaford 2004)
    ``direct`` with the time-domain passivity observer and controller at the device port.

Every scheme's force is clamped to the device's maximum force. Nothing here reads a clock, a
socket or a thread: time is the servo tick index.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from haptic_collab.shared.full_loop import DAMPER_FILTER_S, Hand, ProxyHold, _hand_zoh
from haptic_collab.shared.gain_design import GainDesign
from haptic_collab.shared.gain_key import loop_delay_ticks
from haptic_collab.shared.types import FloatArray

SchemeName = Literal[
    "local-p",
    "local-pi",
    "mmt",
    "force-jacobian",
    "direct",
    "virtual-coupling",
    "static-local",
    "direct-tdpa",
]

#: Every scheme, this project's first.
SCHEMES: tuple[SchemeName, ...] = get_args(SchemeName)

#: The schemes that are this project's local models (the rest are peers).
LOCAL_MODELS: tuple[SchemeName, ...] = ("local-p", "local-pi")

#: Probe peak-to-peak [m] during the hold below which a cell counts as stable (issue 9).
STABLE_HOLD_P2P_M = 0.5e-3

#: A probe further than this from the surface [m] (or not finite) has run away.
RUNAWAY_M = 0.5

#: The way each scheme's renderer is fed (:class:`Rendering`'s ``kind``):
#: ``coupling`` the product's local model (a spring, integral and damper to the proxy the
#: simulation reports, the simulation receiving the force); ``mmt`` a plane at the rest surface
#: the simulation estimates, with the stiffness it estimates, the simulation receiving the force;
#: ``wall`` a plane at the rest surface with a fixed stiffness, never updated; ``tool`` a
#: spring-damper to a simulated tool whose equilibrium with the object the simulation solves
#: from the probe position it receives; ``jacobian`` the simulation's force and its local
#: stiffness, ``f_s + K (x - x_s)``; ``direct`` the simulation's force, held.
RenderKind = Literal["coupling", "mmt", "wall", "tool", "jacobian", "direct"]

ObjectKind = Literal["spring", "sls", "stiffening"]


def _stiffening_force(k1: FloatArray | float, xs: FloatArray | float, x: FloatArray) -> FloatArray:
    """``k_1 x_s (exp(x / x_s) - 1)`` [N] at depth ``x`` >= 0 [m] (the exponent capped at 50)."""
    return np.asarray(k1 * xs * np.expm1(np.minimum(x / xs, 50.0)))


def _stiffening_depth(k1: FloatArray | float, xs: FloatArray | float, f: FloatArray) -> FloatArray:
    """Depth [m] at which the stiffening law holds the force ``f`` >= 0 [N] (its inverse)."""
    return np.asarray(xs * np.log1p(f / (k1 * xs)))


def _stiffening_tangent(
    k1: FloatArray | float, xs: FloatArray | float, x: FloatArray
) -> FloatArray:
    """Tangent stiffness ``k_1 exp(x / x_s)`` [N/m] at depth ``x`` >= 0 [m]."""
    return np.asarray(k1 * np.exp(np.minimum(x / xs, 50.0)))


@dataclass(frozen=True, slots=True)
class ObjectModel:
    """The simulated object along the contact normal (SI units), relative to the K_o reported.

    The simulation reports K_o (what the product's gain design and every scheme that uses a
    stiffness is given); the object itself is ``stiffness_error`` times stiffer, and may have
    dynamics the design does not model:

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
            return _stiffening_depth(k1, self.stiffening_m, f)
        return np.asarray(f / k1)

    def static_force_n(self, k_o: float, depth_m: FloatArray | float) -> FloatArray:
        """Force [N] with which the relaxed object holds a depth ``depth_m`` [m] (0 outside)."""
        k1 = k_o * self.stiffness_error
        x = np.maximum(np.asarray(depth_m, dtype=float), 0.0)
        if self.kind == "stiffening":
            return _stiffening_force(k1, self.stiffening_m, x)
        return np.asarray(k1 * x)

    def impedance(self, k_o: float, freq_hz: float, depth_m: float) -> complex:
        """The object's own dynamic stiffness dF/dx [N/m] at ``freq_hz`` about ``depth_m``: what
        an ideal rendering would make the hand feel (the reference of :func:`felt_response`)."""
        k1 = k_o * self.stiffness_error
        w = 2.0 * math.pi * freq_hz
        if self.kind == "stiffening":
            return complex(_stiffening_tangent(k1, self.stiffening_m, np.asarray(depth_m)))
        if self.kind == "sls":
            k2 = self.relax_ratio * k1
            jwt = 1j * w * self.relax_time_s
            return (
                k1 + k2 * jwt / (1.0 + jwt) - self.mass_kg * w * w + 1j * w * self.damping_n_s_per_m
            )
        return complex(k1)

    def peak_stiffness(self, k_o: float, depth_m: float) -> float:
        """The largest |dF/dx| [N/m] the object shows down to ``depth_m`` at any speed."""
        k1 = k_o * self.stiffness_error
        if self.kind == "stiffening":
            return float(_stiffening_tangent(k1, self.stiffening_m, np.asarray(depth_m)))
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
class DeviceModel:
    """The device every scheme renders on (the simulated Phantom Desktop's limits), SI units.

    Attributes
    ----------
    name : str
    max_force_n : float
        Force clamp [N].
    max_stiffness_n_per_m : float
        Largest stiffness [N/m] the device renders stably on its own (the virtual coupling's gain).
    max_damping_n_s_per_m : float
        Largest virtual damping [N*s/m] (the virtual coupling's damper, the PC's alpha_max).
    """

    name: str = "phantom-desktop"
    max_force_n: float = 7.9
    max_stiffness_n_per_m: float = 1000.0
    max_damping_n_s_per_m: float = 10.0


@dataclass(frozen=True, slots=True)
class Rendering:
    """How one scheme renders one object (SI units).

    Attributes
    ----------
    scheme : str
        One of :data:`SCHEMES`.
    kind : str
        How the renderer is fed (:data:`RenderKind`).
    k_h, i_gain, b_h : float
        Spring K_h [N/m] (``coupling``, ``wall``, ``tool``; the cap [N/m] on the estimated
        stiffness for ``mmt`` and ``jacobian``), integral I [N/(m*s)] (``coupling``), probe damper
        [N*s/m] (every kind but ``direct``).
    proxy_hold : {"zoh", "foh"}
    theta_m : float
        Integration threshold of eq. 17 [m] (used when ``i_gain > 0``).
    release_time_s : float
        Ramp [s] driving the integral force to zero on release (section 5.1).
    passivity : bool
        Time-domain passivity observer/controller at the device port.
    passivity_bias_j : float
        Energy [J] the PC tolerates before acting.
    passivity_max_damping : float or None
        The PC's largest damping [N*s/m]; None: the device's maximum; ``math.inf``: uncapped
        (only the force clamp limits it).
    two_port : bool
        ``direct`` with ``passivity``: the two-port form for a delayed channel (module docstring).
    own_gain : float
        Own-force compensation C_h [m/N] (``coupling`` only, :mod:`shared.full_loop`): the proxy
        is the reported surface moved out by C_h times the force the simulation applied.
    jacobian_scale : float
        ``jacobian``: the fraction of the simulation's local stiffness rendered.
    follows_k_o : bool
        ``coupling`` with ``own_gain`` > 0: the gains follow the K_o the simulation reports each
        tick, as the product's client renders each patch with its design scaled to the patch's
        K_o (:meth:`shared.gain_design.GainDesign.at`): K_h times s up to the device's
        stiffness, C_h over s, s = max(K_o reported / K_o designed for, 1); B_h and the hold
        stay. Where the reported K_o leaves the design's cell the client renders a new cell's
        design; here the scaling continues instead.
    variant : str
        The peer's tuning among those swept (:func:`peer_renderings`), for the report.
    tuning : str
        How the gains were chosen, for the report.
    """

    scheme: str
    kind: RenderKind
    k_h: float = 0.0
    i_gain: float = 0.0
    b_h: float = 0.0
    proxy_hold: ProxyHold = "zoh"
    theta_m: float = 0.0
    release_time_s: float = 0.1
    passivity: bool = False
    passivity_bias_j: float = 0.0
    passivity_max_damping: float | None = None
    two_port: bool = False
    own_gain: float = 0.0
    jacobian_scale: float = 1.0
    follows_k_o: bool = False
    variant: str = ""
    tuning: str = ""


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


def felt_trajectory(freq_hz: float, depth_m: float = FELT_DEPTH_M) -> Trajectory:
    """Position-source probe: ramp to ``depth_m`` (:func:`felt_depth_m`), settle 3.5 s, then
    oscillate at ``freq_hz`` by :data:`FELT_AMPLITUDE_M`; the felt stiffness is fitted over
    :func:`felt_window_s` after 2 s of settling (a 400 ms round trip needs them).

    Raises
    ------
    ValueError
        As :func:`felt_window_s`.
    """
    t_s = 4.0
    t_fit = t_s + 2.0
    t_e = t_fit + felt_window_s(freq_hz)
    return Trajectory(
        f"sine-{freq_hz:g}hz",
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
    """

    rendering: Rendering
    k_o: float
    sim_rate_hz: float
    delay_ms: float
    hand: Hand | None
    trajectory: Trajectory
    obj: ObjectModel = SPRING


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


def passivity_step(
    pc_energy: FloatArray,
    pc_fa: FloatArray,
    f_d: FloatArray,
    v: FloatArray,
    *,
    servo_period_s: float,
    max_damping_n_s_per_m: FloatArray | float,
    energy_bias_j: FloatArray | float,
    max_force_n: float,
    on: NDArray[np.bool_] | bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One tick of the 1-D passivity observer and controller for a batch (Ryu, Kwon and Hannaford
    2004; the difference equations of :mod:`shared.passivity`, reset on release).

    Parameters
    ----------
    pc_energy, pc_fa : (B,) float
        Observed energy E(n-1) [J] and the force applied on the previous tick f_a(n-1) [N].
    f_d : (B,) float
        Force the environment wants ON the handle this tick [N].
    v : (B,) float
        Handle velocity [m/s], backward difference over the tick that just ended.
    servo_period_s, max_damping_n_s_per_m, energy_bias_j, max_force_n
        As :class:`shared.passivity.PassivityParams`; the damping may be per cell, and
        ``math.inf`` (uncapped: only the force clamp limits the controller).
    on : bool or (B,) bool
        Cells whose controller acts (the observer always runs).

    Returns
    -------
    (energy, f_a, dissipated) : (B,) float each
        E(n) [J], the force to apply f_a(n) [N], the energy the damper dissipates this tick [J].
    """
    t = servo_period_s
    energy = pc_energy - pc_fa * v * t
    energy = np.where(f_d == 0.0, 0.0, energy)
    fd = np.clip(f_d, -max_force_n, max_force_n)
    predicted = energy - t * fd * v
    vv = v * v
    deficit = -np.asarray(energy_bias_j) - predicted
    act = (deficit > 0.0) & (vv > 0.0) & np.asarray(on)
    tvv = t * vv
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.minimum(deficit / np.where(tvv > 0.0, tvv, 1.0), max_damping_n_s_per_m)
    alpha = np.where(act, alpha, 0.0)
    fa = fd - alpha * v
    fa_c = np.clip(fa, -max_force_n, max_force_n)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(fa != 0.0, fa_c / np.where(fa != 0.0, fa, 1.0), 1.0)
    dissipated = scale * alpha * vv * t
    return energy, fa_c, dissipated


def simulate(
    cells: Sequence[Cell],
    *,
    device: DeviceModel = DeviceModel(),
    servo_rate_hz: float = 1000.0,
    options: RunOptions = RunOptions(),
) -> Run:
    """Run a batch of cells side by side at the servo rate (module docstring for the model).

    Parameters
    ----------
    cells : sequence of Cell
        Any mix of schemes, objects, rates, delays, hands and trajectories; the batch runs for
        the longest trajectory.
    device : DeviceModel
    servo_rate_hz : float
    options : RunOptions
        Servo jitter and encoder quantisation (off by default).

    Returns
    -------
    Run

    Raises
    ------
    ValueError
        An empty batch, a rate that does not divide the servo rate, a delay that is not a whole
        number of servo ticks, or a non-positive K_o.
    """
    if not cells:
        raise ValueError("simulate needs at least one cell")
    T = 1.0 / float(servo_rate_hz)
    B = len(cells)
    r = [c.rendering for c in cells]
    n_ratio = np.empty(B, dtype=np.int64)
    d_ticks = np.empty(B, dtype=np.int64)
    for i, c in enumerate(cells):
        q = servo_rate_hz / c.sim_rate_hz
        if not (c.sim_rate_hz > 0.0 and abs(q - round(q)) < 1e-9 and round(q) >= 1):
            raise ValueError(f"servo rate / simulation rate must be whole, got {c.sim_rate_hz!r}")
        dq = c.delay_ms * 1e-3 * servo_rate_hz
        if not (c.delay_ms >= 0.0 and abs(dq - round(dq)) < 1e-9):
            raise ValueError(f"delay must be whole servo ticks >= 0, got {c.delay_ms!r} ms")
        if not (math.isfinite(c.k_o) and c.k_o > 0.0):
            raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {c.k_o!r}")
        n_ratio[i] = round(q)
        d_ticks[i] = round(dq)
    k_o = np.array([c.k_o for c in cells])
    kind = np.array([x.kind for x in r])
    direct = kind == "direct"
    jac = kind == "jacobian"
    tool = kind == "tool"
    mmt = kind == "mmt"
    wall = kind == "wall"
    fed_position = direct | jac | tool  # the simulation receives the probe, not a force
    k_h = np.array([x.k_h for x in r])
    ti = T * np.array([x.i_gain for x in r])
    b_h = np.array([x.b_h for x in r])
    foh = np.array([x.proxy_hold == "foh" for x in r])
    theta = np.where(ti > 0.0, np.array([x.theta_m for x in r]), 0.0)
    rel_per_tick = T / np.array([x.release_time_s for x in r])
    recovery = np.where(ti > 0.0, 1.0 / k_o, 0.0)  # [m/N]
    pc_any = np.array([x.passivity for x in r])
    two_port = pc_any & direct & np.array([x.two_port for x in r])
    pc_on = pc_any & ~two_port
    pc_bias = np.array([x.passivity_bias_j for x in r])
    pc_bmax = np.array(
        [
            device.max_damping_n_s_per_m
            if x.passivity_max_damping is None
            else x.passivity_max_damping
            for x in r
        ]
    )
    own = np.array([x.own_gain for x in r])
    follow = (kind == "coupling") & (own > 0.0) & np.array([x.follows_k_o for x in r])
    kh_follow_max = np.maximum(k_h, float(device.max_stiffness_n_per_m))
    jscale = np.array([x.jacobian_scale for x in r])
    fmax = float(device.max_force_n)
    a_u = T / (T + DAMPER_FILTER_S)

    # the object (ObjectModel): implicit Euler at the simulation rate, x' = a + c F when linear
    objs = [c.obj for c in cells]
    k1 = k_o * np.array([o.stiffness_error for o in objs])
    k2 = k1 * np.array([o.relax_ratio for o in objs])
    tau = np.array([max(o.relax_time_s, 1e-9) for o in objs])
    m_o = np.array([o.mass_kg for o in objs])
    b_o = np.array([o.damping_n_s_per_m for o in objs])
    nonlin = np.array([o.kind == "stiffening" for o in objs])
    xs = np.array([o.stiffening_m if o.kind == "stiffening" else 1.0 for o in objs])
    h = n_ratio * T
    alpha = tau / (tau + h)  # Maxwell arm: q' = alpha q + (1 - alpha) x'
    D = m_o / h**2 + b_o / h + k1 + k2 * alpha
    xo = np.zeros(B)
    vo = np.zeros(B)
    qo = np.zeros(B)

    # hands: exact ZOH of m x'' = -b (x' - y') - k (x - y) - f  (input f - k y - b y')
    src = np.array([c.hand is None for c in cells])
    hm = np.array([1.0 if c.hand is None else c.hand.mass_kg for c in cells])
    hb = np.array([0.0 if c.hand is None else c.hand.damping_n_s_per_m for c in cells])
    hk = np.array([0.0 if c.hand is None else c.hand.stiffness_n_per_m for c in cells])
    n_steps = max(round(c.trajectory.duration_s * servo_rate_hz) for c in cells)
    cols = np.arange(B)
    if options.jitter_s > 0.0:
        # wake-up offsets j_n in J {-1, -1/2, 0, 1/2, 1}: periods T + j_(n+1) - j_n, 9 levels
        levels = [_hand_zoh(hm, hb, hk, T + 0.25 * options.jitter_s * k) for k in range(-4, 5)]
        phis = np.stack([p for p, _ in levels])
        gams = np.stack([g for _, g in levels])
        draws = np.random.default_rng(options.seed).integers(0, 5, size=(n_steps + 1, B))
        level = draws[1:] - draws[:-1] + 4
    else:
        phi, gam = _hand_zoh(hm, hb, hk, T)
    quantum = options.quantum_m

    t = np.arange(n_steps, dtype=np.float64) * T
    Y = np.empty((B, n_steps))
    YD = np.empty((B, n_steps))
    trajs: dict[Trajectory, list[int]] = {}
    for i, c in enumerate(cells):
        trajs.setdefault(c.trajectory, []).append(i)
    for tr, idx in trajs.items():
        y, yd = tr.target(t)
        Y[idx] = y
        YD[idx] = yd
    # impact: the hand is already moving with its intention
    x = Y[:, 0].copy()
    v = YD[:, 0].copy()
    xr_prev = x.copy()

    # servo state
    s = np.zeros(B)  # integral force [N]
    rel_step = np.zeros(B)
    was_contact = np.zeros(B, dtype=bool)
    u = np.zeros(B)  # filtered probe velocity
    p_new = np.zeros(B)  # latest surface received
    p_old = np.zeros(B)  # FOH start
    hold_i = np.zeros(B, dtype=np.int64)
    f_recv = np.zeros(B)  # direct, jacobian: force received
    k_recv = k_o.copy()  # mmt, jacobian: stiffness estimate received (the rest value at first)
    x_ref = np.zeros(B)  # jacobian: the probe position the force received belongs to
    e_env = np.zeros(B)  # two-port: energy the environment has given back, as received [J]
    e_out = np.zeros(B)  # two-port: energy the port has given the user [J]
    seq_seen = np.zeros(B, dtype=np.int64)
    pc_e = np.zeros(B)
    pc_fa = np.zeros(B)
    # network: ring buffers on the servo clock
    L = int(d_ticks.max()) + 2
    up = np.zeros((L, B))  # what the servo sent at tick n (force, or probe position)
    down = np.zeros((L, B, 4))  # latest (value, stiffness, x_ref, energy) published by tick n
    down_seq = np.zeros((L, B), dtype=np.int64)
    pub = np.zeros((B, 4))
    pub[:, 1] = k_o
    pub_seq = np.zeros(B, dtype=np.int64)
    # two-port, the simulation's side: the probe it used, its force, the energy given back
    x_used = np.zeros(B)
    f_env = np.zeros(B)
    e_env_out = np.zeros(B)
    runaway = np.zeros(B, dtype=bool)

    # which kinds this batch has, once (the tick skips what none of its cells needs)
    any_jac = bool(jac.any())
    any_pc = bool(pc_on.any())
    any_two_port = bool(two_port.any())
    any_follow = bool(follow.any())
    any_tool_nonlin = bool((tool & nonlin).any())
    all_src = bool(src.all())

    X = np.empty((B, n_steps))
    F = np.empty((B, n_steps))
    for n in range(n_steps):
        # 1. read: the probe, and what arrived from the simulation
        if n > 0:
            x = np.where(src, Y[:, n], x)
        bad = ~np.isfinite(x) | (np.abs(x) > RUNAWAY_M)
        if bad.any():
            runaway |= bad
            x = np.where(bad, np.nan_to_num(np.clip(x, -RUNAWAY_M, RUNAWAY_M)), x)
            v = np.where(bad, 0.0, v)
        xr = np.round(x / quantum) * quantum if quantum > 0.0 else x
        vel = (xr - xr_prev) / T
        k_read = n - 1 - d_ticks
        ok = k_read >= 0
        slot = np.where(ok, k_read, 0) % L
        seq = np.where(ok, down_seq[slot, cols], 0)
        fresh = seq != seq_seen
        if fresh.any():
            got = down[slot, cols]
            # first-order hold starts from wherever the proxy is now
            blend = np.minimum(1.0, (hold_i + 1.0) / n_ratio)
            p_cur = np.where(foh, p_old + (p_new - p_old) * blend, p_new)
            p_old = np.where(fresh, p_cur, p_old)
            proxied = fresh & ~(direct | jac | wall)
            p_new = np.where(proxied, got[:, 0], p_new)
            f_recv = np.where(fresh & (direct | jac), got[:, 0], f_recv)
            k_recv = np.where(fresh & (mmt | jac | follow), got[:, 1], k_recv)
            x_ref = np.where(fresh & jac, got[:, 2], x_ref)
            e_env = np.where(fresh & two_port, got[:, 3], e_env)
            hold_i = np.where(fresh, 0, hold_i + 1)
            seq_seen = seq
        else:
            hold_i = hold_i + 1
        # 2. compute
        w = np.where(foh, np.minimum(1.0, (hold_i + 1.0) / n_ratio), 1.0)
        proxy = p_old + (p_new - p_old) * w
        e = xr - proxy
        k_eff = np.where(mmt, np.minimum(k_recv, k_h), k_h)
        if any_follow:
            k_eff = np.where(
                follow, np.minimum(k_h * np.maximum(k_recv / k_o, 1.0), kh_follow_max), k_eff
            )
        # contact: the probe past the proxy; an integral keeps it while the probe is within the
        # deformation its force holds (s / K_o: the object's surface follows a retreating probe
        # back, the proxy is a stale copy of it; shared.local_model's recovery band)
        contact = (e > 0.0) | (was_contact & (e > -s * recovery))
        # local model, eq. 12 with eq. 17's threshold and the release ramp (shared.local_model)
        f_lm = np.where(contact, np.maximum(k_eff * e + s, 0.0), s)
        start_rel = ~contact & (was_contact | (rel_step == 0.0))
        rel_step = np.where(contact, 0.0, np.where(start_rel, s * rel_per_tick, rel_step))
        s = np.where(
            contact,
            np.clip(s + ti * (e - theta), 0.0, fmax),
            np.maximum(s - rel_step, 0.0),
        )
        was_contact = contact
        u = u + a_u * (vel - u)
        f_lm = np.where(contact & (b_h > 0.0), np.maximum(f_lm + b_h * u, 0.0), f_lm)
        f = np.where(direct, f_recv, f_lm)
        if any_jac:
            # force-jacobian: the simulation's force and its local stiffness about x_ref
            f_j = f_recv + np.minimum(jscale * k_recv, k_h) * (xr - x_ref)
            f = np.where(jac, np.where(f_j > 0.0, np.maximum(f_j + b_h * u, 0.0), 0.0), f)
        f = np.clip(f, -fmax, fmax)
        # passivity layer at the device port: force ON the handle is -f, its velocity vel
        if any_pc:
            pc_e, fa, _ = passivity_step(
                pc_e,
                pc_fa,
                -f,
                vel,
                servo_period_s=T,
                max_damping_n_s_per_m=pc_bmax,
                energy_bias_j=pc_bias,
                max_force_n=fmax,
                on=pc_on,
            )
            pc_fa = np.where(pc_on, fa, pc_fa)
            f = np.where(pc_on, -fa, f)
        if any_two_port:
            # two-port, the device's side: give the user no more energy than the environment
            # has given back (as far as it is known here); the power to the user is (-f) vel
            p_last = pc_fa * vel * T
            e_out = e_out + np.where(two_port, np.maximum(p_last, 0.0), 0.0)
            want = np.maximum(-f * vel * T, 0.0)
            deficit = e_out + want - e_env - pc_bias
            vv = vel * vel
            act = two_port & (deficit > 0.0) & (vv > 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                damp = np.where(act, deficit / np.where(vv > 0.0, vv * T, 1.0), 0.0)
            f_tp = np.clip(f + damp * vel, -fmax, fmax)
            f = np.where(two_port, f_tp, f)
            pc_fa = np.where(two_port, -f, pc_fa)
        X[:, n] = xr
        F[:, n] = f
        # 3. write: the hand moves under the force held over the tick
        if not all_src:
            if options.jitter_s > 0.0:
                phi = phis[level[n], cols]
                gam = gams[level[n], cols]
            inp = f - hk * Y[:, n] - hb * YD[:, n]
            xn = phi[:, 0, 0] * x + phi[:, 0, 1] * v + gam[:, 0] * inp
            vn = phi[:, 1, 0] * x + phi[:, 1, 1] * v + gam[:, 1] * inp
            x = np.where(runaway, x, xn)
            v = np.where(runaway, 0.0, vn)
        xr_prev = xr
        # uplink, then the simulation's tick
        up[n % L] = np.where(fed_position, xr, f)
        sim_now = (n % n_ratio) == 0
        if sim_now.any():
            k_up = n - d_ticks
            slot_up = np.where(k_up >= 0, k_up, 0) % L
            got = np.where(k_up >= 0, up[slot_up, cols], 0.0)
            a = (m_o * (xo + h * vo) / h**2 + b_o * xo / h + k2 * alpha * qo) / D
            # a force pushes the object (the local models, MMT, the wall)
            f_in = np.maximum(got, 0.0)
            x_f = np.where(nonlin, _stiffening_depth(k1, xs, f_in), a + f_in / D)
            # the probe position drives it (direct, force-jacobian): the surface put at the probe
            contact = got > a
            x_in = np.clip(got, 0.0, RUNAWAY_M)
            f_p = np.where(
                nonlin, _stiffening_force(k1, xs, x_in), np.where(contact, (got - a) * D, 0.0)
            )
            x_p = np.where(nonlin, x_in, np.where(contact, got, a))
            if any_two_port:
                # two-port, the simulation's side: the energy the object has given back
                de = 0.5 * (f_env + f_p) * (x_p - x_used)
                e_env_out = np.where(
                    two_port & sim_now, e_env_out + np.maximum(-de, 0.0), e_env_out
                )
                x_used = np.where(two_port & sim_now, x_p, x_used)
                f_env = np.where(two_port & sim_now, f_p, f_env)
            # the tool (virtual coupling): its equilibrium between the coupling and the object
            kc = k_h
            f_t = np.where(got > a, kc * (got - a) / (1.0 + kc / D), 0.0)
            x_t = a + f_t / D
            if any_tool_nonlin:
                gp = np.maximum(got, 0.0)
                z = kc * gp / (kc + k1)
                for _ in range(8):  # Newton on the convex, increasing F(z) + K_c (z - x)
                    z = z - (_stiffening_force(k1, xs, z) + kc * (z - gp)) / (
                        _stiffening_tangent(k1, xs, z) + kc
                    )
                z = np.clip(z, 0.0, gp)
                x_t = np.where(nonlin, z, x_t)
                f_t = np.where(nonlin, kc * (gp - z), f_t)
            x_new = np.where(tool, x_t, np.where(fed_position, x_p, x_f))
            f_obj = np.where(tool, f_t, np.where(fed_position, f_p, f_in))
            upd = sim_now & ~runaway
            vo = np.where(upd, (x_new - xo) / h, vo)
            qo = np.where(upd, alpha * qo + (1.0 - alpha) * x_new, qo)
            xo = np.where(upd, x_new, xo)
            # what the simulation publishes: its stiffness estimate is the object's tangent
            # stiffness as it believes it (off by the object's stiffness error)
            k_est = np.where(nonlin, _stiffening_tangent(k_o, xs, np.maximum(xo, 0.0)), k_o)
            # own-force compensation of a local model that follows the reported K_o: C_h / s
            own_eff = (
                np.where(follow, own / np.maximum(k_est / k_o, 1.0), own) if any_follow else own
            )
            val = np.where(
                fed_position & ~tool,
                f_obj,
                np.where(
                    mmt,
                    xo - f_obj / k_est,
                    np.where(
                        tool,
                        xo,
                        xo - own_eff * f_obj,
                    ),
                ),
            )
            new = np.stack([val, k_est, got, e_env_out], axis=1)
            pub = np.where(sim_now[:, None], new, pub)
            pub_seq = pub_seq + sim_now
        down[n % L] = pub
        down_seq[n % L] = pub_seq
    return Run(t=t, x=X, f=F, runaway=runaway)


@dataclass(frozen=True, slots=True)
class CellMetrics:
    """What a user would notice in one cell (issue 9's metrics), SI-derived units as named.

    Attributes
    ----------
    stable : bool
        Bounded (no runaway) and ``hold_p2p_mm`` below :data:`STABLE_HOLD_P2P_M`.
    hold_p2p_mm : float
        Probe peak to peak [mm] over the trajectory's hold window.
    peak_penetration_mm : float
        Largest ``x - x_s(f)`` [mm], ``x_s(f)`` the depth at which the relaxed object holds the
        force ``f`` (:meth:`ObjectModel.static_depth_m`; ``f / K_o`` for the design model): how
        far the probe went past the surface of the object pushing back with the force the user
        actually feels (0 for an ideal rendering; for a coupling it includes the steady-state
        error).
    steady_state_error_mm : float
        Mean of ``x - x_s(f)`` [mm] over the last half of the hold window (the probe-proxy gap of
        a P coupling, f / K_h; eq. 17's theta for PI).
    energy_out_mj : float
        Energy the device port gave the user over the trajectory's energy window [mJ]
        (``sum -f (x(n+1) - x(n))``); > 0 is active.
    force_ripple_n : float
        Force peak to peak [N] over the hold window.
    """

    stable: bool
    hold_p2p_mm: float
    peak_penetration_mm: float
    steady_state_error_mm: float
    energy_out_mj: float
    force_ripple_n: float

    def to_json(self) -> dict[str, object]:
        """The cell's metric fields of ``haptic bench fidelity --json``."""
        return {
            "stable": self.stable,
            "hold_p2p_mm": self.hold_p2p_mm,
            "peak_penetration_mm": self.peak_penetration_mm,
            "steady_state_error_mm": self.steady_state_error_mm,
            "energy_out_mj": self.energy_out_mj,
            "force_ripple_n": self.force_ripple_n,
        }


def _window(t: FloatArray, w: tuple[float, float]) -> NDArray[np.bool_]:
    return (t >= w[0] - 1e-9) & (t < w[1] - 1e-9)


def cell_metrics(run: Run, cells: Sequence[Cell]) -> list[CellMetrics]:
    """The :class:`CellMetrics` of every cell of a :func:`simulate` run, in order."""
    out: list[CellMetrics] = []
    for i, c in enumerate(cells):
        tr = c.trajectory
        n_i = round(tr.duration_s / (run.t[1] - run.t[0])) if run.t.size > 1 else 1
        t = run.t[:n_i]
        x = run.x[i, :n_i]
        f = run.f[i, :n_i]
        hold = _window(t, tr.hold_window_s)
        half = _window(t, (0.5 * (tr.hold_window_s[0] + tr.hold_window_s[1]), tr.hold_window_s[1]))
        pen = x - c.obj.static_depth_m(c.k_o, f)
        hold_p2p = float(np.ptp(x[hold]))
        ew = _window(t, tr.energy_window_s)
        dx = np.diff(x, append=x[-1])
        energy = float(np.sum(-f[ew] * dx[ew]))
        finite = bool(np.isfinite(x).all() and np.isfinite(f).all())
        stable = finite and not bool(run.runaway[i]) and hold_p2p < STABLE_HOLD_P2P_M
        out.append(
            CellMetrics(
                stable=stable,
                hold_p2p_mm=hold_p2p * 1e3,
                peak_penetration_mm=float(np.max(pen)) * 1e3,
                steady_state_error_mm=float(np.mean(pen[half])) * 1e3,
                energy_out_mj=energy * 1e3,
                force_ripple_n=float(np.ptp(f[hold])),
            )
        )
    return out


#: Felt-stiffness fits over the two halves of the window that differ by more than this fraction
#: are not a steady response (the loop has not settled, or it is growing): no number is reported.
FELT_FIT_TOLERANCE = 0.05


def _fundamental(t: FloatArray, y: FloatArray, w: float) -> complex:
    A = np.stack([np.ones_like(t), t - t[0], np.cos(w * t), np.sin(w * t)], axis=1)
    c = np.linalg.lstsq(A, y, rcond=None)[0]
    return complex(c[2], -c[3])


def felt_response(run: Run, cells: Sequence[Cell]) -> list[complex | None]:
    """Felt dynamic stiffness over the object's own, ``(dF/dx) / Z_o`` (complex: magnitude and
    phase at the probe frequency), of position-source cells (:func:`felt_trajectory`), in
    order; ``Z_o`` is :meth:`ObjectModel.impedance` at that frequency and depth (K_o for the
    design model), so 1 is an ideal rendering of the object. :func:`felt_stiffness_ratio` is its
    magnitude, its real part the elastic share (a lagging force is partly felt as damping, or,
    lagging by a long delay, as an active push).

    Least-squares fit of ``a + b t + c cos(w t) + d sin(w t)`` to the probe position and to the
    force over the trajectory's hold window (whole cycles of the probe and of every simulation
    rate of the grid; the multirate ripple is not at w and drops out); the ratio of the
    fundamentals over Z_o, as :func:`shared.gain_design.felt_stiffness` computes it exactly for
    the linear loop. None when the cell ran away, the fits over the two halves of the window
    differ by more than :data:`FELT_FIT_TOLERANCE` (not a steady response), or the force still
    ripples by more than that fraction of the response's peak to peak while the probe is held
    still before the oscillation (a limit cycle).

    Raises
    ------
    ValueError
        A cell that is not a position source oscillating at a frequency.
    """
    out: list[complex | None] = []
    resp: complex = 0j
    dt = run.t[1] - run.t[0]
    for i, c in enumerate(cells):
        tr = c.trajectory
        if c.hand is not None or tr.sine_hz <= 0.0:
            raise ValueError("felt stiffness needs a position-source cell on a sine trajectory")
        n_i = round(tr.duration_s / dt)
        t = run.t[:n_i]
        w = 2.0 * math.pi * tr.sine_hz
        z_obj = c.obj.impedance(c.k_o, tr.sine_hz, tr.y1_m)
        a, b = tr.hold_window_s
        mid = 0.5 * (a + b)
        ratios = []
        for lo, hi in ((a, b), (a, mid), (mid, b)):
            m = _window(t, (lo, hi))
            x1 = _fundamental(t[m], run.x[i, :n_i][m], w)
            f1 = _fundamental(t[m], run.f[i, :n_i][m], w)
            q = f1 / x1 / z_obj if abs(x1) > 0.0 else complex(math.nan)
            if hi == b and lo == a:
                resp = q
            ratios.append(abs(q))
        whole, h1, h2 = ratios
        steady = all(math.isfinite(q) for q in ratios) and abs(h1 - h2) <= FELT_FIT_TOLERANCE * max(
            abs(whole), 1e-9
        )
        # a still probe must feel a still force: a limit cycle (the unilateral contact bounds an
        # unstable loop) is periodic too, but it is there before the probe moves
        still = _window(t, (tr.sine_start_s - 0.5, tr.sine_start_s))
        ripple = float(np.ptp(run.f[i, :n_i][still]))
        quiet = ripple <= FELT_FIT_TOLERANCE * 2.0 * whole * abs(z_obj) * tr.sine_amplitude_m
        out.append(resp if steady and quiet and not run.runaway[i] else None)
    return out


def felt_stiffness_ratio(run: Run, cells: Sequence[Cell]) -> list[float | None]:
    """Felt stiffness |dF/dx| / K_o of position-source cells, in order (:func:`felt_response`)."""
    return [None if q is None else abs(q) for q in felt_response(run, cells)]


#: Integration threshold of eq. 17 the product's client renders with (``haptic client
#: --theta``, default 1 mm).
PRODUCT_THETA_M = 1e-3
#: Energy [J] the product's passivity layer tolerates (client.servo.ServoConfig's default).
PRODUCT_PASSIVITY_BIAS_J = 1e-3


def design_delay_ticks(one_way_delay_s: float, sim_rate_hz: float) -> int:
    """Delay ticks the product's client designs for over a network of this one-way delay.

    :meth:`client.session.ClientSession.delay_ticks` with a steady round trip of twice the delay
    and a state sent every half simulation period
    (:func:`shared.gain_key.loop_delay_ticks`).

    Raises
    ------
    ValueError
        A negative or non-finite delay, or a non-positive rate.
    """
    if not sim_rate_hz > 0.0:
        raise ValueError(f"sim_rate_hz must be > 0, got {sim_rate_hz!r}")
    return loop_delay_ticks(2.0 * one_way_delay_s, 0.5 / sim_rate_hz, sim_rate_hz)


def scheme_tuning(scheme: str, device: DeviceModel = DeviceModel()) -> str:
    """How ``scheme`` is tuned, in one sentence (the benchmark's report).

    Raises
    ------
    ValueError
        An unknown scheme.
    """
    b, k = device.max_damping_n_s_per_m, device.max_stiffness_n_per_m
    swept = "the best of the sweep per condition (every hand of the box stable, then felt closest)"
    text = {
        "local-p": (
            "the product's full-loop design (haptic gains) for K_o, rate and the delay ticks the "
            "client measures, own-force compensation included (docs/own-force.md)"
        ),
        "local-pi": (
            "the product's full-loop design (haptic gains) for K_o, rate and the delay ticks the "
            "client measures, own-force compensation included (docs/own-force.md: a compensated "
            "P model where that is closer to K_o); eq. 17 threshold 1 mm; passivity layer on "
            "(the client's default for PI)"
        ),
        "mmt": (
            "model-mediated teleoperation (Mitra and Niemeyer 2008): a plane at the rest surface "
            "the simulation estimates each tick (its surface less its own deformation F / K), "
            f"with the stiffness it estimates, capped at {k:g} N/m; probe damper 0, "
            f"{0.25 * b:g} or {b:g} N*s/m, {swept}"
        ),
        "force-jacobian": (
            "the simulation's force and local stiffness at the probe it received, f_s + K (x - "
            f"x_s) at 1 kHz (Cavusoglu and Tendick 2000); K times 0.5 or 1, capped at {k:g} N/m; "
            f"probe damper {0.25 * b:g} or {b:g} N*s/m, {swept}"
        ),
        "virtual-coupling": (
            "a spring-damper to a simulated tool whose equilibrium with the object the "
            "simulation solves from the probe it receives (Colgate, Stanley and Brown 1995; "
            "Adams and Hannaford 1999; the light-tool limit); coupling "
            f"{0.5 * k:g} or {k:g} N/m (the device's passive range for its own damping) and "
            f"{0.25 * b:g} or {b:g} N*s/m, {swept}"
        ),
        "static-local": (
            "a plane at the object's rest surface with the K_o reported (capped at "
            f"{k:g} N/m), never updated (Mark et al. 1996's intermediate plane, placed where "
            f"the object rests); probe damper 0, {0.25 * b:g} or {b:g} N*s/m, {swept}"
        ),
        "direct": "the simulation's own contact force from the probe it received, held (ZOH)",
        "direct-tdpa": (
            "direct with time-domain passivity, force clamp only (no damping cap): the one-port "
            "observer at the device (Ryu, Kwon and Hannaford 2004) or the two-port form for a "
            "delayed channel, its device side (Artigas et al. 2010: the device gives the user no "
            "more energy than the object has given back, as far as it is known there), "
            f"{swept}"
        ),
    }
    if scheme not in text:
        raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")
    return text[scheme]


def peer_renderings(
    scheme: str,
    *,
    k_o: float,
    sim_rate_hz: float,
    device: DeviceModel = DeviceModel(),
) -> list[Rendering]:
    """Every tuning of a peer that the benchmark sweeps (:func:`scheme_tuning`), the default
    (the one :func:`rendering_for` gives) first.

    Parameters
    ----------
    scheme : str
        A peer of :data:`SCHEMES` (not a local model).
    k_o : float
        The K_o reported [N/m] (the static plane's stiffness).
    sim_rate_hz : float
        Simulation rate [Hz] (unused by today's peers; kept for tunings that depend on it).
    device : DeviceModel

    Raises
    ------
    ValueError
        An unknown scheme, a local model, or a non-positive K_o.
    """
    if not (math.isfinite(k_o) and k_o > 0.0):
        raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
    b, k = device.max_damping_n_s_per_m, device.max_stiffness_n_per_m
    dampers = (b, 0.25 * b)
    # the planes also without a damper: what the product's design picks on soft objects
    plane_dampers = (*dampers, 0.0)
    tune = scheme_tuning(scheme, device) if scheme in SCHEMES else ""
    if scheme in LOCAL_MODELS:
        raise ValueError(f"{scheme} is a local model: its gains come from the product's design")
    if scheme == "mmt":
        return [
            Rendering("mmt", "mmt", k_h=k, b_h=bh, variant=f"B={bh:g}", tuning=tune)
            for bh in plane_dampers
        ]
    if scheme == "force-jacobian":
        return [
            Rendering(
                "force-jacobian",
                "jacobian",
                k_h=k,
                b_h=bh,
                jacobian_scale=sc,
                variant=f"K x{sc:g}, B={bh:g}",
                tuning=tune,
            )
            for sc in (1.0, 0.5)
            for bh in dampers
        ]
    if scheme == "virtual-coupling":
        return [
            Rendering(
                "virtual-coupling",
                "tool",
                k_h=kc,
                b_h=bh,
                variant=f"K_c={kc:g}, B_c={bh:g}",
                tuning=tune,
            )
            for kc in (k, 0.5 * k)
            for bh in dampers
        ]
    if scheme == "static-local":
        return [
            Rendering(
                "static-local", "wall", k_h=min(k_o, k), b_h=bh, variant=f"B={bh:g}", tuning=tune
            )
            for bh in plane_dampers
        ]
    if scheme == "direct":
        return [Rendering("direct", "direct", tuning=tune)]
    if scheme == "direct-tdpa":
        return [
            Rendering(
                "direct-tdpa",
                "direct",
                passivity=True,
                passivity_max_damping=math.inf,
                two_port=tp,
                variant="two-port" if tp else "one-port",
                tuning=tune,
            )
            for tp in (False, True)
        ]
    raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")


def rendering_for(
    scheme: str,
    *,
    sim_rate_hz: float,
    device: DeviceModel = DeviceModel(),
    design: GainDesign | None = None,
    k_o: float | None = None,
) -> Rendering:
    """How ``scheme`` renders an object simulated at ``sim_rate_hz`` (module docstring): a local
    model's design, or a peer's default tuning (:func:`peer_renderings`).

    Parameters
    ----------
    scheme : str
        One of :data:`SCHEMES`.
    sim_rate_hz : float
        Simulation rate [Hz] (the local models' release ramp is two simulation periods).
    device : DeviceModel
        Limits the peers are tuned to.
    design : GainDesign, optional
        The product's gains for this object, rate and delay (required for ``local-p`` and
        ``local-pi``): :class:`shared.gain_design.GainTable` with the client's key.
    k_o : float, optional
        The K_o reported [N/m] (``static-local``'s plane; default the device's stiffness).

    Raises
    ------
    ValueError
        An unknown scheme, or a local model without its design.
    """
    if scheme in LOCAL_MODELS:
        if design is None:
            raise ValueError(f"{scheme} needs the product's gain design")
        pi = scheme == "local-pi"
        return Rendering(
            scheme,
            "coupling",
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            theta_m=PRODUCT_THETA_M,
            release_time_s=2.0 / sim_rate_hz,
            passivity=pi,
            passivity_bias_j=PRODUCT_PASSIVITY_BIAS_J,
            own_gain=design.own_gain,
            follows_k_o=True,
            tuning=scheme_tuning(scheme, device),
        )
    kk = k_o if k_o is not None else device.max_stiffness_n_per_m
    return peer_renderings(scheme, k_o=kk, sim_rate_hz=sim_rate_hz, device=device)[0]
