"""Each scheme's user of the fidelity benchmark's 3-D cells: its hand target, device, servo or
force loop, and the patch it renders after each World tick.

The blocks of :mod:`haptic_collab.research.fidelity_3d` (which documents the model) on the
harness of :mod:`haptic_collab.research.harness_3d`: the top of the object and its K_o
(:func:`top_contact`), the 1-D intention as a hand target along the top's normal
(:class:`NormalTrajectory`), the simulated Phantom Desktop with the 1-D device's limits
(:func:`scheme_device`), the product's servo of a servo-side scheme (:func:`scheme_servo`,
:func:`renewed_patch`) and the force loop of a direct scheme (:class:`DirectPort`). The
two-user cells (:mod:`haptic_collab.research.fidelity_pairs_3d`) use the same blocks.
"""

from __future__ import annotations

import math
import multiprocessing as mp
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from haptic_collab.client.devices.base import Vec3
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.servo import ServoCore
from haptic_collab.research.fidelity_cases import IMPACT, PRESS, Trajectory
from haptic_collab.research.fidelity_schemes import (
    PRODUCT_GAIN_TRANSFER_S,
    PRODUCT_PASSIVITY_BIAS_J,
    PRODUCT_THETA_M,
    SCHEMES,
    DeviceModel,
    Rendering,
    design_delay_ticks,
    rendering_for,
    scheme_tuning,
)
from haptic_collab.research.harness_3d import (
    RATE_RATIO,
    SERVO_RATE_HZ,
    SIM_RATE_HZ,
    experiment_limits,
    local_model,
    place_device,
    reused_world,
    servo_core,
)
from haptic_collab.server.object_info import object_info
from haptic_collab.server.world import ContactInput, World
from haptic_collab.shared.gains.choose import table_design
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.rest_plane import rest_plane_gains
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.passivity import PassivityController
from haptic_collab.shared.primitives import Plane, Sphere, moved_out
from haptic_collab.shared.types import FloatArray

__all__ = [
    "DEFAULT_DEVICE",
    "DESIGN_MARGIN",
    "DIRECT_REFERENCE",
    "SCHEMES_3D",
    "TRAJECTORIES_3D",
    "UNCAPPED_DAMPING_N_S_PER_M",
    "USER",
    "VELOCITY_LIMIT_M_S",
    "DirectPort",
    "DirectReference",
    "NormalTrajectory",
    "PortDevice",
    "check_delay",
    "check_known",
    "check_runs",
    "gain_key",
    "rendering_3d",
    "renewed_patch",
    "scheme_device",
    "scheme_servo",
    "top_contact",
    "top_k_o",
]

DirectReference = Literal["undisturbed", "patch"]

#: The servo's velocity limit [m/s] during these runs (the 1-D model has none; the product's
#: 0.6 m/s would withhold forces on a fast impact or an oscillating scheme).
VELOCITY_LIMIT_M_S = 100.0
#: The damping cap [N*s/m] standing in for "uncapped" in the servo's passivity controller (which
#: needs a finite one): far above anything the 7.9 N force clamp lets act.
UNCAPPED_DAMPING_N_S_PER_M = 1e6
#: The schemes the World cells run: those whose simulation side the World has (the virtual
#: coupling's tool, the force-jacobian's stiffness about the received probe and mmt-id's online
#: identification are modelled in 1-D only).
SCHEMES_3D: tuple[str, ...] = tuple(
    s for s in SCHEMES if s not in ("virtual-coupling", "force-jacobian", "mmt-id")
)
#: Default rule of the direct schemes (module docstring).
DIRECT_REFERENCE: DirectReference = "undisturbed"
#: The 3-D trajectories, by name, with the 1-D windows their metrics use.
TRAJECTORIES_3D: dict[str, Trajectory] = {"press": PRESS, "impact": IMPACT}
#: The device every scheme renders on by default (the simulated Phantom Desktop's limits).
DEFAULT_DEVICE = DeviceModel()
#: Design margin and other fixed parts of the client's gain key (as :mod:`haptic_collab.bench.fidelity`).
DESIGN_MARGIN = 0.15

