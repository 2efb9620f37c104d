"""Side-by-side fidelity of rendering schemes for a slow, delayed deformable object (1-D model).

The product's claim (the paper's section 1 and footnote 4) is that an adaptive local model renders
a slow (tens of Hz), delayed simulation stably and stiffly where the usual approaches do not. This
module measures it: one vectorised multirate simulator runs every scheme against the same hands,
objects, network delays and trajectories (``haptic bench fidelity``, :mod:`server.bench_fidelity`).

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
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.shared.full_loop import DAMPER_FILTER_S, Hand, ProxyHold, _hand_zoh
from haptic_collab.shared.gain_design import GainDesign, loop_delay_ticks
from haptic_collab.shared.types import FloatArray

SchemeName = Literal[
    "local-p", "local-pi", "direct", "virtual-coupling", "static-local", "direct-tdpa"
]

#: Every scheme, this project's first.
SCHEMES: tuple[SchemeName, ...] = (
    "local-p",
    "local-pi",
    "direct",
    "virtual-coupling",
    "static-local",
    "direct-tdpa",
)

#: Probe peak-to-peak [m] during the hold below which a cell counts as stable (issue 9).
STABLE_HOLD_P2P_M = 0.5e-3

#: A probe further than this from the surface [m] (or not finite) has run away.
RUNAWAY_M = 0.5


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
    kind : {"coupling", "direct"}
        ``coupling``: a local model (spring K_h, integral I, probe damper B_h) to the surface the
        simulation reports, the simulation receiving the force; ``direct``: the simulation
        computes the force from the probe position it receives.
    k_h, i_gain, b_h : float
        K_h [N/m], I [N/(m*s)], probe damper [N*s/m] (``coupling`` only).
    proxy_hold : {"zoh", "foh"}
    theta_m : float
        Integration threshold of eq. 17 [m] (used when ``i_gain > 0``).
    release_time_s : float
        Ramp [s] driving the integral force to zero on release (section 5.1).
    passivity : bool
        Time-domain passivity observer/controller at the device port.
    passivity_bias_j : float
        Energy [J] the PC tolerates before acting.
    own_gain : float
        Own-force compensation C_h [m/N] (``coupling`` only, :mod:`shared.full_loop`): the proxy
        is the reported surface moved out by C_h times the force the simulation applied.
    tuning : str
        How the gains were chosen, for the report.
    """

    scheme: str
    kind: Literal["coupling", "direct"]
    k_h: float = 0.0
    i_gain: float = 0.0
    b_h: float = 0.0
    proxy_hold: ProxyHold = "zoh"
    theta_m: float = 0.0
    release_time_s: float = 0.1
    passivity: bool = False
    passivity_bias_j: float = 0.0
    own_gain: float = 0.0
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


def felt_depth_m(k_o: float, max_force_n: float) -> float:
    """Depth [m] of the felt-stiffness oscillation on an object of stiffness ``k_o``: at most
    :data:`FELT_DEPTH_M`, shallow enough that even ``K_o x`` stays within 80 % of the device's
    force (a saturated force would read as no stiffness at all)."""
    return max(
        2.0 * FELT_AMPLITUDE_M, min(FELT_DEPTH_M, 0.8 * max_force_n / k_o - FELT_AMPLITUDE_M)
    )


