"""The 1 kHz servo loop: a sans-I/O core (:class:`ServoCore`) and the thread that times it.

DESIGN section 4 (client side) and section 7; the paper's haptic loop of section 6, Steps 2-3.
Every servo period T one :meth:`ServoCore.tick` runs three phases (CHAI3D's haptic tick):

1. update from device: x_h = device.read(t)
2. compute: (e, n) = primitive.contact(x_h); f = L(z) e (eq. 12 with the threshold of eq. 17-18,
   :class:`shared.local_model.LocalModel`); the force on the user is
   F = g * clamp(f, +-F_max) * n, n the outward normal, g in [0, 1] the safety ramp
3. apply to device: device.write(F)

The local model (primitive + gains K_h, I) is a zero-order hold of the slow simulation's output
(eq. 1): :meth:`ServoCore.set_patch` may be called from the network thread at any time; it swaps
one reference that the next tick picks up, so a patch is applied whole and between ticks. The
LocalModel's integral state is kept across patches (only its gains change), so a new patch does
not make the integral force jump.

Safety, as device vendors do it (STYLE rule 9):

- forces are off until :meth:`ServoCore.enable_forces` *and* the first patch;
- every force is clamped to ``limits.max_force_n`` (``FORCE_LIMIT`` counted per episode);
- K_h is clamped to ``limits.max_stiffness_n_per_m``;
- the safety gain g ramps linearly (never jumps) by T / ``ramp_s`` per tick: down to zero when the
  link is silent for ``link_timeout_s`` (``LINK_LOST``), when the device reports a fault
  (``DEVICE_FAULT``), when the probe moves faster than ``limits.max_velocity_m_s``
  (``VELOCITY_LIMIT``), on :meth:`ServoCore.disable_forces` and on stop; back up to one when the
  cause is gone (after a link loss: when a *new* patch arrives). While g is zero with forces
  withheld the local model is reset, so no integral winds up;
- a stop ramps down, writes a zero force and disables the device's forces.

The tick reads no clock (time is an input, as in aioquic), does not log, does not await, and
allocates only its small result tuples; telemetry goes to a preallocated ring buffer
(:class:`client.recorder.TelemetryRecorder`).

:class:`ServoThread` runs the core on its own thread at ``servo_rate_hz``: tick k is due at
``start + k*T`` (integer tick counts, never accumulated float time); it sleeps until ``spin_s``
before the deadline and spins the rest; a deadline missed by more than ``late_tolerance`` periods
is counted (``SERVO_OVERRUN``) and skipped, never piled up. Clock and sleep are injected.
"""

from __future__ import annotations

import array
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from haptic_collab.client.devices.base import Device, HapticError, Vec3
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.thermal import (
    DEFAULT_THERMAL_TIME_CONSTANT_S,
    ThermalLimit,
    ThermalParams,
)
from haptic_collab.shared.full_loop import DAMPER_FILTER_S
from haptic_collab.shared.local_model import LocalModel, LocalModelParams
from haptic_collab.shared.passivity import PassivityController, PassivityParams
from haptic_collab.shared.primitives import Plane, Primitive, Sphere

Clock = Callable[[], float]
Sleep = Callable[[float], None]


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
        for PI local models).
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


@dataclass(frozen=True, slots=True)
class Patch:
    """The local model received from the server: primitive and gains (no pydantic inside).

    Parameters
    ----------
    primitive : Plane or Sphere
        Local geometric model of the surface near the probe (paper section 6, Step 1).
    k_h : float
        Local model stiffness K_h [N/m] (already clamped to the device's max stiffness).
    i_gain : float
        Integral weight I [N/(m*s)] (eq. 12).
    b_h : float
        Probe damper B_h [N*s/m] on the backward difference of the probe position, in contact
        only (already clamped to the device's max damping).
    proxy_hold : {"zoh", "foh"}
        ``zoh``: the new surface replaces the old at once (eq. 1); ``foh``: the penetration moves
        linearly from the old surface's to the new one's over ``hold_ticks`` servo ticks (from
        where the previous slide had got to, if this patch arrived before it finished).
    hold_ticks : int
        Servo ticks of the first-order hold (N, one simulation period), >= 1.
    recovery_m_per_n : float or None
        1/K_o of the contact [m/N]: the local model keeps a PI contact while the probe is within
        the deformation its integral force holds (:class:`shared.local_model.LocalModelParams`);
        None keeps the local model's own.
    """

    primitive: Primitive
    k_h: float
    i_gain: float
    b_h: float = 0.0
    proxy_hold: str = "zoh"
    hold_ticks: int = 1
    recovery_m_per_n: float | None = None


@dataclass(frozen=True, slots=True)
class ServoEvent:
    """One safety event: its kind, the servo time [s] it happened, a human-readable detail."""

    kind: HapticError
    t_s: float
    detail: str