#: The one user's name in the World.
USER = "user"


def top_contact(world: World) -> tuple[SurfacePatch, FloatArray, FloatArray]:
    """One World tick with the user's probe exactly at the top of the rest surface, no force.

    The top is the demo's (:func:`server.room.object_info`): the highest vertex nearest the
    vertical axis of the bounding box (the balloon's pole, the middle of a box's top face, a
    torus's ring rather than its hole).

    Returns
    -------
    (output, top, normal)
        The user's :class:`SurfacePatch` (K_o at the top, the rest-surface patch), the top
        point (3,) [m] and the outward unit normal (3,) there (the patch's).
    """
    info = object_info(world.vertices, world.faces)
    top = np.array(info.top_m, dtype=np.float64)
    out = world.tick({USER: ContactInput(probe=top, force=np.zeros(3))})[USER]
    n = np.asarray(out.normal, dtype=np.float64)
    return out, top, n / float(np.linalg.norm(n))


def top_k_o(stiffness_scale: float, mesh: str = "balloon") -> float:
    """K_o [N/m] the World reports at the top of ``mesh`` scaled by ``stiffness_scale``.

    Raises
    ------
    ValueError
        A scale that is not a finite number > 0 (:func:`server.main.build_world`).
    """
    out, _, _ = top_contact(reused_world(stiffness_scale, mesh))
    return float(out.k_o)


