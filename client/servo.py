"""The 1 kHz servo loop's sans-I/O core (:class:`ServoCore`) and the values it publishes.

DESIGN section 4 (client side) and section 7; the paper's haptic loop of section 6, Steps 2-3.
Every servo period T one :meth:`ServoCore.tick` runs CHAI3D's three haptic-tool phases, each a
unit of its own that is tested without threads:

1. update from device: x_h = device.read(t), the buttons, the probe's filtered velocity
   v(k) = v(k-1) + a * ((x_h(k) - x_h(k-1)) / dt - v(k-1)), a = T / (T + ``velocity_filter_s``);
2. compute interaction forces: (f, e, n) = render(x_h) (:class:`client.render.LocalRenderer`: the
   patch hand-over with its first-order hold, f = L(z) e of eq. 12 with the threshold of eq.
   17-18 plus the probe damper); the safety gain g = update(...) and the force on the user
   F = g * clamp(f, +-F_max) * n through the passivity controller
   (:class:`client.safety.SafetySupervisor`);
3. apply to device: device.write(F); then the telemetry row and the latest-wins snapshot.

The local model (a :class:`shared.local_model_update.LocalModelUpdate`: primitive + gains K_h, I)
is a zero-order hold of the slow simulation's output (eq. 1): :meth:`ServoCore.set_patch` may be
called from the network thread at any time; it swaps one reference that the next tick picks up,
so a patch is applied whole and between ticks. The LocalModel's integral state is kept across
patches (only its gains change), so a new patch does not make the integral force jump.

Safety, as device vendors do it (STYLE rule 9; :mod:`client.safety`):

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

Two hosts time the core at ``servo_rate_hz``: its own process
(:class:`client.servo_process.ServoProcess`, the default) or a thread of the client
(:class:`client.servo_thread.ServoThread`). The link side reads what the core publishes as
:class:`ServoSnapshot` and :class:`ServoStatus`.
"""

from __future__ import annotations

import array
import math
from dataclasses import asdict, dataclass, replace
from typing import Any, cast

from haptic_collab.client.devices.base import Device, DeviceLimits, HapticError, Vec3
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.render import LocalRenderer
from haptic_collab.client.safety import SafetySupervisor, ServoEvent
from haptic_collab.client.servo_config import ServoConfig
from haptic_collab.shared.full_loop import ProxyHold
from haptic_collab.shared.local_model import LocalModel, LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate, SurfacePatch
from haptic_collab.shared.primitives import Primitive