@dataclass(frozen=True, slots=True)
class ServoStatus:
    """Safety state of the servo loop (:meth:`ServoCore.status`).

    Attributes
    ----------
    ticks : int
        Ticks run.
    counts : dict of str to int
        Events per :class:`HapticError` value (every kind present, 0 if none).
    last_event : ServoEvent or None
        The newest event.
    forces_enabled : bool
        Forces enabled by the user (:meth:`ServoCore.enable_forces`).
    engaged : bool
        Forces engaged with the stylus button (always True without
        ``ServoConfig.engage_with_button``).
    has_patch : bool
        A patch has been received and is current (False again after a link loss until a new one).
    link_alive : bool
        The link spoke within ``link_timeout_s`` at the last tick.
    force_scale : float
        Safety gain g in [0, 1] at the last tick.
    device_fault : str or None
        The device's fault message.
    stiffness_clamps : int
        Patches whose K_h exceeded the device's max stiffness and were clamped.
    stopped : bool
        The stop ramp finished and the device's forces are disabled.
    error : str or None
        An unexpected exception that ended the servo thread (forces were zeroed).
    passivity : dict or None
        The passivity controller's energies [J]: ``observed_j`` (energy the virtual environment
        holds, > 0 passive), ``dissipated_j`` (removed by the controller), ``active_j`` (energy
        the local model would have given the user); None when the controller is off.
    """

    ticks: int
    counts: dict[str, int]
    last_event: ServoEvent | None
    forces_enabled: bool
    has_patch: bool
    link_alive: bool
    force_scale: float
    device_fault: str | None
    stiffness_clamps: int
    stopped: bool
    error: str | None = None
    passivity: dict[str, float] | None = None
    engaged: bool = True

    def as_dict(self) -> dict[str, Any]:
        """JSON-able dictionary of the status."""
        ev = self.last_event
        return {
            "ticks": self.ticks,
            "counts": dict(self.counts),
            "last_event": None
            if ev is None
            else {"kind": ev.kind.value, "t_s": ev.t_s, "detail": ev.detail},
            "forces_enabled": self.forces_enabled,
            "engaged": self.engaged,
            "has_patch": self.has_patch,
            "link_alive": self.link_alive,
            "force_scale": self.force_scale,
            "device_fault": self.device_fault,
            "stiffness_clamps": self.stiffness_clamps,
            "stopped": self.stopped,
            "error": self.error,
            "passivity": None if self.passivity is None else dict(self.passivity),
        }