def felt_trajectory(freq_hz: float, depth_m: float = FELT_DEPTH_M) -> Trajectory:
    """Position-source probe: ramp to ``depth_m`` (:func:`felt_depth_m`), settle 3.5 s, then
    oscillate at ``freq_hz`` by :data:`FELT_AMPLITUDE_M`; the felt stiffness is fitted over the
    last whole second(s) of it (4 cycles below 4 Hz, else 8), after 2 s of settling (a 400 ms
    round trip needs them)."""
    cycles_fit = 4 if freq_hz < 4.0 else 8
    t_s = 4.0
    t_fit = t_s + 2.0
    t_e = t_fit + cycles_fit / freq_hz
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
        Object stiffness K_o [N/m], > 0.
    sim_rate_hz : float
        Simulation rate [Hz]; the servo rate over it must be a whole number.
    delay_ms : float
        One-way network delay [ms], a whole number of servo ticks, >= 0.
    hand : Hand or None
        None: the probe is a position source (it follows the trajectory exactly).
    trajectory : Trajectory
    """

    rendering: Rendering
    k_o: float
    sim_rate_hz: float
    delay_ms: float
    hand: Hand | None
    trajectory: Trajectory


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
    max_damping_n_s_per_m: float,
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
        As :class:`shared.passivity.PassivityParams`.
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
        alpha = np.where(
            deficit >= max_damping_n_s_per_m * tvv,
            max_damping_n_s_per_m,
            deficit / np.where(tvv > 0.0, tvv, 1.0),
        )
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
) -> Run:
    """Run a batch of cells side by side at the servo rate (module docstring for the model).

    Parameters
    ----------
    cells : sequence of Cell
        Any mix of schemes, objects, rates, delays, hands and trajectories; the batch runs for
        the longest trajectory.
    device : DeviceModel
    servo_rate_hz : float

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
    direct = np.array([x.kind == "direct" for x in r])
    k_h = np.array([x.k_h for x in r])
    ti = T * np.array([x.i_gain for x in r])
    b_h = np.array([x.b_h for x in r])
    foh = np.array([x.proxy_hold == "foh" for x in r])
    theta = np.where(ti > 0.0, np.array([x.theta_m for x in r]), 0.0)
    rel_per_tick = T / np.array([x.release_time_s for x in r])
    recovery = np.where(ti > 0.0, 1.0 / k_o, 0.0)  # [m/N]
    pc_on = np.array([x.passivity for x in r])
    pc_bias = np.array([x.passivity_bias_j for x in r])
    own = np.array([x.own_gain for x in r])
    fmax = float(device.max_force_n)
    a_u = T / (T + DAMPER_FILTER_S)

    # hands: exact ZOH of m x'' = -b (x' - y') - k (x - y) - f  (input f - k y - b y')
    src = np.array([c.hand is None for c in cells])
    hm = np.array([1.0 if c.hand is None else c.hand.mass_kg for c in cells])
    hb = np.array([0.0 if c.hand is None else c.hand.damping_n_s_per_m for c in cells])
    hk = np.array([0.0 if c.hand is None else c.hand.stiffness_n_per_m for c in cells])
    phi, gam = _hand_zoh(hm, hb, hk, T)

    n_steps = max(round(c.trajectory.duration_s * servo_rate_hz) for c in cells)
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
    x_prev = x.copy()

    # servo state
    s = np.zeros(B)  # integral force [N]
    rel_step = np.zeros(B)
    was_contact = np.zeros(B, dtype=bool)
    u = np.zeros(B)  # filtered probe velocity
    p_new = np.zeros(B)  # latest surface received
    p_old = np.zeros(B)  # FOH start
    hold_i = np.zeros(B, dtype=np.int64)
    f_recv = np.zeros(B)  # direct: force received
    seq_seen = np.zeros(B, dtype=np.int64)
    pc_e = np.zeros(B)
    pc_fa = np.zeros(B)
    # network: ring buffers on the servo clock
    L = int(d_ticks.max()) + 2
    up = np.zeros((L, B))  # what the servo sent at tick n (force, or position for direct)
    down = np.zeros((L, B))  # latest value the simulation had published by the end of tick n
    down_seq = np.zeros((L, B), dtype=np.int64)
    pub = np.zeros(B)
    pub_seq = np.zeros(B, dtype=np.int64)
    cols = np.arange(B)
    runaway = np.zeros(B, dtype=bool)

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
        vel = (x - x_prev) / T
        k_read = n - 1 - d_ticks
        ok = k_read >= 0
        slot = np.where(ok, k_read, 0) % L
        val = np.where(ok, down[slot, cols], 0.0)
        seq = np.where(ok, down_seq[slot, cols], 0)
        fresh = seq != seq_seen
        if fresh.any():
            # first-order hold starts from wherever the proxy is now
            blend = np.minimum(1.0, (hold_i + 1.0) / n_ratio)
            p_cur = np.where(foh, p_old + (p_new - p_old) * blend, p_new)
            p_old = np.where(fresh, p_cur, p_old)
            p_new = np.where(fresh & ~direct, val, p_new)
            f_recv = np.where(fresh & direct, val, f_recv)
            hold_i = np.where(fresh, 0, hold_i + 1)
            seq_seen = seq
        else:
            hold_i = hold_i + 1
        # 2. compute
        w = np.where(foh, np.minimum(1.0, (hold_i + 1.0) / n_ratio), 1.0)
        proxy = p_old + (p_new - p_old) * w
        e = x - proxy
        # contact: the probe past the proxy; an integral keeps it while the probe is within the
        # deformation its force holds (s / K_o: the object's surface follows a retreating probe
        # back, the proxy is a stale copy of it; shared.local_model's recovery band)
        contact = (e > 0.0) | (was_contact & (e > -s * recovery))
        # local model, eq. 12 with eq. 17's threshold and the release ramp (shared.local_model)
        f_lm = np.where(contact, np.maximum(k_h * e + s, 0.0), s)
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
        f = np.clip(f, -fmax, fmax)
        # passivity layer at the device port: force ON the handle is -f, its velocity vel
        if pc_on.any():
            pc_e, fa, _ = passivity_step(
                pc_e,
                pc_fa,
                -f,
                vel,
                servo_period_s=T,
                max_damping_n_s_per_m=device.max_damping_n_s_per_m,
                energy_bias_j=pc_bias,
                max_force_n=fmax,
                on=pc_on,
            )
            pc_fa = fa
            f = np.where(pc_on, -fa, f)
        X[:, n] = x
        F[:, n] = f
        # 3. write: the hand moves under the force held over the tick
        x_prev = x
        if not src.all():
            inp = f - hk * Y[:, n] - hb * YD[:, n]
            xn = phi[:, 0, 0] * x + phi[:, 0, 1] * v + gam[:, 0] * inp
            vn = phi[:, 1, 0] * x + phi[:, 1, 1] * v + gam[:, 1] * inp
            x = np.where(runaway, x, xn)
            v = np.where(runaway, 0.0, vn)
        # uplink, then the simulation's tick
        up[n % L] = np.where(direct, x_prev, f)
        sim_now = (n % n_ratio) == 0
        if sim_now.any():
            k_up = n - d_ticks
            got = np.where(k_up >= 0, up[np.where(k_up >= 0, k_up, 0) % L, cols], 0.0)
            x_o = np.where(direct, np.maximum(got, 0.0), np.maximum(got, 0.0) / k_o)
            # a local model receives the surface and the force applied (own-force compensation)
            val_pub = np.where(direct, k_o * x_o, x_o - own * np.maximum(got, 0.0))
            pub = np.where(sim_now, val_pub, pub)
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
        Largest ``x - f / K_o`` [mm]: how far the probe went past the surface of an object of
        stiffness K_o that pushes back with the force the user actually feels (0 for an ideal
        rendering; for a coupling it includes the steady-state error).
    steady_state_error_mm : float
        Mean of ``x - f / K_o`` [mm] over the last half of the hold window (the probe-proxy gap of
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
        pen = x - f / c.k_o
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
    """Felt stiffness dF/dx / K_o (complex: magnitude and phase at the probe frequency) of
    position-source cells (:func:`felt_trajectory`), in order; :func:`felt_stiffness_ratio` is
    its magnitude, its real part the elastic share (a lagging force is partly felt as damping,
    or, lagging by a long delay, as an active push).

    Least-squares fit of ``a + b t + c cos(w t) + d sin(w t)`` to the probe position and to the
    force over the trajectory's hold window (whole cycles of the probe and of every simulation
    rate of the grid; the multirate ripple is not at w and drops out); the ratio of the
    fundamentals over K_o, as :func:`shared.gain_design.felt_stiffness` computes it exactly for
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
        a, b = tr.hold_window_s
        mid = 0.5 * (a + b)
        ratios = []
        for lo, hi in ((a, b), (a, mid), (mid, b)):
            m = _window(t, (lo, hi))
            x1 = _fundamental(t[m], run.x[i, :n_i][m], w)
            f1 = _fundamental(t[m], run.f[i, :n_i][m], w)
            q = f1 / x1 / c.k_o if abs(x1) > 0.0 else complex(math.nan)
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
        quiet = ripple <= FELT_FIT_TOLERANCE * 2.0 * whole * c.k_o * tr.sine_amplitude_m
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
    (:func:`shared.gain_design.loop_delay_ticks`).

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
        "virtual-coupling": (
            f"spring {k:g} N/m and damper {b:g} N*s/m: the {device.name}'s maximum stable "
            "stiffness and damping, whatever K_o"
        ),
        "static-local": (
            f"plane stiffness {0.5 * k:g} N/m (half the {device.name}'s maximum), no damping, "
            "whatever K_o"
        ),
        "direct": "the simulation's own contact force K_o x, held (ZOH) until the next one",
        "direct-tdpa": (
            f"direct, with the passivity observer/controller at the port: alpha_max = {b:g} "
            "N*s/m (the device's maximum damping), no energy bias"
        ),
    }
    if scheme not in text:
        raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")
    return text[scheme]


def rendering_for(
    scheme: str,
    *,
    sim_rate_hz: float,
    device: DeviceModel = DeviceModel(),
    design: GainDesign | None = None,
) -> Rendering:
    """How ``scheme`` renders an object simulated at ``sim_rate_hz`` (module docstring).

    Parameters
    ----------
    scheme : str
        One of :data:`SCHEMES`.
    sim_rate_hz : float
        Simulation rate [Hz] (the local models' release ramp is two simulation periods).
    device : DeviceModel
        Limits the fixed schemes are tuned to.
    design : GainDesign, optional
        The product's gains for this object, rate and delay (required for ``local-p`` and
        ``local-pi``): :class:`shared.gain_design.GainTable` with the client's key.

    Raises
    ------
    ValueError
        An unknown scheme, or a local model without its design.
    """
    if scheme in ("local-p", "local-pi"):
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
            tuning=scheme_tuning(scheme, device),
        )
    if scheme == "virtual-coupling":
        return Rendering(
            scheme,
            "coupling",
            k_h=device.max_stiffness_n_per_m,
            b_h=device.max_damping_n_s_per_m,
            tuning=scheme_tuning(scheme, device),
        )
    if scheme == "static-local":
        return Rendering(
            scheme,
            "coupling",
            k_h=0.5 * device.max_stiffness_n_per_m,
            tuning=scheme_tuning(scheme, device),
        )
    if scheme == "direct":
        return Rendering(scheme, "direct", tuning=scheme_tuning(scheme, device))
    if scheme == "direct-tdpa":
        return Rendering(
            scheme,
            "direct",
            passivity=True,
            tuning=scheme_tuning(scheme, device),
        )
    raise ValueError(f"unknown scheme {scheme!r}; expected one of {', '.join(SCHEMES)}")