class NormalTrajectory:
    """The 1-D intention ``y(t)`` (:class:`haptic_collab.research.fidelity_cases.Trajectory`) as a hand target in 3-D.

    ``target(t) = top - y(t) normal`` [m] (``y`` positive inside), the callable
    :class:`client.devices.sim.SimDevice` pulls the hand toward; tabulated on the servo ticks
    ``t = n / servo_rate_hz`` of the trajectory's duration and linearly interpolated between them
    (held after the end).

    Parameters
    ----------
    trajectory : Trajectory
    top, normal : (3,) float
        Rest top [m] and its outward unit normal.
    servo_rate_hz : float
    """

    def __init__(
        self,
        trajectory: Trajectory,
        top: ArrayLike,
        normal: ArrayLike,
        servo_rate_hz: float = SERVO_RATE_HZ,
    ) -> None:
        self.trajectory = trajectory
        self._top = np.asarray(top, dtype=np.float64).reshape(3)
        self._n = np.asarray(normal, dtype=np.float64).reshape(3)
        self._T = 1.0 / float(servo_rate_hz)
        n = round(trajectory.duration_s * servo_rate_hz) + 1
        self._t = np.arange(n, dtype=np.float64) * self._T
        y, yd = trajectory.target(self._t)
        self._y = np.asarray(y, dtype=np.float64)
        self.initial_speed_in_m_s = float(yd[0])

    def depth_m(self, t_s: float) -> float:
        """Intended depth ``y`` [m] at ``t_s`` [s]."""
        k = t_s / self._T
        i = round(k)
        if abs(k - i) < 1e-9 and 0 <= i < len(self._y):
            return float(self._y[i])
        return float(np.interp(t_s, self._t, self._y))

    @property
    def initial_velocity_m_s(self) -> Vec3:
        """The hand's velocity (3,) [m/s] at t = 0 (an impact starts already moving)."""
        v = -self.initial_speed_in_m_s * self._n
        return (float(v[0]), float(v[1]), float(v[2]))

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at ``t_s`` [s]."""
        p = self._top - self.depth_m(t_s) * self._n
        return (float(p[0]), float(p[1]), float(p[2]))


class PortDevice(SimDevice):
    """A :class:`SimDevice` whose handle starts with a given velocity and that remembers the
    position the servo last read (the 1-D model's ``x``).

    SimDevice has no public way to start the handle moving: this sets its velocity state
    (``_v``) right after the first read, which places the handle (``_t`` is None before it).
    """

    def __init__(self, *args: Any, initial_velocity: Vec3 = (0.0, 0.0, 0.0), **kw: Any) -> None:
        super().__init__(*args, **kw)
        self._v_start = initial_velocity
        self.last_read: Vec3 = (math.nan, math.nan, math.nan)

    def read(self, t_s: float) -> Vec3:
        first = self._t is None
        q = super().read(t_s)
        if first:
            self._v = self._v_start  # the hand already moving with its intention (1-D: v = y')
        self.last_read = q
        return q

    def at_end_stop(self) -> bool:
        """The handle is on a face of the workspace box (the device's mechanical stop)."""
        x, lo, hi = self.position_m, self.limits.workspace_min_m, self.limits.workspace_max_m
        return any(x[i] <= lo[i] or x[i] >= hi[i] for i in range(3))


def gain_key(mode: Literal["p", "pi"], delay_ms: float, device: DeviceModel) -> GainKey:
    """The client's gain key at 20 Hz for a one-way delay ``delay_ms`` [ms] (the 1-D bench's)."""
    return GainKey(
        servo_rate_hz=SERVO_RATE_HZ,
        sim_rate_hz=SIM_RATE_HZ,
        delay_ticks=design_delay_ticks(delay_ms * 1e-3, SIM_RATE_HZ),
        mode=mode,
        margin=DESIGN_MARGIN,
        k_h_max=device.max_stiffness_n_per_m,
        b_h_max=device.max_damping_n_s_per_m,
    )


def rendering_3d(
    scheme: str,
    k_o: float,
    delay_ms: float,
    *,
    device: DeviceModel = DEFAULT_DEVICE,
    gain_table: GainTable | None = None,
    rest_plane: bool = False,
    b_o: float = 0.0,
) -> Rendering:
    """:func:`haptic_collab.research.fidelity_schemes.rendering_for` at 20 Hz, designing the local models' gains for
    ``k_o`` [N/m], ``delay_ms`` [ms] and ``b_o`` [N/m] by the client's rule
    (:func:`shared.gains.choose.table_design`; seconds per design; ``gain_table`` caches them).

    With ``rest_plane`` a local model is the client alone on the object: the rest plane each
    patch carries (:mod:`shared.gains.rest_plane`), with the gains of ``k_o`` (K_h = min(K_o, the
    device's), its damper for ``b_o`` [N/m] (the balloon and the FEM box report 0 at the top),
    no integral or compensation, zero-order hold; :func:`renewed_patch`). Without, its design
    against the current surface, as with another user near.

    Raises
    ------
    ValueError
        An unknown scheme, or a K_o the design refuses.
    """
    if rest_plane and scheme in ("local-p", "local-pi"):
        g = rest_plane_gains(
            k_o, b_o, SIM_RATE_HZ, device.max_stiffness_n_per_m, device.max_damping_n_s_per_m,
            servo_period_s=1.0 / SERVO_RATE_HZ,
        )  # fmt: skip
        # the client's local model (rendering_for's), with the rest plane's gains
        return Rendering(
            scheme,
            "coupling",
            k_h=g.k_h,
            b_h=g.b_h,
            theta_m=PRODUCT_THETA_M,
            release_time_s=2.0 / SIM_RATE_HZ,
            passivity=scheme == "local-pi",
            passivity_bias_j=PRODUCT_PASSIVITY_BIAS_J,
            rest_plane=True,
            gain_transfer_s=PRODUCT_GAIN_TRANSFER_S,
            tuning=f"{scheme_tuning(scheme, device)}; alone: the rest plane (shared.gains.rest_plane)",
        )
    design = None
    if scheme in ("local-p", "local-pi"):
        mode: Literal["p", "pi"] = "pi" if scheme == "local-pi" else "p"
        table = gain_table if gain_table is not None else GainTable()
        # the client's key and rule (shared.gains.choose.table_design): B_o floored to whole N/m
        # as make_gain_key does; a damped key renders its own design, or the undamped one where
        # the table's damping coverage reaches it, else the design the session makes
        key = replace(gain_key(mode, delay_ms, device), b_o=float(math.floor(max(0.0, b_o))))
        design = table_design(table, key, k_o)[0]
        if design is None:
            design = table.design(key, k_o)
    return rendering_for(scheme, sim_rate_hz=SIM_RATE_HZ, device=device, design=design, k_o=k_o)


def scheme_device(
    r: Rendering,
    point: FloatArray,
    normal: FloatArray,
    tr: Trajectory,
    device: DeviceModel,
    hand: HandParams,
) -> PortDevice:
    """The simulated Phantom Desktop of one user, its workspace centred on ``point`` and its hand
    following ``tr`` along ``normal`` (module docstring), opened with forces enabled."""
    limits = experiment_limits(
        r.k_h,
        max_force_n=device.max_force_n,
        max_stiffness_n_per_m=device.max_stiffness_n_per_m,
        max_damping_n_s_per_m=device.max_damping_n_s_per_m,
        max_velocity_m_s=VELOCITY_LIMIT_M_S,
    )
    target = NormalTrajectory(tr, point, normal)
    dev = place_device(
        target,
        hand,
        limits,
        (float(point[0]), float(point[1]), float(point[2])),
        device_cls=PortDevice,
        enable_forces=True,
        initial_velocity=target.initial_velocity_m_s,
    )
    assert isinstance(dev, PortDevice)
    return dev


def scheme_servo(
    r: Rendering, dev: PortDevice, device: DeviceModel, k_o: float, out0: SurfacePatch
) -> tuple[ServoCore, dict[str, Any]]:
    """The servo loop of a servo-side scheme on ``dev``, holding the rest patch ``out0``, with
    the keyword arguments of its later ``set_patch`` calls (module docstring)."""
    lm = local_model(
        r.k_h,
        r.i_gain,
        theta_m=r.theta_m,
        release_time_s=r.release_time_s,
        integral_limit_n=device.max_force_n,
    )
    core = servo_core(
        dev,
        lm,
        recorder_capacity=64,
        ramp_s=1.0 / SERVO_RATE_HZ,
        passivity=r.passivity,
        passivity_energy_bias_j=r.passivity_bias_j if r.passivity else 1e-3,
    )
    patch_kw: dict[str, Any] = {
        "b_h": r.b_h,
        "proxy_hold": r.proxy_hold,
        "hold_ticks": RATE_RATIO,
        "k_o": k_o,
    }
    k_h0 = min(r.k_h, k_o) if r.kind == "mmt" else r.k_h
    core.set_patch(out0.primitive, k_h0, r.i_gain, **patch_kw)
    core.enable_forces()
    return core, patch_kw


def renewed_patch(
    r: Rendering, out: SurfacePatch, out0: SurfacePatch
) -> tuple[Plane | Sphere, float]:
    """The patch and K_h [N/m] a servo-side scheme renders after a World tick gave ``out``
    (``out0``: the user's first output, the rest surface)."""
    if r.kind == "mmt":
        # the rest surface and stiffness the World estimates: its patch less its own
        # deformation F / K_o, rendered with that K_o (capped)
        k_est = float(out.k_o)
        return moved_out(out.primitive, out.own_force_n / k_est), min(r.k_h, k_est)
    if r.rest_plane and out.rest_plane is not None:
        # the client alone: the rest plane the World sends, with the gains of the top's K_o
        return out.rest_plane, r.k_h
    if r.kind == "coupling":
        # own-force compensation: the surface moved out by C_h times the force applied
        return moved_out(out.primitive, r.own_gain * out.own_force_n), r.k_h
    # a wall keeps the rest surface it started with, sent afresh each tick (the servo ramps out
    # a patch that is not renewed)
    return out0.primitive, r.k_h


def check_known(names: Sequence[str], known: Sequence[str], what: str) -> None:
    """Raise ValueError naming the first of ``names`` not in ``known`` (``what`` it is)."""
    for name in names:
        if name not in known:
            raise ValueError(f"unknown {what} {name!r}; expected one of {', '.join(known)}")


@contextmanager
def executor(pool: Executor | None, workers: int | None) -> Iterator[Executor]:
    """``pool`` as it is (the caller's, left open), else a pool of ``workers`` spawned worker
    processes (None: every core), shut down on leaving."""
    if pool is not None:
        yield pool
        return
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as own:
        yield own


def check_runs(delays_ms: Sequence[float], workers: int | None) -> None:
    """Raise ValueError for a delay :func:`check_delay` refuses or ``workers < 1``."""
    for dm in delays_ms:
        check_delay(dm)
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers!r}")


def check_delay(delay_ms: float) -> int:
    """The one-way delay ``delay_ms`` [ms] in servo ticks; ValueError unless whole and >= 0."""
    dq = delay_ms * 1e-3 * SERVO_RATE_HZ
    if not (math.isfinite(delay_ms) and delay_ms >= 0.0 and abs(dq - round(dq)) < 1e-9):
        raise ValueError(f"delay must be whole servo ticks >= 0 ms, got {delay_ms!r}")
    return round(dq)


class DirectPort:
    """The user of a direct scheme: the loop (read the device, write the force) holding the force
    the World sent (zero-order hold), through the passivity controller ``pc`` when given (with
    the device velocity, the backward difference of the positions read) and the force clamp
    ``max_force_n`` [N]; it sends the probe it read (module docstring of
    :mod:`haptic_collab.research.fidelity_3d`). ``after_tick(n)`` runs after each tick.
    """

    __slots__ = ("dev", "pc", "fmax", "start", "after_tick", "held", "q")

    def __init__(
        self,
        dev: PortDevice,
        pc: PassivityController | None,
        max_force_n: float,
        start: FloatArray,
        after_tick: Callable[[int], None],
    ) -> None:
        self.dev = dev
        self.pc = pc
        self.fmax = max_force_n
        self.start = start
        self.after_tick = after_tick
        self.held: Vec3 = (0.0, 0.0, 0.0)
        self.q: Vec3 = (math.nan, math.nan, math.nan)

    def start_state(self) -> FloatArray:
        """The starting probe (3,) [m]."""
        return self.start

    def receive(self, message: Vec3) -> None:
        """The World's force (3,) [N], held from the next tick."""
        self.held = message

    def state(self) -> FloatArray:
        """The probe (3,) [m] read on the last tick."""
        qx, qy, qz = self.q
        return np.array([qx, qy, qz], dtype=np.float64)

    def tick(self, n: int) -> None:
        """Servo tick ``n``: read, the PC, the clamp, write; then ``after_tick(n)``."""
        T = 1.0 / SERVO_RATE_HZ
        fmax = self.fmax
        px, py, pz = self.q
        qx, qy, qz = self.dev.read(n * T)
        hx, hy, hz = self.held
        if self.pc is not None:
            if n:
                vx, vy, vz = (qx - px) / T, (qy - py) / T, (qz - pz) / T
            else:  # no backward difference yet (the 1-D model's first tick too)
                vx = vy = vz = 0.0
            hx, hy, hz = self.pc.step(hx, hy, hz, vx, vy, vz)
        m2 = hx * hx + hy * hy + hz * hz
        if m2 > fmax * fmax:
            sc = fmax / math.sqrt(m2)
            hx, hy, hz = hx * sc, hy * sc, hz * sc
        self.dev.write(hx, hy, hz)
        self.q = (qx, qy, qz)
        self.after_tick(n)