@dataclass(frozen=True, slots=True)
class ServoSnapshot:
    """The newest servo state, for the network side to send each simulation tick (latest wins).

    Attributes
    ----------
    tick : int
        Index of the tick it comes from.
    t_s : float
        Servo time [s] of that tick.
    probe_m : (3,) float
        Probe position x_h [m].
    force_n : (3,) float
        Force [N] rendered on the user (and applied to the object with the opposite sign, Step 3).
    penetration_m : float
        Penetration e [m] into the local model (NaN before the first patch).
    in_contact : bool
        The local model was in contact.
    k_h : float
        K_h [N/m] in use.
    i_gain : float
        I [N/(m*s)] in use.
    force_scale : float
        Safety gain g in [0, 1].
    servo_rate_hz : float
        Achieved rate [Hz]: 1 / mean period over the last ``period_window`` ticks.
    period_mean_s, period_p50_s, period_p99_s, period_max_s : float
        Period statistics [s] over the same window (NaN before two ticks).
    """

    tick: int
    t_s: float
    probe_m: Vec3
    force_n: Vec3
    penetration_m: float
    in_contact: bool
    k_h: float
    i_gain: float
    force_scale: float
    servo_rate_hz: float
    period_mean_s: float
    period_p50_s: float
    period_p99_s: float
    period_max_s: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-able dictionary (vectors as lists; NaN stays NaN)."""
        return {
            "tick": self.tick,
            "t_s": self.t_s,
            "probe_m": list(self.probe_m),
            "force_n": list(self.force_n),
            "penetration_m": self.penetration_m,
            "in_contact": self.in_contact,
            "k_h": self.k_h,
            "i_gain": self.i_gain,
            "force_scale": self.force_scale,
            "servo_rate_hz": self.servo_rate_hz,
            "period_mean_s": self.period_mean_s,
            "period_p50_s": self.period_p50_s,
            "period_p99_s": self.period_p99_s,
            "period_max_s": self.period_max_s,
        }


_NAN = math.nan


class ServoCore:
    """Sans-I/O servo core: one :meth:`tick` reads the device, renders the local model, writes.

    Parameters
    ----------
    device : Device
        An opened device.
    config : ServoConfig
        Rate and safety parameters.
    local_model : LocalModelParams, optional
        Threshold, release time and contact type of the local model; its ``servo_period_s`` must
        equal the config's period. Its gains are replaced by each patch's. Default: a unilateral
        model with no threshold.
    recorder : TelemetryRecorder, optional
        Where each tick writes its telemetry row (default: a new 120000-row recorder).

    Raises
    ------
    ValueError
        ``local_model.servo_period_s`` differs from ``1 / config.servo_rate_hz`` (the local model
        is a discrete block of period T; running it at another rate is a different system).

    Notes
    -----
    A stop is final: after :attr:`stopped` further ticks do nothing; build a new core to restart.

    Thread safety: :meth:`set_patch`, :meth:`notify_link`, :meth:`enable_forces`,
    :meth:`disable_forces`, :meth:`request_stop`, :meth:`latest` and :meth:`status` may be called
    from any thread; :meth:`tick` only from the servo thread.
    """

    def __init__(
        self,
        device: Device,
        config: ServoConfig | None = None,
        *,
        local_model: LocalModelParams | None = None,
        recorder: TelemetryRecorder | None = None,
    ) -> None:
        cfg = config if config is not None else ServoConfig()
        T = cfg.servo_period_s
        lim = device.limits
        if local_model is None:
            local_model = LocalModelParams(k_h=lim.max_stiffness_n_per_m, servo_period_s=T)
        if not math.isclose(local_model.servo_period_s, T, rel_tol=1e-9):
            raise ValueError(
                f"local model period {local_model.servo_period_s} s differs from the servo period "
                f"{T} s (servo_rate_hz={cfg.servo_rate_hz})"
            )
        self.device = device
        self.config = cfg
        self.recorder = recorder if recorder is not None else TelemetryRecorder()
        self.local_model = LocalModel(local_model)
        self._T = T
        self._step = cfg.ramp_step
        self._fmax = lim.max_force_n
        # peak force for a limited time, then the continuous force (client.thermal)
        self._thermal: ThermalLimit | None = None
        if lim.has_force_output and lim.max_continuous_force_n is not None and lim.max_force_n > 0:
            self._thermal = ThermalLimit(
                ThermalParams(
                    peak_force_n=lim.max_force_n,
                    continuous_force_n=lim.max_continuous_force_n,
                    time_constant_s=lim.thermal_time_constant_s or DEFAULT_THERMAL_TIME_CONSTANT_S,
                    servo_period_s=T,
                )
            )
        self._vmax2 = lim.max_velocity_m_s**2
        self._vresume2 = (cfg.velocity_resume_ratio * lim.max_velocity_m_s) ** 2
        tau = cfg.velocity_filter_s
        self._alpha = 1.0 if tau == 0.0 else T / (T + tau)
        self._timeout = cfg.link_timeout_s
        # patch hand-over (one reference swap; see set_patch)
        self._patch_in: Patch | None = None
        self._patch: Patch | None = None
        self._primitive: Primitive | None = None
        self._prim_old: Primitive | None = None  # the surface a first-order hold moves away from
        self._hold_off = 0.0  # depth [m] added to _prim_old: where the slide really starts
        # a patch that arrived mid-slide: (start surface, its offset, weight reached); the new
        # slide's start offset is computed from it on the next tick, once the probe is read
        self._rebase: tuple[Primitive, float, float] | None = None
        self._hold_i = 0
        self._hold_n = 1
        self._k_h = 0.0
        self._i_gain = 0.0
        self._b_h = 0.0
        self._inv_T = 1.0 / T
        self._a_u = T / (T + DAMPER_FILTER_S)  # the damper's velocity filter (shared.full_loop)
        self._u = 0.0
        self._pc: PassivityController | None = None
        if cfg.passivity and lim.has_force_output and lim.max_damping_n_s_per_m > 0.0:
            # the controller's damper is bounded by what the device can render stably
            self._pc = PassivityController(
                PassivityParams(
                    max_damping_n_s_per_m=lim.max_damping_n_s_per_m,
                    energy_bias_j=cfg.passivity_energy_bias_j,
                    servo_period_s=T,
                    max_force_n=lim.max_force_n,
                )
            )
        self._need_patch = True
        self._link_t = -math.inf
        # switches set from other threads
        self._enabled = False
        self._stopping = False
        # the stylus button (ServoConfig.engage_with_button)
        self._by_button = cfg.engage_with_button
        self._engaged = not cfg.engage_with_button
        self._button_was = False
        # tick state
        self._ticks = 0
        self._t = 0.0
        self._px = self._py = self._pz = 0.0
        self._vx = self._vy = self._vz = 0.0
        self._scale = 0.0
        self._overspeed = False
        self._limited = False
        self._link_ok = False
        self._fault: str | None = None
        self._dev_enabled = False
        self._stopped = False
        self.error: str | None = None
        # events
        self._counts: dict[HapticError, int] = dict.fromkeys(HapticError, 0)
        self._last_event: ServoEvent | None = None
        self._stiffness_clamps = 0
        # latest-wins publication and period window
        self._pub: tuple[Any, ...] | None = None
        self._periods = array.array("d", bytes(8 * cfg.period_window))
        self._n_periods = 0

    # -- inputs from other threads ---------------------------------------------------------------
    def set_patch(
        self,
        primitive: Primitive,
        k_h: float,
        i_gain: float,
        *,
        b_h: float = 0.0,
        proxy_hold: str = "zoh",
        hold_ticks: int = 1,
        k_o: float | None = None,
    ) -> Patch:
        """Hand a new local model to the servo loop; applied whole at the start of the next tick.

        K_h above the device's ``max_stiffness_n_per_m`` is clamped to it (counted in
        ``status().stiffness_clamps``), B_h to ``max_damping_n_s_per_m``. The LocalModel's
        integral state is kept (eq. 12 gains change, its state does not). With ``proxy_hold="foh"``
        the surface moves from the previous patch's to this one's over ``hold_ticks`` ticks
        (:mod:`shared.full_loop` analyses exactly this); a patch that arrives before the previous
        slide is over (network jitter) slides on from the blend reached, so the force never steps.

        Parameters
        ----------
        primitive : Plane or Sphere
            Local geometric model [m] (:mod:`shared.primitives`).
        k_h : float
            K_h [N/m], finite and > 0.
        i_gain : float
            I [N/(m*s)], finite and >= 0.
        b_h : float
            Probe damper B_h [N*s/m], finite and >= 0.
        proxy_hold : {"zoh", "foh"}
        hold_ticks : int
            Servo ticks per simulation tick N for the first-order hold, >= 1.
        k_o : float, optional
            The contact's K_o [N/m], > 0: sets the local model's recovery band (a PI contact is
            kept while the probe is within s/K_o of the proxy; :mod:`shared.local_model`).

        Returns
        -------
        Patch
            What will be applied.

        Raises
        ------
        TypeError
            ``primitive`` is not a Plane or Sphere.
        ValueError
            Non-finite or out-of-range gains.
        """
        if not isinstance(primitive, Plane | Sphere):
            raise TypeError(f"primitive must be a Plane or Sphere, got {type(primitive).__name__}")
        k = float(k_h)
        i = float(i_gain)
        if not (math.isfinite(k) and k > 0.0):
            raise ValueError(f"k_h must be a finite stiffness > 0 N/m, got {k_h!r}")
        if not (math.isfinite(i) and i >= 0.0):
            raise ValueError(f"i_gain must be finite and >= 0 N/(m*s), got {i_gain!r}")
        bh = float(b_h)
        if not (math.isfinite(bh) and bh >= 0.0):
            raise ValueError(f"b_h must be finite and >= 0 N*s/m, got {b_h!r}")
        if proxy_hold not in ("zoh", "foh"):
            raise ValueError(f"proxy_hold must be 'zoh' or 'foh', got {proxy_hold!r}")
        if isinstance(hold_ticks, bool) or int(hold_ticks) != hold_ticks or hold_ticks < 1:
            raise ValueError(f"hold_ticks must be a whole number >= 1, got {hold_ticks!r}")
        lim = self.device.limits
        kmax = lim.max_stiffness_n_per_m
        if k > kmax:
            k = kmax
            self._stiffness_clamps += 1
        bh = min(bh, lim.max_damping_n_s_per_m)
        rec = None
        if k_o is not None:
            if not (math.isfinite(k_o) and k_o > 0.0):
                raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
            rec = 1.0 / k_o
        patch = Patch(primitive, k, i, bh, proxy_hold, int(hold_ticks), rec)
        self._patch_in = patch
        return patch

    def notify_link(self, now_s: float) -> None:
        """The server spoke (a patch or a pong arrived) at servo time ``now_s`` [s]."""
        if now_s > self._link_t:
            self._link_t = now_s

    def enable_forces(self) -> None:
        """Allow forces (they ramp up once a patch is current and nothing else withholds them)."""
        self._enabled = True

    def disable_forces(self) -> None:
        """Ramp forces down to zero and keep them there until :meth:`enable_forces`."""
        self._enabled = False

    def request_stop(self) -> None:
        """Ramp forces down, then write zero and disable the device's forces (see :attr:`stopped`)."""
        self._stopping = True

    @property
    def stopped(self) -> bool:
        """True once a requested stop finished (forces at zero and disabled)."""
        return self._stopped

    # -- the tick ----------------------------------------------------------------------------------
    def tick(self, now_s: float) -> bool:
        """Run one servo period at servo time ``now_s`` [s]: read device, compute, write device.

        Returns
        -------
        bool
            True once the core has stopped (after :meth:`request_stop` and the ramp down).
        """
        if self._stopped:
            return True
        p = self._patch_in
        if p is not self._patch and p is not None:
            self._patch = p
            fresh = self._primitive is None or self._need_patch
            old = self._prim_old
            if fresh or p.proxy_hold != "foh":
                self._prim_old = None
                self._rebase = None
            else:
                # a patch arriving before the last slide finished (network jitter) slides on from
                # the blend reached, not from the last target (that would be a step)
                self._rebase = (
                    None if old is None else (old, self._hold_off, self._hold_i / self._hold_n)
                )
                self._prim_old = self._primitive
                self._hold_off = 0.0
            self._hold_i = 0
            self._hold_n = p.hold_ticks
            self._primitive = p.primitive
            # the damper's share of the force step is carried off with the stiffness's
            carry = (self._b_h - p.b_h) * self._u if self._b_h > 0.0 or p.b_h > 0.0 else 0.0
            self.local_model.set_gains(p.k_h, p.i_gain, p.recovery_m_per_n, carry_n=carry)
            self._k_h = p.k_h
            self._i_gain = p.i_gain
            self._b_h = p.b_h
            self._need_patch = False
            if now_s > self._link_t:
                self._link_t = now_s

        # 1. update from device
        dev = self.device
        x, y, z = dev.read(now_s)
        if self._by_button:  # a press of button 0 toggles the engagement
            pressed = bool(dev.buttons() & 1)
            if pressed and not self._button_was:
                self._engaged = not self._engaged
            self._button_was = pressed
        bad_position = not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z))
        if bad_position:  # keep the last finite position; treated as a device fault below
            x, y, z = self._px, self._py, self._pz

        # 2. compute
        n = self._ticks
        ox, oy, oz = (self._px, self._py, self._pz) if n else (x, y, z)
        if n:
            period = now_s - self._t
            if period > 0.0:
                a = self._alpha
                inv = 1.0 / period
                self._vx += a * ((x - self._px) * inv - self._vx)
                self._vy += a * ((y - self._py) * inv - self._vy)
                self._vz += a * ((z - self._pz) * inv - self._vz)
            self._periods[self._n_periods % len(self._periods)] = period
            self._n_periods += 1
        else:
            period = _NAN
        self._t, self._px, self._py, self._pz = now_s, x, y, z

        # safety state
        speed2 = self._vx * self._vx + self._vy * self._vy + self._vz * self._vz
        if self._overspeed:
            if speed2 < self._vresume2:
                self._overspeed = False
        elif speed2 > self._vmax2:
            self._overspeed = True
            self._event(HapticError.VELOCITY_LIMIT, now_s, "probe speed above the device limit")
        fault = dev.fault
        if fault is None and bad_position:
            fault = "device reported a non-finite position"
        if fault is not None and self._fault is None:
            self._event(HapticError.DEVICE_FAULT, now_s, fault)
        self._fault = fault
        link_ok = now_s - self._link_t <= self._timeout
        if self._link_ok and not link_ok and not self._need_patch:
            self._need_patch = True
            self._event(HapticError.LINK_LOST, now_s, "no patch or pong within the link timeout")
        self._link_ok = link_ok
        want = (
            self._enabled
            and self._engaged
            and not self._need_patch
            and link_ok
            and fault is None
            and not self._overspeed
            and not self._stopping
        )
        s0 = self._scale
        if want:
            s = s0 + self._step
            if s > 1.0:
                s = 1.0
        else:
            s = s0 - self._step
            if s < 0.0:
                s = 0.0
        self._scale = s
        ramping = s != s0

        # local model (eq. 12, 17-18) along the outward normal
        lm = self.local_model
        prim = self._primitive
        if prim is not None:
            e, nx, ny, nz = prim.contact(x, y, z)
            old = self._prim_old
            if old is not None:  # first-order hold: slide from the old surface to the new one
                rb = self._rebase
                if rb is not None:  # start where the interrupted slide was: its blend, here
                    s_prim, s_off, w = rb
                    self._hold_off = (1.0 - w) * (
                        s_prim.contact(x, y, z)[0] + s_off - old.contact(x, y, z)[0]
                    )
                    self._rebase = None
                hi = self._hold_i + 1
                if hi >= self._hold_n:
                    self._prim_old = None
                else:
                    self._hold_i = hi
                    e_old = old.contact(x, y, z)[0] + self._hold_off
                    e = e_old + (e - e_old) * (hi / self._hold_n)
            # the probe's depth rate along the inward normal (backward difference, never the proxy's)
            v_in = -((x - ox) * nx + (y - oy) * ny + (z - oz) * nz) * self._inv_T
            f = lm.step(e, v_in)
            in_contact = lm.in_contact
            self._u += self._a_u * (v_in - self._u)
            if in_contact and self._b_h > 0.0:
                f += self._b_h * self._u  # probe damper on the filtered probe velocity
                if f < 0.0:
                    f = 0.0
        else:
            e, nx, ny, nz, f, in_contact = _NAN, 0.0, 0.0, 0.0, 0.0, False
        th = self._thermal
        fmax = self._fmax if th is None else th.limit_n
        limited = f > fmax or f < -fmax
        if limited:
            f = fmax if f > 0.0 else -fmax
            if not self._limited:
                self._event(
                    HapticError.FORCE_LIMIT,
                    now_s,
                    "local model force above the device max"
                    if fmax >= self._fmax
                    else f"motors warm: force limited to {fmax:.2f} N, falling to the continuous "
                    "force",
                )
        self._limited = limited
        fo = f * s
        fx, fy, fz = fo * nx, fo * ny, fo * nz
        pc = self._pc
        if pc is not None:  # passivity observer/controller at the device port
            it = self._inv_T
            fx, fy, fz = pc.step(fx, fy, fz, (x - ox) * it, (y - oy) * it, (z - oz) * it)
        if th is not None:  # the motors heat with the force displayed (the safety scale included)
            th.step(math.sqrt(fx * fx + fy * fy + fz * fz) if self._dev_enabled else 0.0)
        if s == 0.0 and not want and prim is not None:
            lm.reset()  # forces withheld: no integral wind-up while off

        # 3. apply to device
        if want and not self._dev_enabled:
            dev.enable_forces()
            self._dev_enabled = True
        dev.write(fx, fy, fz)
        if self._stopping and s == 0.0:
            dev.write(0.0, 0.0, 0.0)
            dev.disable_forces()
            self._dev_enabled = False
            self._stopped = True

        # telemetry (plain stores) and latest-wins publication (one reference swap)
        if prim is not None:
            qx, qy, qz = x + e * nx, y + e * ny, z + e * nz
        else:
            qx, qy, qz = x, y, z
        self.recorder.append(
            n,
            now_s,
            x,
            y,
            z,
            qx,
            qy,
            qz,
            e,
            fx,
            fy,
            fz,
            fo,
            self._k_h,
            self._i_gain,
            lm.integral_n,
            lm.theta_m,
            period,
            0.0,
            s,
            in_contact,
            ramping,
            fault is not None,
            limited,
            self._b_h,
            pc.observed_energy_j if pc is not None else 0.0,
            pc.dissipated_energy_j if pc is not None else 0.0,
        )
        self._pub = (n, now_s, x, y, z, fx, fy, fz, e, in_contact, self._k_h, self._i_gain, s)
        self._ticks = n + 1
        return self._stopped

    def record_compute(self, compute_s: float) -> None:
        """Store the measured duration [s] of the tick that just ran in its telemetry row."""
        self.recorder.set_compute_s(compute_s)

    def note_overrun(self, missed: int, now_s: float) -> None:
        """Count ``missed`` skipped deadlines (``SERVO_OVERRUN``) noticed at servo time ``now_s``."""
        if missed > 0:
            # one event (last_event) for the whole gap, counted once per missed deadline
            self._counts[HapticError.SERVO_OVERRUN] += missed - 1
            self._event(
                HapticError.SERVO_OVERRUN, now_s, f"{missed} deadline(s) missed and skipped"
            )

    def shutdown_now(self, error: str | None = None) -> None:
        """Zero and disable the device's forces at once, without a ramp.

        Used when the servo thread dies (``error`` says why; it shows in ``status().error``) or
        is stopped without having run the ramp. Call it only when no tick is running.
        """
        if error is not None:
            self.error = error
        self._scale = 0.0
        try:
            self.device.write(0.0, 0.0, 0.0)
            self.device.disable_forces()
        finally:
            self._dev_enabled = False
            self._stopped = True

    def _event(self, kind: HapticError, t_s: float, detail: str) -> None:
        self._counts[kind] += 1
        self._last_event = ServoEvent(kind, t_s, detail)

    # -- outputs to other threads ----------------------------------------------------------------
    def latest(self) -> ServoSnapshot | None:
        """The newest tick's state and period statistics (None before the first tick)."""
        pub = self._pub
        if pub is None:
            return None
        m = min(self._n_periods, len(self._periods))
        if m:
            v = sorted(self._periods[:m])
            mean = sum(v) / m
            p50, p99, pmax = v[(m - 1) // 2], v[int(0.99 * (m - 1))], v[-1]
            rate = 1.0 / mean if mean > 0.0 else _NAN
        else:
            mean = p50 = p99 = pmax = rate = _NAN
        n, t, x, y, z, fx, fy, fz, e, c, k_h, i_gain, s = pub
        return ServoSnapshot(
            tick=n,
            t_s=t,
            probe_m=(x, y, z),
            force_n=(fx, fy, fz),
            penetration_m=e,
            in_contact=bool(c),
            k_h=k_h,
            i_gain=i_gain,
            force_scale=s,
            servo_rate_hz=rate,
            period_mean_s=mean,
            period_p50_s=p50,
            period_p99_s=p99,
            period_max_s=pmax,
        )

    def status(self) -> ServoStatus:
        """Counters per :class:`HapticError`, the last event and the safety switches."""
        return ServoStatus(
            ticks=self._ticks,
            counts={k.value: v for k, v in self._counts.items()},
            last_event=self._last_event,
            forces_enabled=self._enabled,
            engaged=self._engaged,
            has_patch=self._patch is not None and not self._need_patch,
            link_alive=self._link_ok,
            force_scale=self._scale,
            device_fault=self._fault,
            stiffness_clamps=self._stiffness_clamps,
            stopped=self._stopped,
            error=self.error,
            passivity=None
            if self._pc is None
            else {
                "observed_j": self._pc.observed_energy_j,
                "dissipated_j": self._pc.dissipated_energy_j,
                "active_j": self._pc.active_energy_j,
            },
        )


@dataclass
class DeadlineLoop:
    """Deadline scheduler: tick k is due at ``start + k * period_s`` (integer k, no float drift).

    Parameters
    ----------
    period_s : float
        Period T [s], > 0.
    clock : callable
        Monotonic clock [s] (default :func:`time.perf_counter`).
    sleep : callable
        ``sleep(seconds)`` (default :func:`time.sleep`).
    spin_s : float
        The last ``spin_s`` [s] before a deadline are busy-waited on ``clock`` instead of slept
        (sleep overshoots by ~0.1 ms on a stock Linux kernel; default 3e-4).
    late_tolerance : float
        A deadline is missed when the loop gets to it more than ``late_tolerance * period_s``
        late; missed deadlines are skipped (default 0.5).

    Attributes
    ----------
    overruns : int
        Deadlines missed and skipped so far.
    ticks : int
        Ticks run so far.
    """

    period_s: float
    clock: Clock = time.perf_counter
    sleep: Sleep = time.sleep
    spin_s: float = 3e-4
    late_tolerance: float = 0.5
    overruns: int = field(default=0, init=False)
    ticks: int = field(default=0, init=False)
    _halt: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period_s) and self.period_s > 0.0):
            raise ValueError(f"period_s must be > 0, got {self.period_s!r}")
        if not (0.0 < self.late_tolerance < 1.0):
            raise ValueError("late_tolerance must be in (0, 1) periods")

    def halt(self) -> None:
        """Make :meth:`run` return after the current tick (from any thread)."""
        self._halt = True

    def run(
        self,
        tick: Callable[[float], bool],
        *,
        max_ticks: int | None = None,
        after_tick: Callable[[float], None] | None = None,
        on_overrun: Callable[[int, float], None] | None = None,
    ) -> int:
        """Call ``tick(now_s)`` at every deadline until it returns True, ``max_ticks`` or halt.

        Parameters
        ----------
        tick : callable
            ``tick(now_s) -> stop``; ``now_s`` [s] is the clock when the deadline was reached.
        max_ticks : int, optional
            Stop after this many ticks.
        after_tick : callable, optional
            ``after_tick(compute_s)`` with the tick's duration [s].
        on_overrun : callable, optional
            ``on_overrun(missed, now_s)`` when deadlines were missed and skipped.

        Returns
        -------
        int
            Ticks run by this call.
        """
        clock, sleep = self.clock, self.sleep
        T, spin = self.period_s, self.spin_s
        tol = self.late_tolerance * T
        self._halt = False
        start = clock()
        k = 0
        done = 0
        while True:
            deadline = start + k * T
            now = clock()
            wait = deadline - now
            if wait > spin:
                sleep(wait - spin)
                now = clock()
            while now < deadline:
                now = clock()
            stop = tick(now)
            end = clock()
            done += 1
            if after_tick is not None:
                after_tick(end - now)
            if stop or self._halt or (max_ticks is not None and done >= max_ticks):
                break
            k += 1
            if end - (start + k * T) > tol:
                k_next = math.ceil((end - tol - start) / T)
                missed = k_next - k
                self.overruns += missed
                if on_overrun is not None:
                    on_overrun(missed, end)
                k = k_next
        self.ticks += done
        return done