__all__ = [
    "PUBLISHED",
    "LocalModelUpdate",
    "ServoConfig",
    "ServoCore",
    "ServoEvent",
    "ServoSnapshot",
    "ServoStatus",
    "clamp_to_device",
    "snapshot_of",
]


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
        # Written out, not dataclasses.asdict: the event kind goes out as its string value (asdict
        # keeps the enum member), and "engaged" sits after "forces_enabled" (the field came last
        # so that the constructor's positional order stays the same).
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
        Force [N] of the local model on the user, clamped and scaled by the safety gain, before
        the passivity controller's damper: what the coupling applies to the object with the
        opposite sign (Step 3). The force the device displayed is in the telemetry rows.
    penetration_m : float
        Penetration e [m] into the local model (NaN before the first patch).
    in_contact : bool
        The local model was in contact.
    k_h : float
        K_h [N/m] in use.
    i_gain : float
        I [N/(m*s)] in use.
    own_gain : float
        Own-force compensation C_h [m/N] in use (0: none).
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
    own_gain: float
    force_scale: float
    servo_rate_hz: float
    period_mean_s: float
    period_p50_s: float
    period_p99_s: float
    period_max_s: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-able dictionary (vectors as lists; NaN stays NaN)."""
        return {**asdict(self), "probe_m": list(self.probe_m), "force_n": list(self.force_n)}


_NAN = math.nan

#: Values of a published tick, in order (:attr:`ServoCore.published`): tick, t [s], probe x, y, z
#: [m], force x, y, z [N], penetration [m], in contact, K_h [N/m], I [N/(m*s)], C_h [m/N], g.
PUBLISHED = 14


def snapshot_of(
    pub: tuple[float, ...] | list[float], periods: Any, n_periods: int
) -> ServoSnapshot:
    """A :class:`ServoSnapshot` from a published tick (:data:`PUBLISHED` values) and the ring of
    the last periods [s] (``n_periods`` ever written; any sequence of floats)."""
    m = min(int(n_periods), len(periods))
    if m:
        v = sorted(periods[:m])
        mean = sum(v) / m
        p50, p99, pmax = v[(m - 1) // 2], v[int(0.99 * (m - 1))], v[-1]
        rate = 1.0 / mean if mean > 0.0 else _NAN
    else:
        mean = p50 = p99 = pmax = rate = _NAN
    n, t, x, y, z, fx, fy, fz, e, c, k_h, i_gain, own, s = pub
    return ServoSnapshot(
        tick=int(n),
        t_s=t,
        probe_m=(x, y, z),
        force_n=(fx, fy, fz),
        penetration_m=e,
        in_contact=bool(c),
        k_h=k_h,
        i_gain=i_gain,
        own_gain=own,
        force_scale=s,
        servo_rate_hz=rate,
        period_mean_s=mean,
        period_p50_s=p50,
        period_p99_s=p99,
        period_max_s=pmax,
    )


def clamp_to_device(
    update: LocalModelUpdate, limits: DeviceLimits
) -> tuple[LocalModelUpdate, bool]:
    """``update`` with K_h clamped to ``limits.max_stiffness_n_per_m`` and B_h to
    ``limits.max_damping_n_s_per_m``, and whether K_h was clamped (what the servo applies)."""
    k = update.k_h
    clamped = k > limits.max_stiffness_n_per_m
    if clamped:
        k = limits.max_stiffness_n_per_m
    bh = min(update.b_h, limits.max_damping_n_s_per_m)
    if k != update.k_h or bh != update.b_h:
        update = replace(update, k_h=k, b_h=bh)
    return update, clamped


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
    period_buffer : memoryview, optional
        Where the last ``config.period_window`` periods are kept (8 bytes each; shared memory
        that another process reads, :mod:`client.servo_process`). Default: private memory.

    Attributes
    ----------
    renderer : LocalRenderer
        Phase 2, the local model rendered at the probe (:mod:`client.render`).
    safety : SafetySupervisor
        The safety gain, clamp and passivity controller (:mod:`client.safety`).
    local_model : LocalModel
        ``renderer.model``.

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
        period_buffer: memoryview | None = None,
    ) -> None:
        cfg = config if config is not None else ServoConfig()
        T = cfg.servo_period_s
        lim = device.limits
        if local_model is None:
            # a placeholder: no force is displayed before the first patch brings its gains (a
            # position-only input has no finite max stiffness to start from)
            local_model = LocalModelParams(k_h=1.0, servo_period_s=T)
        if not math.isclose(local_model.servo_period_s, T, rel_tol=1e-9):
            raise ValueError(
                f"local model period {local_model.servo_period_s} s differs from the servo period "
                f"{T} s (servo_rate_hz={cfg.servo_rate_hz})"
            )
        self.device = device
        self.config = cfg
        self.recorder = recorder if recorder is not None else TelemetryRecorder()
        self.renderer = LocalRenderer(local_model, own_force_limit_n=lim.max_force_n)
        self.local_model: LocalModel = self.renderer.model
        self.safety = SafetySupervisor(lim, cfg)
        tau = cfg.velocity_filter_s
        self._alpha = 1.0 if tau == 0.0 else T / (T + tau)
        self._by_button = cfg.engage_with_button
        # patch hand-over (one reference swap; see set_patch)
        self._patch_in: LocalModelUpdate | None = None
        # tick state
        self._ticks = 0
        self._t = 0.0
        self._px = self._py = self._pz = 0.0
        self._vx = self._vy = self._vz = 0.0
        self._dev_enabled = False
        self._stopped = False
        self.error: str | None = None
        self._stiffness_clamps = 0
        # latest-wins publication and period window
        self._pub: tuple[Any, ...] | None = None
        self._periods: Any = (
            array.array("d", bytes(8 * cfg.period_window))
            if period_buffer is None
            else period_buffer.cast("B")[: 8 * cfg.period_window].cast("d")
        )
        self._n_periods = 0

    # -- inputs from other threads ---------------------------------------------------------------
    def set_patch(
        self,
        primitive: LocalModelUpdate | Primitive,
        k_h: float | None = None,
        i_gain: float | None = None,
        *,
        b_h: float | None = None,
        proxy_hold: str | None = None,
        hold_ticks: int | None = None,
        k_o: float | None = None,
    ) -> LocalModelUpdate:
        """Hand a new local model to the servo loop; applied whole at the start of the next tick.

        Either ``set_patch(update)`` with a :class:`shared.local_model_update.LocalModelUpdate`
        (what :class:`client.session.ClientSession` builds from a server patch), or
        ``set_patch(primitive, k_h, i_gain, b_h=..., proxy_hold=..., hold_ticks=..., k_o=...)``,
        which builds one.

        K_h above the device's ``max_stiffness_n_per_m`` is clamped to it (counted in
        ``status().stiffness_clamps``), B_h to ``max_damping_n_s_per_m``. The LocalModel's
        integral state is kept (eq. 12 gains change, its state does not). With ``proxy_hold="foh"``
        the surface moves from the previous patch's to this one's over ``hold_ticks`` ticks
        (:mod:`shared.full_loop` analyses exactly this); a patch that arrives before the previous
        slide is over (network jitter) slides on from the blend reached, so the force never steps.

        Parameters
        ----------
        primitive : LocalModelUpdate, or Plane or Sphere
            The whole update; or the local geometric model [m] (:mod:`shared.primitives`), with
            the gains below.
        k_h : float
            K_h [N/m], finite and > 0 (required with a primitive).
        i_gain : float
            I [N/(m*s)], finite and >= 0 (required with a primitive).
        b_h : float
            Probe damper B_h [N*s/m], finite and >= 0 (default 0).
        proxy_hold : {"zoh", "foh"}
            Default ``"zoh"``.
        hold_ticks : int
            Servo ticks per simulation tick N for the first-order hold, >= 1 (default 1).
        k_o : float, optional
            The contact's K_o [N/m], > 0: sets the local model's recovery band (a PI contact is
            kept while the probe is within s/K_o of the proxy; :mod:`shared.local_model`),
            through a surface patch made by hand (:meth:`SurfacePatch.of`).

        Returns
        -------
        LocalModelUpdate
            What will be applied (K_h and B_h clamped to the device).

        Raises
        ------
        TypeError
            ``primitive`` is not a LocalModelUpdate, Plane or Sphere; a primitive without
            ``k_h`` and ``i_gain``; or an update with gains besides.
        ValueError
            Non-finite or out-of-range gains.
        """
        if isinstance(primitive, LocalModelUpdate):
            given = (k_h, i_gain, b_h, proxy_hold, hold_ticks, k_o)
            if any(v is not None for v in given):
                raise TypeError(
                    "set_patch takes a LocalModelUpdate alone, or a primitive and gains"
                )
            update = primitive
        else:
            if k_h is None or i_gain is None:
                raise TypeError("set_patch(primitive, k_h, i_gain): K_h and I are required")
            update = LocalModelUpdate(
                primitive,
                k_h,
                i_gain,
                b_h=0.0 if b_h is None else b_h,
                proxy_hold=cast(ProxyHold, "zoh" if proxy_hold is None else proxy_hold),
                hold_ticks=1 if hold_ticks is None else hold_ticks,
                surface=None if k_o is None else SurfacePatch.of(primitive, k_o),
            )
        update, stiffness_clamped = clamp_to_device(update, self.device.limits)
        self._stiffness_clamps += stiffness_clamped
        self._patch_in = update
        return update

    def notify_link(self, now_s: float) -> None:
        """The server spoke (a patch or a pong arrived) at servo time ``now_s`` [s]."""
        self.safety.notify_link(now_s)

    def enable_forces(self) -> None:
        """Allow forces (they ramp up once a patch is current and nothing else withholds them)."""
        self.safety.enable()

    def disable_forces(self) -> None:
        """Ramp forces down to zero and keep them there until :meth:`enable_forces`."""
        self.safety.disable()

    def request_stop(self) -> None:
        """Ramp forces down, then write zero and disable the device's forces (see :attr:`stopped`)."""
        self.safety.request_stop()

    @property
    def stopped(self) -> bool:
        """True once a requested stop finished (forces at zero and disabled)."""
        return self._stopped

    @property
    def published(self) -> tuple[Any, ...] | None:
        """The newest tick's :data:`PUBLISHED` values (None before the first tick)."""
        return self._pub

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
        rd = self.renderer
        sup = self.safety
        p = self._patch_in
        if p is not rd.patch and p is not None:  # hand-over between ticks (one reference swap)
            rd.hand_over(p, sup.need_patch)
            sup.patch_arrived(now_s)

        # 1. update from device: position, buttons, filtered velocity, period
        dev = self.device
        x, y, z = dev.read(now_s)
        pressed = bool(dev.buttons() & 1) if self._by_button else False
        position_ok = math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        if not position_ok:  # keep the last finite position; the supervisor calls it a fault
            x, y, z = self._px, self._py, self._pz
        n = self._ticks
        if n:
            dx, dy, dz = x - self._px, y - self._py, z - self._pz
            period = now_s - self._t
            if period > 0.0:
                a = self._alpha
                inv = 1.0 / period
                self._vx += a * (dx * inv - self._vx)
                self._vy += a * (dy * inv - self._vy)
                self._vz += a * (dz * inv - self._vz)
            self._periods[self._n_periods % len(self._periods)] = period
            self._n_periods += 1
        else:
            dx = dy = dz = 0.0
            period = _NAN
        self._t, self._px, self._py, self._pz = now_s, x, y, z
        vx, vy, vz = self._vx, self._vy, self._vz

        # 2. compute interaction forces, then the safety gain, clamp and passivity
        f, e, nx, ny, nz, in_contact = rd.render(x, y, z, dx, dy, dz)
        s = sup.update(now_s, pressed, dev.fault, position_ok, vx * vx + vy * vy + vz * vz)
        want = sup.want
        fx, fy, fz, fo = sup.output(f, nx, ny, nz, dx, dy, dz, now_s, self._dev_enabled)
        if s == 0.0 and not want:
            rd.reset()  # forces withheld: no integral wind-up while off

        # 3. apply to device
        if want and not self._dev_enabled:
            dev.enable_forces()
            self._dev_enabled = True
        dev.write(fx, fy, fz)
        if s == 0.0 and sup.stopping:
            dev.write(0.0, 0.0, 0.0)
            dev.disable_forces()
            self._dev_enabled = False
            self._stopped = True

        # telemetry (plain stores) and latest-wins publication (one reference swap)
        if rd.primitive is not None:
            qx, qy, qz = x + e * nx, y + e * ny, z + e * nz
        else:
            qx, qy, qz = x, y, z
        lm = rd.model
        pc = sup.passivity
        k_h, i_gain = rd.k_h, rd.i_gain
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
            k_h,
            i_gain,
            lm.integral_n,
            lm.theta_m,
            period,
            0.0,
            s,
            in_contact,
            sup.ramping,
            sup.fault is not None,
            sup.limited,
            rd.b_h,
            pc.observed_energy_j if pc is not None else 0.0,
            pc.dissipated_energy_j if pc is not None else 0.0,
            rd.own_offset_m,
            rd.own_gain,
        )
        # the coupling's force, not the passivity controller's damper: the object is pushed by the
        # local model (Step 3), and a damper that acts on the hand alone must not enter the slow
        # loop (with it, three PI users on a soft object rang 8.7 mm: docs/stability.md)
        fcx, fcy, fcz = fo * nx, fo * ny, fo * nz
        self._pub = (n, now_s, x, y, z, fcx, fcy, fcz, e, in_contact, k_h, i_gain, rd.own_gain, s)
        self._ticks = n + 1
        return self._stopped

    def record_compute(self, compute_s: float) -> None:
        """Store the measured duration [s] of the tick that just ran in its telemetry row."""
        self.recorder.set_compute_s(compute_s)

    def note_overrun(self, missed: int, now_s: float) -> None:
        """Count ``missed`` skipped deadlines (``SERVO_OVERRUN``) noticed at servo time ``now_s``."""
        if missed > 0:
            # one event (last_event) for the whole gap, counted once per missed deadline
            sup = self.safety
            sup.counts[HapticError.SERVO_OVERRUN] += missed - 1
            sup.event(HapticError.SERVO_OVERRUN, now_s, f"{missed} deadline(s) missed and skipped")

    def shutdown_now(self, error: str | None = None) -> None:
        """Zero and disable the device's forces at once, without a ramp.

        Used when the servo thread dies (``error`` says why; it shows in ``status().error``) or
        is stopped without having run the ramp. Call it only when no tick is running.
        """
        if error is not None:
            self.error = error
        self.safety.zero()
        try:
            self.device.write(0.0, 0.0, 0.0)
            self.device.disable_forces()
        finally:
            self._dev_enabled = False
            self._stopped = True

    # -- outputs to other threads ----------------------------------------------------------------
    def latest(self) -> ServoSnapshot | None:
        """The newest tick's state and period statistics (None before the first tick)."""
        pub = self._pub
        if pub is None:
            return None
        return snapshot_of(pub, self._periods, self._n_periods)

    def status(self) -> ServoStatus:
        """Counters per :class:`HapticError`, the last event and the safety switches."""
        sup = self.safety
        return ServoStatus(
            ticks=self._ticks,
            counts={k.value: v for k, v in sup.counts.items()},
            last_event=sup.last_event,
            forces_enabled=sup.enabled,
            engaged=sup.engaged,
            has_patch=self.renderer.patch is not None and not sup.need_patch,
            link_alive=sup.link_ok,
            force_scale=sup.scale,
            device_fault=sup.fault,
            stiffness_clamps=self._stiffness_clamps,
            stopped=self._stopped,
            error=self.error,
            passivity=sup.passivity_energies(),
        )