class _SwitchInterval:
    """Reference-counted lowering of the interpreter's thread switch interval (process-wide)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved = 0.0

    def lower(self, interval_s: float) -> None:
        with self._lock:
            if self._users == 0:
                self._saved = sys.getswitchinterval()
            self._users += 1
            sys.setswitchinterval(min(sys.getswitchinterval(), interval_s))

    def restore(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                sys.setswitchinterval(self._saved)


_switch_interval = _SwitchInterval()


def try_realtime_priority(priority: int) -> bool:
    """Put the calling thread under SCHED_FIFO at ``priority`` (1-99) if the OS allows it.

    What haptic vendors do for their servo thread: a real-time thread is not preempted by the
    ordinary processes of the machine, so it wakes on time even when the CPUs are busy. The loop
    still sleeps most of each period, and Linux caps real-time threads at 95 % of a CPU by
    default, so it cannot lock the machine up.

    Returns
    -------
    bool
        True if granted; False where unsupported or not permitted (the thread keeps its policy).
    """
    setsched = getattr(os, "sched_setscheduler", None)
    fifo = getattr(os, "SCHED_FIFO", None)
    if setsched is None or fifo is None:
        return False
    try:
        setsched(0, fifo, os.sched_param(priority))
    except (OSError, ValueError):
        return False
    return True


class ServoThread:
    """Runs a :class:`ServoCore` at its servo rate on a dedicated thread (DESIGN section 4).

    Parameters
    ----------
    core : ServoCore
        The core to tick; its device must be open.
    clock, sleep : callable
        Injected time source and sleep (defaults :func:`time.perf_counter`, :func:`time.sleep`);
        ``notify_link()`` without an argument uses the same clock.
    spin_s : float
        Busy-wait margin [s] before each deadline (default 3e-4).
    late_tolerance : float
        Lateness, in periods, beyond which a deadline is missed and skipped (default 0.5).
    switch_interval_s : float or None
        While running, the interpreter's thread switch interval is lowered to this [s] (default
        2e-4) so another Python thread holding the GIL delays a tick by at most about this much;
        None leaves it alone. Restored on stop.
    realtime_priority : int or None
        SCHED_FIFO priority (1-99) asked for the servo thread (default 10; see
        :func:`try_realtime_priority`); None keeps the ordinary policy. Whether it was granted is
        :attr:`realtime`.
    name : str
        Thread name.

    Notes
    -----
    The caller opens the device before :meth:`start` and closes it after :meth:`stop`.
    """

    def __init__(
        self,
        core: ServoCore,
        *,
        clock: Clock = time.perf_counter,
        sleep: Sleep = time.sleep,
        spin_s: float = 3e-4,
        late_tolerance: float = 0.5,
        switch_interval_s: float | None = 2e-4,
        realtime_priority: int | None = 10,
        name: str = "haptic-servo",
    ) -> None:
        self.core = core
        self.clock = clock
        self.loop = DeadlineLoop(
            core.config.servo_period_s,
            clock=clock,
            sleep=sleep,
            spin_s=spin_s,
            late_tolerance=late_tolerance,
        )
        self._switch = switch_interval_s
        self._priority = realtime_priority
        self.realtime = False
        self._old_switch: float | None = None
        self._name = name
        self._thread: threading.Thread | None = None

    @property
    def servo_rate_hz(self) -> float:
        """Set servo rate [Hz]."""
        return self.core.config.servo_rate_hz

    @property
    def running(self) -> bool:
        """The thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def run(self, max_ticks: int | None = None) -> int:
        """Run the servo loop in the calling thread until stopped (or ``max_ticks``).

        An unexpected exception in a tick zeroes and disables the device's forces, is stored in
        ``status().error`` and ends the loop.

        Returns
        -------
        int
            Ticks run.
        """
        core = self.core
        try:
            return self.loop.run(
                core.tick,
                max_ticks=max_ticks,
                after_tick=core.record_compute,
                on_overrun=core.note_overrun,
            )
        except Exception as exc:  # the device must never keep a force after the loop dies
            core.shutdown_now(f"servo loop failed: {exc!r}")
            return 0

    def _main(self) -> None:
        if self._priority is not None:
            self.realtime = try_realtime_priority(self._priority)
        self.run()

    def start(self) -> None:
        """Start the servo thread.

        Raises
        ------
        RuntimeError
            Already running.
        """
        if self.running:
            raise RuntimeError("servo thread already running")
        if self._switch is not None:
            _switch_interval.lower(self._switch)
            self._old_switch = self._switch
        self._thread = threading.Thread(target=self._main, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float | None = None) -> bool:
        """Ramp forces down, disable them and join the thread.

        Parameters
        ----------
        timeout_s : float, optional
            Longest wait [s]; default the ramp time plus one second. If the thread has not ended
            by then it is told to halt after its current tick.

        Returns
        -------
        bool
            True if the thread ended (or was not running).
        """
        core = self.core
        core.request_stop()
        th = self._thread
        ok = True
        if th is not None:
            wait = core.config.ramp_s + 1.0 if timeout_s is None else timeout_s
            th.join(wait)
            if th.is_alive():
                self.loop.halt()
                th.join(0.5)
            ok = not th.is_alive()
            self._thread = None
        if ok and not core.stopped:
            core.shutdown_now(None)  # no thread ran the ramp: zero and disable at once
        if self._old_switch is not None:
            _switch_interval.restore()
            self._old_switch = None
        return ok

    # -- delegation for the network side -------------------------------------------------------------
    def set_patch(
        self,
        primitive: Primitive,
        k_h: float,
        i_gain: float,
        *,
        b_h: float = 0.0,
        proxy_hold: str = "zoh",
        hold_ticks: int = 1,
        k_o: float | None = None,
    ) -> Patch:
        """See :meth:`ServoCore.set_patch`; also counts as link activity now."""
        patch = self.core.set_patch(
            primitive,
            k_h,
            i_gain,
            b_h=b_h,
            proxy_hold=proxy_hold,
            hold_ticks=hold_ticks,
            k_o=k_o,
        )
        self.core.notify_link(self.clock())
        return patch

    def notify_link(self, now_s: float | None = None) -> None:
        """The server spoke (patch or pong); ``now_s`` defaults to the servo clock now."""
        self.core.notify_link(self.clock() if now_s is None else now_s)

    def enable_forces(self) -> None:
        """See :meth:`ServoCore.enable_forces`."""
        self.core.enable_forces()

    def disable_forces(self) -> None:
        """See :meth:`ServoCore.disable_forces`."""
        self.core.disable_forces()

    def latest(self) -> ServoSnapshot | None:
        """See :meth:`ServoCore.latest` (never blocks the tick)."""
        return self.core.latest()

    def status(self) -> ServoStatus:
        """See :meth:`ServoCore.status`."""
        return self.core.status()
